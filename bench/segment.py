"""Benchmark: joint material estimation and segmentation (issue 8) on held-out three-material captures.

The captures are the ``segment`` preset of ``damcap synth-set`` (both held-out objects under the
held-out environment map and held-out point lights, three materials, 128 px, 32 views, 10 train).
Per capture:

* the paper's Table 1 segmentation rows: novel-view DSSIM of ours (n = 3 DAMs + Psi) vs k-means
  in RGB + normal space with one DAM per cluster; novel views with the true weights of the new
  view (the paper's protocol) and with weights carried from the geometry (no ground truth).
  Target: ours <= 0.9x k-means;
* segmentation quality: mean IoU against the true weights (labels matched), on the training
  frames (Psi's weights) and on the test frames (weights carried from the geometry). Target >= 0.85;
* ``--materials auto``: the n it chooses and the held-out curve behind it (how often it finds 3);
* time per capture on this CPU;
* with ``--closed-form``: ``--materials auto`` on closed-form captures whose n is known (1 or 2);
* with ``--dev``: the development set where the defaults are chosen (``segment-dev`` preset:
  training objects under training illuminations, never the held-out captures above): mean IoU of
  the default options next to each ablation (one knob back to its alternative).

Run (from the repository root; renders the corpus first when it is missing, ~5 min)::

    .venv/bin/python -m bench.segment --closed-form --dev --seed-study

Results: ``bench/results/segment.json`` and ``bench/segment.md`` (``--out DIR``: both in DIR).
Finished captures are kept in the JSON and skipped on a rerun (``--fresh`` recomputes).
``--steps``, ``--init-steps`` and ``--kmeans-steps`` shorten the fits (smoke runs).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import torch

from bench.common import BENCH, CACHE, RESULTS, CpuMeter, command_line, log, machine_info, shared_data_dir

from damcap.appearance.segment.choose import choose_materials
from damcap.appearance.segment.options import SegmentOptions
from damcap.appearance.segment.train import segment_materials
from damcap.appearance.views import load_views
from damcap.common.atomic import write_json_atomic, write_text_atomic
from damcap.common.capture_folder import read_capture
from damcap.paper.tables import PAPER, TableOptions, heldout_entries, mean_iou, segmentation_rows


def bench_capture(path: Path, entry: dict, opts: TableOptions, auto: bool, restarts: int) -> dict:
    cap = read_capture(path)
    train, test = load_views(cap, "train"), load_views(cap, "test")
    with CpuMeter() as meter:
        scores, extra, _ = segmentation_rows(train, test, opts, materials=entry["materials"])
    rec = {"name": entry["name"], "light_kind": entry["light_kind"], "materials": entry["materials"],
           "dssim": {m: {v: s.mean for v, s in views.items()} for m, views in scores.items()},
           **extra, "wall_s": meter.wall, "others_cpu_frac": meter.foreign_frac}
    log(f"{entry['name']}: novel ours {rec['dssim']['ours (true weights)']['novel']:.4f} vs k-means "
        f"{rec['dssim']['k-means (true weights)']['novel']:.4f}; IoU ours {extra['iou_train']['ours']:.3f} "
        f"(test, carried {extra['iou_test_carried']['ours']:.3f}), k-means {extra['iou_train']['k-means']:.3f}")
    if auto:
        with CpuMeter() as meter:
            choice = choose_materials(train, test, opts.segment, restarts=restarts)
        rec["auto"] = {"chosen": choice.materials, "reason": choice.reason, "curve": choice.curve, "wall_s": meter.wall,
                       "others_cpu_frac": meter.foreign_frac, "restarts": restarts}
        log(f"{entry['name']}: --materials auto chose {choice.materials} ({choice.reason}) in {meter.wall:.0f} s")
    return rec


#: closed-form captures for --materials auto: (name, true n, ClosedFormOptions keywords)
CLOSED_FORM = [
    ("torus_env_m1_s2", 1, dict(shape="torus", light="env", env_grid=12, materials=1, resolution=40, seed=2)),
    ("torus_env_m1_s5", 1, dict(shape="torus", light="env", env_grid=12, materials=1, resolution=40, seed=5)),
    ("torus_dir_m1_s0", 1, dict(shape="torus", light="directional", materials=1, resolution=40, seed=0)),
    ("sphere_dir_m1_s0", 1, dict(shape="sphere", light="directional", materials=1, resolution=32, seed=0)),
    ("torus_env_m2_s2", 2, dict(shape="torus", light="env", env_grid=12, materials=2, resolution=40, seed=2)),
    ("torus_env_m2_s5", 2, dict(shape="torus", light="env", env_grid=12, materials=2, resolution=40, seed=5)),
    ("sphere_env_m2_s0", 2, dict(shape="sphere", light="env", env_grid=12, materials=2, resolution=48, seed=0)),
    ("sphere_dir_m2_s0", 2, dict(shape="sphere", light="directional", materials=2, resolution=48, seed=0)),
]


def stage_closed_form(restarts: int) -> list[dict]:
    """--materials auto (default options) on closed-form captures of known n: 12 views, 5 train."""
    from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

    out = []
    for name, true_n, kw in CLOSED_FORM:
        path = CACHE / "segment_closed_form" / name
        if not (path / "transforms.json").is_file():
            make_closed_form_capture(path, ClosedFormOptions(views=12, train_views=5, dtype="float", **kw))
        cap = read_capture(path)
        with CpuMeter() as meter:
            choice = choose_materials(load_views(cap, "train"), load_views(cap, "test"), SegmentOptions(), max_materials=3, restarts=restarts)
        out.append({"name": name, "true_n": true_n, "chosen": choice.materials, "reason": choice.reason, "wall_s": meter.wall,
                    "curve": [{k: c[k] for k in ("materials", "heldout_dssim", "restarts", "shares")} for c in choice.curve]})
        log(f"closed form {name}: true n {true_n}, chose {choice.materials} ({choice.reason})")
    return out


#: the development-set ablations: name -> the options that differ from the default
DEV_VARIANTS = {"default": {}, "init_colour=pixel (each pixel's own colour)": {"init_colour": "pixel"},
                "colour_floor=0.02 (bright pixels only)": {"colour_floor": 0.02},
                "illumination_degree=0 (plain chromaticity k-means)": {"illumination_degree": 0},
                "prior_weight=0 (the paper's cost alone)": {"prior_weight": 0.0},
                "psi_resolution=64 (faster)": {"psi_resolution": 64}}


def ensure_corpus(folder: Path, preset: str) -> None:
    """Render a synth-set preset into folder unless every capture is there (resumable)."""
    corpus = folder / "corpus.json"
    if corpus.is_file() and all(e.get("status") == "done" for e in json.loads(corpus.read_text())["captures"]):
        return
    from damcap.synth.corpus import make_corpus

    log(f"rendering the {preset} preset into {folder} (resumable)")
    make_corpus(folder, preset, shared_data_dir())


#: the held-out seed study: this session's defaults next to the previous ones, over fit seeds
SEED_VARIANTS = {"default": {}, "previous default (init_colour=pixel, colour_floor=0.02)": {"init_colour": "pixel", "colour_floor": 0.02}}


def iou_study(captures: list[tuple[Path, dict]], variants: dict[str, dict], seeds: tuple[int, ...], label: str) -> dict:
    """Mean IoU on the training frames per capture and options variant, averaged over seeds."""
    rows = []
    for path, e in captures:
        train = load_views(read_capture(path), "train")
        row: dict = {"name": e["name"], "light_kind": e["light_kind"], "seeds": list(seeds), "iou_train": {}, "iou_train_lit": {},
                     "iou_train_per_seed": {}, "wall_s": {}}
        for name, change in variants.items():
            ious, lits, walls = [], [], []
            for seed in seeds:
                opts = SegmentOptions(**{**asdict(SegmentOptions()), "materials": e["materials"], "seed": seed, **change})
                t = time.perf_counter()
                model = segment_materials(train, opts)
                walls.append(time.perf_counter() - t)
                ious.append(mean_iou(model, train, carried=False))
                lits.append(mean_iou(model, train, carried=False, lit_only=True))
            row["iou_train"][name], row["iou_train_lit"][name] = statistics.fmean(ious), statistics.fmean(lits)
            row["iou_train_per_seed"][name], row["wall_s"][name] = ious, statistics.fmean(walls)
        log(f"{label} {e['name']}: " + ", ".join(f"{k.split(' ')[0]} {v:.3f}" for k, v in row["iou_train"].items()))
        rows.append(row)
    mean = {k: statistics.fmean(r["iou_train"][k] for r in rows) for k in variants}
    mean_lit = {k: statistics.fmean(r["iou_train_lit"][k] for r in rows) for k in variants}
    return {"variants": variants, "seeds": list(seeds), "per_capture": rows, "mean_iou_train": mean, "mean_iou_train_lit": mean_lit}


def stage_dev(corpus: Path) -> dict:
    """Mean IoU on the training frames of the segment-dev captures, default vs each ablation."""
    ensure_corpus(corpus, "segment-dev")
    entries = json.loads((corpus / "corpus.json").read_text())["captures"]
    return {"corpus": str(corpus), **iou_study([(corpus / e["path"], e) for e in entries], DEV_VARIANTS, (0,), "dev")}


def summarise(per_capture: list[dict]) -> dict:
    out = {}
    for kind in ("point", "env"):
        rows = [r for r in per_capture if r["light_kind"] == kind]
        if not rows:
            continue
        cell = {m: statistics.fmean(r["dssim"][m]["novel"] for r in rows) for m in rows[0]["dssim"]}
        cell["ours/k-means (true weights)"] = cell["ours (true weights)"] / cell["k-means (true weights)"]
        cell["ours/k-means (estimated weights)"] = cell["ours (estimated weights)"] / cell["k-means (estimated weights)"]
        cell["captures"] = len(rows)
        out[kind] = cell
    ious = [r["iou_train"]["ours"] for r in per_capture]
    out["iou_train_ours_mean"] = statistics.fmean(ious) if ious else None
    out["iou_test_carried_ours_mean"] = statistics.fmean(r["iou_test_carried"]["ours"] for r in per_capture) if per_capture else None
    out["iou_train_lit_ours_mean"] = statistics.fmean(r["iou_train_lit"]["ours"] for r in per_capture) if per_capture else None
    out["iou_train_kmeans_mean"] = statistics.fmean(r["iou_train"]["k-means"] for r in per_capture) if per_capture else None
    autos = [r["auto"]["chosen"] == r["materials"] for r in per_capture if "auto" in r]
    out["auto_found_true_n"] = f"{sum(autos)}/{len(autos)}" if autos else None
    return out


def study_table(d: dict) -> list[str]:
    """Markdown rows of an :func:`iou_study` result."""
    names = list(d["variants"])
    L = ["| capture | light | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for r in d["per_capture"]:
        L.append(f"| {r['name']} | {r['light_kind']} | " + " | ".join(f"{r['iou_train'][k]:.3f} / {r['iou_train_lit'][k]:.3f}" for k in names) + " |")
    L.append("| **mean** | | " + " | ".join(f"**{d['mean_iou_train'][k]:.3f}** / {d['mean_iou_train_lit'][k]:.3f}" for k in names) + " |")
    L.append("| time per run (mean, s) | | " + " | ".join(f"{statistics.fmean(r['wall_s'][k] for r in d['per_capture']):.0f}" for k in names) + " |")
    return L + [""]


def write_markdown(res: dict, path: Path) -> None:
    s = res["summary"]
    L = ["# Joint material estimation and segmentation (issue 8)", "",
         "Commands whose results this report holds (a later one reuses the earlier ones' parts it does not redo): "
         + "; ".join(f"`{c}`" for c in res.get("commands", [res["command"]])), "", f"Machine: {res['machine']['cpu_model']}, {res['machine']['nproc']} cores, "
         f"torch {res['machine']['torch']} ({res['machine']['torch_threads']} threads), {res['machine']['date_utc']}.", "",
         "Held-out synthetic captures with three materials (`damcap synth-set --preset segment`), 128 px, 10 train / 22 test views.", "",
         "## The paper's Table 1 segmentation rows (novel-view DSSIM, lower is better)", "",
         "| light | ours (true weights) | k-means (true weights) | ratio | paper (ours vs k-means) | ours (carried weights) | k-means (carried) | ratio |",
         "|---|---|---|---|---|---|---|---|"]
    for kind in ("point", "env"):
        if kind not in s:
            continue
        c, p = s[kind], PAPER["segmentation"][kind]
        L.append(f"| {kind} ({c['captures']}) | {c['ours (true weights)']:.4f} | {c['k-means (true weights)']:.4f} | "
                 f"**{c['ours/k-means (true weights)']:.3f}** | {p['ours novel']} vs {p['k-means novel']} "
                 f"({p['ours novel'] / p['k-means novel']:.3f}) | {c['ours (estimated weights)']:.4f} | "
                 f"{c['k-means (estimated weights)']:.4f} | {c['ours/k-means (estimated weights)']:.3f} |")
    L += ["", "Target: ours <= 0.9x k-means.", "", "## Per capture", "",
          "| capture | light | ours novel | k-means novel | ours IoU train (Psi) | ours IoU train, lit pixels | ours IoU test (carried) | k-means IoU train | time ours + k-means | auto n (curve) |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["per_capture"]:
        auto = "-"
        if "auto" in r:
            curve = ", ".join(f"{c['materials']}: {c['heldout_dssim']:.4f}" for c in r["auto"]["curve"])
            auto = f"{r['auto']['chosen']} ({curve}; {r['auto']['wall_s']:.0f} s)"
        L.append(f"| {r['name']} | {r['light_kind']} | {r['dssim']['ours (true weights)']['novel']:.4f} | "
                 f"{r['dssim']['k-means (true weights)']['novel']:.4f} | {r['iou_train']['ours']:.3f} | {r['iou_train_lit']['ours']:.3f} | {r['iou_test_carried']['ours']:.3f} | "
                 f"{r['iou_train']['k-means']:.3f} | {r['seconds']['ours']:.0f} + {r['seconds']['k-means']:.0f} s | {auto} |")
    L += ["", f"Mean IoU, ours: {s['iou_train_ours_mean']:.3f} on training frames (target >= 0.85), "
          f"{s['iou_train_lit_ours_mean']:.3f} on the training frames' lit pixels, "
          f"{s['iou_test_carried_ours_mean']:.3f} on test frames (weights carried from the geometry); "
          f"k-means: {s['iou_train_kmeans_mean']:.3f}.", ""]
    if res.get("closed_form"):
        L += ["## `--materials auto` on closed-form captures of known n (12 views, 5 train, default options)", "",
              "| capture | true n | chosen | held-out DSSIM on the seen surface per n (best of the restarts) | reason |", "|---|---|---|---|---|"]
        for r in res["closed_form"]:
            curve = ", ".join(f"{c['materials']}: {c['heldout_dssim']:.4f}" for c in r["curve"])
            L.append(f"| {r['name']} | {r['true_n']} | {r['chosen']} | {curve} | {r['reason']} |")
        L.append("")
    if res.get("dev"):
        L += ["## Development set: where the defaults were chosen", "",
              "`damcap synth-set --preset segment-dev`: six three-material captures of training objects under training "
              "illuminations (none of the held-out captures above). Mean IoU on the training frames (Psi's weights), "
              "all covered pixels / lit pixels; each column turns one default back to its alternative (seed 0).", ""]
        L += study_table(res["dev"])
    if res.get("seed_study"):
        L += ["## Held-out captures over fit seeds (a measurement, not used to choose anything)", "",
              f"Mean IoU on the training frames, all covered pixels / lit pixels, averaged over seeds {res['seed_study']['seeds']} "
              "(per-seed values in the JSON). The held-out table above is seed 0 of the default.", ""]
        L += study_table(res["seed_study"])
    if s.get("auto_found_true_n"):
        L += [f"`--materials auto` found the true n = 3 on {s['auto_found_true_n']} captures "
              f"(margin {res['auto_margin']:.0%}, {res['auto_restarts']} restarts per n).", ""]
    write_text_atomic(path, "\n".join(L) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--corpus", type=Path, default=CACHE / "synth_segment")
    ap.add_argument("--no-auto", action="store_true", help="skip --materials auto (the slowest part)")
    ap.add_argument("--restarts", type=int, default=2, help="--materials auto: runs per n")
    ap.add_argument("--fresh", action="store_true")
    ap.add_argument("--closed-form", action="store_true", help="also --materials auto on closed-form captures of known n")
    ap.add_argument("--dev", action="store_true", help="also the development set (segment-dev preset): default options vs ablations")
    ap.add_argument("--dev-corpus", type=Path, default=CACHE / "synth_segment_dev")
    ap.add_argument("--seed-study", action="store_true", help="also the held-out captures' IoU over 3 fit seeds, default vs the previous default")
    ap.add_argument("--steps", type=int, default=None, help="our segmentation's fit steps (default: SegmentOptions' default)")
    ap.add_argument("--init-steps", type=int, default=None, help="our segmentation's initial steps (default: SegmentOptions' default)")
    ap.add_argument("--kmeans-steps", type=int, default=None, help="fit steps of each k-means cluster's DAM (default: TableOptions' default)")
    ap.add_argument("--out", type=Path, default=None, help="write segment.json and segment.md here instead of bench/results/ and bench/")
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    out_json = RESULTS / "segment.json" if args.out is None else args.out / "segment.json"
    out_md = BENCH / "segment.md" if args.out is None else args.out / "segment.md"
    old, old_closed_form, old_dev, old_seed_study = {}, None, None, None
    previous_doc = json.loads(out_json.read_text()) if out_json.is_file() else None
    if previous_doc and not args.fresh:
        old = {r["name"]: r for r in previous_doc.get("per_capture", [])}
        old_closed_form = previous_doc.get("closed_form")
        old_dev = previous_doc.get("dev")
        old_seed_study = previous_doc.get("seed_study")
    opts = TableOptions()
    changed = {k: v for k, v in (("steps", args.steps), ("init_steps", args.init_steps)) if v is not None}
    opts = replace(opts, segment=replace(opts.segment, **changed),
                   kmeans_steps=opts.kmeans_steps if args.kmeans_steps is None else args.kmeans_steps)
    res = {"command": command_line("segment", sys.argv[1:] if argv is None else argv), "machine": machine_info(),
           "segment_options": asdict(opts.segment), "kmeans_steps": opts.kmeans_steps, "auto_margin": 0.1, "auto_restarts": args.restarts,
           "per_capture": []}
    res["commands"] = ([] if args.fresh or not previous_doc else previous_doc.get("commands", [previous_doc["command"]])) + [res["command"]]
    ensure_corpus(args.corpus, "segment")
    for path, entry in heldout_entries([args.corpus]):
        if entry["materials"] < 2:
            continue
        if entry["name"] in old and ("auto" in old[entry["name"]] or args.no_auto):
            res["per_capture"].append(old[entry["name"]])
            continue
        t = time.perf_counter()
        res["per_capture"].append(bench_capture(path, entry, opts, not args.no_auto, args.restarts))
        log(f"{entry['name']}: {time.perf_counter() - t:.0f} s")
        res["summary"] = summarise(res["per_capture"])
        write_json_atomic(out_json, res)
    res["summary"] = summarise(res["per_capture"])
    if args.closed_form:
        res["closed_form"] = stage_closed_form(args.restarts)
    elif old_closed_form:
        res["closed_form"] = old_closed_form
    if args.dev:
        res["dev"] = stage_dev(args.dev_corpus)
    elif old_dev:
        res["dev"] = old_dev
    if args.seed_study:
        res["seed_study"] = iou_study([(p, e) for p, e in heldout_entries([args.corpus]) if e["materials"] >= 2], SEED_VARIANTS, (0, 1, 2), "seeds")
    elif old_seed_study:
        res["seed_study"] = old_seed_study
    write_json_atomic(out_json, res)
    write_markdown(res, out_md)
    log(f"wrote {out_json} and {out_md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
