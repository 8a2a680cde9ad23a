"""Do damcap's defaults take its best path on objects it was never tuned on, judged on whole
rings of cameras held out?

For each capture (real photos: the cape, the fox; rendered photos: the studio bunny's two rings,
the blob), each geometry (visual hull, dense), the capture is split by camera rings
(:func:`damcap.reconstruct.split.ring_split`): the training views are one ring (or the densest elevation band), the novel
views are every camera more than ``--gap-deg`` away in elevation. Every method fits on the
training views only and is scored by its mean DSSIM on the novel views, beside RM++ on the same
views, and timed (wall seconds of the whole ``damcap fit`` path, :func:`.fit_views.fit_views`).

Run from the repository root::

    .venv/bin/python -m bench.real_defaults [--captures studio,cape,blob,fox] [--methods ...] [--fresh]

Writes ``bench/results/real_defaults.json`` (rows accumulate: a rerun of some methods keeps the
others) and ``bench/real_defaults.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.common import (BENCH, CACHE, RESULTS, command_line, log, machine_info, machine_line, shared_data_dir, study_paths,
                          write_report_keeping)

RESULT = RESULTS / "real_defaults.json"
HISTORY_MARK = "## Notes"
"""everything from this heading on is hand-written and survives a rerun"""
REPORT = BENCH / "real_defaults.md"
WORK = CACHE / "real_defaults"


def capture_sources(data: Path) -> dict[str, dict]:
    """name -> photos, masks (or None) and known cameras of each capture."""
    real = data / "real"
    samples = BENCH.parent / "samples"
    return {
        "studio": {"photos": samples / "photos_studio" / "images", "masks": samples / "photos_studio" / "masks",
                   "poses": samples / "photos_studio" / "transforms.json", "kind": "rendered photos (Mitsuba), 3 materials"},
        "cape": {"photos": real / "mold_gold_cape" / "images", "masks": real / "mold_gold_cape" / "masks",
                 "poses": real / "mold_gold_cape" / "poses_bounds.npy", "kind": "real photos, glossy gold"},
        "blob": {"photos": samples / "photos_blob" / "images", "masks": samples / "photos_blob" / "masks",
                 "poses": samples / "photos_blob" / "transforms.json", "kind": "rendered photos, printed texture"},
        "fox": {"photos": real / "fox" / "images", "masks": None, "poses": real / "fox" / "transforms.json",
                "kind": "real phone photos, no masks"},
    }


def build_capture(name: str, src: dict, geometry: str, size: int, fresh: bool) -> Path:
    """The capture folder of ``name`` at ``size`` px with ``geometry`` (built once, cached)."""
    import shutil

    from damcap.reconstruct.geometry import GeometryOptions
    from damcap.reconstruct.pipeline import ReconstructOptions, reconstruct_capture

    out = WORK / f"{name}-{geometry}-{size}"
    if fresh and out.exists():
        shutil.rmtree(out)
    if (out / "transforms.json").is_file():
        return out
    opts = ReconstructOptions(capture_size=size, train_views=2, geometry=GeometryOptions(mode=geometry))
    poses = str(src["poses"]) if src["poses"] else None
    reconstruct_capture(src["photos"], out, opts, masks_dir=src["masks"], poses=poses, log=log)
    return out


def novel_split(cap, views: list, train_views: int, gap_deg: float = 15.0) -> tuple[list[int], list[int], str]:
    """The study's split of a capture's views: ``train_views`` on the fullest elevation band and
    every camera more than ``gap_deg`` above or below it novel
    (:func:`damcap.reconstruct.split.ring_split`, 'rings'); where all cameras lie on one ring, the
    90-degree arc opposite camera 0 novel (:func:`~damcap.reconstruct.split.arc_split`, 'arc')."""
    from damcap.appearance.fit import camera_directions
    from damcap.reconstruct.split import arc_split, ring_split

    dirs = camera_directions(views)
    train_idx, test_idx = ring_split(dirs, cap.up_world, train_views, gap_deg=gap_deg)
    if test_idx:
        return train_idx, test_idx, "rings"
    train_idx, test_idx = arc_split(dirs, cap.up_world, train_views)
    return train_idx, test_idx, "arc"


def methods() -> dict[str, dict]:
    """method name -> FitOptions changes from the defaults (``predict``: the predictor alone).
    *joint DAM* methods fit the paper's joint network (``--no-separable``), as every default did
    before the separable DAM became one."""
    plain = {"normal_refine": "off", "spatial": "off", "prior": "off", "separable": False}
    old = {**plain, "holdout": "spread"}
    joint = {"separable": False}
    return {
        "fit (old default)": old,
        "fit": plain,
        "fit + prior": {**plain, "prior": "predictor"},
        "predict": {"predict": True},
        "predict --refine-steps auto": {"predict": True, "refine": "auto"},
        "auto with the spread hold-out": {**old, "normal_refine": "auto", "spatial": "auto"},
        "defaults": {},
        "defaults without the prior": {"prior": "off"},
        "defaults + prior always": {"prior": "predictor"},
        "defaults --width 44": {"width": 44},
        "joint DAM (the defaults before)": joint,
        "joint DAM without the prior": {**joint, "prior": "off"},
        "joint DAM + prior always": {**joint, "prior": "predictor"},
        "joint DAM --encoding vn": {**joint, "encoding": "vn"},
        "joint DAM --prior-weight 0.3": {**joint, "prior_weight": 0.3},
        "joint DAM --prior-weight 3": {**joint, "prior_weight": 3.0},
        "refine + albedo": {**plain, "normal_refine": "on", "spatial": "albedo"},
    }


def run_method(name: str, change: dict, train, test, base=None) -> dict:
    """Fit (or predict) on ``train``; mean DSSIM on ``test``; wall seconds."""
    from damcap.appearance.evaluate import evaluate_split
    from damcap.appearance.fit import FitOptions
    from damcap.appearance.fit_views import fit_views
    from damcap.appearance.hyper.predict import predict_views

    base = base or FitOptions()
    t0 = time.perf_counter()
    record: dict = {}
    if change.get("predict"):
        model = predict_views(train)
        if change.get("refine") == "auto":  # what predict's advice points to: refinement judged on the held-out arc
            from damcap.appearance.fit import held_out
            from damcap.appearance.hyper.predict import PredictOptions, refine_auto
            from damcap.appearance.views import samples_of

            po = PredictOptions()
            model, auto = refine_auto(model, samples_of(train), max_steps=po.refine_max_steps, patience_steps=po.refine_patience,
                                      learning_rate=po.refine_learning_rate, held=held_out(train, FitOptions()))
            record = {"refine_steps_used": auto.steps_used}
    else:
        opts = replace(base, **change)
        out = fit_views(train, opts, log=log)
        model = out.model
        record = {"best_step": out.result.best_step, "held_out": [train[k].name for k in out.held],
                  "normal_refine": out.normals.record(), "spatial": out.spatial.record(), "options": change}
    seconds = time.perf_counter() - t0
    scores = evaluate_split(train, test, {name: model}, baselines=False)[name]
    return {"method": name, "novel_dssim": scores.mean, "seconds": seconds, **record}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", default="studio,cape,blob,fox")
    ap.add_argument("--geometries", default="visual-hull,dense")
    ap.add_argument("--methods", default=",".join(methods()))
    ap.add_argument("--size", type=int, default=256, help="capture size, px")
    ap.add_argument("--train-views", type=int, default=10)
    ap.add_argument("--gap-deg", type=float, default=15.0)
    ap.add_argument("--fresh", action="store_true", help="rebuild the captures and drop earlier rows")
    ap.add_argument("--capture", action="append", default=[], metavar="NAME=DIR",
                    help="an existing capture folder instead of --captures (repeatable)")
    ap.add_argument("--steps", type=int, default=None, help="fit steps (default: FitOptions')")
    ap.add_argument("--refine-steps", type=int, default=None, help="normal refinement steps (default: FitOptions')")
    ap.add_argument("--out", type=Path, default=None, help="write real_defaults.json and .md here instead of bench/")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (the seconds depend on it)")
    args = ap.parse_args(argv)

    import torch

    from damcap.appearance.baselines import rm_plus_plus
    from damcap.appearance.evaluate import score_view
    from damcap.appearance.fit import FitOptions
    from damcap.appearance.views import load_views
    from damcap.common.capture_folder import read_capture

    torch.set_num_threads(args.threads)
    data = shared_data_dir()
    sources = capture_sources(data)
    result, report = study_paths(RESULT, REPORT, args.out)
    base = FitOptions()
    if args.steps is not None:
        base = replace(base, steps=args.steps)
    if args.refine_steps is not None:
        base = replace(base, normal_refine_steps=args.refine_steps)
    given = dict(c.split("=", 1) for c in args.capture)
    jobs = [(n, g) for n in args.captures.split(",") if n and not given for g in args.geometries.split(",")
            if not (sources[n]["masks"] is None and g == "visual-hull")] + [(n, "given") for n in given]
    prev = json.loads(result.read_text()) if result.is_file() and not args.fresh else {}
    rows: list[dict] = prev.get("rows", [])
    splits: dict = prev.get("splits", {})
    wanted = [m for m in args.methods.split(",") if m]
    unknown = set(wanted) - set(methods())
    if unknown:
        sys.exit(f"unknown methods {sorted(unknown)}; known: {list(methods())}")
    for name, geometry in jobs:
        src = sources.get(name, {"kind": "given capture folder"})
        cap_dir = Path(given[name]) if name in given else build_capture(name, src, geometry, args.size, args.fresh)
        cap = read_capture(cap_dir)
        views = load_views(cap, "all")
        train_idx, test_idx, split = novel_split(cap, views, args.train_views, args.gap_deg)
        train, test = [views[k] for k in train_idx], [views[k] for k in test_idx]
        key = f"{name}/{geometry}"
        rmpp = float(np.mean([s for t, p in zip(test, rm_plus_plus(train, test)) if (s := score_view(t, p)) is not None]))
        splits[key] = {"train": [v.name for v in train], "test": len(test), "rm++": rmpp, "kind": src["kind"], "split": split,
                       "capture": str(cap_dir), "size": args.size}
        log(f"{key}: {len(train)} train, {len(test)} novel views; RM++ {rmpp:.4f}")
        for m in wanted:
            row = {"capture": name, "geometry": geometry, **run_method(m, methods()[m], train, test, base)}
            row["x_rmpp"] = row["novel_dssim"] / rmpp
            log(f"{key} {m}: novel DSSIM {row['novel_dssim']:.4f} (x{row['x_rmpp']:.2f} RM++), {row['seconds']:.1f} s")
            rows = [r for r in rows if (r["capture"], r["geometry"], r["method"]) != (name, geometry, m)] + [row]
            res = {"command": command_line("real_defaults", argv if argv is not None else sys.argv[1:]), "machine": machine_info(),
                   "splits": splits, "rows": rows}
            result.write_text(json.dumps(res, indent=1, default=float))
    write_report(json.loads(result.read_text()), report)
    return 0


AUTO_GEOMETRY = {"cape": "dense", "studio": "visual-hull", "blob": "visual-hull", "fox": "dense"}
"""what ``damcap reconstruct --geometry auto`` chose on each capture at 256 px (photo consistency;
the reconstruct lines are quoted in the report's notes)"""


def summary_table(by: dict, auto_geometry: dict) -> list[str]:
    """Per capture: the old defaults, the joint DAM's defaults before the separable one, the new
    defaults and the best method found (any geometry), on the geometry ``--geometry auto`` chooses."""
    out = ["## Summary", "",
           "On the geometry `--geometry auto` chooses; *best* is the lowest novel-view DSSIM of any method on either geometry.", "",
           "| capture | auto's geometry | old defaults | joint DAM | new defaults | best (method, geometry) | new / best | x RM++ (new) | seconds (old / new) |",
           "|---|---|---:|---:|---:|---|---:|---:|---|"]
    for cap in dict.fromkeys(c for c, _ in by):
        geo = auto_geometry.get(cap, AUTO_GEOMETRY.get(cap, "given"))
        rows = {r["method"]: r for r in by.get((cap, geo), [])}
        if "defaults" not in rows or "fit (old default)" not in rows:
            continue
        best = min((r for (c, _), rs in by.items() if c == cap for r in rs), key=lambda r: r["novel_dssim"])
        old, new = rows["fit (old default)"], rows["defaults"]
        joint = rows.get("joint DAM (the defaults before)")
        out.append(f"| {cap} | {geo} | {old['novel_dssim']:.4f} | {joint['novel_dssim'] if joint else float('nan'):.4f} | "
                   f"{new['novel_dssim']:.4f} | {best['novel_dssim']:.4f} ({best['method']}, "
                   f"{best['geometry']}) | {new['novel_dssim'] / best['novel_dssim']:.3f} | {new['x_rmpp']:.2f} | "
                   f"{old['seconds']:.0f} / {new['seconds']:.0f} |")
    return out + [""]


def write_report(res: dict, report: Path = REPORT) -> None:
    """bench/real_defaults.md from the results (generated tables above the history marker)."""
    lines = ["# Defaults on objects damcap was not tuned on, judged on held-out camera rings", "",
             "Question: do `damcap fit`'s defaults take its best path on captures it was never tuned on? Each capture is split by "
             "camera rings (`damcap.reconstruct.split.ring_split`): train on one elevation band, score the mean DSSIM on every camera more "
             "than 15 deg above or below it (novel views), beside RM++ on the same views. Seconds: the whole fit path "
             "(prediction, fit, refinement, albedo), wall clock on the machine below.", "",
             f"Command (last run; rows accumulate over runs): `{res['command']}`", "",
             machine_line(res["machine"]), ""]
    by: dict = {}
    for r in res["rows"]:
        by.setdefault((r["capture"], r["geometry"]), []).append(r)
    lines += summary_table(by, res.get("auto_geometry", {}))
    for (cap, geo), rs in by.items():
        sp = res["splits"][f"{cap}/{geo}"]
        held = "a 90 deg arc of the ring held out" if sp.get("split") == "arc" else "other rings held out"
        lines += [f"## {cap}, {geo} ({sp['kind']}; {len(sp['train'])} train views, {sp['test']} novel: {held}; RM++ {sp['rm++']:.4f})", "",
                  "| method | novel DSSIM | x RM++ | seconds | kept |", "|---|---:|---:|---:|---|"]
        for r in sorted(rs, key=lambda r: r["novel_dssim"]):
            kept = []
            if r.get("normal_refine", {}).get("mode", "off") != "off":
                kept.append(f"normals {'kept' if r['normal_refine']['kept'] else 'not kept'}")
            if r.get("spatial", {}).get("mode", "off") != "off":
                kept.append(f"albedo {'kept' if r['spatial']['kept'] else 'not kept'}")
            lines.append(f"| {r['method']} | {r['novel_dssim']:.4f} | {r['x_rmpp']:.2f} | {r['seconds']:.0f} | {', '.join(kept)} |")
        lines.append("")
    write_report_keeping(report, lines, HISTORY_MARK)


if __name__ == "__main__":
    sys.exit(main())
