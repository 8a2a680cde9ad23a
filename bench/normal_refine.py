"""Benchmark: does photometric normal refinement pay on a real object (issue 27)?

On a reconstructed capture of a real object (default: the cape, the realworld bench's cached dense
capture, 8 train views at 256 px): same-view (train) and novel-view (test) DSSIM of the fitted DAM,
with and without the spatial albedo factor (``fit --spatial albedo``), against the DAM whose
normals were refined by :func:`damcap.appearance.normal_refine.refine_normals` at several voxel
sizes, and a control that continues the DAM's fit for as many steps with the normals left alone
(so the gain is the normals', not more steps). Novel views get the refined normals through the
same field (a surface point has one normal in every view).

Run (from the repository root)::

    .venv/bin/python -m bench.normal_refine

It writes bench/results/normal_refine.json and bench/normal_refine.md (``--out DIR`` elsewhere).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import torch

from bench.common import BENCH, CACHE, RESULTS, command_line, log, machine_info

from damcap.appearance.fit import FitOptions, fit_dam
from damcap.appearance.normal_field import refined_normals
from damcap.appearance.normal_refine import NormalRefineOptions, refine_normals
from damcap.appearance.spatial_fit import estimate_for, mean_dssim, training_footprint
from damcap.appearance.views import ViewData, load_views, positions_of, samples_of
from damcap.common.capture_folder import read_capture


def with_normals(views: list[ViewData], nf) -> list[ViewData]:
    """The views with every covered pixel's normal refined by the field ``nf``."""
    out = []
    for v in views:
        d = v.data
        cov = d.coverage > 0
        n = d.normal_world.copy()
        n[cov] = refined_normals(nf, d.normal_world[cov], d.position_world[cov])
        out.append(ViewData(v.name, dataclasses.replace(d, normal_world=n), v.world_from_cam))
    return out


def scores(model, train: list[ViewData], test: list[ViewData], albedo_voxel: float) -> dict:
    """Same / novel DSSIM of the DAM alone and with the spatial albedo estimated on ``train``."""
    with_albedo = model.with_spatial(estimate_for(model, train, albedo_voxel, FitOptions.spatial_prior))
    return {"same": mean_dssim(model, train), "novel": mean_dssim(model, test),
            "same_albedo": mean_dssim(with_albedo, train), "novel_albedo": mean_dssim(with_albedo, test)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", type=Path, default=CACHE / "reconstruct" / "realworld" / "cape-8-256")
    ap.add_argument("--voxel-px", type=float, nargs="+", default=[1.0, 2.0, 4.0])
    ap.add_argument("--steps", type=int, default=NormalRefineOptions.steps)
    ap.add_argument("--fit-steps", type=int, default=None, help="fit steps (default: FitOptions' default)")
    ap.add_argument("--test-every", type=int, default=1, help="score every k-th test view (smoke runs: more)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    cap = read_capture(args.capture)
    train, test = load_views(cap, "train"), load_views(cap, "test")[::args.test_every]
    samples, points = samples_of(train), positions_of(train)
    footprint = training_footprint(train)
    albedo_voxel = FitOptions.spatial_voxel_px * footprint
    fit_opts = FitOptions(checkpoint_every=0) if args.fit_steps is None else FitOptions(checkpoint_every=0, steps=args.fit_steps)
    t = time.perf_counter()
    base = fit_dam(samples, fit_opts).model
    rows = [{"method": "DAM (fit)", "seconds": time.perf_counter() - t, **scores(base, train, test, albedo_voxel)}]
    log(f"fit: {rows[-1]}")
    t = time.perf_counter()
    control, _ = refine_normals(base, samples, points, footprint, NormalRefineOptions(steps=args.steps, lr_offsets=0.0))
    rows.append({"method": f"control: DAM + {args.steps} more steps, normals kept", "seconds": time.perf_counter() - t,
                 **scores(control, train, test, albedo_voxel)})
    log(f"control: {rows[-1]}")
    for vox in args.voxel_px:
        t = time.perf_counter()
        model, nf = refine_normals(base, samples, points, footprint, NormalRefineOptions(voxel_px=vox, steps=args.steps))
        secs = time.perf_counter() - t
        tilt = torch.rad2deg(torch.atan(torch.from_numpy(nf.offset).norm(dim=-1)))
        rows.append({"method": f"normals refined, voxel {vox:g} px", "seconds": secs, "corners": int(nf.keys.size),
                     "tilt_median_deg": float(tilt.median()), "tilt_p90_deg": float(tilt.quantile(0.9)),
                     **scores(model, with_normals(train, nf), with_normals(test, nf), albedo_voxel)})
        log(f"voxel {vox}: {rows[-1]}")
    res = {"command": command_line("normal_refine", argv if argv is not None else __import__("sys").argv[1:]),
           "machine": machine_info(), "capture": str(args.capture), "train_views": len(train), "test_views": len(test),
           "footprint_world": footprint, "steps": args.steps, "rows": rows}
    out_json, out_md = (args.out or RESULTS) / "normal_refine.json", (args.out or BENCH) / "normal_refine.md"
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(res, indent=1))
    lines = ["# Photometric normal refinement on a real object (issue 27)", "", f"Command (from the repository root): `{res['command']}`", "",
             f"Machine: {res['machine']['cpu_model']} ({res['machine']['nproc']} cores), torch {res['machine']['torch']}; "
             f"{res['machine']['date_utc']}. Capture: `{args.capture.name}`, {len(train)} train views, {len(test)} test views; "
             f"{args.steps} refinement steps.", "",
             "DSSIM (lower is better); `+ albedo` = with the spatial albedo factor (`fit --spatial albedo`) estimated afterwards.", "",
             "| method | same view | novel view | same + albedo | novel + albedo | seconds | offset tilt median / p90 |",
             "|---|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        tilt = f"{r['tilt_median_deg']:.1f} / {r['tilt_p90_deg']:.1f} deg" if "tilt_median_deg" in r else ""
        lines.append(f"| {r['method']} | {r['same']:.4f} | {r['novel']:.4f} | {r['same_albedo']:.4f} | {r['novel_albedo']:.4f} | "
                     f"{r['seconds']:.0f} | {tilt} |")
    out_md.write_text("\n".join(lines) + "\n")
    log(f"wrote {out_json} and {out_md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
