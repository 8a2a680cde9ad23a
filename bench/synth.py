"""Benchmark: the synthetic data set (``damcap synth`` / ``synth-set``) on this machine.

Stages (``--stages``, default all, in this order):

* ``throughput``: images per second at 128x128 and 256x256, 64 spp (bunny, one material, an
  environment map): the path tracer alone, and whole frames (ray-cast geometry + render +
  validation + EXR writes) through ``make_synthetic_capture``.
* ``noise``: the path-tracing noise floor: DSSIM (docs/capture-format.md) between two renders of the
  same views with different sampler seeds, at 64..1024 spp under environment maps and 16..256 spp
  under the point light, 128x128; plus the paper preset's setting at 256x256.
* ``small``: ``damcap synth-set --preset small`` timed from scratch (in ``bench/.cache``).
* ``paper``: the paper preset's time, estimated from measured per-frame times at its settings
  (256x256; see ``synth_set.preset('paper')``) times its 720 x 32 frames -- rendering it all here
  is not feasible; the estimate says so.
* ``table1``: the paper's Table 1 representation rows on the held-out, single-material captures
  of the small preset: mean DSSIM of a DAM fit (``fit_dam`` with default ``FitOptions``, 3 fit
  seeds) vs RM++ and RM, same view (train frames) and novel view (test frames), point light and
  environment map, with each capture's own noise floor (its frames re-rendered with another
  seed, compared with the stored ones).
* ``why``: what limits the DAM on each held-out capture, measured: (a) the same views, geometry
  and material re-shaded with local shading only (the renderer's light and BRDF, no shadows, no
  interreflection: exactly a function of (V, N), which a DAM can represent), fitted and
  evaluated the same way; (b) how far the test pixels' DAM inputs (normal, mirrored view) lie
  from the nearest training input (extrapolation); (c) a DAM fitted to all 32 views, scored on
  the test views (how much of the novel-view error is extrapolation rather than representation).
* ``anchor``: the ``table1`` protocol on training-part captures (the small preset's bunny under
  the point light and sphere under an environment map, and a bunny under the studio map rendered
  at the small preset's settings): context for the issue's bunny anchor, not the target.
* ``activation``: how ``FitOptions.activation`` was chosen: the default (shifted softplus), leaky
  ReLU and plain softplus, 2 fit seeds, on seven training-part captures (the anchor stage's three
  and four more rendered here); the held-out captures play no part.
* ``weight_decay``: ``FitOptions.weight_decay`` (0 by default) at several strengths and step
  counts on the same training-part captures, then the best of them on the held-out Table 1
  captures next to the ``table1`` stage's default rows.
* ``design``: the rest of the fit's design on the same training-part captures: the input encoding
  (``nr``, ``vnr``, ``vn``), smaller networks than the default 32x4, and the paper's adversarial
  cost, 2 fit seeds.
* ``quantile``: the data cost's quantile (``FitOptions.quantile``, 0.5 = L1 by default), alone
  and with weight decay 0.1, on the same training-part captures; then the best of them on the
  held-out Table 1 captures.
* ``separable``: a separable DAM, f(N) + g(R) (``FitOptions.separable``): 44x4 (about the
  paper's size), 32x4, 44x3, 44x4 with 4000 steps, with weight decay 0.1 and with weight decay
  plus the 0.75-quantile cost, on the same training-part captures; then 44x4 and the best of
  them on the held-out Table 1 captures, over the ``table1`` stage's fit seeds and three more.

Every timed section records the wall time and the CPU time other processes took meanwhile
(the machine is shared). Outputs: ``bench/results/synth.json`` (stages merged into an existing
file, so stages can be rerun alone) and ``bench/synth.md``.

Run (from the repository root)::

    .venv/bin/python -m bench.synth

``--out DIR`` writes synth.json and synth.md into DIR (merging into DIR/synth.json) instead of
bench/results/ and bench/; ``--corpus DIR`` and ``--fit-steps N`` run the ``table1`` stage on another
corpus with shorter fits (smoke runs).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

from bench.common import BENCH, CACHE, REPO, RESULTS, CpuMeter, command_line, cpu_model, log, shared_data_dir

from damcap.appearance.views import ViewData
from damcap.appearance.evaluate import evaluate_split
from damcap.appearance.fit import FitOptions, fit_dam
from damcap.appearance.metrics import dssim
from damcap.appearance.pixels import PixelSamples
from damcap.appearance.fit import adversarial_frames
from damcap.appearance.views import load_views, samples_of
from damcap.common.capture_folder import read_capture, read_frame
from damcap.synth.mitsuba_capture import SynthOptions, compose_frame, make_synthetic_capture, render_seeds, resolve_scene
from damcap.synth.geometry import GeometryBuffers, RayCaster, frame_geometry
from damcap.synth.mitsuba_render import build_scene, pass_sample_counts, render_view, select_variant
from damcap.synth.corpus import plan_corpus, preset

DATA = shared_data_dir()
STAGES = ("throughput", "noise", "small", "paper", "table1", "why", "anchor", "activation", "weight_decay", "design", "quantile",
          "separable")
TARGET_NOVEL_RATIO = 0.5
"""the issue's target: novel-view DAM / RM++ at most this in both Table 1 columns"""
#: seed offset of the second render in noise-floor measurements
NOISE_SEED_OFFSET = 7919


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


class Timed(CpuMeter):
    """A :class:`CpuMeter` section with this benchmark's JSON record."""

    def as_dict(self) -> dict:
        return {"wall_s": round(self.wall, 3), "own_cpu_s": round(self.own_cpu, 3), "idle_s": round(self.idle, 3),
                "foreign_cpu_frac": round(self.foreign_frac, 3)}


def machine_info() -> dict:
    import drjit as dr
    import mitsuba as mi

    return {
        "date_utc": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC"),
        "nproc": os.cpu_count(), "cpu_model": cpu_model(), "mem_gib": round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1),
        "mitsuba": mi.__version__, "drjit": dr.__version__, "variant": select_variant("auto"), "drjit_threads": dr.thread_count(),
        "torch": torch.__version__, "torch_threads": torch.get_num_threads(), "python": platform.python_version(),
        "platform": platform.platform(),
    }


def bunny_options(light: str, resolution: int, spp: int, views: int = 32, seed: int = 0) -> SynthOptions:
    return SynthOptions(object=str(DATA / "meshes" / "stanford-bunny.obj"), light=light, materials=1, views=views,
                        resolution=resolution, spp=spp, seed=seed)


def env(name: str, rotation: float = 0.0) -> str:
    return f"env:{DATA / 'envmaps' / name}:{rotation:g}"


class SceneRenderer:
    """A capture's scene, ready to re-render any of its views with any seed."""

    def __init__(self, opts: SynthOptions) -> None:
        from damcap.synth.mitsuba_capture import camera_setup

        select_variant(opts.variant)
        self.opts = opts
        self.desc = resolve_scene(opts)
        self.scene = build_scene(self.desc.parts, self.desc.materials, self.desc.light, opts.max_depth)
        self.caster = RayCaster(self.desc.geometry)
        self.cams, self.intr, _, _ = camera_setup(opts)

    def render(self, view: int, spp: int, seed: int, geometry: GeometryBuffers | None = None) -> tuple[np.ndarray, GeometryBuffers]:
        """Radiance of one view as a capture stores it (un-premultiplied, 0 off the object)."""
        geo = geometry or frame_geometry(self.caster, self.cams[view], self.intr, self.opts.supersample)
        pass_spp = pass_sample_counts(spp, self.intr.w, self.intr.h)
        rad, alpha = render_view(self.scene, self.cams[view], self.intr, pass_spp, render_seeds(seed, view, len(pass_spp)))
        return compose_frame(rad, alpha, geo).radiance_lin, geo


def noise_floor_pair(r: SceneRenderer, views: list[int], spp: int) -> dict:
    vals = []
    with Timed() as t:
        for v in views:
            a, geo = r.render(v, spp, r.opts.seed)
            b, _ = r.render(v, spp, r.opts.seed + NOISE_SEED_OFFSET, geo)
            d = dssim(a, b, geo.coverage)
            if d is not None:
                vals.append(d)
    return {"spp": spp, "views": views, "dssim_mean": statistics.fmean(vals), "dssim_per_view": vals,
            "s_per_image": t.wall / (2 * len(views)), **t.as_dict()}


# --------------------------------------------------------------------------------------------
# stages
# --------------------------------------------------------------------------------------------


def stage_throughput() -> dict:
    out = {}
    for res in (128, 256):
        r = SceneRenderer(bunny_options(env("studio.hdr"), res, 64))
        r.render(0, 64, 1)  # warm-up: kernel compilation
        n = 8 if res == 128 else 4
        with Timed() as t:
            for v in range(1, n + 1):
                r.render(v, 64, 1)
        render_only = {"images": n, "images_per_s": n / t.wall, "images_per_s_idle": n / t.idle, **t.as_dict()}
        cap = CACHE / f"synth_throughput_{res}"
        shutil.rmtree(cap, ignore_errors=True)
        frames = 8 if res == 128 else 4
        opts = replace(bunny_options(env("studio.hdr"), res, 64, views=frames), train_views=2)
        with Timed() as t:
            make_synthetic_capture(cap, opts)
        shutil.rmtree(cap, ignore_errors=True)
        whole = {"frames": frames, "frames_per_s": frames / t.wall, "frames_per_s_idle": frames / t.idle,
                 "includes": "scene set-up, kernel compilation, geometry, validation, EXR writes", **t.as_dict()}
        out[f"{res}x{res}"] = {"spp": 64, "render_only": render_only, "whole_frames": whole}
        log(f"throughput {res}: render {render_only['images_per_s']:.2f} img/s, whole {whole['frames_per_s']:.2f} frames/s "
            f"(others used {t.foreign_frac:.0%} of the cores)")
    return out


def stage_noise() -> dict:
    out = []
    views = [0, 8, 16, 24]
    paper = preset("paper")
    settings = [(env("studio.hdr"), "env studio", 128, (64, 256, 1024)),
                (env("sunset.hdr", 90), "env sunset (held out)", 128, (64, 128, 256, 512)),
                ("point:52.5:22.9", "point", 128, (16, 64, 128, 256)),
                (env("sunset.hdr", 90), "env sunset (held out)", paper.resolution, (paper.spp_env,))]
    for light, label, res, spps in settings:
        r = SceneRenderer(bunny_options(light, res, 64, seed=3))
        r.render(0, 4, 0)  # warm-up
        for spp in spps:
            rec = noise_floor_pair(r, views if res == 128 else views[:2], spp)
            rec.update({"light": label, "resolution": res})
            out.append(rec)
            log(f"noise {label} {res}px {spp} spp: DSSIM {rec['dssim_mean']:.4f} ({rec['s_per_image']:.2f} s/image)")
    return {"object": "stanford-bunny, 1 material (seed 3)", "rows": out}


def small_corpus_dir() -> Path:
    return CACHE / "synth_small"


def stage_small(jobs: int, fresh: bool) -> dict:
    out = small_corpus_dir()
    if fresh and out.exists():
        shutil.rmtree(out)
    cmd = [str(REPO / ".venv" / "bin" / "damcap"), "synth-set", str(out), "--preset", "small", "--jobs", str(jobs), "--data", str(DATA)]
    log("small preset: " + " ".join(cmd))
    with Timed() as t:
        proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"synth-set failed ({proc.returncode}): {proc.stderr[-2000:]}")
    doc = json.loads((out / "corpus.json").read_text())
    per = [{"name": c["name"], "seconds": c["seconds"], "light": c["light_kind"], "materials": c["materials"], "status": c["status"]}
           for c in doc["captures"]]
    log(f"small preset: {t.wall:.0f} s for {len(per)} captures (others used {t.foreign_frac:.0%} of the cores)")
    return {"command": " ".join(["damcap"] + cmd[1:]), "captures": len(per), "jobs": jobs, "fresh": fresh,
            "per_capture": per, "target_s": 600, **t.as_dict()}


def stage_paper() -> dict:
    p = preset("paper")
    entries, options = plan_corpus(p, DATA)
    rows = {}
    for kind, spp, light in (("env", p.spp_env, env("sunset.hdr", 90)), ("point", p.spp_point, "point:52.5:22.9")):
        cap = CACHE / f"synth_paper_{kind}"
        shutil.rmtree(cap, ignore_errors=True)
        opts = replace(bunny_options(light, p.resolution, spp, views=3, seed=1), train_views=2)
        with Timed() as t:
            make_synthetic_capture(cap, opts)
        shutil.rmtree(cap, ignore_errors=True)
        rows[kind] = {"spp": spp, "resolution": p.resolution, "frames_timed": 3, "s_per_frame": t.wall / 3,
                      "s_per_frame_idle": t.idle / 3, **t.as_dict()}
        log(f"paper preset frame ({kind}, {spp} spp, {p.resolution}px): {t.wall / 3:.1f} s/frame")
    n = {k: sum(e.light_kind == k for e in entries) for k in ("env", "point")}
    total = sum(n[k] * p.views * rows[k]["s_per_frame"] for k in n)
    total_idle = sum(n[k] * p.views * rows[k]["s_per_frame_idle"] for k in n)
    return {"captures": len(entries), "captures_by_light": n, "views": p.views, "per_frame": rows, "estimated_s": total,
            "estimated_h": total / 3600, "estimated_h_idle": total_idle / 3600, "measured": False,
            "note": "estimated from per-frame times measured on the bunny (3 frames each, including scene set-up); "
                    "rendering all 720 captures here is not feasible"}


def _capture_noise_floor(root: Path, every: int) -> dict[str, float]:
    """DSSIM between the stored radiance and a re-render with another seed, for every
    ``every``-th frame (the floor of a split is then the mean over its re-rendered frames)."""
    cap = read_capture(root)
    opts = SynthOptions(**cap.extra["damcap_source"]["options"])
    r = SceneRenderer(opts)
    out = {}
    for i, f in enumerate(cap.frames):
        if i % every:
            continue
        d = read_frame(cap, f, with_weights=False)
        geo = GeometryBuffers(d.normal_world, d.position_world, d.coverage, np.zeros(d.coverage.shape + (1,), np.float32))
        again, _ = r.render(i, opts.spp, opts.seed + NOISE_SEED_OFFSET, geo)
        out[f.name] = dssim(d.radiance_lin, again, d.coverage)
    return out


def summarise_table1(per_capture: list[dict], fit_seeds: list[int]) -> dict:
    """Table 1 cells (point / env x same / novel view): means over the captures of each light;
    the DAM's spread is the std over fit seeds of the per-seed means."""
    table = {}
    for kind in ("point", "env"):
        rows = [r for r in per_capture if r["light_kind"] == kind]
        cell = {}
        for col in ("same_view", "novel_view"):
            per_seed = [statistics.fmean(next(f[col] for f in r["fits"] if f["seed"] == s) for r in rows) for s in fit_seeds]
            c = {
                "DAM": statistics.fmean(per_seed), "DAM_std_over_fits": statistics.stdev(per_seed) if len(per_seed) > 1 else 0.0,
                "RM++": statistics.fmean(r["baselines"][col]["RM++"] for r in rows),
                "RM": statistics.fmean(r["baselines"][col]["RM"] for r in rows),
                "noise_floor": statistics.fmean(r["noise_floor"][col] for r in rows),
            }
            c["DAM/RM++"] = c["DAM"] / c["RM++"]
            c["DAM/RM++_per_fit_seed"] = [x / c["RM++"] for x in per_seed]
            cell[col] = c
        table[kind] = cell
    return table


def split_views(root: Path) -> tuple[list[ViewData], list[ViewData], PixelSamples]:
    """A capture's train views, test views and training pixels."""
    cap = read_capture(root)
    train, test = load_views(cap, "train"), load_views(cap, "test")
    return train, test, samples_of(train)


def table1_capture(root: Path, c: dict, fit_seeds: list[int], floor_every: int, fit: FitOptions = FitOptions()) -> dict:
    """One capture's Table 1 record: its noise floor, DAM fits (one per seed) and RM++ / RM, same
    view (train frames) and novel view (test frames). ``c``: its corpus entry (name, object, light)."""
    train, test, samples = split_views(root)
    with Timed() as tn:
        floor = _capture_noise_floor(root, floor_every)
    rec = {"name": c["name"], "object": c["object"], "light": c["light"], "light_kind": c["light_kind"],
           "noise_floor": {split: statistics.fmean(floor[v.name] for v in views if floor.get(v.name) is not None)
                           for split, views in (("same_view", train), ("novel_view", test))},
           "noise_floor_frames": sorted(floor), "noise_floor_s": round(tn.wall, 1), "fits": []}
    base = None
    for s in fit_seeds:
        with Timed() as tf:
            fitted = fit_dam(samples, replace(fit, seed=s))
        res_same = evaluate_split(train, train, {"DAM": fitted.model}, baselines=base is None)
        res_novel = evaluate_split(train, test, {"DAM": fitted.model}, baselines=base is None)
        if base is None:
            base = {"same_view": {m: res_same[m].mean for m in ("RM++", "RM")},
                    "novel_view": {m: res_novel[m].mean for m in ("RM++", "RM")}}
        rec["fits"].append({"seed": s, "fit_s": round(fitted.seconds, 2), "best_step": fitted.best_step,
                            "same_view": res_same["DAM"].mean, "novel_view": res_novel["DAM"].mean, **tf.as_dict()})
    rec["baselines"] = base
    rec["dam"] = {k: statistics.fmean(f[k] for f in rec["fits"]) for k in ("same_view", "novel_view")}
    log(f"table1 {c['name']}: DAM same {rec['dam']['same_view']:.4f} novel {rec['dam']['novel_view']:.4f} | "
        f"RM++ same {base['same_view']['RM++']:.4f} novel {base['novel_view']['RM++']:.4f} | "
        f"floor same {rec['noise_floor']['same_view']:.4f} novel {rec['noise_floor']['novel_view']:.4f}")
    return rec


def stage_table1(fit_seeds: list[int], floor_every: int, corpus_dir: Path | None = None, fit: FitOptions = FitOptions()) -> dict:
    corpus_dir = corpus_dir or small_corpus_dir()
    corpus = json.loads((corpus_dir / "corpus.json").read_text())
    held = [c for c in corpus["captures"] if c["split"] == "heldout" and c["materials"] == 1]
    if not held or any(c["status"] not in ("done", "skipped") for c in held):
        raise SystemExit("run the 'small' stage first: held-out captures are missing")
    per_capture = [table1_capture(corpus_dir / c["path"], c, fit_seeds, floor_every, fit) for c in held]
    table = summarise_table1(per_capture, fit_seeds)
    return {"captures": [c["name"] for c in held], "fit_options": asdict(fit), "fit_seeds": fit_seeds, "floor_every": floor_every,
            "table": table, "per_capture": per_capture, "target_novel_ratio": TARGET_NOVEL_RATIO}


ANCHOR_SMALL = ("stanford-bunny__point-03__m1", "sphere__env-forest-r180__m1")
"""training-part, single-material captures of the small preset used by the ``anchor`` stage"""


ANCHOR_RENDERED = CACHE / "synth_anchor" / "stanford-bunny__env-studio-r000__m1"
"""the bunny under the studio map that the ``anchor`` stage renders"""
DEV_COMBOS = (("armadillo.obj", "env-forest-r000", 1), ("cow.obj", "point-05", 1), ("beetle.obj", "env-museum-r180", 1),
              ("igea.ply", "point-11", 1))
"""four more training-part captures (object, illumination, materials) for the ``activation`` stage,
rendered at the small preset's settings"""
DEV_SEEDS = (11, 12, 13, 14)
"""their render seeds (those the activation was chosen on; the preset's own would be per name)"""
ACTIVATION_VARIANTS = {"default": {}, "leaky_relu": {"activation": "leaky_relu"}, "softplus": {"activation": "softplus"}}


def training_part_roots() -> list[Path]:
    """The seven training-part single-material captures that fit defaults are chosen on: the
    anchor stage's three and DEV_COMBOS (rendered here, or reused, at the small preset's 128 px
    and 32 views). The held-out captures are not among them."""
    roots = [small_corpus_dir() / "captures" / n for n in ANCHOR_SMALL] + [ANCHOR_RENDERED]
    if not all((r / "transforms.json").is_file() for r in roots):
        raise SystemExit("run the 'small' and 'anchor' stages first")
    entries, options = plan_corpus(replace(preset("small"), combos=DEV_COMBOS), DATA)
    for e, opts, seed in zip(entries, options, DEV_SEEDS):
        root = CACHE / "synth_dev" / e.name
        make_synthetic_capture(root, replace(opts, seed=seed), threads=os.cpu_count())  # resumes / skips a finished render
        roots.append(root)
    return roots


def novel_ratios(root: Path, variants: dict[str, dict], fit_seeds: list[int]) -> dict[str, list[float]]:
    """Novel-view DSSIM / RM++ of a DAM fitted with each variant's FitOptions overrides, per fit seed."""
    train, test, samples = split_views(root)
    rm_pp, out = None, {}
    for label, ov in variants.items():
        per = []
        for seed in fit_seeds:
            opts = FitOptions(seed=seed, **ov)
            fit = fit_dam(samples, opts, frames_for_adversarial=adversarial_frames(train, samples, opts))
            res = evaluate_split(train, test, {"DAM": fit.model}, baselines=rm_pp is None)
            rm_pp = res["RM++"].mean if rm_pp is None else rm_pp
            per.append(res["DAM"].mean / rm_pp)
        out[label] = per
    return out


def dev_rows(stage: str, variants: dict[str, dict], fit_seeds: list[int]) -> list[dict]:
    """Per training-part capture (:func:`training_part_roots`): its name and :func:`novel_ratios`
    of ``variants``, logged as ``stage``."""
    rows = []
    for root in training_part_roots():
        t = time.perf_counter()
        rows.append({"name": root.name, "ratio_novel": novel_ratios(root, variants, fit_seeds)})
        log(f"{stage} {root.name} ({time.perf_counter() - t:.0f} s): "
            + ", ".join(f"{k} {statistics.fmean(v):.2f}" for k, v in rows[-1]["ratio_novel"].items()))
    return rows


def reused_dev_rows(res: dict, key: str, stage: str, variants: dict[str, dict], fit_seeds: list[int]) -> list[dict]:
    """:func:`dev_rows` of ``variants``, or those stored in ``res[key]`` when they were made for
    the same variants and fit seeds (refits in another process agree to about 0.2 %)."""
    prev = res.get(key, {})
    if prev.get("variants") == variants and prev.get("dev_fit_seeds") == fit_seeds:
        log(f"{stage}: training-part results reused from bench/results/synth.json")
        return prev["dev_rows"]
    return dev_rows(stage, variants, fit_seeds)


def stage_activation(fit_seeds: list[int]) -> dict:
    """How FitOptions.activation was chosen: novel-view DSSIM / RM++ of the default (shifted
    softplus), leaky ReLU and plain softplus on the training-part captures
    (:func:`training_part_roots`), fit seeds ``fit_seeds``."""
    return {"fit_seeds": fit_seeds, "default": FitOptions().activation, "rows": dev_rows("activation", ACTIVATION_VARIANTS, fit_seeds)}


REGULARISED_VARIANTS: dict[str, dict] = {
    "0": {},
    "0, 4000 steps": {"steps": 4000},
    "0.03": {"weight_decay": 0.03},
    "0.1": {"weight_decay": 0.1},
    "0.2": {"weight_decay": 0.2},
    "0.1, 4000 steps": {"weight_decay": 0.1, "steps": 4000},
    "0.2, 4000 steps": {"weight_decay": 0.2, "steps": 4000},
    "0.1, 8000 steps": {"weight_decay": 0.1, "steps": 8000},
}
"""the ``weight_decay`` stage's fits, by label: FitOptions overrides (weight decay, and steps,
since the decay acts once per step); "0" is ``FitOptions()``"""


def mean_ratio(rows: list[dict], label: str) -> float:
    """Mean over captures of each capture's mean over fit seeds of ``ratio_novel[label]``."""
    return statistics.fmean(statistics.fmean(r["ratio_novel"][label]) for r in rows)


def stage_weight_decay(fit_seeds: list[int], res: dict) -> dict:
    """Weight decay (``FitOptions.weight_decay``, default 0): novel-view DSSIM / RM++ on the
    training-part captures (fit seeds ``fit_seeds[:2]``) for each of REGULARISED_VARIANTS; then
    two of them on the held-out captures (Table 1's representation rows, next to the ``table1``
    stage's default rows: same captures, seeds and baselines): the best on the training-part
    captures among those with the default number of steps (a fit as fast as the default), and
    the best of all. Training-part results already in ``res`` for the same variants and seeds
    are reused rather than refitted (refits in another process agreed to about 0.2 %)."""
    if "table1" not in res:
        raise SystemExit("run the 'table1' stage first")
    rows = reused_dev_rows(res, "weight_decay", "weight decay", REGULARISED_VARIANTS, fit_seeds[:2])
    by_dev = lambda label: mean_ratio(rows, label)  # noqa: E731
    choices = {"same_steps": min((k for k, v in REGULARISED_VARIANTS.items() if "steps" not in v), key=by_dev),
               "overall": min(REGULARISED_VARIANTS, key=by_dev)}
    heldout = heldout_tables("weight decay", {label: REGULARISED_VARIANTS[label] for label in choices.values()}, res["table1"])
    return {"dev_fit_seeds": fit_seeds[:2], "variants": REGULARISED_VARIANTS, "dev_rows": rows, "choices": choices,
            "heldout": heldout}


def heldout_tables(stage: str, variants: dict[str, dict], t1: dict) -> dict:
    """Table 1's representation rows for each of ``variants`` (label -> FitOptions overrides) on
    the ``table1`` stage's held-out captures, with its fit seeds and baselines."""
    per_capture: dict[str, list[dict]] = {label: [] for label in variants}
    for rec in t1["per_capture"]:
        train, test, samples = split_views(small_corpus_dir() / "captures" / rec["name"])
        for label, ov in variants.items():
            fits = []
            for seed in t1["fit_seeds"]:
                fit = fit_dam(samples, FitOptions(seed=seed, **ov))
                fits.append({"seed": seed, "fit_s": round(fit.seconds, 2),
                             "same_view": evaluate_split(train, train, {"DAM": fit.model}, baselines=False)["DAM"].mean,
                             "novel_view": evaluate_split(train, test, {"DAM": fit.model}, baselines=False)["DAM"].mean})
            per_capture[label].append({**{k: rec[k] for k in ("name", "light_kind", "baselines", "noise_floor")}, "fits": fits})
            log(f"{stage} {label} held-out {rec['name']}: novel "
                f"{statistics.fmean(f['novel_view'] for f in fits):.4f} (default {rec['dam']['novel_view']:.4f})")
    return {label: {"options": ov, "per_capture": per_capture[label], "table": summarise_table1(per_capture[label], t1["fit_seeds"])}
            for label, ov in variants.items()}


QUANTILE_VARIANTS: dict[str, dict] = {
    f"{q}{', wd 0.1' if wd else ''}": {"quantile": q, **({"weight_decay": wd} if wd else {})}
    for wd in (0.0, 0.1) for q in (0.65, 0.75, 0.85)
}
"""the ``quantile`` stage's fits, by label: the data cost's quantile (0.5 = L1, the weight decay
stage's '0' and '0.1'), alone and with weight decay 0.1; 2000 steps"""


def stage_quantile(fit_seeds: list[int], res: dict) -> dict:
    """The data cost's quantile (``FitOptions.quantile``, default 0.5 = L1): novel-view
    DSSIM / RM++ on the training-part captures (fit seeds ``fit_seeds[:2]``) for each of
    QUANTILE_VARIANTS, then the best of them on the held-out captures (Table 1's representation
    rows, next to the ``table1`` and ``weight_decay`` stages' rows). The L1 columns (quantile 0.5,
    without and with weight decay 0.1) are the ``weight_decay`` stage's fits: same captures and
    seeds."""
    if "table1" not in res or "weight_decay" not in res:
        raise SystemExit("run the 'table1' and 'weight_decay' stages first")
    rows = dev_rows("quantile", QUANTILE_VARIANTS, fit_seeds[:2])
    chosen = min(QUANTILE_VARIANTS, key=lambda label: mean_ratio(rows, label))
    return {"dev_fit_seeds": fit_seeds[:2], "variants": QUANTILE_VARIANTS, "dev_rows": rows, "chosen": chosen,
            "heldout": heldout_tables("quantile", {chosen: QUANTILE_VARIANTS[chosen]}, res["table1"])}


SEPARABLE_44X4 = {"width": 44, "separable": True}
"""a separable DAM of about the paper's size: two branches of 22 units x 4 layers, 3168 weights"""
SEPARABLE_VARIANTS: dict[str, dict] = {
    "44x4": SEPARABLE_44X4,
    "32x4": SEPARABLE_44X4 | {"width": 32},
    "44x3": SEPARABLE_44X4 | {"depth": 3},
    "44x4, 4000 steps": SEPARABLE_44X4 | {"steps": 4000},
    "44x4, wd 0.1": SEPARABLE_44X4 | {"weight_decay": 0.1},
    "44x4, q 0.75, wd 0.1": SEPARABLE_44X4 | {"quantile": 0.75, "weight_decay": 0.1},
}
"""the ``separable`` stage's fits, by label (width x depth, both branches counted in the width)"""


def stage_separable(fit_seeds: list[int], res: dict) -> dict:
    """A separable DAM (``FitOptions.separable``: softplus(f(N) + g(R)), block-diagonal hidden
    layers): novel-view DSSIM / RM++ on the training-part captures (fit seeds ``fit_seeds[:2]``)
    for each of SEPARABLE_VARIANTS; then, on the held-out captures (Table 1's representation
    rows), two fits named before any held-out fit was made: the plain 44x4 network and the best
    variant on the training-part captures, with the ``table1`` stage's fit seeds and with as many
    more (the point-light column's seeds differ widely). Training-part results already in
    ``res`` for the same variants and seeds are reused rather than refitted."""
    if "table1" not in res:
        raise SystemExit("run the 'table1' stage first")
    rows = reused_dev_rows(res, "separable", "separable", SEPARABLE_VARIANTS, fit_seeds[:2])
    chosen = min(SEPARABLE_VARIANTS, key=lambda label: mean_ratio(rows, label))
    variants = {label: SEPARABLE_VARIANTS[label] for label in dict.fromkeys(("44x4", chosen))}
    t1 = res["table1"]
    more_seeds = [max(t1["fit_seeds"]) + 1 + k for k in range(len(t1["fit_seeds"]))]
    heldout = heldout_tables("separable", variants, t1)
    more = heldout_tables("separable", variants, {**t1, "fit_seeds": more_seeds})
    all_seeds = t1["fit_seeds"] + more_seeds
    pooled = {}
    for label in variants:
        per_capture = [{**a, "fits": a["fits"] + b["fits"]} for a, b in zip(heldout[label]["per_capture"], more[label]["per_capture"])]
        pooled[label] = {"per_capture": per_capture, "table": summarise_table1(per_capture, all_seeds)}
    weights = {k: FitOptions(**v).architecture.num_weights for k, v in SEPARABLE_VARIANTS.items()}
    return {"dev_fit_seeds": fit_seeds[:2], "variants": SEPARABLE_VARIANTS, "num_weights": weights, "dev_rows": rows,
            "chosen": chosen, "heldout": heldout, "heldout_all_seeds": {"fit_seeds": all_seeds, "by_variant": pooled}}


DESIGN_VARIANTS: dict[str, dict] = {
    "default": {},
    "vnr": {"encoding": "vnr"},
    "vn": {"encoding": "vn"},
    "24x3": {"width": 24, "depth": 3},
    "16x4": {"width": 16},
    "32x2": {"depth": 2},
    "16x2": {"width": 16, "depth": 2},
    "adversarial": {"adversarial": True},
}
"""the ``design`` stage's fits, by label: FitOptions overrides ("default" is ``FitOptions()``, a
32x4 network on the encoding 'nr'); sizes are width x depth"""


def stage_design(fit_seeds: list[int]) -> dict:
    """The rest of the fit's design on path-traced captures: input encoding, network size and the
    paper's adversarial cost (DESIGN_VARIANTS), novel-view DSSIM / RM++ on the training-part
    captures (:func:`training_part_roots`), fit seeds ``fit_seeds``, with each variant's number
    of weights."""
    weights = {k: FitOptions(**v).architecture.num_weights for k, v in DESIGN_VARIANTS.items()}
    return {"fit_seeds": fit_seeds, "variants": DESIGN_VARIANTS, "num_weights": weights,
            "rows": dev_rows("design", DESIGN_VARIANTS, fit_seeds)}


def stage_anchor(fit_seeds: list[int], floor_every: int) -> dict:
    """Table 1's protocol on training-part single-material captures: the small preset's bunny
    (point) and sphere (env), plus one bunny under an environment map rendered here at the small
    preset's settings. Context for the issue's anchor (a plain fit on Mitsuba bunny renders,
    128x128: DAM/RM++ 0.38-0.48), not the target (that is measured on the held-out part)."""
    corpus = json.loads((small_corpus_dir() / "corpus.json").read_text())
    entries = {c["name"]: (small_corpus_dir() / c["path"], c) for c in corpus["captures"] if c["name"] in ANCHOR_SMALL}
    if len(entries) != len(ANCHOR_SMALL):
        raise SystemExit("run the 'small' stage first: the anchor stage reads its training-part captures")
    p = preset("small")
    opts = bunny_options(env("studio.hdr"), p.resolution, p.spp_env, views=p.views, seed=7)
    root = ANCHOR_RENDERED
    with Timed() as tr:
        make_synthetic_capture(root, opts, threads=os.cpu_count())  # resumes a partial render
    entries[root.name] = (root, {"name": root.name, "object": "stanford-bunny", "light": opts.light, "light_kind": "env"})
    per_capture = [table1_capture(r, c, fit_seeds, floor_every) for r, c in entries.values()]
    for rec in per_capture:
        rec["ratio_novel_per_fit_seed"] = [f["novel_view"] / rec["baselines"]["novel_view"]["RM++"] for f in rec["fits"]]
    return {"per_capture": per_capture, "fit_seeds": fit_seeds, "render_s": round(tr.wall, 1),
            "rendered": {"name": root.name, "options": asdict(opts)}}


def _local_lighting(record: dict):
    """The capture's light as distant lighting for closed_form.shade (no shadows)."""
    from damcap.common.exr import read_exr
    from damcap.synth.closed_form import Lighting, directional_lighting

    light = record["light"]
    if light["kind"] == "point":
        c = np.asarray(light["centre_world"], np.float64)
        return directional_lighting(tuple(c / np.linalg.norm(c)), (math.pi,) * 3)
    pixels = read_exr(DATA / "envmaps" / light["file"])[0][..., :3].astype(np.float64) * light["scale"]
    h, w = 32, 64
    bh, bw = pixels.shape[0] // h, pixels.shape[1] // w
    grid = pixels[: h * bh, : w * bw].reshape(h, bh, w, bw, 3).mean((1, 3))
    theta = (np.arange(h) + 0.5) * math.pi / h
    phi = (np.arange(w) + 0.5) * 2 * math.pi / w
    t, ph = np.meshgrid(theta, phi, indexing="ij")
    # Mitsuba's envmap: u = atan2(x, -z) / 2 pi, v = acos(y) / pi, then rotated about +y
    v = np.stack([np.sin(t) * np.sin(ph), np.cos(t), -np.sin(t) * np.cos(ph)], -1).reshape(-1, 3)
    a = math.radians(light["rotation_deg"])
    rot = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    solid = (np.sin(t) * (math.pi / h) * (2 * math.pi / w)).reshape(-1, 1)
    return Lighting(torch.from_numpy(v @ rot.T).float(), torch.from_numpy(grid.reshape(-1, 3) * solid).float())


def local_shading_copy(src: Path, dst: Path) -> None:
    """A copy of a one-material capture whose radiance is re-shaded locally (no shadows, no
    interreflection) with the capture's light and an equivalent Lambert + GGX material."""
    from damcap.common.capture_folder import RADIANCE_CHANNELS
    from damcap.common.exr import write_exr
    from damcap.synth.closed_form import Material, shade

    cap = read_capture(src)
    rec = cap.extra["damcap_source"]
    m = rec["materials"][0]
    w = m["specular_weight"]
    mat = Material(tuple((1 - w) * x for x in m["diffuse_rgb"]), m["roughness_alpha"], tuple(w * x for x in m["specular_rgb"]))
    lighting = _local_lighting(rec)
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    for f in cap.frames:
        d = read_frame(cap, f, with_weights=False)
        fg = d.coverage > 0
        v = f.camera_centre_world - d.position_world[fg]
        v /= np.linalg.norm(v, axis=-1, keepdims=True)
        rad = np.zeros_like(d.radiance_lin)
        rad[fg] = shade(torch.from_numpy(d.normal_world[fg]).float(), torch.from_numpy(v).float(), lighting, mat, chunk=2048).numpy()
        write_exr(dst / f.file_path, rad, RADIANCE_CHANNELS, dtype="float")


def input_extrapolation(train, test) -> float:
    """Median over test pixels of the distance from their DAM input (normal, mirrored view;
    the 'nr' encoding) to the nearest training pixel's input."""
    from scipy.spatial import cKDTree

    from damcap.appearance.dam import encode_inputs

    def inputs(views):
        s = samples_of(views)
        return encode_inputs(s.view_dir_world, s.normal_world, "nr").numpy()

    d, _ = cKDTree(inputs(train)).query(inputs(test), k=1)
    return float(np.median(d))


def stage_why(fit_seed: int = 0) -> dict:
    corpus = json.loads((small_corpus_dir() / "corpus.json").read_text())
    held = [c for c in corpus["captures"] if c["split"] == "heldout" and c["materials"] == 1]
    rows = []
    for c in held:
        src = small_corpus_dir() / c["path"]
        dst = CACHE / "synth_why" / c["name"]
        local_shading_copy(src, dst)
        row = {"name": c["name"], "light_kind": c["light_kind"]}
        for label, root in (("rendered", src), ("local_shading", dst)):
            cap = read_capture(root)
            train, test = load_views(cap, "train"), load_views(cap, "test")
            fit = fit_dam(samples_of(train), FitOptions(seed=fit_seed))
            same = evaluate_split(train, train, {"DAM": fit.model})
            novel = evaluate_split(train, test, {"DAM": fit.model})
            row[label] = {"DAM_same": same["DAM"].mean, "DAM_novel": novel["DAM"].mean, "RM++_same": same["RM++"].mean,
                          "RM++_novel": novel["RM++"].mean, "ratio_novel": novel["DAM"].mean / novel["RM++"].mean}
            if label == "rendered":
                row["input_extrapolation_median"] = input_extrapolation(train, test)
                # every view fitted, test views scored: near the best this network can do on them,
                # so the rest of the novel-view error is extrapolation from the training views
                everything = fit_dam(samples_of(train + test), FitOptions(seed=fit_seed))
                all_novel = evaluate_split(train + test, test, {"DAM": everything.model}, baselines=False)["DAM"].mean
                row["all_views_fit"] = {"DAM_novel": all_novel, "ratio_novel": all_novel / novel["RM++"].mean}
        rows.append(row)
        log(f"why {c['name']}: rendered DAM/RM++ novel {row['rendered']['ratio_novel']:.2f} "
            f"(DAM same {row['rendered']['DAM_same']:.4f}); local shading only {row['local_shading']['ratio_novel']:.2f} "
            f"(DAM same {row['local_shading']['DAM_same']:.4f}); input extrapolation {row['input_extrapolation_median']:.3f}")
    return {"fit_seed": fit_seed, "rows": rows}


# --------------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------------


def ratio_table(rows: list[dict], labels: list[str]) -> list[str]:
    """Markdown rows: per capture, each label's mean novel-view ratio (per fit seed in brackets),
    then the mean over captures."""
    L = ["| capture | " + " | ".join(labels) + " |", "|---|" + "---:|" * len(labels)]
    for r in rows:
        L.append(f"| {r['name']} | " + " | ".join(f"{statistics.fmean(r['ratio_novel'][k]):.2f} ("
                                                + ", ".join(f"{x:.2f}" for x in r['ratio_novel'][k]) + ")" for k in labels) + " |")
    L.append("| **mean** | " + " | ".join(f"**{mean_ratio(rows, k):.3f}**" for k in labels) + " |")
    return L


def dev_table(rows: list[dict], fit_seeds: list[int], columns: str) -> list[str]:
    """Markdown: the training-part captures' table of a stage (:func:`ratio_table` of every label
    in ``rows``), after one sentence whose end, ``columns``, says what the columns are."""
    return ([f"Training-part captures: novel-view DSSIM / RM++, mean over fit seeds {fit_seeds} (per seed in brackets)"
             + columns, ""] + ratio_table(rows, list(rows[0]["ratio_novel"])))


def with_columns_of(rows: list[dict], other: list[dict], columns: dict[str, str]) -> list[dict]:
    """Training-part rows with columns of another stage's rows on the same captures put first:
    ``columns`` maps the new label to the label in ``other``."""
    by_name = {r["name"]: r["ratio_novel"] for r in other}
    return [{"name": r["name"], "ratio_novel": {new: by_name[r["name"]][old] for new, old in columns.items()} | r["ratio_novel"]}
            for r in rows]


def novel_target(table: dict, digits: int = 2, target: float = TARGET_NOVEL_RATIO) -> str:
    """'point P, env E -> **met**' (or missed): a :func:`summarise_table1` table's novel-view
    DAM / RM++ against the target (at most ``target`` in both columns)."""
    nv = [table[k]["novel_view"]["DAM/RM++"] for k in ("point", "env")]
    return f"point {nv[0]:.{digits}f}, env {nv[1]:.{digits}f} -> **{'met' if max(nv) <= target else 'missed'}**"


def heldout_table(tables: dict[str, dict]) -> list[str]:
    """Markdown rows of Table 1's representation columns for several fits (label -> the
    :func:`summarise_table1` table; the first one's RM++ row is shown: every fit shares it)."""
    L = ["| fit | point, same view | point, novel view | env, same view | env, novel view |", "|---|---:|---:|---:|---:|"]
    cols = [(k, c) for k in ("point", "env") for c in ("same_view", "novel_view")]
    for label, t in tables.items():
        L.append(f"| {label} | " + " | ".join(
            f"{t[k][c]['DAM']:.4f} ({', '.join(f'{x:.2f}' for x in t[k][c]['DAM/RM++_per_fit_seed'])})" for k, c in cols) + " |")
    first = next(iter(tables.values()))
    L.append("| RM++ | " + " | ".join(f"{first[k][c]['RM++']:.4f}" for k, c in cols) + " |")
    for label, t in tables.items():
        L.append(f"| DAM / RM++, {label} | " + " | ".join(f"**{t[k][c]['DAM/RM++']:.2f}**" for k, c in cols) + " |")
    return L


def write_markdown(res: dict, path: Path) -> None:
    m = res.get("machine", {})
    L = ["# Synthetic data set (Mitsuba 3): throughput, noise floor, corpus time, Table 1", "",
         f"Machine: {m.get('cpu_model')} ({m.get('nproc')} cores, shared with other engineers; {m.get('mem_gib')} GiB), "
         f"Mitsuba {m.get('mitsuba')} `{m.get('variant')}` ({m.get('drjit_threads')} threads), torch {m.get('torch')} "
         f"({m.get('torch_threads')} threads), Python {m.get('python')}; {m.get('date_utc')}.", "",
         "Command (from the repository root): `" + res.get("command", command_line("synth", [])) + "` (all stages; "
         "`--stages a,b` reruns some, merging into the results). This file's results came from these runs: "
         + "; ".join(f"`{r['command']}` ({r['started_utc']})" for r in res.get("runs", [])) + ".", "",
         "*others* = share of all cores that other processes used during the timed section (the machine is shared). "
         "*idle est.* = the larger of own CPU time / cores and wall time x (1 - others): an estimate for an otherwise "
         "idle machine.", ""]
    if "throughput" in res:
        L += ["## Render throughput (64 spp, bunny, environment map)", "",
              "| resolution | path tracer alone, images/s: measured (idle est.) | whole frames, frames/s: measured (idle est.) | others |",
              "|---|---:|---:|---:|"]
        for k, v in res["throughput"].items():
            ro, wf = v["render_only"], v["whole_frames"]
            L.append(f"| {k} | {ro['images_per_s']:.2f} ({ro['images_per_s_idle']:.2f}) | {wf['frames_per_s']:.2f} ({wf['frames_per_s_idle']:.2f}) | "
                     f"{ro['foreign_cpu_frac']:.0%} / {wf['foreign_cpu_frac']:.0%} |")
        L += ["", "Whole frames include scene set-up and kernel compilation (once per capture), the ray-cast geometry "
              "(4x4 sub-pixel rays), validation and EXR writes.", ""]
    if "noise" in res:
        L += ["## Path-tracing noise floor", "",
              "DSSIM (capture-format.md) between two renders of the same 4 views (2 at 256 px) with different seeds; "
              f"{res['noise']['object']}.", "",
              "| light | resolution | spp | noise floor DSSIM | s / image | others |", "|---|---:|---:|---:|---:|---:|"]
        for r in res["noise"]["rows"]:
            L.append(f"| {r['light']} | {r['resolution']} | {r['spp']} | {r['dssim_mean']:.4f} | {r['s_per_image']:.2f} | {r['foreign_cpu_frac']:.0%} |")
        L += [""]
    if "small" in res or "paper" in res:
        L += ["## Corpus time", "", "| preset | captures | time: measured (idle est.) | target | how | others |", "|---|---:|---:|---:|---|---:|"]
        if "small" in res:
            s = res["small"]
            sp = preset("small")
            L.append(f"| small ({sp.resolution} px; env {sp.spp_env} spp, point {sp.spp_point} spp; --jobs {s['jobs']}) | {s['captures']} | "
                     f"{s['wall_s'] / 60:.1f} min ({s['idle_s'] / 60:.1f} min) | "
                     f"< 10 min | measured, from scratch | {s['foreign_cpu_frac']:.0%} |")
        if "paper" in res:
            p = res["paper"]
            L.append(f"| paper (256 px; env {p['per_frame']['env']['spp']} spp, point {p['per_frame']['point']['spp']} spp) | "
                     f"{p['captures']} | {p['estimated_h']:.0f} h ({p['estimated_h_idle']:.0f} h) | - | **estimated** from per-frame times "
                     f"(env {p['per_frame']['env']['s_per_frame']:.1f} s, point {p['per_frame']['point']['s_per_frame']:.1f} s per frame) | "
                     f"{p['per_frame']['env']['foreign_cpu_frac']:.0%} |")
        if "small" in res:
            L += ["", "Small preset command: `" + res["small"]["command"] + "`"]
        L += [""]
    if "table1" in res:
        t = res["table1"]
        tb = t["table"]
        L += ["## Table 1, representation rows (held-out objects and illuminations, one material)", "",
              f"Captures: {', '.join(t['captures'])} (small preset, 128 px, 32 views: 10 train, 22 test). DAM: `fit_dam` with "
              f"default `FitOptions` ({t['fit_options']['width']}x{t['fit_options']['depth']}, encoding "
              f"`{t['fit_options']['encoding']}`, {t['fit_options']['steps']} steps), mean over fit seeds {t['fit_seeds']}. "
              f"Noise floor: every {t.get('floor_every', 1)}th frame of each capture re-rendered with another seed vs the stored frame, "
              "averaged per split.", "",
              "| method | point, same view | point, novel view | env, same view | env, novel view |", "|---|---:|---:|---:|---:|"]
        for meth in ("DAM", "RM++", "RM", "noise_floor"):
            cells = []
            for kind in ("point", "env"):
                for col in ("same_view", "novel_view"):
                    c = tb[kind][col]
                    extra = f" ± {c['DAM_std_over_fits']:.4f}" if meth == "DAM" else ""  # std over fit seeds
                    cells.append(f"{c[meth]:.4f}{extra}")
            L.append(f"| {meth.replace('_', ' ')} | " + " | ".join(cells) + " |")
        cells = []
        for kind in ("point", "env"):
            for col in ("same_view", "novel_view"):
                c = tb[kind][col]
                cells.append(f"**{c['DAM/RM++']:.2f}** ({', '.join(f'{x:.2f}' for x in c['DAM/RM++_per_fit_seed'])})")
        L.append("| DAM / RM++ (per fit seed) | " + " | ".join(cells) + " |")
        L += ["", f"Target: novel-view DAM/RM++ <= {t['target_novel_ratio']} in both columns: "
              f"{novel_target(tb, target=t['target_novel_ratio'])} (the paper reports 0.80 and 0.85).", "", "Per capture:", "",
              "| capture | DAM same | DAM novel | RM++ same | RM++ novel | floor same | floor novel |", "|---|---:|---:|---:|---:|---:|---:|"]
        for r in t["per_capture"]:
            L.append(f"| {r['name']} | {r['dam']['same_view']:.4f} | {r['dam']['novel_view']:.4f} | {r['baselines']['same_view']['RM++']:.4f} | "
                     f"{r['baselines']['novel_view']['RM++']:.4f} | {r['noise_floor']['same_view']:.4f} | {r['noise_floor']['novel_view']:.4f} |")
        L += [""]
    if "why" in res:
        L += ["## Why the DAM loses where it does (measured)", "",
              "Same captures, DAM fit seed " + str(res["why"]["fit_seed"]) + ". *rendered*: the path-traced capture. *local shading "
              "only*: the same views, geometry, light and material re-shaded without shadows and interreflection (a function "
              "of (V, N), which a DAM can represent). *input extrapolation*: median distance from a test pixel's DAM input "
              "(normal, mirrored view) to the nearest training input. *all views fitted*: a DAM fitted to all 32 views of the "
              "rendered capture (train and test), scored on the test views: near the best this network can do on them, so "
              "the difference to *rendered: DAM novel* is extrapolation from the 10 training views.", "",
              "| capture | rendered: DAM same / novel | rendered: RM++ novel | rendered: DAM/RM++ novel | local only: DAM same / novel "
              "| local only: RM++ novel | local only: DAM/RM++ novel | input extrapolation | all views fitted: DAM novel (/ RM++) |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in res["why"]["rows"]:
            a, b, c = r["rendered"], r["local_shading"], r.get("all_views_fit")
            L.append(f"| {r['name']} | {a['DAM_same']:.4f} / {a['DAM_novel']:.4f} | {a['RM++_novel']:.4f} | {a['ratio_novel']:.2f} | "
                     f"{b['DAM_same']:.4f} / {b['DAM_novel']:.4f} | {b['RM++_novel']:.4f} | {b['ratio_novel']:.2f} | "
                     f"{r['input_extrapolation_median']:.3f} | " + (f"{c['DAM_novel']:.4f} ({c['ratio_novel']:.2f})" if c else "-") + " |")
        if all("all_views_fit" in r for r in res["why"]["rows"]):
            cols = {}
            for kind in ("point", "env"):
                rs = [r for r in res["why"]["rows"] if r["light_kind"] == kind]
                cols[kind] = (statistics.fmean(r["all_views_fit"]["DAM_novel"] for r in rs),
                              statistics.fmean(r["rendered"]["DAM_novel"] for r in rs),
                              statistics.fmean(r["rendered"]["RM++_novel"] for r in rs))
            L += ["", "Per column (mean over its captures): all views fitted "
                  + ", ".join(f"{k} {a:.4f} ({a / c:.2f}x RM++) against {b:.4f} ({b / c:.2f}x) fitted on the training views"
                              for k, (a, b, c) in cols.items()) + "."]
        L += [""]
    if "anchor" in res:
        a = res["anchor"]
        L += ["## Context: the same protocol on training-part captures (not the target)", "",
              "The issue's anchor: a plain 3360-weight fit on Mitsuba bunny renders at 128x128 reaches DAM/RM++ 0.38-0.48 "
              "over 3 seeds. The same `table1` protocol (10 consecutive train views, 22 test, default `FitOptions`, fit seeds "
              f"{a['fit_seeds']}) on training-part single-material captures of the small preset, plus "
              f"`{a['rendered']['name']}` rendered here at its settings ({a['rendered']['options']['spp']} spp, {a['render_s']:.0f} s):", "",
              "| capture | DAM same | DAM novel | RM++ novel | floor novel | DAM/RM++ novel (per fit seed) |", "|---|---:|---:|---:|---:|---:|"]
        for r in a["per_capture"]:
            per = r["ratio_novel_per_fit_seed"]
            L.append(f"| {r['name']} | {r['dam']['same_view']:.4f} | {r['dam']['novel_view']:.4f} | {r['baselines']['novel_view']['RM++']:.4f} | "
                     f"{r['noise_floor']['novel_view']:.4f} | **{statistics.fmean(per):.2f}** ({', '.join(f'{x:.2f}' for x in per)}) |")
        means = [statistics.fmean(r["ratio_novel_per_fit_seed"]) for r in a["per_capture"]]
        spread = max(max(r["ratio_novel_per_fit_seed"]) - min(r["ratio_novel_per_fit_seed"]) for r in a["per_capture"])
        inside = sum(m <= 0.48 for m in means)
        L += ["", f"Here the default fit reaches {min(means):.2f}-{max(means):.2f} per capture ({inside} of {len(means)} within or "
              f"below the anchor's 0.38-0.48); one capture's fit seeds differ by up to {spread:.2f}. The anchor's light, material "
              "and split are not known, so this places our numbers next to it without reproducing it. These captures are "
              "training-part: with four more (`damcap synth` renders of armadillo / forest, beetle / museum, cow / point-05, "
              "igea / point-11) they are the seven on which `FitOptions.activation` was chosen.", ""]
    if "activation" in res:
        a = res["activation"]
        labels = list(ACTIVATION_VARIANTS)
        L += ["## How the default activation was chosen (training-part captures only)", "",
              f"Novel-view DSSIM / RM++, mean over fit seeds {a['fit_seeds']} (per seed in brackets); *default* = "
              f"`FitOptions()` (activation `{a['default']}`), the others change only the activation.", ""]
        L += ratio_table(a["rows"], labels)
        L += ["", "A ratio near 1 with identical seeds is a fit that collapsed to a black image (plain softplus under point lights).", ""]
    if "weight_decay" in res:
        w = res["weight_decay"]
        L += ["## Weight decay (`FitOptions.weight_decay`; not the default)", ""]
        L += dev_table(w["dev_rows"], w["dev_fit_seeds"], ", by weight decay, with 2000 steps unless it says otherwise "
                       "(0 = `FitOptions()`).")
        if "table1" in res:
            d = res["table1"]["table"]
            ch = w["choices"]
            L += ["", f"Held-out captures (Table 1's representation rows, fit seeds {res['table1']['fit_seeds']}) with two of "
                  f"these, chosen on the training-part captures: the best at the default 2000 steps (weight decay "
                  f"{ch['same_steps']}) and the best of all (weight decay {ch['overall']}). DAM mean DSSIM (DAM / RM++ per fit seed):", ""]
            L += heldout_table({"default": d} | {f"weight decay {label}": v["table"] for label, v in w["heldout"].items()})
        L += ["", "Weight decay is not the default: on the closed-form captures of `bench/dam_core.md` (local shading only) "
              "it raises the ratio (study *weight decay* there).", ""]
    if "quantile" in res and "weight_decay" in res:
        q, w = res["quantile"], res["weight_decay"]
        rows = with_columns_of(q["dev_rows"], w["dev_rows"], {"0.5 (L1, default)": "0", "0.5, wd 0.1": "0.1"})
        L += ["## The data cost's quantile (`FitOptions.quantile`; not the default)", "",
              "Cast shadows and occlusion only darken a pixel, so at each (view, normal) the upper quantiles of the "
              "observed radiance are nearer the unshadowed appearance that a function of (V, N) can represent. The fit's "
              "L1 cost (quantile 0.5) is replaced by the pinball loss at quantile q (`damcap fit --quantile q`), and the "
              "stopping rule scores the held-out training views with the same cost.", ""]
        L += dev_table(rows, q["dev_fit_seeds"], ", by quantile, alone and with weight decay (*wd*) 0.1, 2000 steps; the "
                       "two L1 columns are the weight decay stage's fits (same captures and seeds).")
        if "table1" in res:
            tables = {"default": res["table1"]["table"]}
            if "0.1" in w["heldout"]:
                tables["weight decay 0.1"] = w["heldout"]["0.1"]["table"]
            tables |= {f"quantile {label}": v["table"] for label, v in q["heldout"].items()}
            L += ["", f"Held-out captures (Table 1's representation rows, fit seeds {res['table1']['fit_seeds']}) with the best "
                  f"of these on the training-part captures (quantile {q['chosen']}), next to the default and weight decay 0.1 "
                  "alone. DAM mean DSSIM (DAM / RM++ per fit seed):", ""]
            L += heldout_table(tables)
            L += ["", f"Target (novel-view DAM / RM++ <= 0.5 in both columns) with quantile {q['chosen']}: "
                  f"{novel_target(q['heldout'][q['chosen']]['table'])}. It is not the default: on the closed-form captures of "
                  "`bench/dam_core.md` (no shadows) it is measured in the study *data-cost quantile*."]
        L += [""]
    if "separable" in res:
        sp = res["separable"]
        rows = sp["dev_rows"]
        if "weight_decay" in res:  # the default's fits on the same captures and seeds, for comparison
            rows = with_columns_of(rows, res["weight_decay"]["dev_rows"], {"default (joint 32x4)": "0"})
        L += ["## A separable DAM (`FitOptions.separable`; not the default)", "",
              "The DAM's hidden units split into two halves, one seeing only the normal N and one only the mirrored view R, "
              "added before the output softplus: softplus(f(N) + g(R)), a diffuse-like term plus a specular-like term "
              "(`damcap fit --separable`; block-diagonal hidden layers, width counts both halves). A novel view pairs "
              "normals and mirror directions that the training views saw, but not together; a separable DAM needs only "
              "each on its own. Weights: " + ", ".join(f"{k} {n}" for k, n in sp["num_weights"].items()) + " (the default "
              "joint 32x4: 3360).", ""]
        L += dev_table(rows, sp["dev_fit_seeds"], "; labels are width x depth, 2000 steps unless they say otherwise; *wd* = "
                       "weight decay, *q* = the data cost's quantile. The default column is the weight decay stage's fits "
                       "(same captures and seeds).")
        if "table1" in res:
            tables = {"default": res["table1"]["table"]}
            if "quantile" in res:
                q = res["quantile"]
                tables[f"quantile {q['chosen']}"] = q["heldout"][q["chosen"]]["table"]
            tables |= {f"separable {label}": v["table"] for label, v in sp["heldout"].items()}
            L += ["", f"Held-out captures (Table 1's representation rows, fit seeds {res['table1']['fit_seeds']}): the "
                  f"separable 44x4 and the best separable variant on the training-part captures ({sp['chosen']}), both named "
                  "before any held-out fit, next to the default and the quantile stage's choice. DAM mean DSSIM "
                  "(DAM / RM++ per fit seed):", ""]
            L += heldout_table(tables)
            pooled = sp.get("heldout_all_seeds")
            if pooled:
                L += ["", f"The same two fits over fit seeds {pooled['fit_seeds']} (the three above and three more):", ""]
                L += heldout_table({f"separable {label}": v["table"] for label, v in pooled["by_variant"].items()})
            for label, v in sp["heldout"].items():
                line = f"Target (novel-view DAM / RM++ <= 0.5 in both columns) with separable {label}: {novel_target(v['table'])}"
                if pooled:
                    line += f"; over {len(pooled['fit_seeds'])} fit seeds {novel_target(pooled['by_variant'][label]['table'], 3)}"
                L += ["", line + "."]
        L += [""]
    if "design" in res:
        d = res["design"]
        labels = list(d["variants"])
        L += ["## Input encoding, network size, adversarial cost (training-part captures only)", "",
              f"Novel-view DSSIM / RM++, mean over fit seeds {d['fit_seeds']} (per seed in brackets). *default* = "
              "`FitOptions()`: 32 units x 4 hidden layers on the encoding `nr` (normal, mirrored view); each other column "
              "changes one thing: the encoding (`vnr` adds the view direction, `vn` is the paper's view and normal), the "
              "size (width x depth), or adds the paper's adversarial cost (alpha 0.001). Weights per network: "
              + ", ".join(f"{k} {n}" for k, n in d["num_weights"].items()) + ".", ""]
        L += ratio_table(d["rows"], labels)
        means = {k: mean_ratio(d["rows"], k) for k in labels}
        base = means["default"]
        near = [k for k in labels[1:] if abs(means[k] - base) <= 0.02]
        worse = [k for k in labels[1:] if means[k] > base + 0.02]
        better = [k for k in labels[1:] if means[k] < base - 0.02]
        L += ["", f"Against the default's mean ({base:.3f}): within 0.02, less than the two fit seeds of one capture "
              f"often differ: {', '.join(near) or 'none'}; worse by more: {', '.join(worse) or 'none'}; better by more: "
              f"{', '.join(better) or 'none'}.", ""]
    if res.get("notes"):
        L += ["## Notes", ""] + [f"- {n}" for n in res["notes"]] + [""]
    path.write_text("\n".join(L), encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stages", default=",".join(STAGES), help="comma-separated subset of " + ", ".join(STAGES) + ", or 'report'")
    ap.add_argument("--jobs", type=int, default=2, help="synth-set --jobs for the small preset")
    ap.add_argument("--keep-small", action="store_true", help="reuse a finished small corpus in bench/.cache (not timed from scratch)")
    ap.add_argument("--fit-seeds", default="0,1,2")
    ap.add_argument("--floor-every", type=int, default=3, help="re-render every n-th frame for the Table 1 noise floors")
    ap.add_argument("--corpus", type=Path, default=None, help="table1: the corpus whose held-out captures are measured (default: the small preset's in bench/.cache)")
    ap.add_argument("--fit-steps", type=int, default=None, help="table1: DAM fit steps (default: FitOptions' default)")
    ap.add_argument("--out", type=Path, default=None, help="write synth.json and synth.md here instead of bench/results/ and bench/")
    args = ap.parse_args(argv)
    stages = [s for s in args.stages.split(",") if s and s != "report"]  # 'report': only rewrite synth.md
    unknown = set(stages) - set(STAGES)
    if unknown:
        raise SystemExit(f"unknown stage(s) {sorted(unknown)}; use {STAGES}")
    torch.set_num_threads(min(2, torch.get_num_threads()))
    CACHE.mkdir(parents=True, exist_ok=True)
    out_json = RESULTS / "synth.json" if args.out is None else args.out / "synth.json"
    out_md = BENCH / "synth.md" if args.out is None else args.out / "synth.md"
    out_json.parent.mkdir(parents=True, exist_ok=True)
    res = json.loads(out_json.read_text()) if out_json.is_file() else {}
    res["command"] = command_line("synth", [])
    if stages:
        res["machine"] = machine_info()
        res.setdefault("runs", []).append({"command": command_line("synth", sys.argv[1:] if argv is None else argv), "stages": stages,
                                           "started_utc": res["machine"]["date_utc"]})
    if "table1" in res:  # derived cells always follow the stored per-capture results
        res["table1"]["table"] = summarise_table1(res["table1"]["per_capture"], res["table1"]["fit_seeds"])
    fit_seeds = [int(s) for s in args.fit_seeds.split(",")]
    t0 = time.perf_counter()
    for stage in stages:
        log(f"stage {stage}")
        if stage == "throughput":
            res["throughput"] = stage_throughput()
        elif stage == "noise":
            res["noise"] = stage_noise()
        elif stage == "small":
            res["small"] = stage_small(args.jobs, fresh=not args.keep_small)
        elif stage == "paper":
            res["paper"] = stage_paper()
        elif stage == "why":
            res["why"] = stage_why()
        elif stage == "activation":
            res["activation"] = stage_activation(fit_seeds[:2])
        elif stage == "design":
            res["design"] = stage_design(fit_seeds[:2])
        elif stage == "weight_decay":
            res["weight_decay"] = stage_weight_decay(fit_seeds, res)
        elif stage == "quantile":
            res["quantile"] = stage_quantile(fit_seeds, res)
        elif stage == "separable":
            res["separable"] = stage_separable(fit_seeds, res)
        elif stage == "anchor":
            res["anchor"] = stage_anchor(fit_seeds, args.floor_every)
        elif stage == "table1":
            fit = FitOptions() if args.fit_steps is None else FitOptions(steps=args.fit_steps)
            res["table1"] = stage_table1(fit_seeds, args.floor_every, args.corpus, fit)
        res.setdefault("stage_wall_s", {})[stage] = round(time.perf_counter() - t0, 1)
        t0 = time.perf_counter()
        out_json.write_text(json.dumps(res, indent=2) + "\n")
        write_markdown(res, out_md)
    out_json.write_text(json.dumps(res, indent=2) + "\n")
    write_markdown(res, out_md)
    log(f"wrote {out_json} and {out_md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
