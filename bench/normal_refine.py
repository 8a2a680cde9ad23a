"""Benchmark: does photometric normal refinement pay on a real object (issue 27)?

On a reconstructed capture of a real object (default: the cape, the realworld bench's cached dense
capture, 8 train views at 256 px): same-view (train) and novel-view (test) DSSIM of the fitted DAM,
with and without the spatial albedo factor (``fit --spatial albedo``), against the DAM whose
normals were refined by :func:`damcap.appearance.normal_refine.refine_normals` at several voxel
sizes, step counts and prior weights, the refinement with the DAM's weights trained as well
(``lr_dam``), and a control that continues the DAM's fit for as many steps with the normals left
alone (so the gain is the normals', not more steps). The refined model carries its field, so
every view, novel ones too, is rendered with the refined normals as ``damcap render`` draws them
(a surface point has one normal in every view).

Each row is also scored the way ``--normal-refine auto`` and ``--spatial auto`` decide: refined
(and the albedo estimated) without the training views the fit held out, then scored on those
views (``heldout``, ``heldout_albedo``), so the table shows whether the rules see what the novel
views see.

Run (from the repository root)::

    .venv/bin/python -m bench.normal_refine

It writes bench/results/normal_refine.json and bench/normal_refine.md (``--out DIR`` elsewhere).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from bench.common import BENCH, CACHE, RESULTS, command_line, log, machine_info

from damcap.appearance.fit import FitOptions, fit_dam, holdout_frames
from damcap.appearance.normal_refine import NormalRefineOptions, refine_normals
from damcap.appearance.spatial_fit import estimate_for, mean_dssim, training_footprint
from damcap.appearance.views import ViewData, load_views, positions_of, samples_of
from damcap.common.capture_folder import read_capture


def scores(model, train: list[ViewData], test: list[ViewData], albedo_voxel: float) -> dict:
    """Same / novel DSSIM of the DAM alone and with the spatial albedo estimated on ``train``."""
    with_albedo = model.with_spatial(estimate_for(model, train, albedo_voxel, FitOptions.spatial_prior))
    return {"same": mean_dssim(model, train), "novel": mean_dssim(model, test),
            "same_albedo": mean_dssim(with_albedo, train), "novel_albedo": mean_dssim(with_albedo, test)}


def heldout_scores(model, held: list[ViewData], rest: list[ViewData], albedo_voxel: float) -> dict:
    """DSSIM of the held-out training views ``held`` for a model refined on ``rest`` alone, without
    and with the albedo estimated on ``rest`` (what the 'auto' rules compare)."""
    with_albedo = model.with_spatial(estimate_for(model, rest, albedo_voxel, FitOptions.spatial_prior))
    return {"heldout": mean_dssim(model, held), "heldout_albedo": mean_dssim(with_albedo, held)}


def refined(base, views: list[ViewData], footprint: float, opts: NormalRefineOptions):
    """(the DAM refined on ``views`` with a new field carried by it, the field)."""
    model, nf = refine_normals(base, samples_of(views), positions_of(views), footprint, opts)
    return model.with_normal_field(nf), nf


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", type=Path, default=CACHE / "reconstruct" / "realworld" / "cape-8-256")
    ap.add_argument("--voxel-px", type=float, nargs="+", default=[1.0, 2.0, 4.0])
    ap.add_argument("--steps", type=int, default=NormalRefineOptions.steps)
    ap.add_argument("--lr-dam", type=float, nargs="*", default=[1e-4, 1e-3],
                    help="rows refining the DAM's weights too, at these learning rates (voxel: the first --voxel-px)")
    ap.add_argument("--step-variants", type=int, nargs="*", default=[200, 800],
                    help="rows refining for these step counts instead of --steps (voxel: the first --voxel-px)")
    ap.add_argument("--priors", type=float, nargs="*", default=[0.001, 0.1],
                    help="rows with these offset prior weights instead of the default (voxel: the first --voxel-px)")
    ap.add_argument("--fit-steps", type=int, default=None, help="fit steps (default: FitOptions' default)")
    ap.add_argument("--test-every", type=int, default=1, help="score every k-th test view (smoke runs: more)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    cap = read_capture(args.capture)
    train, test = load_views(cap, "train"), load_views(cap, "test")[::args.test_every]
    samples = samples_of(train)
    footprint = training_footprint(train)
    albedo_voxel = FitOptions.spatial_voxel_px * footprint
    fit_opts = FitOptions(checkpoint_every=0) if args.fit_steps is None else FitOptions(checkpoint_every=0, steps=args.fit_steps)
    held_idx = holdout_frames(len(train), fit_opts.holdout_views)
    held, rest = [train[k] for k in held_idx], [v for k, v in enumerate(train) if k not in held_idx]
    t = time.perf_counter()
    base = fit_dam(samples, fit_opts).model
    rows = [{"method": "DAM (fit)", "seconds": time.perf_counter() - t, **scores(base, train, test, albedo_voxel),
             **heldout_scores(base, held, rest, albedo_voxel)}]
    log(f"fit: {rows[-1]}")
    variants = [(f"control: DAM + {args.steps} more steps, normals kept", NormalRefineOptions(steps=args.steps, lr_offsets=0.0, lr_dam=1e-3))]
    variants += [(f"normals refined, voxel {vox:g} px", NormalRefineOptions(voxel_px=vox, steps=args.steps)) for vox in args.voxel_px]
    variants += [(f"normals and DAM weights refined (lr_dam {lr:g}), voxel {args.voxel_px[0]:g} px",
                  NormalRefineOptions(voxel_px=args.voxel_px[0], steps=args.steps, lr_dam=lr)) for lr in args.lr_dam]
    variants += [(f"normals refined, voxel {args.voxel_px[0]:g} px, {n} steps", NormalRefineOptions(voxel_px=args.voxel_px[0], steps=n))
                 for n in args.step_variants]
    variants += [(f"normals refined, voxel {args.voxel_px[0]:g} px, prior {w:g} (default {NormalRefineOptions.prior:g})",
                  NormalRefineOptions(voxel_px=args.voxel_px[0], steps=args.steps, prior=w)) for w in args.priors]
    for method, ropts in variants:
        t = time.perf_counter()
        model, nf = refined(base, train, footprint, ropts)
        row = {"method": method, "seconds": time.perf_counter() - t, "lr_dam": ropts.lr_dam, "steps": ropts.steps, "prior": ropts.prior}
        if ropts.lr_offsets > 0:
            tilt = torch.rad2deg(torch.atan(torch.from_numpy(nf.offset).norm(dim=-1)))
            row.update(corners=int(nf.keys.size), tilt_median_deg=float(tilt.median()), tilt_p90_deg=float(tilt.quantile(0.9)))
        row.update(scores(model, train, test, albedo_voxel))
        row.update(heldout_scores(refined(base, rest, footprint, ropts)[0], held, rest, albedo_voxel))
        rows.append(row)
        log(f"{method}: {row}")
    res = {"command": command_line("normal_refine", argv if argv is not None else __import__("sys").argv[1:]),
           "machine": machine_info(), "capture": str(args.capture), "train_views": len(train), "test_views": len(test),
           "footprint_world": footprint, "steps": args.steps,
           "heldout_views": [v.name for v in held], "rows": rows}
    out_json, out_md = (args.out or RESULTS) / "normal_refine.json", (args.out or BENCH) / "normal_refine.md"
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(res, indent=1))
    lines = ["# Photometric normal refinement on a real object (issue 27)", "", f"Command (from the repository root): `{res['command']}`", "",
             f"Machine: {res['machine']['cpu_model']} ({res['machine']['nproc']} cores), torch {res['machine']['torch']}; "
             f"{res['machine']['date_utc']}. Capture: `{args.capture.name}`, {len(train)} train views, {len(test)} test views; "
             f"{args.steps} refinement steps unless a row says otherwise.", "",
             "DSSIM (lower is better); `+ albedo` = with the spatial albedo factor (`fit --spatial albedo`) estimated afterwards. "
             f"*Held out*: refined and the albedo estimated without the training views the fit held out "
             f"({', '.join(res['heldout_views'])}), scored on them, as `--normal-refine auto` and `--spatial auto` decide. "
             "Rows other than the control and those naming lr_dam keep the DAM's weights as fitted (the default, lr_dam 0).", "",
             "| method | same view | novel view | same + albedo | novel + albedo | held out | held out + albedo | seconds | offset tilt median / p90 |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        tilt = f"{r['tilt_median_deg']:.1f} / {r['tilt_p90_deg']:.1f} deg" if "tilt_median_deg" in r else ""
        lines.append(f"| {r['method']} | {r['same']:.4f} | {r['novel']:.4f} | {r['same_albedo']:.4f} | {r['novel_albedo']:.4f} | "
                     f"{r['heldout']:.4f} | {r['heldout_albedo']:.4f} | {r['seconds']:.0f} | {tilt} |")
    out_md.write_text("\n".join(lines) + "\n")
    log(f"wrote {out_json} and {out_md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
