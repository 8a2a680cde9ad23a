"""Benchmark: DAM fit speed/accuracy against the RM++ / RM baselines, and DAM render time, on CPU.

The issue's targets, on a closed-form capture of 32 views at 128x128 (10 consecutive train
views, 22 test), on a 2-core CPU:

* the default fit (``FitOptions()``) reaches novel-view DSSIM <= 0.5 x RM++'s in <= 10 s wall;
* the best setting reaches <= 0.35 x RM++'s within 60 s;
* rendering one 256x256 frame takes <= 20 ms (median).

Every fit runs over several seeds (mean, std, min, max reported); a speed/accuracy sweep varies
steps, input encoding, hold-out stopping, width and the adversarial cost, and studies:

* DAM depth (``w32d2``, ``w32d6``; ``w32d4`` is the default) and width (``w16d4``: 912 weights);
* pixels sampled per step (``batch1024``, ``batch16384``; 4096 is the default);
* input resolution (``input64``, ``input32``: the *training* frames' arrays subsampled to every
  2nd / 4th pixel in both axes, a transformation done here, not in the library; test views, and
  the train views the same-view DSSIM is measured on, stay at 128x128);
* compute precision (``bfloat16``: ``FitOptions.precision``; ``float32`` is the default);
* weight decay (``wd0.03``, ``wd0.1``, and ``wd0.1_s4000`` / ``wd0.1_s8000`` with more steps:
  ``FitOptions.weight_decay``; 0 is the default);
* the data cost's quantile (``q0.75``, and ``q0.75_wd0.1`` with weight decay 0.1:
  ``FitOptions.quantile``; 0.5, the L1 cost, is the default);
* a separable DAM, softplus(f(N) + g(R)) (``sep44x4``: 3168 weights, ``sep32x4``: 1728;
  ``FitOptions.separable``; the default is the joint 32x4 network);
* the shipped learning-to-learn predictor plus K refinement steps (``predict_k0`` ...
  ``predict_k1000``), as ``damcap predict --refine-steps K`` does it (``predictor_inputs``,
  ``predict_dam``, ``refine_dam``); its time includes the prediction (not loading the file).

Outputs: ``bench/results/dam_core.json``, ``bench/results/dam_core_pareto.png`` and
``bench/dam_core.md``. Captures are cached under ``bench/.cache/`` (git-ignored) and reused when
their ``transforms.json`` exists. Every finished fit is also appended to
``bench/.cache/dam_core_runs.jsonl``; ``--resume`` reuses those records instead of refitting
(a run's key is its capture and options; new settings get new keys).

Timing on a shared machine: other processes on the same cores slow a 2-thread torch fit by up
to ~30x (its two worker threads wait on each other whenever one is descheduled). So every timed
fit first waits (bounded) for a quiet machine, is aborted and restarted when other processes
take the CPUs early on, and records, per window of 25 steps, how much CPU time other processes
used (/proc/stat minus this process). A fit that was disturbed anyway reports its raw wall time
and a clean-window estimate (disturbed windows re-timed at the clean windows' speed).

Run (from the repository root)::

    .venv/bin/python -m bench.dam_core

Options (``--help``): ``--only NAME ...`` runs only these settings, ``--seeds 0 1 2`` the fit
seeds, ``--captures sphere_env torus_env``, ``--resume``, ``--render-runs N`` (0 = no render
timing), ``--budget-minutes``, ``--max-aborts``, ``--quiet-wait S`` (0 = do not wait for a quiet
machine) and ``--out DIR``: write the JSON, plot, markdown and run log into DIR instead of the
committed ``bench/results/``, ``bench/dam_core.md`` and ``bench/.cache/`` (for smoke runs);
``--cache DIR`` holds the generated captures, ``--resolution`` and ``--steps`` shrink them and every
fit, e.g.::

    .venv/bin/python -m bench.dam_core --only predict_k100 input32 --seeds 0 --captures sphere_env \
        --render-runs 0 --quiet-wait 0 --out /tmp/dam_core_smoke
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import itertools
import json
import math
import os
import shutil
import statistics
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

from bench.common import BENCH, CACHE, NCPU, REPO, RESULTS, CpuMeter, command_line, log, machine_info, own_cpu_s, system_busy_s

from damcap.appearance.views import ViewData
from damcap.appearance.evaluate import evaluate_split
from damcap.appearance.fit import FitOptions, fit_dam, refine_dam
from damcap.appearance.hyper.model import predict_dam, predictor_inputs
from damcap.appearance.hyper.file import PAPER_SHIPPED, load_predictor, shipped_predictor_path
from damcap.appearance.hyper.predict import PredictOptions
from damcap.appearance.render import render_frame
from damcap.appearance.fit import adversarial_frames
from damcap.appearance.views import load_views, samples_of
from damcap.common.capture_folder import read_capture
from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

THREADS = 2
RUNS_LOG = CACHE / "dam_core_runs.jsonl"

CAPTURES: dict[str, ClosedFormOptions] = {
    "sphere_env": ClosedFormOptions(shape="sphere", light="env", views=32, resolution=128, train_views=10, seed=0),
    "torus_env": ClosedFormOptions(shape="torus", light="env", views=32, resolution=128, train_views=10, seed=0),
}
RENDER_CAPTURE = ("sphere_dir_256", ClosedFormOptions(shape="sphere", light="directional", views=4, resolution=256, train_views=2, seed=0))

#: (setting name, FitOptions overrides) in priority order (a time budget drops the tail);
#: "default" is FitOptions() itself.
SETTINGS: list[tuple[str, dict]] = [
    ("default", {}),
    ("leaky_relu", {"activation": "leaky_relu"}),  # the default before shifted softplus
    ("steps500", {"steps": 500}),
    ("steps1000", {"steps": 1000}),
    ("steps4000", {"steps": 4000}),
    ("steps8000", {"steps": 8000}),
    ("enc_vn", {"encoding": "vn"}),
    ("enc_vnr", {"encoding": "vnr"}),
    ("holdout0_s2000", {"holdout_views": 0}),
    ("w64d4_s4000", {"width": 64, "depth": 4, "steps": 4000}),
    ("adversarial_s2000", {"adversarial": True}),
    ("holdout0_s8000", {"holdout_views": 0, "steps": 8000}),
    # studies (module docstring); keys in BENCH_KEYS are handled here, not by FitOptions
    ("w32d2", {"depth": 2}),
    ("w32d6", {"depth": 6}),
    ("w16d4", {"width": 16}),
    ("batch1024", {"batch_size": 1024}),
    ("batch16384", {"batch_size": 16384}),
    ("input64", {"input_subsample": 2}),
    ("input32", {"input_subsample": 4}),
    ("bfloat16", {"precision": "bfloat16"}),
    ("wd0.03", {"weight_decay": 0.03}),
    ("wd0.1", {"weight_decay": 0.1}),
    ("wd0.1_s4000", {"weight_decay": 0.1, "steps": 4000}),
    ("wd0.1_s8000", {"weight_decay": 0.1, "steps": 8000}),
    ("q0.75", {"quantile": 0.75}),
    ("q0.75_wd0.1", {"quantile": 0.75, "weight_decay": 0.1}),
    ("sep44x4", {"width": 44, "separable": True}),
    ("sep32x4", {"separable": True}),
    ("predict_k0", {"predict_refine_steps": 0}),
    ("predict_k100", {"predict_refine_steps": 100}),
    ("predict_k300", {"predict_refine_steps": 300}),
    ("predict_k1000", {"predict_refine_steps": 1000}),
]
#: table rows that are the same options as another setting: (name, same options as)
ALIASES = [("shifted_softplus", "default"), ("steps2000", "default"), ("enc_nr", "default"), ("holdout2_s2000", "default"), ("holdout2_s8000", "steps8000"),
           ("w32d4", "default"), ("batch4096", "default"), ("input128", "default"), ("float32", "default"), ("wd0", "default")]
BENCH_KEYS = ("input_subsample", "predict_refine_steps")
"""setting keys that are not FitOptions fields: input_subsample = keep every n-th training pixel in
both axes; predict_refine_steps = K, predict with the shipped predictor, then K refine_dam steps"""
#: the families of the study rows (summary lines in the markdown, markers in the plot)
STUDIES: dict[str, list[str]] = {
    "depth (width 32)": ["w32d2", "default", "w32d6"],
    "width (depth 4)": ["w16d4", "default"],
    "pixels per step": ["batch1024", "default", "batch16384"],
    "training input resolution": ["input32", "input64", "default"],
    "precision": ["default", "bfloat16"],
    "hidden activation": ["leaky_relu", "default"],
    "weight decay": ["default", "wd0.03", "wd0.1", "steps4000", "wd0.1_s4000", "steps8000", "wd0.1_s8000"],
    "data-cost quantile": ["default", "q0.75", "wd0.1", "q0.75_wd0.1"],
    "separable DAM": ["default", "sep32x4", "sep44x4"],
    "predictor + K refine steps": ["predict_k0", "predict_k100", "predict_k300", "predict_k1000"],
}

# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def ensure_capture(name: str, opts: ClosedFormOptions, cache: Path = CACHE) -> Path:
    path = cache / name
    if (path / "transforms.json").exists():
        log(f"capture {name}: cached at {path}")
        return path
    if path.exists():  # an interrupted generation: transforms.json is written last
        shutil.rmtree(path)
    log(f"capture {name}: generating ({opts})")
    t = time.perf_counter()
    make_closed_form_capture(path, opts)
    log(f"capture {name}: done in {time.perf_counter() - t:.1f} s")
    return path


def stats_of(xs: list[float]) -> dict:
    finite = [float(x) for x in xs if math.isfinite(float(x))]
    if not finite:
        return {"mean": float("nan"), "std": float("nan"), "min": float("nan"), "max": float("nan"), "n": 0}
    return {
        "mean": statistics.fmean(finite),
        "std": statistics.stdev(finite) if len(finite) > 1 else 0.0,
        "min": min(finite),
        "max": max(finite),
        "n": len(finite),
    }


def split_overrides(overrides: dict) -> tuple[dict, dict]:
    """A setting's (FitOptions overrides, bench-level keys of BENCH_KEYS)."""
    return ({k: v for k, v in overrides.items() if k not in BENCH_KEYS},
            {k: v for k, v in overrides.items() if k in BENCH_KEYS})


def run_key(capture: str, opts: FitOptions, bench: dict | None = None) -> str:
    """The run log's key: capture, FitOptions and bench-level keys (predictor runs: with the
    predictor file's hash). ``precision``, ``weight_decay``, ``quantile`` and ``separable`` are
    left out at their defaults so that runs logged before the options existed keep their keys."""
    d = asdict(opts)
    for name, default in (("precision", "float32"), ("weight_decay", 0.0), ("quantile", 0.5), ("separable", False)):
        if d.get(name) == default:
            del d[name]
    return capture + "|" + json.dumps(d, sort_keys=True) + ("|" + json.dumps(bench, sort_keys=True) if bench else "")


def subsample_view(view: ViewData, step: int) -> ViewData:
    """A view whose per-pixel arrays keep every ``step``-th pixel in both axes ((H, W) ->
    (ceil(H / step), ceil(W / step)), no filtering); its camera pose is unchanged (DAM samples
    need world positions and normals, not intrinsics)."""
    d = view.data
    sub = {f.name: None if getattr(d, f.name) is None else np.ascontiguousarray(getattr(d, f.name)[::step, ::step])
           for f in dataclasses.fields(d)}
    return ViewData(view.name, dataclasses.replace(d, **sub), view.world_from_cam)


def setting_data(data: dict, bench: dict) -> dict:
    """The capture's data as a setting trains on it: subsampled training views (cached in
    ``data``) with full-resolution test views and same-view targets."""
    step = int(bench.get("input_subsample", 1))
    if step == 1:
        return data
    variants = data.setdefault("subsampled", {})
    if step not in variants:
        train = [subsample_view(v, step) for v in data["train"]]
        variants[step] = {**data, "train": train, "samples": samples_of(train), "train_eval": data["train"],
                          "input_resolution": list(train[0].data.coverage.shape)}
        log(f"  training views subsampled every {step} px: {variants[step]['input_resolution']} px, "
            f"{len(variants[step]['samples'])} training pixels")
    return variants[step]


def load_run_log(path: Path = RUNS_LOG) -> dict[str, dict]:
    out: dict[str, dict] = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            out[rec["key"]] = rec
    return out


def append_run_log(rec: dict, path: Path = RUNS_LOG) -> None:
    with path.open("a") as f:
        f.write(json.dumps(rec) + "\n")


# --------------------------------------------------------------------------------------------
# CPU contention
# --------------------------------------------------------------------------------------------

QUIET_FRAC = 0.10
"""a timed stretch counts as clean when other processes used at most this fraction of all cores"""
ABORT_FRAC = 0.25
"""a fit is aborted (and restarted later) when others take more than this early on"""


WAITED_S = 0.0
"""total seconds spent waiting for a quiet machine (not counted against the time budget)"""


def wait_for_quiet(max_wait_s: float, window_s: float = 1.0) -> tuple[float, bool]:
    """Wait (at most max_wait_s) until two consecutive windows see others use < QUIET_FRAC.

    ``max_wait_s <= 0`` does not wait (a smoke run): the machine counts as quiet, and the timed
    run's own CPU meter still reports how much others used."""
    global WAITED_S
    if max_wait_s <= 0:
        return 0.0, True
    t0 = time.perf_counter()
    ok, quiet, last_log = 0, False, t0
    while time.perf_counter() - t0 < max_wait_s:
        with CpuMeter() as m:
            time.sleep(window_s)
        ok = ok + 1 if m.foreign_frac < QUIET_FRAC else 0
        if ok >= 2:
            quiet = True
            break
        if time.perf_counter() - last_log > 120:
            log(f"  waiting for a quiet machine ({time.perf_counter() - t0:.0f} s so far; others use {m.foreign_frac:.0%})")
            last_log = time.perf_counter()
    waited = time.perf_counter() - t0
    WAITED_S += waited
    return waited, quiet


class MachineBusy(Exception):
    """No quiet machine within the wait limit: the remaining measurements are skipped."""


class _Disturbed(Exception):
    def __init__(self, step: int, frac: float) -> None:
        super().__init__(f"disturbed at step {step}")
        self.step, self.frac = step, frac


class Timeline:
    """fit_dam progress callback: per-window (25 steps) wall time and others' CPU share.

    With ``abort_within_s``, raises _Disturbed when, within that many seconds of the start,
    others have used more than ABORT_FRAC of the CPUs (finishing such a fit wastes minutes).
    """

    def __init__(self, every: int = 25, abort_within_s: float = 0.0) -> None:
        self.every, self.abort_within_s = every, abort_within_s
        self.windows: list[dict] = []
        self.s_start, self.p_start, self.t_start = system_busy_s(), own_cpu_s(), time.perf_counter()
        self.s, self.p, self.t, self.step = self.s_start, self.p_start, self.t_start, 0

    def _close(self, step: int) -> None:
        s, p, t = system_busy_s(), own_cpu_s(), time.perf_counter()
        wall = t - self.t
        foreign = max(0.0, (s - self.s) - (p - self.p))
        self.windows.append({"steps": step - self.step, "wall_s": wall, "foreign_frac": foreign / max(wall * NCPU, 1e-9)})
        self.s, self.p, self.t, self.step = s, p, t, step

    def __call__(self, step: int, steps: int, stats: dict) -> None:
        if step % self.every and step != steps:
            return
        self._close(step)
        elapsed = self.t - self.t_start
        if self.abort_within_s and elapsed < self.abort_within_s and elapsed > 0.3:
            own = self.p - self.p_start
            frac = max(0.0, self.s - self.s_start - own) / (elapsed * NCPU)
            if frac > ABORT_FRAC:
                raise _Disturbed(step, frac)

    def clean_estimate(self, total_wall: float) -> dict:
        """Wall time with disturbed windows re-timed at the clean windows' mean speed."""
        clean = [w for w in self.windows if w["foreign_frac"] <= QUIET_FRAC]
        dist = [w for w in self.windows if w["foreign_frac"] > QUIET_FRAC]
        steps_total = sum(w["steps"] for w in self.windows)
        out = {"windows": len(self.windows), "clean_windows": len(clean),
               "clean_step_frac": sum(w["steps"] for w in clean) / max(steps_total, 1)}
        if not clean:
            out["estimate_s"] = float("nan")
            return out
        rate = sum(w["wall_s"] for w in clean) / max(sum(w["steps"] for w in clean), 1)
        out["clean_s_per_step"] = rate
        out["estimate_s"] = total_wall - sum(w["wall_s"] for w in dist) + rate * sum(w["steps"] for w in dist)
        return out


# --------------------------------------------------------------------------------------------
# measurements
# --------------------------------------------------------------------------------------------


def timed(run, *, max_aborts: int, quiet_wait_s: float, budget_left) -> tuple:
    """``run(progress)`` under the contention protocol (wait for a quiet machine; abort and
    restart when disturbed early): (its result, CpuMeter, Timeline, aborts, seconds waited)."""
    aborts, waited_total = 0, 0.0
    while True:
        waited, quiet = wait_for_quiet(quiet_wait_s)
        waited_total += waited
        if not quiet:
            raise MachineBusy(f"other processes kept the CPUs busy for {waited:.0f} s")
        may_abort = aborts < max_aborts and budget_left() > 0
        tl = Timeline(abort_within_s=3.0 if may_abort else 0.0)
        try:
            with CpuMeter() as m:
                out = run(tl)
            return out, m, tl, aborts, waited_total
        except _Disturbed as e:
            aborts += 1
            log(f"  aborted at step {e.step}: other processes used {e.frac:.0%} of the CPUs; waiting for a quiet machine")


def timing_record(m: CpuMeter, tl: Timeline, aborts: int, waited: float) -> dict:
    """The timing fields of a run's record (raw wall, or the clean-window estimate if disturbed)."""
    est = tl.clean_estimate(m.wall)
    clean = m.foreign_frac <= QUIET_FRAC
    seconds = m.wall if clean or not math.isfinite(est["estimate_s"]) else est["estimate_s"]
    return {
        "seconds": seconds,
        "seconds_raw_wall": m.wall,
        "foreign_cpu_frac": m.foreign_frac,
        "clean_timing": clean,
        "timing_source": "wall" if clean else ("clean-window estimate" if seconds != m.wall else "disturbed wall (no clean window)"),
        "clean_window_estimate": est,
        "aborted_attempts": aborts,
        "waited_for_quiet_s": waited,
    }


def accuracy_record(data: dict, model) -> dict:
    """Novel-view (test) and same-view (full-resolution train) DSSIM of a model."""
    test = evaluate_split(data["train"], data["test"], {"DAM": model}, baselines=False)["DAM"].mean
    same = data.get("train_eval", data["train"])
    train = evaluate_split(same, same, {"DAM": model}, baselines=False)["DAM"].mean
    return {"dssim_test": test, "dssim_train": train, "ratio_test_to_rmpp": test / data["rmpp_test"],
            "finite_weights": bool(torch.isfinite(model.weights_flat).all())}


def fit_once(data: dict, opts: FitOptions, *, max_aborts: int, quiet_wait_s: float, budget_left) -> dict:
    """One fit: wall seconds of fit_dam (incl. its setup), novel- and same-view DSSIM."""
    t = time.perf_counter()
    frames = adversarial_frames(data["train"], data["samples"], opts)
    t_prep = time.perf_counter() - t if frames is not None else 0.0
    res, m, tl, aborts, waited = timed(lambda tl: fit_dam(data["samples"], opts, frames_for_adversarial=frames, progress=tl),
                                       max_aborts=max_aborts, quiet_wait_s=quiet_wait_s, budget_left=budget_left)
    timing = timing_record(m, tl, aborts, waited)
    return {
        "seed": opts.seed,
        **timing,
        "seconds_fit_internal": res.seconds,
        "seconds_adversarial_frames": t_prep,
        **accuracy_record(data, res.model),
        "training_pixels": len(data["samples"]),
        "best_step": res.best_step,
        "final_train_l1": res.history[-1]["train_l1"] if res.history else float("nan"),
        "final_holdout_l1": res.history[-1]["holdout_l1"] if res.history else float("nan"),
        "history": res.history,
    }


def predict_once(data: dict, predictor, refine_steps: int, seed: int, *, max_aborts: int, quiet_wait_s: float, budget_left) -> dict:
    """Predict a DAM with the shipped predictor, then ``refine_steps`` steps of refine_dam (as
    ``damcap predict --refine-steps K``); the time covers choosing and cropping the input view,
    the prediction and the refinement."""
    def run(tl: Timeline) -> dict:
        t0 = time.perf_counter()
        ks, crop, scale = predictor_inputs(data["train"], predictor.arch.input_views)
        k = ks[0]
        model = predict_dam(predictor, crop, scale)
        t1 = time.perf_counter()
        refined, before, after = refine_dam(model, data["samples"], refine_steps, PredictOptions.refine_learning_rate, seed=seed, progress=tl)
        return {"model": refined, "input_view": data["train"][k].name, "predict_s": t1 - t0,
                "refine_s": time.perf_counter() - t1, "before": before, "after": after, "accepted": refined is not model}

    out, m, tl, aborts, waited = timed(run, max_aborts=max_aborts, quiet_wait_s=quiet_wait_s, budget_left=budget_left)
    timing = timing_record(m, tl, aborts, waited)
    return {
        "seed": seed,
        **timing,
        "seconds_fit_internal": out["predict_s"] + out["refine_s"],
        "seconds_predict": out["predict_s"],
        "seconds_refine": out["refine_s"],
        **accuracy_record(data, out["model"]),
        "training_pixels": len(data["samples"]),
        "input_view": out["input_view"],
        "refine_steps": refine_steps,
        "refinement_kept": out["accepted"],
        "best_step": refine_steps if out["accepted"] else 0,
        "final_train_l1": out["after"],
        "predicted_train_l1": out["before"],
        "final_holdout_l1": float("nan"),
        "history": [],
    }


def time_render(model_opts: FitOptions, runs: int, quiet_wait_s: float, cache: Path = CACHE) -> dict:
    """Median wall time of render_frame on one 256x256 frame (default architecture)."""
    path = ensure_capture(*RENDER_CAPTURE, cache)
    cap = read_capture(path)
    train, test = load_views(cap, "train"), load_views(cap, "test")
    # a (briefly) fitted model: render time does not depend on the weights' values
    model = fit_dam(samples_of(train), replace(model_opts, steps=200)).model
    view = test[0]
    covered = int((view.data.coverage > 0).sum())
    for _ in range(3):  # warm-up
        render_frame(model, view.data, view.centre_world)
    best = None
    for _attempt in range(5):
        if not wait_for_quiet(quiet_wait_s)[1]:
            raise MachineBusy(f"other processes kept the CPUs busy for {quiet_wait_s:.0f} s")
        times = []
        with CpuMeter() as m:
            for _ in range(runs):
                t = time.perf_counter()
                img = render_frame(model, view.data, view.centre_world)
                times.append(time.perf_counter() - t)
        if best is None or m.foreign_frac < best[1].foreign_frac:
            best = (times, m)
        if m.foreign_frac <= QUIET_FRAC:
            break
    times, m = best
    assert img.shape == (256, 256, 3)
    ms = [1000 * x for x in times]
    return {
        "capture": RENDER_CAPTURE[0],
        "capture_options": asdict(RENDER_CAPTURE[1]),
        "frame": view.name,
        "resolution": list(img.shape[:2]),
        "covered_pixels": covered,
        "architecture": asdict(model.arch),
        "runs": runs,
        "median_ms": statistics.median(ms),
        "min_ms": min(ms),
        "max_ms": max(ms),
        "mean_ms": statistics.fmean(ms),
        "all_ms": ms,
        "foreign_cpu_frac": m.foreign_frac,
        "clean_timing": m.foreign_frac <= QUIET_FRAC,
    }


# --------------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------------


def compute_targets(result: dict) -> dict:
    targets: dict = {"per_capture": {}}
    for cap_name, cap in result["captures"].items():
        rows = {r["name"]: r for r in cap["settings"] if not r.get("alias_of")}
        tt: dict = {"rmpp_test": cap["baselines"]["test"]["RM++"], "default": None, "best": None, "n_settings": len(rows)}
        if "default" in rows:
            d = rows["default"]
            tt["default"] = {
                "seconds_mean": d["seconds"]["mean"], "seconds_max": d["seconds"]["max"],
                "seconds_raw_mean": d["seconds_raw_wall"]["mean"], "clean": f"{d['clean_timings']}/{len(d['seeds'])}",
                "ratio_mean": d["ratio_test_to_rmpp"]["mean"], "ratio_std": d["ratio_test_to_rmpp"]["std"],
                "ratio_max": d["ratio_test_to_rmpp"]["max"], "dssim_mean": d["dssim_test"]["mean"],
                "time_ok": d["seconds"]["mean"] <= 10, "time_ok_all": d["seconds"]["max"] <= 10,
                "ratio_ok": d["ratio_test_to_rmpp"]["mean"] <= 0.5, "ratio_ok_all": d["ratio_test_to_rmpp"]["max"] <= 0.5,
            }
        within = [r for r in rows.values() if r["seconds"]["mean"] <= 60]
        if within:
            b = min(within, key=lambda r: r["ratio_test_to_rmpp"]["mean"])
            tt["best"] = {
                "name": b["name"], "seconds_mean": b["seconds"]["mean"], "seconds_max": b["seconds"]["max"],
                "clean": f"{b['clean_timings']}/{len(b['seeds'])}",
                "ratio_mean": b["ratio_test_to_rmpp"]["mean"], "ratio_std": b["ratio_test_to_rmpp"]["std"],
                "ratio_max": b["ratio_test_to_rmpp"]["max"], "dssim_mean": b["dssim_test"]["mean"],
                "ratio_ok": b["ratio_test_to_rmpp"]["mean"] <= 0.35, "ratio_ok_all": b["ratio_test_to_rmpp"]["max"] <= 0.35,
            }
        curve = {}
        for n, steps in (("steps500", 500), ("steps1000", 1000), ("default", 2000), ("steps4000", 4000), ("steps8000", 8000)):
            if n in rows:
                curve[str(steps)] = {"ratio": rows[n]["ratio_test_to_rmpp"]["mean"], "seconds": rows[n]["seconds"]["mean"],
                                     "same_view_dssim": rows[n]["dssim_train"]["mean"]}
        tt["steps_curve"] = curve
        vals = [v["ratio"] for v in curve.values()]
        tt["steps_non_monotone"] = any(b > a for a, b in itertools.pairwise(vals))
        ho = {}
        for n in ("default", "holdout0_s2000", "steps8000", "holdout0_s8000"):
            if n in rows:
                ho[n] = rows[n]["ratio_test_to_rmpp"]["mean"]
        tt["holdout_compare"] = ho
        studies = {}
        for study, names in STUDIES.items():
            pts = {n: {"seconds": rows[n]["seconds"]["mean"], "ratio": rows[n]["ratio_test_to_rmpp"]["mean"]} for n in names if n in rows}
            if len(pts) > 1 or (pts and "default" not in pts):
                studies[study] = pts
        tt["studies"] = studies
        targets["per_capture"][cap_name] = tt
    targets["render"] = result.get("render")
    return targets


STUDY_MARKERS = {"fit settings": "o", "input resolution": "^", "bfloat16": "D", "predictor + K refine steps": "s"}


def marker_of(name: str) -> str:
    """The plot marker of a setting: predictor runs, subsampled inputs and bf16 stand out."""
    if name.startswith("predict_k"):
        return STUDY_MARKERS["predictor + K refine steps"]
    if name.startswith("input"):
        return STUDY_MARKERS["input resolution"]
    if name == "bfloat16":
        return STUDY_MARKERS["bfloat16"]
    return STUDY_MARKERS["fit settings"]


def pareto_plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 6))
    colours = {"sphere_env": "tab:blue", "torus_env": "tab:orange"}
    for cap_name, cap in result["captures"].items():
        c = colours.get(cap_name, "k")
        pts = []
        for row in cap["settings"]:
            if row.get("alias_of"):
                continue
            x, y = row["seconds"]["mean"], row["ratio_test_to_rmpp"]["mean"]
            ax.errorbar(x, y, xerr=row["seconds"]["std"], yerr=row["ratio_test_to_rmpp"]["std"], fmt=marker_of(row["name"]), color=c,
                        ms=5, capsize=2, alpha=0.85)
            ax.annotate(row["name"], (x, y), fontsize=7, xytext=(4, 3), textcoords="offset points", color=c)
            pts.append((x, y))
        pts.sort()
        front, best = [], math.inf
        for x, y in pts:
            if y < best:
                front.append((x, y))
                best = y
        if front:
            ax.plot(*zip(*front), "-", color=c, alpha=0.5, label=f"{cap_name} (Pareto front)")
    for study, m in STUDY_MARKERS.items():
        ax.plot([], [], m, color="grey", label=f"marker: {study}")
    ax.axhline(0.5, color="grey", ls="--", lw=0.8, label="0.5x RM++ / 10 s (default target)")
    ax.axvline(10, color="grey", ls="--", lw=0.8)
    ax.axhline(0.35, color="grey", ls=":", lw=0.8, label="0.35x RM++ / 60 s (best-setting target)")
    ax.axvline(60, color="grey", ls=":", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel(f"fit_dam wall seconds (predict_k*: prediction + refinement; {result['machine']['nproc']}-core CPU, "
                  f"{THREADS} torch threads); mean ± std over seeds")
    ax.set_ylabel("novel-view DSSIM / RM++ novel-view DSSIM (lower is better)")
    ax.set_title("DAM fit: speed vs novel-view accuracy\nclosed-form captures, 32 views at 128x128, 10 train / 22 test")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _shown(path: Path) -> str:
    """A path as the report shows it: relative to the repository root when inside it."""
    try:
        return str(path.resolve().relative_to(REPO))
    except ValueError:
        return str(path)


def fmt(s: dict, digits: int = 4) -> str:
    return f"{s['mean']:.{digits}f} ± {s['std']:.{digits}f}"


def met(ok: bool) -> str:
    return "**met**" if ok else "**missed**"


def disturbed(t: dict) -> str:
    n, total = (int(x) for x in t["clean"].split("/"))
    return "" if n == total else " — *timings of some seeds disturbed by other processes, so the time is an estimate*"


def write_markdown(result: dict, path: Path, plot_path: Path) -> None:
    m = result["machine"]
    L: list[str] = []
    L.append("# DAM core benchmark: fit speed/accuracy and render time (CPU)\n")
    L.append("Generated by `bench/dam_core.py`; the exact command (from the repository root):\n")
    L.append(f"```\n{result['command']}\n```\n")
    L.append(f"- date: {m['date_utc']} (the run took {result['total_seconds'] / 60:.1f} min, of which "
             f"{result['waited_for_quiet_seconds'] / 60:.1f} min waiting for other people's processes to leave the CPUs)")
    L.append(f"- machine: `nproc` = {m['nproc']}; CPU model (/proc/cpuinfo): {m['cpu_model']}")
    L.append(f"- torch {m['torch']} with `torch.set_num_threads({THREADS})`, numpy {m['numpy']}, Python {m['python']}, {m['platform']}")
    L.append(f"- seeds: {result['seeds']} (`FitOptions.seed`; the captures themselves use seed 0)")
    L.append(f"- raw numbers (per seed, with training histories): `{_shown(plot_path.with_name('dam_core.json'))}`; plot: `{_shown(plot_path)}`\n")
    co = next(iter(result["captures"].values()), {}).get("capture_options", {})
    L.append(f"Captures: `ClosedFormOptions(shape=..., light='env', views={co.get('views', 32)}, resolution={co.get('resolution', 128)}, "
             f"train_views={co.get('train_views', 10)}, seed=0)`: "
             "10 consecutive train views, 22 test views. **Novel-view** = the 22 test views; **same-view** = the 10 train views "
             "(RM/RM++ leave the frame itself out; the DAM saw them). Time = wall seconds of the `fit_dam` call (adversarial: "
             "building its whole-frame inputs, ~0.1 s, is not included; it is in the JSON). Ratio = DAM novel-view DSSIM / RM++ "
             "novel-view DSSIM per seed, then mean ± sample std over seeds. DSSIM does not depend on timing: fits are deterministic per seed.\n")
    L.append("Studies (rows after `holdout0_s8000`): `w32d2`/`w32d6` vary the DAM depth at width 32, `w16d4` the width at depth 4; `batch1024`/`batch16384` the pixels "
             "sampled per step; `input64`/`input32` train on every 2nd/4th pixel of each 128×128 training frame in both axes "
             "(64×64 / 32×32 inputs, subsampled in the benchmark, no filtering), while novel-view DSSIM is still measured on the "
             "full-resolution test views and same-view DSSIM on the full-resolution train views; `bfloat16` runs the training step "
             "under bfloat16 autocast (`FitOptions.precision`; weights stay float32); `wd0.03`/`wd0.1` add decoupled weight decay "
             "(`FitOptions.weight_decay`, AdamW), `wd0.1_s4000`/`wd0.1_s8000` with 4000 / 8000 steps; `q0.75` fits the 0.75-quantile "
             "(pinball) data cost instead of L1 (`FitOptions.quantile`), `q0.75_wd0.1` with weight decay 0.1; `sep44x4`/`sep32x4` "
             "fit a separable DAM, softplus(f(N) + g(R)) with block-diagonal hidden layers (`FitOptions.separable`; 3168 / 1728 "
             "weights); `predict_kK` predicts the DAM with the "
             "shipped learning-to-learn predictor from one train view and refines it K steps on all train views "
             "(`refine_dam`, as `damcap predict --refine-steps K`): its time is choosing and cropping the input view, the "
             "prediction and the refinement"
             + (f" (loading the predictor file, {result['predictor']['load_seconds']:.2f} s once, is not included)" if result.get("predictor") else "")
             + ", and its 'best step' is K when the refinement was kept (0: the prediction itself).\n")
    L.append(f"**Timing on a shared machine.** Other people's experiments, test runs and installs ran on the same 2 cores during this "
             f"benchmark; a 2-thread torch fit slows down by up to ~30x when it does not get both cores. Before each fit the script "
             f"waits (at most {result['quiet_wait_s']:.0f} s) for two quiet seconds; a fit during whose first 3 s other processes "
             f"take more than {ABORT_FRAC:.0%} of the CPUs is aborted and restarted (up to {result['max_aborts']} times); every fit "
             f"records, per 25-step window, the share of CPU time other processes used (/proc/stat minus this process). "
             f"A fit where others used more than {QUIET_FRAC:.0%} overall reports its *clean-window estimate* (disturbed windows "
             f"re-timed at the clean windows' mean speed) instead of its raw wall time; both are in the JSON. 'clean' in the tables "
             f"counts the seeds whose raw wall time was undisturbed.\n")
    if result.get("notes"):
        L.append("Notes:\n")
        L.extend(f"- {n}" for n in result["notes"])
        L.append("")

    L.append("## Targets\n")
    t = result["targets"]
    for cap_name, tt in t["per_capture"].items():
        L.append(f"### {cap_name} (RM++ novel-view DSSIM {tt['rmpp_test']:.4f})\n")
        d = tt["default"]
        if d:
            L.append(f"- **Default fit: ≤ 10 s and ≤ 0.5× RM++** — time {d['seconds_mean']:.2f} s mean, {d['seconds_max']:.2f} s worst seed "
                     f"(raw wall {d['seconds_raw_mean']:.2f} s; clean {d['clean']}): {met(d['time_ok'])}{disturbed(d)}"
                     f"{'' if d['time_ok'] == d['time_ok_all'] else ' on the mean, missed on the worst seed'}. "
                     f"Ratio {d['ratio_mean']:.3f} ± {d['ratio_std']:.3f}, worst seed {d['ratio_max']:.3f} (DAM DSSIM {d['dssim_mean']:.4f}): "
                     f"{met(d['ratio_ok'])}{'' if d['ratio_ok'] == d['ratio_ok_all'] else ' on the mean, missed on the worst seed'}.")
        else:
            L.append("- **Default fit**: not run.")
        b = tt["best"]
        if b:
            L.append(f"- **Best setting within 60 s: ≤ 0.35× RM++** — `{b['name']}`: ratio {b['ratio_mean']:.3f} ± {b['ratio_std']:.3f}, "
                     f"worst seed {b['ratio_max']:.3f} (DAM DSSIM {b['dssim_mean']:.4f}) at {b['seconds_mean']:.2f} s mean, "
                     f"{b['seconds_max']:.2f} s worst seed (clean {b['clean']}{disturbed(b)}): {met(b['ratio_ok'])}"
                     f"{'' if b['ratio_ok'] == b['ratio_ok_all'] else ' on the mean, missed on the worst seed'}.")
        elif tt.get("n_settings", 0) == 0:
            L.append("- **Best setting within 60 s**: not measured.")
        else:
            L.append("- **Best setting within 60 s**: no setting finished within 60 s: **missed**.")
        c = tt["steps_curve"]
        if c:
            L.append("- Steps curve (default options otherwise): " + "; ".join(
                f"{k} steps {v['seconds']:.1f} s → {v['ratio']:.3f}× RM++ (same-view DSSIM {v['same_view_dssim']:.4f})" for k, v in c.items())
                + (". More steps made novel views *worse* somewhere on this curve." if tt["steps_non_monotone"]
                   else ". Novel views improved monotonically with steps on this curve."))
        if len(tt["holdout_compare"]) > 1:
            L.append("- Hold-out stopping (ratio): " + ", ".join(f"`{k}` {v:.3f}" for k, v in tt["holdout_compare"].items()) + ".")
        for study, pts in tt.get("studies", {}).items():
            L.append(f"- Study, {study}: " + "; ".join(f"`{n}` {v['seconds']:.2f} s → {v['ratio']:.3f}× RM++" for n, v in pts.items()) + ".")
        L.append("")
    r = t["render"]
    if r:
        L.append("### Render\n")
        L.append(f"- **One 256×256 frame: ≤ 20 ms (median)** — median {r['median_ms']:.2f} ms over {r['runs']} runs "
                 f"(min {r['min_ms']:.2f}, max {r['max_ms']:.2f} ms; {r['covered_pixels']} covered pixels evaluated; default architecture; "
                 f"others used {r['foreign_cpu_frac']:.0%} of the CPUs meanwhile): {met(r['median_ms'] <= 20)}.\n")

    for cap_name, cap in result["captures"].items():
        L.append(f"## {cap_name}\n")
        bl = cap["baselines"]
        L.append(f"{cap['n_train_views']} train / {cap['n_test_views']} test views, {cap['n_training_pixels']} training pixels.\n")
        L.append("| baseline | novel-view DSSIM (test) | same-view DSSIM (train) |")
        L.append("|---|---|---|")
        for meth in ("RM++", "RM"):
            L.append(f"| {meth} | {bl['test'][meth]:.4f} | {bl['train'][meth]:.4f} |")
        L.append(f"\nRM's oracle source: {bl['rm_source_test']} (test), {bl['rm_source_train']} (train).\n")
        L.append("| setting | options (vs `FitOptions()`) | seeds | fit s | novel-view DSSIM | ratio to RM++ (min–max) | same-view DSSIM | best step per seed | clean |")
        L.append("|---|---|---|---|---|---|---|---|---|")
        for row in cap["settings"]:
            if row.get("alias_of"):
                L.append(f"| {row['name']} | same as `{row['alias_of']}` | | | | | | | |")
                continue
            ov = ", ".join(f"{k}={v}" for k, v in row["overrides"].items()) or "defaults"
            rs = row["ratio_test_to_rmpp"]
            L.append(f"| {row['name']} | {ov} | {','.join(str(s) for s in row['seeds'])} "
                     f"| {row['seconds']['mean']:.2f} ± {row['seconds']['std']:.2f} | {fmt(row['dssim_test'])} "
                     f"| {rs['mean']:.3f} ± {rs['std']:.3f} ({rs['min']:.3f}–{rs['max']:.3f}) | {fmt(row['dssim_train'])} "
                     f"| {'/'.join(str(x['best_step']) for x in row['per_seed'])} | {row['clean_timings']}/{len(row['seeds'])} |")
        L.append("")
    L.append(f"![Pareto plot: fit seconds vs novel-view DSSIM ratio to RM++]({os.path.relpath(plot_path, path.parent)})\n")
    path.write_text("\n".join(L) + "\n")


# --------------------------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------------------------


def load_shipped_predictor(data: dict[str, dict]) -> dict:
    """The shipped predictor (loaded once; loading is not part of a setting's time), its file's
    hash (part of the run keys) and one untimed warm-up prediction + refinement per capture
    (first-call allocations; fits get theirs from earlier fits in the same process)."""
    path = shipped_predictor_path(PAPER_SHIPPED)
    t = time.perf_counter()
    net, meta = load_predictor(path)
    load_s = time.perf_counter() - t
    for d in data.values():
        _, crop, scale = predictor_inputs(d["train"], net.arch.input_views)
        refine_dam(predict_dam(net, crop, scale), d["samples"], 5, PredictOptions.refine_learning_rate)
    log(f"predictor {path.name}: loaded in {load_s:.2f} s")
    return {"net": net, "name": path.name, "sha256": hashlib.sha256(path.read_bytes()).hexdigest(), "load_seconds": load_s,
            "command": meta.get("training", {}).get("command"), "dam_architecture": net.arch.dam.to_json()}


def predictor_options(predictor: dict, refine_steps: int) -> dict:
    """What a predictor setting runs (its row's options)."""
    return {"method": "predict_dam + refine_dam (damcap predict --refine-steps K)", "predictor": predictor["name"],
            "predictor_sha256": predictor["sha256"], "refine_steps": refine_steps,
            "refine_learning_rate": PredictOptions.refine_learning_rate,
            "refine_holdout_views": 0, "batch_size": FitOptions().batch_size}


def measure_setting(result: dict, data: dict, args, name: str, overrides: dict, cached_runs: dict, budget_left,
                    predictor: dict | None = None) -> None:
    fit_ov, bench_ov = split_overrides(overrides)
    if args.steps is not None and "predict_refine_steps" not in bench_ov:
        fit_ov = {**fit_ov, "steps": args.steps}
    k_refine = bench_ov.get("predict_refine_steps")
    for cap_name in args.captures:
        cap_data = setting_data(data[cap_name], bench_ov)
        per_seed = []
        for seed in args.seeds:
            opts = replace(FitOptions(), seed=seed, **fit_ov)
            key_extra = dict(bench_ov, **({"predictor_sha256": predictor["sha256"]} if k_refine is not None else {}))
            key = run_key(cap_name, opts, key_extra)
            if key in cached_runs:
                rec = cached_runs[key]["result"]
                log(f"{cap_name} {name} seed {seed}: reused ({rec['seconds']:.2f} s, novel DSSIM {rec['dssim_test']:.4f})")
            else:
                if k_refine is not None:
                    rec = predict_once(cap_data, predictor["net"], int(k_refine), seed, max_aborts=args.max_aborts,
                                       quiet_wait_s=args.quiet_wait, budget_left=budget_left)
                else:
                    rec = fit_once(cap_data, opts, max_aborts=args.max_aborts, quiet_wait_s=args.quiet_wait, budget_left=budget_left)
                append_run_log({"key": key, "result": rec}, args.runs_log)
                log(f"{cap_name} {name} seed {seed}: {rec['seconds']:.2f} s ({rec['timing_source']}; raw {rec['seconds_raw_wall']:.2f} s, "
                    f"others {rec['foreign_cpu_frac']:.0%}), novel DSSIM {rec['dssim_test']:.4f} (x{rec['ratio_test_to_rmpp']:.3f} RM++), "
                    f"same-view {rec['dssim_train']:.4f}, best step {rec['best_step']}")
            per_seed.append(rec)
        options = (predictor_options(predictor, int(k_refine)) if k_refine is not None
                   else asdict(replace(FitOptions(), **fit_ov)) | bench_ov) | {"seed": "per seed"}
        if "input_resolution" in cap_data:
            options["training_input_resolution"] = cap_data["input_resolution"]
        row = {
            "name": name,
            "overrides": overrides,
            "options": options,
            "seeds": args.seeds,
            "per_seed": per_seed,
            "seconds": stats_of([r["seconds"] for r in per_seed]),
            "seconds_raw_wall": stats_of([r["seconds_raw_wall"] for r in per_seed]),
            "dssim_test": stats_of([r["dssim_test"] for r in per_seed]),
            "dssim_train": stats_of([r["dssim_train"] for r in per_seed]),
            "ratio_test_to_rmpp": stats_of([r["ratio_test_to_rmpp"] for r in per_seed]),
            "training_pixels": per_seed[0].get("training_pixels", len(cap_data["samples"])) if per_seed else len(cap_data["samples"]),
            "clean_timings": sum(bool(r["clean_timing"]) for r in per_seed),
            "diverged_seeds": [r["seed"] for r in per_seed if not (r["finite_weights"] and math.isfinite(r["dssim_test"]))],
        }
        result["captures"][cap_name]["settings"].append(row)
        if row["diverged_seeds"]:
            result["notes"].append(f"{cap_name} `{name}`: non-finite weights or DSSIM for seeds {row['diverged_seeds']}")
    if name == "default" and args.render_runs > 0:
        log("render timing")
        result["render"] = time_render(FitOptions(), args.render_runs, args.quiet_wait, args.cache)
        log(f"render: median {result['render']['median_ms']:.2f} ms (others {result['render']['foreign_cpu_frac']:.0%})")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--only", nargs="*", default=None, help="setting names to run (default: all); see SETTINGS")
    ap.add_argument("--captures", nargs="*", default=list(CAPTURES))
    ap.add_argument("--resume", action="store_true", help="reuse fits recorded in bench/.cache/dam_core_runs.jsonl")
    ap.add_argument("--render-runs", type=int, default=20)
    ap.add_argument("--budget-minutes", type=float, default=30.0,
                    help="start no new setting after this many minutes, not counting waits for a quiet machine (priority order)")
    ap.add_argument("--max-aborts", type=int, default=8, help="restarts of a fit disturbed by other processes")
    ap.add_argument("--quiet-wait", type=float, default=1800.0,
                    help="seconds to wait for a quiet machine before each fit; if it never comes, the rest is skipped "
                         "(0 = do not wait; timings are still flagged when others used the CPUs)")
    ap.add_argument("--out", type=Path, default=None,
                    help="write dam_core.json, dam_core_pareto.png, dam_core.md and the run log here instead of "
                         "bench/results/, bench/ and bench/.cache/ (smoke runs)")
    ap.add_argument("--cache", type=Path, default=CACHE, help="where the generated captures are kept (default bench/.cache/)")
    ap.add_argument("--resolution", type=int, default=128, help="the captures' image size, px (smoke runs: smaller)")
    ap.add_argument("--views", type=int, default=32, help="the captures' views (smoke runs: fewer)")
    ap.add_argument("--train-views", type=int, default=10, help="the captures' consecutive training views")
    ap.add_argument("--steps", type=int, default=None,
                    help="fit steps of every fit setting, replacing its own (smoke runs; default: each setting's)")
    args = ap.parse_args(argv)
    unknown = sorted(set(args.only or []) - {n for n, _ in SETTINGS})
    if unknown:
        ap.error(f"--only: unknown setting(s) {unknown}; choose from {[n for n, _ in SETTINGS]}")
    unknown = sorted(set(args.captures) - set(CAPTURES))
    if unknown:
        ap.error(f"--captures: unknown capture(s) {unknown}; choose from {list(CAPTURES)}")
    results_dir = RESULTS if args.out is None else args.out
    md_path = BENCH / "dam_core.md" if args.out is None else args.out / "dam_core.md"
    args.runs_log = RUNS_LOG if args.out is None else args.out / "dam_core_runs.jsonl"

    torch.set_num_threads(THREADS)
    args.cache.mkdir(parents=True, exist_ok=True)
    results_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.time()
    command = f"cd {REPO} && " + command_line("dam_core", sys.argv[1:] if argv is None else argv)
    result: dict = {"command": command, "machine": machine_info(), "seeds": args.seeds, "captures": {}, "notes": [],
                    "quiet_wait_s": args.quiet_wait, "max_aborts": args.max_aborts, "budget_minutes": args.budget_minutes}
    cached_runs = load_run_log(args.runs_log) if args.resume else {}
    budget_left = lambda: 60 * args.budget_minutes - (time.time() - t_start - WAITED_S)

    data: dict[str, dict] = {}
    for cap_name in args.captures:
        cap_opts = replace(CAPTURES[cap_name], resolution=args.resolution, views=args.views, train_views=args.train_views)
        size = "" if (args.views, args.train_views) == (32, 10) else f"_{args.views}v{args.train_views}t"
        cap = read_capture(ensure_capture(f"{cap_name}_{args.resolution}{size}", cap_opts, args.cache))
        train, test = load_views(cap, "train"), load_views(cap, "test")
        samples = samples_of(train)
        t = time.perf_counter()
        base_test = evaluate_split(train, test, {}, baselines=True)
        base_train = evaluate_split(train, train, {}, baselines=True)
        baselines = {
            "test": {k: v.mean for k, v in base_test.items()},
            "train": {k: v.mean for k, v in base_train.items()},
            "test_per_frame": {k: v.per_frame for k, v in base_test.items()},
            "train_per_frame": {k: v.per_frame for k, v in base_train.items()},
            "rm_source_test": base_test["RM"].note,
            "rm_source_train": base_train["RM"].note,
            "seconds": time.perf_counter() - t,
        }
        log(f"{cap_name}: {len(train)} train / {len(test)} test views, {len(samples)} training pixels; "
            f"RM++ test {baselines['test']['RM++']:.4f} train {baselines['train']['RM++']:.4f}; "
            f"RM test {baselines['test']['RM']:.4f} train {baselines['train']['RM']:.4f}")
        data[cap_name] = {"train": train, "test": test, "samples": samples, "rmpp_test": baselines["test"]["RM++"]}
        result["captures"][cap_name] = {"capture_options": asdict(cap_opts), "n_train_views": len(train), "n_test_views": len(test),
                                        "n_training_pixels": len(samples), "baselines": baselines, "settings": []}

    settings = [s for s in SETTINGS if args.only is None or s[0] in args.only]
    predictor = None
    if any("predict_refine_steps" in ov for _, ov in settings):
        predictor = load_shipped_predictor(data)
        result["predictor"] = {k: v for k, v in predictor.items() if k != "net"}
    skipped, busy = [], None
    for si, (name, overrides) in enumerate(settings):
        if busy or (si > 0 and budget_left() < 0):
            skipped.append(name)
            continue
        try:
            measure_setting(result, data, args, name, overrides, cached_runs, budget_left, predictor)
        except MachineBusy as e:
            busy = f"stopped at setting `{name}`: {e}"
            log(busy)
            skipped.append(name)
    if busy:
        result["notes"].append(busy)
    if skipped:
        result["notes"].append(f"settings not run or not run on every capture (time budget of {args.budget_minutes:.0f} active minutes, or a busy machine): {', '.join(skipped)}")
    for cap_name in args.captures:
        rows = result["captures"][cap_name]["settings"]
        names = {r["name"] for r in rows}
        rows.extend({"name": a, "alias_of": of} for a, of in ALIASES if of in names)
    result["targets"] = compute_targets(result)
    result["total_seconds"] = time.time() - t_start
    result["waited_for_quiet_seconds"] = WAITED_S

    (results_dir / "dam_core.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    pareto_plot(result, results_dir / "dam_core_pareto.png")
    write_markdown(result, md_path, results_dir / "dam_core_pareto.png")
    log(f"done in {result['total_seconds'] / 60:.1f} min: {results_dir / 'dam_core.json'}, {md_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
