"""Does the predictor's prior help ``damcap segment`` on novel views? (``SegmentOptions.prior``)

For each capture, ``damcap segment`` with a fixed number of materials runs with ``--prior off``,
``predictor`` (each material's DAM starts from the shipped predictor's prediction for the
pixels the initial clustering gave it, and is pulled towards it where those pixels say least:
appearance/segment/prior.py) and ``auto`` (both on the training views but a held-out arc, the
mode with the lower held-out DSSIM kept, then all views segmented with it). Each is scored by its
mean DSSIM on the novel views (weights carried from the geometry, no ground truth), beside RM++
on the same views; where the capture has true material weights, by the mean IoU of its labels
against them (materials matched), on the training views (Psi's weights) and the novel views
(carried). Seconds: the whole ``segment_materials`` call, wall clock.

Captures:

* ``studio``: the bundled rendered studio photos (3 materials), reconstructed as
  :mod:`bench.real_defaults` builds them (visual hull) and split by camera rings
  (:func:`damcap.reconstruct.split.ring_split`): one ring trains, the other is novel. No true weights.
* ``torus``: a closed-form torus with two materials under an environment map, with true
  weights (its own train/test split).
* ``cape``: the real cape photos (optional, ``--captures studio,torus,cape``; 2 materials).

Run from the repository root::

    .venv/bin/python -m bench.segment_prior [--captures studio,torus] [--seeds 0,1] [--steps 600 --init-steps 150]

Writes ``bench/results/segment_prior.json`` and ``bench/segment_prior.md`` (rows accumulate: a rerun
of some captures keeps the others; everything from the report's ``## Notes`` heading on is kept).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from bench.common import BENCH, CACHE, RESULTS, command_line, log, machine_info, machine_line, shared_data_dir, study_paths, write_report_keeping

RESULT = RESULTS / "segment_prior.json"
REPORT = BENCH / "segment_prior.md"
HISTORY_MARK = "## Notes"
MODES = ("off", "predictor", "auto")
MATERIALS = {"studio": 3, "torus": 2, "cape": 2}


def load_capture(name: str, size: int, torus_px: int = 64):
    """(train views, novel views, how they were split) of a capture."""
    from bench.real_defaults import build_capture, capture_sources
    from damcap.appearance.fit import camera_directions
    from damcap.appearance.views import load_views
    from damcap.common.capture_folder import read_capture
    from damcap.reconstruct.split import arc_split, ring_split

    if name == "torus":
        from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

        path = CACHE / "segment_prior" / f"torus2-{torus_px}"
        if not (path / "transforms.json").is_file():
            make_closed_form_capture(path, ClosedFormOptions(shape="torus", light="env", env_grid=12, materials=2, views=16, resolution=torus_px,
                                                             train_views=6, seed=2, dtype="float"))
        cap = read_capture(path)
        return load_views(cap, "train"), load_views(cap, "test"), "the capture's own split (6 train, 10 test views on one orbit)"
    cap = read_capture(build_capture(name, capture_sources(shared_data_dir())[name], "visual-hull", size, False))
    views = load_views(cap, "all")
    dirs = camera_directions(views)
    train_idx, test_idx = ring_split(dirs, cap.up_world, 10)
    how = "rings: 10 views of one ring train, the cameras more than 15 deg above or below it are novel"
    if not test_idx:
        train_idx, test_idx = arc_split(dirs, cap.up_world, 10)
        how = "one ring: a 90 deg arc is novel, 10 of the other views train"
    return [views[k] for k in train_idx], [views[k] for k in test_idx], how


def iou(model, views, carried: bool) -> float | None:
    """Mean IoU of the model's labels against the views' true weights (None without them)."""
    from damcap.appearance.segment.score import match_materials

    if not views or any(v.data.weights is None for v in views):
        return None
    fgs = [v.data.coverage > 0.5 for v in views]
    pw = np.concatenate([(model.weights_on(v) if carried else model.weights_of(v))[fg] for v, fg in zip(views, fgs)])
    tw = np.concatenate([v.data.weights[fg] for v, fg in zip(views, fgs)])
    return match_materials(pw, tw)[1]


def run(train, test, opts) -> dict:
    from damcap.appearance.segment.score import novel_view_dssim
    from damcap.appearance.segment.train import segment_materials

    lines: list[str] = []
    t0 = time.perf_counter()
    model = segment_materials(train, opts, log=lines.append)
    seconds = time.perf_counter() - t0
    for line in lines:
        log(f"  {line}")
    return {"novel_dssim": novel_view_dssim(model, test), "novel_dssim_seen": novel_view_dssim(model, test, seen_only=True),
            "iou_train": iou(model, train, carried=False), "iou_novel": iou(model, test, carried=True), "seconds": seconds,
            "prior": model.prior_choice, "messages": lines}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", default="studio,torus")
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--size", type=int, default=256, help="capture size of the photo captures, px")
    ap.add_argument("--steps", type=int, default=600, help="joint steps (SegmentOptions' default: 1200)")
    ap.add_argument("--init-steps", type=int, default=150, help="initialisation steps (default: 300)")
    ap.add_argument("--torus-px", type=int, default=64, help="the closed-form torus's resolution, px")
    ap.add_argument("--out", type=Path, default=None, help="write segment_prior.json and .md here instead of bench/")
    args = ap.parse_args(argv)

    import torch

    from damcap.appearance.baselines import rm_plus_plus
    from damcap.appearance.evaluate import score_view
    from damcap.appearance.segment.options import SegmentOptions

    torch.set_num_threads(2)
    result, report = study_paths(RESULT, REPORT, args.out)
    prev = json.loads(result.read_text()) if result.is_file() else {}
    rows: list[dict] = prev.get("rows", [])
    captures: dict = prev.get("captures", {})
    for name in [c for c in args.captures.split(",") if c]:
        train, test, how = load_capture(name, args.size, args.torus_px)
        rmpp = float(np.mean([s for t, p in zip(test, rm_plus_plus(train, test)) if (s := score_view(t, p)) is not None]))
        captures[name] = {"train": len(train), "test": len(test), "split": how, "rm++": rmpp, "materials": MATERIALS[name],
                          "size": args.size if name != "torus" else args.torus_px}
        log(f"{name}: {len(train)} train, {len(test)} novel views; RM++ {rmpp:.4f}")
        for seed in [int(s) for s in args.seeds.split(",") if s]:
            for mode in [m for m in args.modes.split(",") if m]:
                opts = SegmentOptions(materials=MATERIALS[name], steps=args.steps, init_steps=args.init_steps, prior=mode, seed=seed)
                row = {"capture": name, "mode": mode, "seed": seed, "steps": args.steps, "init_steps": args.init_steps, **run(train, test, opts)}
                row["x_rmpp"] = row["novel_dssim"] / rmpp
                log(f"{name} seed {seed} prior {mode}: novel DSSIM {row['novel_dssim']:.4f} (x{row['x_rmpp']:.2f} RM++, seen surface "
                    f"{row['novel_dssim_seen']:.4f}), IoU {row['iou_train']} / {row['iou_novel']}, {row['seconds']:.0f} s")
                rows = [r for r in rows if _key(r) != _key(row)] + [row]
                result.write_text(json.dumps({"command": command_line("segment_prior", argv if argv is not None else sys.argv[1:]),
                                              "machine": machine_info(), "options": asdict(replace(opts, prior="off", seed=0)),
                                              "captures": captures, "rows": rows}, indent=1, default=float))
    write_report(json.loads(result.read_text()), report)
    return 0


def _key(r: dict) -> tuple:
    return r["capture"], r["mode"], r["seed"], r["init_steps"], r["steps"]


def _f(x, fmt: str = ".4f") -> str:
    return "-" if x is None else format(x, fmt)


def write_report(res: dict, report: Path = REPORT) -> None:
    """bench/segment_prior.md from the results (generated tables above the history marker)."""
    m = res["machine"]
    lines = ["# The predictor's prior in `damcap segment`", "",
             "Question: does starting each material's DAM from the shipped predictor's prediction for its pixels, and pulling it "
             "towards that prediction where its pixels say least (`damcap segment --prior predictor`), lower the novel-view error "
             "of a segmentation? And does `--prior auto` (decide on a held-out arc of the training views) pick the better mode? "
             "Novel DSSIM: mean over the novel views, weights carried from the geometry; *seen*: only where the training views saw "
             "the surface. IoU: labels against the true weights (materials matched), training views (Psi) / novel views (carried). "
             "Seconds: the whole segment call (auto: three segmentations), wall clock on 2 cores shared with other jobs (so "
             "seconds are noisy).", "",
             f"Command (last run; rows accumulate over runs): `{res['command']}`", "",
             machine_line(m), "",
             "Most runs are shortened to fit the machine (*steps*: initialisation + joint steps; the defaults are 300 + 1200); "
             "otherwise `SegmentOptions`' defaults with the number of materials fixed.", ""]
    for name, cap in res["captures"].items():
        rs = [r for r in res["rows"] if r["capture"] == name]
        if not rs:
            continue
        lines += [f"## {name} ({cap['materials']} materials, {cap['size']} px; {cap['split']}; {cap['train']} train, {cap['test']} novel "
                  f"views; RM++ {cap['rm++']:.4f})", "",
                  "| prior | steps | seed | novel DSSIM | x RM++ | novel DSSIM, seen | IoU train / novel | seconds | auto kept (held-out DSSIM off / predictor) |",
                  "|---|---|---:|---:|---:|---:|---|---:|---|"]
        for r in sorted(rs, key=lambda r: (r["steps"], MODES.index(r["mode"]), r["seed"])):
            p = r.get("prior") or {}
            auto = ""
            if r["mode"] == "auto":
                h = p.get("held_out_dssim", {})
                auto = f"{p.get('kept')} ({_f(h.get('off'))} / {_f(h.get('predictor'))})"
            elif r["mode"] == "predictor" and not p.get("used", True):
                auto = "fell back to off"
            lines.append(f"| {r['mode']} | {r['init_steps']} + {r['steps']} | {r['seed']} | {r['novel_dssim']:.4f} | {r['x_rmpp']:.2f} | {r['novel_dssim_seen']:.4f} | "
                         f"{_f(r['iou_train'], '.3f')} / {_f(r['iou_novel'], '.3f')} | {r['seconds']:.0f} | {auto} |")
        lines += ["", "| prior | steps | seeds | mean novel DSSIM | mean x RM++ | mean seconds |", "|---|---|---|---:|---:|---:|"]
        for steps in sorted({(r["init_steps"], r["steps"]) for r in rs}):
            for mode in MODES:
                mr = [r for r in rs if r["mode"] == mode and (r["init_steps"], r["steps"]) == steps]
                if mr:
                    lines.append(f"| {mode} | {steps[0]} + {steps[1]} | {', '.join(str(r['seed']) for r in mr)} | "
                                 f"{np.mean([r['novel_dssim'] for r in mr]):.4f} | {np.mean([r['x_rmpp'] for r in mr]):.2f} | "
                                 f"{np.mean([r['seconds'] for r in mr]):.0f} |")
        lines.append("")
    write_report_keeping(report, lines, HISTORY_MARK)


if __name__ == "__main__":
    sys.exit(main())
