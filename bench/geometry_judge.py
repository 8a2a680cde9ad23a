"""Does ``reconstruct --geometry auto``'s held-out judge choose the geometry the fit does best
on, and what does it cost?

For each capture with masks (the cape, the studio sample, the blob), both geometries (visual
hull, dense) are built once at 256 px with the capture's own cameras
(:func:`bench.real_defaults.build_capture`). The training views are those of
``bench.real_defaults`` (one ring of cameras); the judge
(:func:`damcap.appearance.fit_views.judge_geometries` with
:func:`~damcap.appearance.fit_views.judge_fit`) fits each geometry on them with the same views
held out and keeps photo consistency's choice unless the other scores lower by its margin. Its
choice is compared with the novel-view DSSIM of ``damcap fit`` at its defaults on each geometry
(``bench/results/real_defaults.json``: other rings, never seen by the judge), and its time with a
plain fit's (``--prior off --normal-refine off --spatial off``) on the same views, in the same run.

Run from the repository root::

    .venv/bin/python -m bench.geometry_judge [--captures cape,studio,blob]

Writes ``bench/results/geometry_judge.json`` and ``bench/geometry_judge.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

from bench.common import BENCH, RESULTS, command_line, log, machine_info, machine_line, shared_data_dir, study_paths
from bench.real_defaults import AUTO_GEOMETRY, RESULT as DEFAULTS_RESULT, build_capture, capture_sources, novel_split

RESULT = RESULTS / "geometry_judge.json"
REPORT = BENCH / "geometry_judge.md"
GEOMETRIES = ("visual-hull", "dense")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", default="cape,studio,blob")
    ap.add_argument("--size", type=int, default=256, help="capture size, px")
    ap.add_argument("--train-views", type=int, default=10)
    ap.add_argument("--given", nargs=2, metavar=("HULL_DIR", "DENSE_DIR"), default=None,
                    help="two capture folders of the same photos (visual hull, dense) instead of --captures")
    ap.add_argument("--steps", type=int, default=None, help="the judge's and the plain fit's steps (default: judge_fit's)")
    ap.add_argument("--out", type=Path, default=None, help="write geometry_judge.json and .md here instead of bench/")
    args = ap.parse_args(argv)

    import torch

    from damcap.appearance.fit import FitOptions
    from damcap.appearance.fit_views import fit_views, judge_fit, judge_geometries
    from damcap.appearance.views import load_views
    from damcap.common.capture_folder import read_capture

    torch.set_num_threads(2)
    sources = capture_sources(shared_data_dir())
    defaults = json.loads(DEFAULTS_RESULT.read_text())["rows"] if DEFAULTS_RESULT.is_file() else []
    judge_opts = judge_fit() if args.steps is None else replace(judge_fit(), steps=args.steps, normal_refine_steps=args.steps)
    rows = []
    for name in (["given"] if args.given else args.captures.split(",")):
        first = AUTO_GEOMETRY.get(name, GEOMETRIES[0])  # photo consistency's choice at 256 px, the judge's incumbent
        order = [first] + [g for g in GEOMETRIES if g != first]
        folders = dict(zip(GEOMETRIES, map(Path, args.given))) if args.given else \
            {g: build_capture(name, sources[name], g, args.size, False) for g in order}
        caps = {g: read_capture(folders[g]) for g in order}
        views = {g: load_views(cap, "all") for g, cap in caps.items()}
        base = views[first]
        train_idx, _, _ = novel_split(caps[first], base, args.train_views)
        names = [base[k].name for k in train_idx]
        train = {g: [next(v for v in vs if v.name == n) for n in names] for g, vs in views.items()}
        t0 = time.perf_counter()
        verdict = judge_geometries(train, judge_opts, log=log)
        judge_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        fit_views(train[first], replace(judge_opts, steps=FitOptions().steps if args.steps is None else args.steps, normal_refine="off",
                                        spatial="off"))
        plain_s = time.perf_counter() - t0
        novel = {r["geometry"]: r["novel_dssim"] for r in defaults if r["capture"] == name and r["method"] == "defaults"}
        best = min(novel, key=novel.get) if len(novel) == len(GEOMETRIES) else None
        row = {"capture": name, "photo_consistency": first, "judge": verdict.chosen, "heldout_dssim": verdict.heldout_dssim,
               "held_views": verdict.held_views, "novel_dssim_defaults": novel, "best_downstream": best,
               "judge_seconds": judge_s, "plain_fit_seconds": plain_s}
        log(f"{name}: judge {verdict.chosen} ({verdict.why()}); downstream best {best}; plain fit {plain_s:.1f} s")
        rows.append(row)
    res = {"command": command_line("geometry_judge", argv if argv is not None else sys.argv[1:]), "machine": machine_info(),
           "judge_fit": {"steps": judge_opts.steps, "normal_refine_steps": judge_opts.normal_refine_steps}, "rows": rows}
    result, report = study_paths(RESULT, REPORT, args.out)
    result.write_text(json.dumps(res, indent=1, default=float))
    write_report(res, report)
    return 0


def write_report(res: dict, report: Path = REPORT) -> None:
    lines = ["# The geometry judge of `reconstruct --geometry auto`", "",
             "Question: when `--geometry auto` has built both the visual hull and the dense geometry, does fitting the DAM to each "
             "(the same training views, the same ones held out) choose the geometry on which `damcap fit` at its defaults does best "
             "on novel views, and at what cost against a plain fit?", "",
             f"Command: `{res['command']}`", "",
             machine_line(res["machine"]),
             "", f"Judge fit: fit's defaults without the prior, {res['judge_fit']['steps']} DAM steps, "
             f"{res['judge_fit']['normal_refine_steps']} normal-refinement steps. Novel-view DSSIM: `damcap fit` at its defaults, "
             "other camera rings (bench/real_defaults.md).", "",
             "| capture | photo consistency | judge | held-out DSSIM (hull / dense) | novel DSSIM of the defaults (hull / dense) | "
             "judge's geometry / best, novel | judge s | plain fit s | judge / plain |",
             "|---|---|---|---|---|---:|---:|---:|---:|"]
    for r in res["rows"]:
        h, n = r["heldout_dssim"], r["novel_dssim_defaults"]
        novel = f"{n.get('visual-hull', float('nan')):.4f} / {n.get('dense', float('nan')):.4f}" if n else "not measured"
        ratio = f"{n[r['judge']] / min(n.values()):.3f}" if r["judge"] in n else "not measured"
        lines.append(f"| {r['capture']} | {r['photo_consistency']} | {r['judge']} | {h['visual-hull']:.4f} / {h['dense']:.4f} | {novel} | "
                     f"{ratio} | {r['judge_seconds']:.0f} | {r['plain_fit_seconds']:.0f} | {r['judge_seconds'] / r['plain_fit_seconds']:.1f} |")
    report.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    sys.exit(main())
