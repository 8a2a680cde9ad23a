"""Benchmark: the predictor on captures unlike its training set (issue 28).

Novel-view DSSIM, side by side in one run, on held-out captures of kinds the predictors never
saw: closed-form spheres and blobs (``damcap closed-form``) under a directional light and under
the analytic sky, the held-out Mitsuba captures of a ``damcap synth-set`` corpus (shadows,
interreflection, measured environment maps), and the real cape (the realworld bench's cached
capture). Per capture: RM++, ``damcap fit`` (default options, timed), each predictor alone, with
its output layer solved on the train pixels (timed; ``--readout`` iteration counts,
``--readout-samples``), then its first and output layers solved together (timed; ``--joint``
iteration counts, ``--joint-prior``; with predict's own counts, ``damcap predict`` without
refinement) and each refined 100 / 300 steps (timed, as ``damcap predict --refine-steps K``; also at the learning
rate that was the default before 2026-11-27, ``--compare-lr``) and with ``--refine-steps auto``. With
``--snapshots``: predict alone for each snapshot of the predictors' training runs (how
out-of-distribution error falls with training compute, counted over warm starts), also with its output
layer solved (the first ``--readout`` count). With ``--refine-from-readout``: each predictor refined
100 / 300 steps from its solved output layer as well (rows ``NAME readout + K``).

Targets (issue 28): predict alone at most 1.15x the fit's DSSIM on every kind and never worse
than RM++; predict + refinement within 2 s at most 1.0x the fit; prediction under 100 ms on CPU.

Run (from the repository root)::

    .venv/bin/python -m bench.hyper_ood --predictors appearance/hyper/predictors/dam-predictor-v1.safetensors \\
        appearance/hyper/predictors/dam-predictor-v10.safetensors

(a retired predictor, e.g. v3, from the history first: ``git show d796965:appearance/hyper/predictors/dam-predictor-v3.safetensors
> v3.safetensors``; bench/train_predictor.sh holds the recipes).

It writes bench/results/hyper_ood.json and bench/hyper_ood.md (``--out DIR`` elsewhere, ``--tag T``:
hyper_ood_T.*). Rewriting a report keeps everything from its :data:`HISTORY_MARK` line on (the
study's history in bench/hyper_ood.md); a ``--tag`` study's report is merged into that history
by hand (bench/README.md indexes the reports).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from pathlib import Path

import torch

from bench.common import BENCH, CACHE, RESULTS, command_line, log, machine_info

from damcap.appearance.evaluate import evaluate_split
from damcap.appearance.fit import FitOptions, fit_dam, refine_dam
from damcap.appearance.hyper.file import load_predictor
from damcap.appearance.hyper.orientation import light_up_world
from damcap.appearance.hyper.model import input_images, predict_dam, predictor_inputs
from damcap.appearance.hyper.predict import PredictOptions, refine_auto
from damcap.appearance.readout import solve_first_and_output_layers, solve_output_layer
from damcap.appearance.views import load_views, samples_of
from damcap.common.capture_folder import read_capture
from damcap.paper.tables import heldout_entries
from damcap.synth.closed_form import ClosedFormOptions, directional_lighting, make_closed_form_capture

CLOSED_FORM = [("sphere", "directional", 3), ("sphere", "env", 3), ("blob", "directional", 5), ("blob", "env", 5),
               ("blob", "directional", 11), ("sphere", "env", 12)]
"""(shape, light, seed) of the closed-form captures: 10 train / 22 test views at 128 px, the issue's setting"""

CLOSED_FORM_CHECK = [("sphere", "directional", 4), ("sphere", "directional", 6), ("blob", "directional", 6),
                     ("blob", "directional", 13), ("sphere", "env", 5), ("blob", "env", 7)]
"""other seeds of the same kinds (``--closed-form-set check``): a second look at options chosen on the first set"""


def closed_form_captures(cache: Path, count: int = len(CLOSED_FORM), resolution: int = 128,
                         which: list[tuple[str, str, int]] = CLOSED_FORM) -> list[tuple[str, Path]]:
    """(kind, folder) of the first ``count`` closed-form captures of ``which``, rendered once into ``cache``."""
    out = []
    for shape, light, seed in which[:count]:
        path = cache / f"{shape}-{light}-s{seed}" if resolution == 128 else cache / f"{shape}-{light}-s{seed}-{resolution}px"
        if not (path / "transforms.json").exists():
            make_closed_form_capture(path, ClosedFormOptions(shape=shape, light=light, views=32, train_views=10,
                                                             resolution=resolution, seed=seed))
        out.append((f"closed-form {shape}, {'distant light' if light == 'directional' else 'environment'}", path))
    return out


def refine_runs(name: str, refine_steps: list[int], compare_lr: tuple[float, ...], auto: bool) -> list[tuple[str, int | None, float]]:
    """A predictor's refined rows, in the tables' order: (row name, steps K or None for
    ``--refine-steps auto``, learning rate).

    >>> [r[0] for r in refine_runs("v1", [100], (0.003,), True)]
    ['v1 + 100', 'v1 + 100 (lr 0.003)', 'v1 + auto']
    """
    lr0 = PredictOptions.refine_learning_rate
    out = []
    for k in refine_steps:
        out += [(f"{name} + {k}", k, lr0)] + [(f"{name} + {k} (lr {lr:g})", k, lr) for lr in compare_lr]
    return out + ([(f"{name} + auto", None, lr0)] if auto else [])


def readout_runs(name: str, iterations: list[int], samples: list[int]) -> list[tuple[str, int, int]]:
    """A predictor's rows with its output layer solved (``damcap predict`` without refinement):
    (row name, iterations, samples). Rows at predict's own sample count are named by the
    iterations alone.

    >>> [r[0] for r in readout_runs("v1", [3], [PredictOptions.readout_samples, 16384])]
    ['v1 readout 3', 'v1 readout 3 (16384 px)']
    """
    return [(f"{name} readout {k}" + ("" if n == PredictOptions.readout_samples else f" ({n} px)"), k, n)
            for k in iterations for n in samples]


def first_readout_key(name: str, readout: tuple[list[int], list[int]]) -> str | None:
    """The row of a predictor or snapshot with its output layer solved at the first ``--readout``
    count and sample size (a snapshot's one solved row; where the joint rows start), or None
    without ``--readout``.

    >>> first_readout_key("v5.step200", ([3, 5], [4096])), first_readout_key("v5.step200", ([], [4096]))
    ('v5.step200 readout 3', None)
    """
    return readout_runs(name, readout[0][:1], readout[1][:1])[0][0] if readout[0] else None


def joint_runs(name: str, readout: tuple[list[int], list[int]], iterations: list[int], priors: list[float]) -> list[tuple[str, int, float]]:
    """A predictor's rows with its first and output layers then solved together (``damcap predict``'s
    default without refinement), each from its first ``--readout`` row: (row name, iterations,
    prior). Rows at predict's own prior are named by the iterations alone; none without ``--readout``.

    >>> [r[0] for r in joint_runs("v10", ([3], [4096]), [5], [PredictOptions.joint_prior, 0.0])]
    ['v10 readout 3 + joint 5', 'v10 readout 3 + joint 5 (prior 0)']
    """
    base = first_readout_key(name, readout)
    if base is None:
        return []
    return [(f"{base} + joint {j}" + ("" if p == PredictOptions.joint_prior else f" (prior {p:g})"), j, p)
            for j in iterations for p in priors]


def solved_refine_runs(name: str, refine_steps: list[int]) -> list[tuple[str, int]]:
    """A predictor's rows refined from its solved output layer instead of its own output (predict's
    readout defaults, then K steps at predict's learning rate): (row name, K).

    >>> solved_refine_runs("v4", [100, 300])
    [('v4 readout + 100', 100), ('v4 readout + 300', 300)]
    """
    return [(f"{name} readout + {k}", k) for k in refine_steps]


def light_orientation_record(net: torch.nn.Module, crops: list[torch.Tensor], scale: float, light_world: torch.Tensor | None) -> dict:
    """Where a light-orientation predictor puts the light (:mod:`damcap.appearance.hyper.orientation`):
    ``orientation.light_up_world`` of its input images, world space (0 when it has no direction),
    and its angle in degrees to the capture's one distant light when both are known
    (``light_world``, unit; else None)."""
    images, _ = input_images(crops, net.arch.input_size, scale)
    d = light_up_world(images[None])[0].double()
    angle = None if light_world is None or not d.any() else math.degrees(math.acos(float((d @ light_world.double()).clamp(-1, 1))))
    return {"up_world": [float(x) for x in d], "angle_to_light_deg": angle}


def bench_capture(kind: str, path: Path, nets: dict[str, torch.nn.Module], refine_steps: list[int], snapshots: dict,
                  fit: FitOptions = FitOptions(checkpoint_every=0), compare_lr: tuple[float, ...] = (), auto: bool = False,
                  readout: tuple[list[int], list[int]] = ([], []), refine_from_readout: bool = False,
                  light_world: torch.Tensor | None = None, joint: tuple[list[int], list[float]] = ([], [])) -> dict:
    cap = read_capture(path)
    train, test = load_views(cap, "train"), load_views(cap, "test")
    samples = samples_of(train)
    t = time.perf_counter()
    fitted = fit_dam(samples, fit).model
    fit_s = time.perf_counter() - t
    models, rec = {"fit": fitted}, {"kind": kind, "capture": str(path), "fit_seconds": fit_s, "predict_ms": {}, "refine_seconds": {}}
    for name, net in {**nets, **snapshots}.items():
        ks, crops, scale = predictor_inputs(train, net.arch.input_views)
        times = []
        for _ in range(5):
            t = time.perf_counter()
            model = predict_dam(net, crops, scale)
            times.append(time.perf_counter() - t)
        models[name] = model
        rec["predict_ms"][name] = 1000 * statistics.median(times)
        if name in nets and net.arch.orientation == "light":
            rec.setdefault("light_orientation", {})[name] = light_orientation_record(net, crops, scale, light_world)
        for key, k, n in readout_runs(name, *readout) if name in nets else []:
            solve_times = []
            for _ in range(5):
                t = time.perf_counter()
                models[key] = solve_output_layer(model, samples, k, n).model
                solve_times.append(time.perf_counter() - t)
            rec.setdefault("readout_ms", {})[key] = rec["predict_ms"][name] + 1000 * statistics.median(solve_times)
        for key, j, prior in joint_runs(name, readout, *joint) if name in nets else []:
            base = first_readout_key(name, readout)
            solve_times = []
            for _ in range(5):
                t = time.perf_counter()
                models[key] = solve_first_and_output_layers(models[base], samples, j, PredictOptions.joint_samples, prior).model
                solve_times.append(time.perf_counter() - t)
            rec["readout_ms"][key] = rec["readout_ms"][base] + 1000 * statistics.median(solve_times)
        snap_key = first_readout_key(name, readout) if name in snapshots else None
        if snap_key:
            models[snap_key] = solve_output_layer(model, samples, readout[0][0], readout[1][0]).model
        for key, k, lr in refine_runs(name, refine_steps, compare_lr, auto) if name in nets else []:
            t = time.perf_counter()
            if k is None:
                models[key], chosen = refine_auto(model, samples, max_steps=PredictOptions.refine_max_steps,
                                                  patience_steps=PredictOptions.refine_patience, learning_rate=lr)
                rec.setdefault("auto_steps", {})[name] = chosen.steps_used
            else:
                models[key] = refine_dam(model, samples, k, lr)[0]
            rec["refine_seconds"][key] = time.perf_counter() - t + times[0]
        if name in nets and refine_from_readout:  # one solve (predict's defaults), then each K from it
            t = time.perf_counter()
            solved = solve_output_layer(model, samples, PredictOptions.readout_iterations, PredictOptions.readout_samples).model
            solve_s = time.perf_counter() - t
            for key, k in solved_refine_runs(name, refine_steps):
                t = time.perf_counter()
                models[key] = refine_dam(solved, samples, k, PredictOptions.refine_learning_rate)[0]
                rec["refine_seconds"][key] = time.perf_counter() - t + solve_s + times[0]
    scores = evaluate_split(train, test, models)
    rec["novel"] = {k: v.mean for k, v in scores.items()}
    log(f"{kind} {path.name}: " + ", ".join(f"{k} {v:.4f}" for k, v in rec["novel"].items()))
    return rec


def summarise(per_capture: list[dict]) -> dict:
    kinds = list(dict.fromkeys(r["kind"] for r in per_capture))
    out = {}
    for kind in kinds:
        rows = [r for r in per_capture if r["kind"] == kind]
        methods = rows[0]["novel"].keys()
        out[kind] = {"captures": len(rows), "novel": {m: statistics.mean(r["novel"][m] for r in rows) for m in methods}}
    return out


HISTORY_MARK = "<!-- history: bench.hyper_ood keeps everything from this line on when it rewrites this report -->"
"""the line from which a report's hand-kept history starts: a rerun rewrites only what is above it"""


def with_history(new_text: str, old_text: str) -> str:
    r"""The freshly written report ``new_text`` followed by the history kept in ``old_text`` (from
    :data:`HISTORY_MARK` on), or ``new_text`` alone when the old report has none.

    >>> with_history("# new\n", "# old\n" + HISTORY_MARK + "\n## History\n")
    '# new\n\n<!-- history: bench.hyper_ood keeps everything from this line on when it rewrites this report -->\n## History\n'
    >>> with_history("# new\n", "# old\n")
    '# new\n'
    """
    if HISTORY_MARK not in old_text:
        return new_text
    return new_text.rstrip("\n") + "\n\n" + old_text[old_text.index(HISTORY_MARK):]


def write_markdown(res: dict, path: Path) -> None:
    nets, refined, solved = res["predictors"], res["refined"], res.get("readout", [])
    cols = ["RM++", "fit"] + nets + solved + refined
    lines = ["# The predictor on captures unlike its training set (issue 28)", "",
             f"Command (from the repository root): `{res['command']}`", "",
             f"Machine: {res['machine']['cpu_model']} ({res['machine']['nproc']} cores), torch {res['machine']['torch']} with {torch.get_num_threads()} threads; "
             f"{res['date']}. Predictors: " + "; ".join(f"`{n}` ({res['predictor_info'][n]})" for n in nets) + ".", "",
             "Novel-view DSSIM, mean over each kind's captures (ratio to `damcap fit` in brackets). "
             f"`+ K` = the prediction refined K steps (`damcap predict --refine-steps K`) at predict's learning rate "
             f"({res['refine_learning_rate']:g}); `(lr X)` at learning rate X instead; `+ auto` = `--refine-steps auto` "
             "(the steps it chose are in the JSON); `readout K` = the prediction with its output layer solved on the train "
             "pixels, K iterations (`damcap predict --readout-iterations K --joint-iterations 0`); `+ joint J` = then its first "
             "and output layers solved together, J iterations (`--joint-iterations J`; predict's default without refinement is "
             f"readout {PredictOptions.readout_iterations} + joint {PredictOptions.joint_iterations}); `(prior P)` at "
             "`--joint-prior P`.", "",
             "| kind | captures | " + " | ".join(cols) + " |", "|---|---:|" + "---:|" * len(cols)]
    for kind, s in res["summary"].items():
        fit = s["novel"]["fit"]
        cells = [f"{s['novel']['RM++']:.4f}", f"{fit:.4f}"] + [f"{s['novel'][c]:.4f} (x{s['novel'][c] / fit:.2f})" for c in cols[2:]]
        lines.append(f"| {kind} | {s['captures']} | " + " | ".join(cells) + " |")
    lines += ["", "## Time (CPU)", "", "| capture | fit s | " + " | ".join(f"predict {n} ms" for n in nets + solved) + " | "
              + " | ".join(f"{c} s" for c in refined) + " |", "|---|---:|" + "---:|" * (len(nets) + len(solved) + len(refined))]
    for r in res["per_capture"]:
        lines.append(f"| {Path(r['capture']).name} | {r['fit_seconds']:.1f} | "
                     + " | ".join(f"{r['predict_ms'][n]:.0f}" for n in nets) + "".join(f" | {r['readout_ms'][c]:.0f}" for c in solved)
                     + " | " + " | ".join(f"{r['refine_seconds'][c]:.2f}" for c in refined) + " |")
    lines += ["", "## All captures", "", "| method | mean DSSIM | mean ratio to fit | captures below RM++ |", "|---|---:|---:|---:|"]
    n_caps = len(res["per_capture"])
    for c in cols:
        vals = [r["novel"][c] for r in res["per_capture"]]
        ratio = statistics.mean(r["novel"][c] / r["novel"]["fit"] for r in res["per_capture"])
        below = sum(r["novel"][c] < r["novel"]["RM++"] for r in res["per_capture"])
        lines.append(f"| {c} | {statistics.mean(vals):.4f} | x{ratio:.2f} | {below} of {n_caps} |")
    if res["snapshots"]:
        solved_rows = res.get("snapshot_readout") or {}
        lines += ["", "## Out-of-distribution error against training compute", "",
                  "Predict alone, mean novel-view DSSIM over all captures above, for snapshots of the predictors' training runs and "
                  "the predictors themselves (their best validation step), and with the output layer solved (the first `--readout` "
                  "count). Total steps count the steps of the predictor a run started from (`train-hyper --init`).", "",
                  "| model | run step | total steps | mean DSSIM | mean ratio to fit |" + (" solved: mean DSSIM | solved: ratio to fit |" if solved_rows else ""),
                  "|---|---:|---:|---:|---:|" + ("---:|---:|" if solved_rows else "")]
        points = [(name, d["step"], d["total"]) for name, d in res["snapshots"].items()]
        runs = {name.rsplit(".step", 1)[0] for name in res["snapshots"]}  # predictors whose run has snapshots
        points += [(n, res["predictor_steps"][n]["step"], res["predictor_steps"][n]["total"]) for n in nets if n in runs]
        def cells(key: str) -> str:
            if any(key not in r["novel"] for r in res["per_capture"]):
                return " | |"
            vals = [r["novel"][key] for r in res["per_capture"]]
            ratio = statistics.mean(r["novel"][key] / r["novel"]["fit"] for r in res["per_capture"])
            return f" {statistics.mean(vals):.4f} | x{ratio:.2f} |"
        for name, step, total in sorted(points, key=lambda x: x[2]):
            lines.append(f"| {name} | {step} | {total} |" + cells(name) + (cells(solved_rows.get(name, "")) if solved_rows else ""))
    # results written before the predictor's coordinates were called its orientation say "light_frame"
    lights = [(r, n, f) for r in res["per_capture"] for n, f in (r.get("light_orientation") or r.get("light_frame") or {}).items()]
    if lights:
        how = {"terminator_fit": "the unit least-absolute-deviations fit of its input views' radiance by c + max(0, b . N) "
                                 "(`orientation.terminator_fit`)"}.get(res.get("light_orientation_fit", res.get("light_frame_fit", "")),
                                                                       "the unit least-squares brightness gradient of its input views over their normals")
        lines += ["", "## Light orientation", "", f"Where each light-orientation predictor puts the light (its +y): {how}, world space, "
                  "and on the closed-form captures under one distant light its angle to that light.", "",
                  "| capture | predictors | light orientation's +y, world | angle to the light, deg |", "|---|---|---|---:|"]
        rows: dict[tuple, list[str]] = {}  # predictors reading the same views find the same orientation: one row
        for r, n, f in lights:
            angle = "" if f["angle_to_light_deg"] is None else f"{f['angle_to_light_deg']:.1f}"
            rows.setdefault((Path(r["capture"]).name, f"({', '.join(f'{x:.2f}' for x in f['up_world'])})", angle), []).append(n)
        lines += [f"| {cap} | {', '.join(names)} | {up} | {angle} |" for (cap, up, angle), names in rows.items()]
    lines += ["", "## Per capture", "", "| kind | capture | " + " | ".join(cols) + " |", "|---|---|" + "---:|" * len(cols)]
    for r in res["per_capture"]:
        lines.append(f"| {r['kind']} | {Path(r['capture']).name} | " + " | ".join(f"{r['novel'][c]:.4f}" for c in cols) + " |")
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--predictors", type=Path, nargs="+", required=True, help="predictor files; the last is the newest")
    ap.add_argument("--snapshots", type=Path, nargs="*", default=[], help="snapshots of the predictors' training runs (NAME.stepN.safetensors, "
                    "counted after the steps of the predictor their run started from: their own record of it, or else predictor NAME's)")
    ap.add_argument("--corpus", type=Path, default=CACHE / "synth_small", help="synth-set corpus whose held-out captures are used")
    ap.add_argument("--real", type=Path, nargs="*", default=[CACHE / "reconstruct" / "realworld" / "cape-8-256"])
    ap.add_argument("--refine-steps", type=int, nargs="+", default=[100, 300])
    ap.add_argument("--compare-lr", type=float, nargs="*", default=[3e-3],
                    help="refined rows at these learning rates as well (predict's own: PredictOptions.refine_learning_rate)")
    ap.add_argument("--readout", type=int, nargs="*", default=[PredictOptions.readout_iterations],
                    help="rows with the output layer solved, at these iteration counts (predict's own: PredictOptions.readout_iterations)")
    ap.add_argument("--readout-samples", type=int, nargs="+", default=[PredictOptions.readout_samples],
                    help="... on at most this many train pixels (predict's own: PredictOptions.readout_samples)")
    ap.add_argument("--joint", type=int, nargs="*", default=[PredictOptions.joint_iterations],
                    help="rows with the first and output layers then solved together, at these iteration counts, from the first "
                         "--readout row (predict's own: PredictOptions.joint_iterations)")
    ap.add_argument("--joint-prior", type=float, nargs="+", default=[PredictOptions.joint_prior],
                    help="... at these priors (predict's own: PredictOptions.joint_prior)")
    ap.add_argument("--refine-from-readout", action="store_true",
                    help="rows refined from the solved output layer (predict's readout defaults) as well as from the network's own output")
    ap.add_argument("--auto", action=argparse.BooleanOptionalAction, default=True, help="rows refined with --refine-steps auto")
    ap.add_argument("--closed-form", type=int, default=len(CLOSED_FORM), help="how many of the closed-form captures (smoke runs: fewer)")
    ap.add_argument("--closed-form-set", choices=["bench", "check"], default="bench",
                    help="the closed-form captures: the bench's (CLOSED_FORM) or other seeds of the same kinds (CLOSED_FORM_CHECK)")
    ap.add_argument("--res", type=int, default=128, help="closed-form captures' resolution (smoke runs: smaller)")
    ap.add_argument("--fit-steps", type=int, default=None, help="fit steps (default: FitOptions' default)")
    ap.add_argument("--cache", type=Path, default=CACHE / "hyper_ood", help="where the closed-form captures are rendered once")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--tag", default="", help="write hyper_ood_TAG.json / .md (a study beside the main table)")
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    nets, info, before, pred_steps = {}, {}, {}, {}
    for p in args.predictors:
        net, meta = load_predictor(p)
        name = p.stem
        nets[name] = net
        tr = meta.get("training", {})
        init = tr.get("init") or {}
        before[name] = int(init.get("steps", 0))
        info[name] = (f"input views {net.arch.input_views}, {tr.get('seconds', float('nan')):.0f} s of training"
                      + (f" on {tr['launcher']['device']}" if tr.get("launcher", {}).get("device") else "")
                      + (f", started from {init['file']} ({before[name]} steps, {init.get('seconds', 0):.0f} s)" if init else ""))
        if isinstance(tr.get("best_step"), int):
            pred_steps[name] = {"step": tr["best_step"], "total": tr["best_step"] + before[name]}
    snaps, snap_steps = {}, {}
    for p in args.snapshots:
        net, meta = load_predictor(p)
        snaps[p.stem] = net
        step = int(meta.get("training", {}).get("snapshot_step"))
        run = p.stem.rsplit(".step", 1)[0]  # NAME.stepN: the run of predictor NAME
        own = meta.get("training", {}).get("init")  # snapshots since 2026-11-28 hold their run's --init record
        snap_steps[p.stem] = {"step": step, "total": step + (int(own.get("steps", 0)) if isinstance(own, dict) else before.get(run, 0))}
    captures = closed_form_captures(args.cache, args.closed_form, args.res, CLOSED_FORM if args.closed_form_set == "bench" else CLOSED_FORM_CHECK)
    if (args.corpus / "corpus.json").exists():
        captures += [("Mitsuba held-out", path) for path, e in heldout_entries([args.corpus]) if int(e.get("materials", 1)) == 1]
    else:
        log(f"{args.corpus}: no corpus; the Mitsuba kind is left out")
    captures += [(f"real ({p.name.split('-')[0]})", p) for p in args.real if (p / "transforms.json").exists()]  # cape-8-256: real (cape)
    fit = FitOptions(checkpoint_every=0) if args.fit_steps is None else FitOptions(checkpoint_every=0, steps=args.fit_steps)
    readout = (args.readout, args.readout_samples)
    light = directional_lighting().dirs[0]  # the closed-form captures' one distant light (ClosedFormOptions' default)
    joint = (args.joint, args.joint_prior)
    per = [bench_capture(kind, path, nets, args.refine_steps, snaps, fit, tuple(args.compare_lr), args.auto, readout, args.refine_from_readout,
                         light if kind.startswith("closed-form") and kind.endswith("distant light") else None, joint)
           for kind, path in captures]
    res = {"command": command_line("hyper_ood", argv if argv is not None else __import__("sys").argv[1:]),
           "machine": machine_info(), "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
           "predictors": list(nets), "predictor_info": info, "refine_steps": args.refine_steps,
           "refine_learning_rate": PredictOptions.refine_learning_rate,
           "readout": [r[0] for n in nets for r in readout_runs(n, *readout) + joint_runs(n, readout, *joint)],
           "readout_defaults": {"iterations": PredictOptions.readout_iterations, "samples": PredictOptions.readout_samples,
                                "joint_iterations": PredictOptions.joint_iterations, "joint_samples": PredictOptions.joint_samples,
                                "joint_prior": PredictOptions.joint_prior},
           "refined": [r[0] for n in nets for r in refine_runs(n, args.refine_steps, tuple(args.compare_lr), args.auto)]
           + ([r[0] for n in nets for r in solved_refine_runs(n, args.refine_steps)] if args.refine_from_readout else []),
           "snapshots": snap_steps,
           "snapshot_readout": {n: first_readout_key(n, readout) for n in [*snaps, *nets]} if args.readout and snaps else {},
           "predictor_steps": pred_steps, "per_capture": per, "summary": summarise(per),
           "light_orientation_fit": "terminator_fit"}  # what orientation.light_up_world fits (before 2026-11-28 05:00 UTC: brightness_gradient)
    stem = f"hyper_ood_{args.tag}" if args.tag else "hyper_ood"
    out_json = (args.out or RESULTS) / f"{stem}.json"
    out_md = (args.out or BENCH) / f"{stem}.md"
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(res, indent=1, default=float))
    old_md = out_md.read_text() if out_md.exists() else ""
    write_markdown(json.loads(out_json.read_text()), out_md)
    out_md.write_text(with_history(out_md.read_text(), old_md))
    log(f"wrote {out_json} and {out_md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
