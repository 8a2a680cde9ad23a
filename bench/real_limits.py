"""What keeps damcap's defaults above half of RM++'s novel-view DSSIM on real photos, and which
part of the model would have to change?

For each real capture (the cape, the fox) on the geometry ``--geometry auto`` chooses, the views
are split as in ``bench.real_defaults`` (one ring of cameras trains, every camera more than 15 deg
above or below it is novel). ``damcap fit`` at its defaults (:func:`damcap.appearance.fit_views.fit_views`)
fits the training ring; its novel-view DSSIM is then taken apart two ways:

- *Swaps with oracles.* The same path fitted on every view, training and novel
  (``--normal-refine on --spatial albedo``, nothing held out), supplies parts no real fit can
  have, one at a time: its refined normals, its DAM and normals, its albedo texture. Where a
  part fitted on the novel views closes most of the gap, that part's extrapolation from one ring
  is what limits the result; a part whose swap leaves the score near the defaults' is not.
- *Image tests of the defaults' renders.* Per novel view: the best per-channel gain (an exposure
  or white balance the model cannot know), the best whole-pixel shift within 2 px (a
  registration error) and both images blurred by a Gaussian of 1.5 px (how much of the score is
  fine detail).

Run from the repository root::

    .venv/bin/python -m bench.real_limits [--captures cape,fox]

Writes ``bench/results/real_limits.json`` and ``bench/real_limits.md``; the captures are
``bench.real_defaults``' cached ones (built on first use).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.common import (BENCH, RESULTS, command_line, log, machine_info, machine_line, shared_data_dir, study_paths,
                          write_report_keeping)
from bench.real_defaults import AUTO_GEOMETRY, build_capture, capture_sources, novel_split

RESULT = RESULTS / "real_limits.json"
REPORT = BENCH / "real_limits.md"
HISTORY_MARK = "## Notes"
"""everything from this heading on is hand-written and survives a rerun"""
SHIFT_PX = 2
BLUR_SIGMA_PX = 1.5


def best_gain(reference_lin: np.ndarray, prediction_lin: np.ndarray, foreground: np.ndarray) -> np.ndarray:
    """Per-channel gain g minimising sum over the foreground of (reference - g * prediction)^2.

    Args:
        reference_lin, prediction_lin: (H, W, 3) linear radiance.
        foreground: (H, W) bool.

    Returns:
        (3,) float64 gains (1 where the prediction is black).

    >>> best_gain(np.full((2, 2, 3), 2.0), np.ones((2, 2, 3)), np.ones((2, 2), bool)).tolist()
    [2.0, 2.0, 2.0]
    """
    r, p = reference_lin[foreground].astype(np.float64), prediction_lin[foreground].astype(np.float64)
    den = (p * p).sum(0)
    return np.where(den > 0, (r * p).sum(0) / np.where(den > 0, den, 1.0), 1.0)


def image_tests(view, render_lin: np.ndarray) -> dict[str, float]:
    """DSSIM of one novel view's render as is, after :func:`best_gain`, at the best whole-pixel
    shift within ``SHIFT_PX`` (image content moved, np.roll), and with both images blurred by
    ``BLUR_SIGMA_PX``; plus the mean gain."""
    import cv2

    from damcap.appearance.metrics import dssim
    from damcap.appearance.pixels import FOREGROUND_COVERAGE

    ref, cov = view.data.radiance_lin, view.data.coverage
    fg = cov > FOREGROUND_COVERAGE
    g = best_gain(ref, render_lin, fg)
    shifts = [dssim(ref, np.roll(render_lin, (dy, dx), (0, 1)), cov) for dy in range(-SHIFT_PX, SHIFT_PX + 1)
              for dx in range(-SHIFT_PX, SHIFT_PX + 1)]
    blur = lambda a: cv2.GaussianBlur(np.ascontiguousarray(a, np.float32), (0, 0), BLUR_SIGMA_PX)  # noqa: E731
    return {"as_is": dssim(ref, render_lin, cov), "gain": dssim(ref, render_lin * g.astype(np.float32), cov),
            "shift": min(shifts), "blurred": dssim(blur(ref), blur(render_lin), cov), "mean_gain": float(g.mean())}


def swaps(fitted, oracle, train: list, test: list, voxel_size: float, prior: float) -> dict:
    """name -> model: the defaults' model ``fitted`` with parts of the all-view ``oracle`` swapped
    in; where the albedo is not named, it is re-estimated from the training views only (the
    closed form of :func:`damcap.appearance.spatial_fit.estimate_for`, on the voxels of
    ``voxel_size`` with ridge ``prior``)."""
    from damcap.appearance.spatial_fit import estimate_for

    def albedo_from(m, views):
        m = m.with_spatial(None)
        return m.with_spatial(estimate_for(m, views, voxel_size, prior))

    dam = fitted.with_spatial(None)
    return {
        "defaults (everything from the training ring)": fitted,
        "normals from every view": albedo_from(dam.with_normal_field(oracle.normal_field), train),
        "DAM and normals from every view": albedo_from(oracle, train),
        "DAM and normals from every view, no albedo": oracle.with_spatial(None),
        "albedo from every view": albedo_from(dam, train + test),
        "everything from every view": oracle,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", default="cape,fox")
    ap.add_argument("--size", type=int, default=256, help="capture size, px")
    ap.add_argument("--train-views", type=int, default=10)
    ap.add_argument("--steps", type=int, default=None, help="steps of the fits and of their normal refinement (default: FitOptions')")
    ap.add_argument("--capture", action="append", default=[], metavar="NAME=DIR",
                    help="an existing capture folder instead of --captures (repeatable)")
    ap.add_argument("--out", type=Path, default=None, help="write real_limits.json and .md here instead of bench/")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (the seconds depend on it)")
    args = ap.parse_args(argv)

    import torch

    from damcap.appearance.baselines import rm_plus_plus
    from damcap.appearance.evaluate import score_view
    from damcap.appearance.fit import FitOptions
    from damcap.appearance.fit_views import fit_views
    from damcap.appearance.render import render_frame
    from damcap.appearance.spatial_fit import mean_dssim, training_footprint
    from damcap.appearance.views import load_views
    from damcap.common.capture_folder import read_capture

    torch.set_num_threads(args.threads)
    base = FitOptions() if args.steps is None else replace(FitOptions(), steps=args.steps, normal_refine_steps=args.steps)
    given = dict(c.split("=", 1) for c in args.capture)
    names = list(given) or [n for n in args.captures.split(",") if n]
    sources = capture_sources(shared_data_dir()) if not given else {}
    rows = []
    for name in names:
        geometry = "given" if given else AUTO_GEOMETRY[name]
        cap_dir = Path(given[name]) if given else build_capture(name, sources[name], geometry, args.size, False)
        cap = read_capture(cap_dir)
        views = load_views(cap, "all")
        train_idx, test_idx, split = novel_split(cap, views, args.train_views)
        train, test = [views[k] for k in train_idx], [views[k] for k in test_idx]
        rmpp = float(np.mean([s for t, p in zip(test, rm_plus_plus(train, test)) if (s := score_view(t, p)) is not None]))
        t0 = time.perf_counter()
        fitted = fit_views(train, base, log=log)
        fit_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        oracle = fit_views(train + test, replace(base, prior="off", normal_refine="on", spatial="albedo", holdout_views=0), log=log).model
        oracle_s = time.perf_counter() - t0
        voxel = base.spatial_voxel_px * training_footprint(train)  # the defaults' albedo voxel
        models = swaps(fitted.model, oracle, train, test, voxel, base.spatial_prior)
        scores = {k: mean_dssim(m, test) for k, m in models.items()}
        for k, s in scores.items():
            log(f"{name}: {k}: novel DSSIM {s:.4f} (x{s / rmpp:.2f} RM++)")
        tests = [image_tests(v, render_frame(fitted.model, v.data, v.centre_world)) for v in test]
        image = {k: float(np.mean([t[k] for t in tests if t[k] is not None])) for k in tests[0]}
        log(f"{name}: image tests {image}")
        rows.append({"capture": name, "geometry": geometry, "split": split, "train": len(train), "novel": len(test), "rm++": rmpp,
                     "train_dssim": mean_dssim(fitted.model, train), "swaps": scores, "image_tests": image,
                     "fit_seconds": fit_s, "oracle_seconds": oracle_s, "kind": sources.get(name, {}).get("kind", "given capture folder")})
    res = {"command": command_line("real_limits", argv if argv is not None else sys.argv[1:]), "machine": machine_info(), "rows": rows}
    result, report = study_paths(RESULT, REPORT, args.out)
    result.write_text(json.dumps(res, indent=1, default=float))
    write_report(res, report)
    return 0


def write_report(res: dict, report: Path = REPORT) -> None:
    """bench/real_limits.md from the results (generated tables above the notes)."""
    lines = ["# What limits the defaults on real photos' held-out rings", "",
             "Question: what keeps `damcap fit`'s defaults above half of RM++'s novel-view DSSIM on the real captures, and which part "
             "of the model would have to change? The defaults fit one ring of cameras; parts fitted on every view (the novel ones "
             "too, which no real fit has) are swapped in one at a time, and the defaults' renders are tested for an exposure, a "
             "registration shift and fine detail. Split and captures as in [real_defaults.md](real_defaults.md).", "",
             f"Command: `{res['command']}`", "",
             machine_line(res["machine"]), ""]
    for r in res["rows"]:
        rmpp = r["rm++"]
        lines += [f"## {r['capture']}, {r['geometry']} ({r['kind']}; {r['train']} train views, {r['novel']} novel; RM++ {rmpp:.4f})", "",
                  f"The defaults' DSSIM on their own training views: {r['train_dssim']:.4f}. Fit {r['fit_seconds']:.0f} s, "
                  f"the all-view fit {r['oracle_seconds']:.0f} s.", "",
                  "| model (parts not named: the defaults', fitted on the training ring) | novel DSSIM | x RM++ |", "|---|---:|---:|"]
        lines += [f"| {k} | {s:.4f} | {s / rmpp:.2f} |" for k, s in r["swaps"].items()]
        t = r["image_tests"]
        lines += ["", "| the defaults' renders of the novel views | mean DSSIM |", "|---|---:|",
                  f"| as rendered | {t['as_is']:.4f} |", f"| best per-channel gain per view (mean gain {t['mean_gain']:.2f}) | {t['gain']:.4f} |",
                  f"| best whole-pixel shift within {SHIFT_PX} px per view | {t['shift']:.4f} |",
                  f"| both blurred, Gaussian sigma {BLUR_SIGMA_PX} px | {t['blurred']:.4f} |", ""]
    write_report_keeping(report, lines, HISTORY_MARK)


if __name__ == "__main__":
    sys.exit(main())
