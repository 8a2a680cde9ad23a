"""Benchmark: what to do with a photo's clipped pixels (``reconstruct --clipped drop|keep``).

A sensor that clips records a highlight's radiance only as a lower bound. ``reconstruct`` can
drop such pixels (coverage 0) or keep them as if exact (``ReconstructOptions.clipped``). This
study measures the two on closed-form captures, where the unclipped truth is known: the
train views are clipped as a fixed-exposure camera would clip them (every channel at the level
that ``--clip-fraction`` of the train views' object pixels exceed in some channel), the DAM is
fitted on them with the default options, and the novel views are scored against the unclipped
truth. Reported: novel-view DSSIM, and the mean absolute error on the novel pixels whose true
radiance exceeds the clip level (in units of that level: how well the highlight is recovered).

Run (from the repository root)::

    .venv/bin/python -m bench.clipped

It writes bench/results/clipped.json and bench/clipped.md (``--out DIR`` elsewhere); the captures
are cached under bench/.cache/clipped.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from bench.common import BENCH, CACHE, RESULTS, command_line, log, machine_info

from damcap.appearance.evaluate import score_view
from damcap.appearance.fit import FitOptions, fit_dam
from damcap.appearance.render import render_frame
from damcap.appearance.views import ViewData, load_views, samples_of
from damcap.common.capture_folder import read_capture
from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

TREATMENTS = ("drop", "keep")
#: seed 1: the sharpest of the closed-form materials (GGX alpha 0.15, dielectric)
SCENES = {f"{shape}-{light}": ClosedFormOptions(shape=shape, light=light, seed=1)
          for shape in ("sphere", "blob") for light in ("directional", "env")}


def clip_level(views: list[ViewData], fraction: float) -> float:
    """The radiance that ``fraction`` of the views' object pixels (A > 0.5) exceed in their
    largest channel: where a camera whose white sits there clips."""
    peak = np.concatenate([v.data.radiance_lin[v.data.coverage > 0.5].max(-1) for v in views])
    return float(np.quantile(peak, 1 - fraction))


def clipped_views(views: list[ViewData], level: float, treatment: str) -> list[ViewData]:
    """The views as a camera clipping every channel at ``level`` records them, with the clipped
    pixels (any channel at or above the level, on the object) dropped or kept."""
    out = []
    for v in views:
        d = v.data
        hit = (d.radiance_lin >= level).any(-1) & (d.coverage > 0)
        data = replace(d, radiance_lin=np.minimum(d.radiance_lin, level).astype(np.float32))
        if treatment == "drop":
            data = replace(data, coverage=np.where(hit, 0, d.coverage).astype(np.float32))
        out.append(ViewData(v.name, data, v.world_from_cam))
    return out


def highlight_error(predictions_lin: list[np.ndarray], views: list[ViewData], level: float) -> tuple[float, int]:
    """Mean |prediction - truth| over the channels of the object pixels (A > 0.5) whose true
    radiance reaches ``level`` in some channel, in units of ``level``; and how many there are.

    Args:
        predictions_lin: (H, W, 3) rendered radiance per view.
        views: the views (their radiance is the truth).
        level: the clip level, radiance units.
    """
    errs = []
    for pred, v in zip(predictions_lin, views, strict=True):
        d = v.data
        sel = (d.coverage > 0.5) & (d.radiance_lin >= level).any(-1)
        if sel.any():
            errs.append(np.abs(pred[sel] - d.radiance_lin[sel]).mean(-1) / level)
    e = np.concatenate(errs) if errs else np.zeros(0)
    return (float(e.mean()) if e.size else float("nan")), int(e.size)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--clip-fraction", type=float, nargs="+", default=[0.03, 0.1],
                    help="share of the train views' object pixels that clip")
    ap.add_argument("--fit-steps", type=int, default=None, help="fit steps (default: FitOptions' default)")
    ap.add_argument("--resolution", type=int, default=ClosedFormOptions.resolution, help="the captures' image side, px")
    ap.add_argument("--cache", type=Path, default=CACHE / "clipped", help="where the captures are rendered once")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    fit_opts = FitOptions(checkpoint_every=0) if args.fit_steps is None else FitOptions(checkpoint_every=0, steps=args.fit_steps)
    rows = []
    t_all = time.perf_counter()
    for name in args.scenes:
        folder = args.cache / f"{name}-{args.resolution}"
        if not (folder / "transforms.json").exists():
            make_closed_form_capture(folder, replace(SCENES[name], resolution=args.resolution))
        cap = read_capture(folder)
        train, test = load_views(cap, "train"), load_views(cap, "test")
        true_peak = float(max(v.data.radiance_lin.max() for v in train))
        for fraction in args.clip_fraction:
            level = clip_level(train, fraction)
            for treatment in TREATMENTS:
                t0 = time.perf_counter()
                model = fit_dam(samples_of(clipped_views(train, level, treatment)), fit_opts).model
                preds = [render_frame(model, v.data, v.centre_world) for v in test]  # each novel view rendered once
                err, n_px = highlight_error(preds, test, level)
                novel = [d for p, v in zip(preds, test) if (d := score_view(v, p)) is not None]
                rows.append({"scene": name, "clip_fraction": fraction, "clip_level": level, "true_peak_over_level": true_peak / level,
                             "treatment": treatment, "novel_dssim": float(np.mean(novel)), "highlight_error": err,
                             "highlight_pixels": n_px, "seconds": time.perf_counter() - t0})
                log(f"{name} clip {fraction:.0%} {treatment}: novel DSSIM {rows[-1]['novel_dssim']:.4f}, highlight error {err:.3f}")
    res = {"command": command_line("clipped", argv if argv is not None else __import__("sys").argv[1:]),
           "machine": machine_info(), "fit_steps": fit_opts.steps, "resolution": args.resolution, "rows": rows,
           "seconds": time.perf_counter() - t_all}
    out_json, out_md = (args.out or RESULTS) / "clipped.json", (args.out or BENCH) / "clipped.md"
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(res, indent=1))
    write_markdown(res, out_md)
    log(f"wrote {out_json} and {out_md}")
    return 0


def write_markdown(res: dict, path: Path) -> None:
    m = res["machine"]
    lines = ["# Clipped pixels: drop them or keep them (`reconstruct --clipped`)", "",
             f"Command (from the repository root): `{res['command']}`", "",
             f"Machine: {m['cpu_model']} ({m['nproc']} cores); {m['date_utc']}; the whole study took {res['seconds']:.0f} s.", "",
             f"Closed-form captures (Lambert + GGX with GGX alpha 0.15, seed 1; 10 train / 22 test views, {res['resolution']} px). The train views are clipped at the "
             "level that the given share of their object pixels reach in some channel; each row fits one DAM "
             f"({res['fit_steps']} steps, default options) and scores the novel views against the unclipped truth. "
             "Highlight error: mean absolute error on the novel pixels at or above the clip level, in units of that level. "
             "Peak: the train views' true peak radiance over the clip level. A fit's seconds are in the JSON.", "",
             "| scene | clipped | peak | treatment | novel DSSIM | highlight error |",
             "|---|---:|---:|---|---:|---:|"]
    for r in res["rows"]:
        lines.append(f"| {r['scene']} | {r['clip_fraction']:.0%} | x{r['true_peak_over_level']:.1f} | {r['treatment']} | "
                     f"{r['novel_dssim']:.4f} | {r['highlight_error']:.3f} |")
    path.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
