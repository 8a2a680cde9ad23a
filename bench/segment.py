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
* with ``--closed-form``: ``--materials auto`` on closed-form captures whose n is known (1 or 2).

Run (from the repository root; renders the corpus first when it is missing, ~5 min)::

    .venv/bin/python bench/segment.py --closed-form

Results: ``bench/results/segment.json`` and ``bench/segment.md``. Finished captures are kept in
the JSON and skipped on a rerun (``--fresh`` recomputes).
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import sys
import time
from dataclasses import asdict
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import CpuMeter, log, machine_info  # noqa: E402

from damcap.appearance.segment import SegmentOptions, choose_materials  # noqa: E402
from damcap.appearance.tables import PAPER, TableOptions, heldout_entries, segmentation_rows  # noqa: E402
from damcap.appearance.views import load_views  # noqa: E402
from damcap.common.atomic import write_json_atomic, write_text_atomic  # noqa: E402
from damcap.common.capture_folder import read_capture  # noqa: E402

BENCH = Path(__file__).resolve().parent
RESULTS = BENCH / "results"


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
    from damcap.reconstruct.closed_form import ClosedFormOptions, make_closed_form_capture

    out = []
    for name, true_n, kw in CLOSED_FORM:
        path = BENCH / ".cache" / "segment_closed_form" / name
        if not (path / "transforms.json").is_file():
            make_closed_form_capture(path, ClosedFormOptions(views=12, train_views=5, dtype="float", **kw))
        cap = read_capture(path)
        with CpuMeter() as meter:
            choice = choose_materials(load_views(cap, "train"), load_views(cap, "test"), SegmentOptions(), max_materials=3, restarts=restarts)
        out.append({"name": name, "true_n": true_n, "chosen": choice.materials, "reason": choice.reason, "wall_s": meter.wall,
                    "curve": [{k: c[k] for k in ("materials", "heldout_dssim", "restarts", "shares")} for c in choice.curve]})
        log(f"closed form {name}: true n {true_n}, chose {choice.materials} ({choice.reason})")
    return out


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


def write_markdown(res: dict, path: Path) -> None:
    s = res["summary"]
    L = ["# Joint material estimation and segmentation (issue 8)", "",
         f"Command: `{res['command']}`", "", f"Machine: {res['machine']['cpu_model']}, {res['machine']['nproc']} cores, "
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
    if s.get("auto_found_true_n"):
        L += [f"`--materials auto` found the true n = 3 on {s['auto_found_true_n']} captures "
              f"(margin {res['auto_margin']:.0%}, {res['auto_restarts']} restarts per n).", ""]
    write_text_atomic(path, "\n".join(L) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--corpus", type=Path, default=BENCH / ".cache" / "synth_segment")
    ap.add_argument("--no-auto", action="store_true", help="skip --materials auto (the slowest part)")
    ap.add_argument("--restarts", type=int, default=2, help="--materials auto: runs per n")
    ap.add_argument("--fresh", action="store_true")
    ap.add_argument("--closed-form", action="store_true", help="also --materials auto on closed-form captures of known n")
    args = ap.parse_args()
    torch.set_num_threads(2)
    out_json = RESULTS / "segment.json"
    old, old_closed_form = {}, None
    if out_json.is_file() and not args.fresh:
        previous = json.loads(out_json.read_text())
        old = {r["name"]: r for r in previous.get("per_capture", [])}
        old_closed_form = previous.get("closed_form")
    opts = TableOptions()
    res = {"command": "python bench/segment.py " + " ".join(shlex.quote(a) for a in sys.argv[1:]), "machine": machine_info(),
           "segment_options": asdict(opts.segment), "kmeans_steps": opts.kmeans_steps, "auto_margin": 0.1, "auto_restarts": args.restarts,
           "per_capture": []}
    if not (args.corpus / "corpus.json").is_file() or any(e.get("status") != "done" for e in json.loads((args.corpus / "corpus.json").read_text())["captures"]):
        from damcap.cli.synth_cmds import default_data_dir
        from damcap.reconstruct.synth_set import make_corpus

        log(f"rendering the segment preset into {args.corpus} (resumable)")
        make_corpus(args.corpus, "segment", default_data_dir())
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
    write_json_atomic(out_json, res)
    write_markdown(res, BENCH / "segment.md")
    log(f"wrote {out_json} and {BENCH / 'segment.md'}")


if __name__ == "__main__":
    main()
