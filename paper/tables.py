"""The paper's tables (Maximov et al. 2019, Tables 1 and 2) as one evaluation.

Table 1, on the held-out captures of ``damcap synth-set`` corpora (objects and illuminations
never used for training), point-light and environment-map columns, same view (train split) and
novel view (test split), mean DSSIM (docs/capture-format.md):

* representation rows (one-material captures): the SGD-fitted DAM against RM and RM++;
* learning-to-learn rows (one-material captures): the predictor's DAM alone and refined for K
  steps, against the SGD fit;
* segmentation rows (three-material captures): ours (n DAMs + Psi) against k-means in RGB +
  normal space with one DAM per cluster. Novel views as in the paper, with the true weights of
  the new view, and without ground truth, with weights carried from the geometry.

Table 2 is the same rows on one real capture (no true weights: segmentation novel views use the
weights carried from the geometry).

Every method's per-frame DSSIM is kept, for the paper-style sorted-DSSIM plots.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from damcap.common.corpus_index import finished_captures
from damcap.common.errors import DamcapError
from damcap.common.validate import COUNT, COUNT_OR_ZERO

from damcap.appearance.views import ViewData
from damcap.appearance.evaluate import MethodScores, evaluate_split
from damcap.appearance.fit import FitOptions, fit_dam, refine_dam
from damcap.appearance.pixels import FOREGROUND_COVERAGE
from damcap.appearance.segment.options import SegmentOptions
from damcap.appearance.segment.cluster import chromaticity_features
from damcap.appearance.segment.kmeans_baseline import kmeans_baseline
from damcap.appearance.segment.score import match_materials, segmentation_scores
from damcap.appearance.segment.train import segment_materials
from damcap.appearance.views import samples_of

#: the paper's published figures, for the side-by-side columns (Table 1 ratios and Table 2)
PAPER = {
    "representation": {"point": {"DAM/RM++ novel": 0.80}, "env": {"DAM/RM++ novel": 0.85}},
    "learning-to-learn": {"point": {"predicted/SGD novel": 1.146}, "env": {"predicted/SGD novel": 1.055}},
    "segmentation": {"point": {"ours novel": 0.161, "k-means novel": 0.172}, "env": {"ours novel": 0.154, "k-means novel": 0.164}},
    "real": {"DAM novel": 0.079, "RM++ novel": 0.090, "RM novel": 0.127},
}

TASKS = ("representation", "learning-to-learn", "segmentation")
VIEWS = ("same", "novel")


@dataclass(frozen=True)
class TableOptions:
    """What every row runs (the defaults are damcap's defaults)."""

    fit: FitOptions = FitOptions(checkpoint_every=0)
    """the SGD fit of the representation and learning-to-learn rows"""
    refine_steps: tuple[int, ...] = field(default=(100, 300), metadata=COUNT_OR_ZERO)
    """predictor + K refinement steps rows (0 = the predictor alone is always reported), at
    ``damcap predict``'s learning rate (:attr:`.PredictOptions.refine_learning_rate`)"""
    segment: SegmentOptions = SegmentOptions(materials=3)
    """our segmentation (``materials`` = n, the true count on the synthetic corpus)"""
    kmeans_steps: int = field(default=1500, metadata=COUNT)
    """fit steps of each k-means cluster's DAM"""


@dataclass
class CaptureRows:
    """One capture's rows: per task, per method, per view (same/novel), per-frame DSSIM."""

    name: str
    light_kind: str
    materials: int
    scores: dict[str, dict[str, dict[str, MethodScores]]] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    """IoU, seconds, the predictor's input view, ..."""

    def as_json(self) -> dict:
        return {"name": self.name, "light_kind": self.light_kind, "materials": self.materials, **self.extra,
                "scores": {task: {m: {v: {"mean": s.mean, "per_frame": s.per_frame} for v, s in views.items()}
                                  for m, views in methods.items()} for task, methods in self.scores.items()}}


def _both(train: list[ViewData], test: list[ViewData], models: dict, baselines: bool) -> dict[str, dict[str, MethodScores]]:
    """{method: {'same': scores on train, 'novel': scores on test}}."""
    same = evaluate_split(train, train, models, baselines=baselines)
    novel = evaluate_split(train, test, models, baselines=baselines)
    return {m: {"same": same[m], "novel": novel[m]} for m in novel}


StageProgress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``: which stage runs and how far it is (the CLI draws bars / log lines)"""


def _steps(progress: StageProgress | None, stage: str) -> Callable[[int, int, dict[str, float]], None] | None:
    """A training loop's ``progress(step, steps, stats)`` reported as ``stage``."""
    if progress is None:
        return None
    return lambda step, steps, stats: progress(stage, step, steps)


def representation_rows(train: list[ViewData], test: list[ViewData], opts: TableOptions,
                        progress: StageProgress | None = None) -> tuple[dict, Any, float]:
    """SGD fit vs RM++ and RM. Returns (scores, the fitted model, fit seconds)."""
    fit = fit_dam(samples_of(train), opts.fit, progress=_steps(progress, "fit"))
    return _both(train, test, {"DAM (SGD fit)": fit.model}, baselines=True), fit.model, fit.seconds


def learning_to_learn_rows(train: list[ViewData], test: list[ViewData], net, fitted, opts: TableOptions,
                           progress: StageProgress | None = None) -> tuple[dict, dict]:
    """The predictor alone and refined K steps, next to an SGD fit of the same DAM architecture:
    ``fitted`` when the predictor's architecture is the fit's, else a fit of the predictor's (the
    paper compares a predicted DAM with the same DAM fitted; the shipped predictor emits leaky-ReLU
    DAMs, ``damcap fit`` defaults to shifted softplus); ``fitted=None``: no SGD row.

    Returns (scores, extra: the input view, seconds of the prediction and of each refinement, and
    each refinement's training L1 before and after, ``{"refine K": [before, after]}``)."""
    from damcap.appearance.hyper.model import predict_dam, predictor_inputs
    from damcap.appearance.hyper.predict import PredictOptions

    ks, crop, scale = predictor_inputs(train, net.arch.input_views)
    k = ks[0]
    t = time.perf_counter()
    predicted = predict_dam(net, crop, scale)
    predict_s = time.perf_counter() - t
    samples = samples_of(train)
    models = {}
    if fitted is not None:
        if predicted.arch != fitted.arch:
            fitted = fit_dam(samples, opts.fit.for_architecture(predicted.arch), progress=_steps(progress, "fit (predictor's DAM)")).model
        models["DAM (SGD fit)"] = fitted
    models["predicted"] = predicted
    seconds, train_l1 = {"predict": predict_s}, {}
    for steps in opts.refine_steps:
        t = time.perf_counter()
        models[f"predicted + {steps} refine"], before, after = refine_dam(predicted, samples, steps, PredictOptions.refine_learning_rate)
        seconds[f"refine {steps}"] = time.perf_counter() - t
        train_l1[f"refine {steps}"] = [before, after]
    return _both(train, test, models, baselines=False), {"input_view": train[k].name, "seconds": seconds, "train_l1": train_l1}


def mean_iou(model, views: list[ViewData], carried: bool, lit_only: bool = False) -> float | None:
    """Mean IoU of a segmentation against the views' true weights (labels matched), or None.

    ``lit_only``: only pixels bright enough to show their colour (:func:`.segment.chromaticity_features`);
    unlit pixels carry no evidence of their material.
    """
    if not views or any(v.data.weights is None for v in views):
        return None
    fgs = [v.data.coverage > FOREGROUND_COVERAGE for v in views]
    if lit_only:
        fgs = [fg & _lit(v, model.radiance_scale) for v, fg in zip(views, fgs)]
    pw = np.concatenate([(model.weights_on(v) if carried else model.weights_of(v))[fg] for v, fg in zip(views, fgs)])
    tw = np.concatenate([v.data.weights[fg] for v, fg in zip(views, fgs)])
    return match_materials(pw, tw)[1]


def _lit(view: ViewData, scale: float) -> np.ndarray:
    """(H, W) bool: pixels bright enough to show their colour."""
    rad = view.data.radiance_lin
    return chromaticity_features(rad.reshape(-1, 3), scale)[1].reshape(rad.shape[:-1])


def segmentation_rows(train: list[ViewData], test: list[ViewData], opts: TableOptions, materials: int | None = None,
                      progress: StageProgress | None = None) -> tuple[dict, dict, dict]:
    """Ours vs the k-means baseline with n materials (``materials`` or ``opts.segment.materials``).

    Returns (scores, extra: IoUs and seconds, the two models by name).
    """
    seg_opts = opts.segment if materials is None else SegmentOptions(**{**asdict(opts.segment), "materials": materials})
    models = {"ours": segment_materials(train, seg_opts, _steps(progress, "segment")),
              "k-means": kmeans_baseline(train, seg_opts.materials, steps=opts.kmeans_steps, seed=seg_opts.seed, encoding=seg_opts.encoding)}
    scores: dict[str, dict[str, MethodScores]] = {}
    extra: dict[str, Any] = {"seconds": {}, "iou_train": {}, "iou_train_lit": {}, "iou_test_carried": {}}
    for name, model in models.items():
        same = segmentation_scores(model, train, train, same_view=True)
        novel = segmentation_scores(model, train, test, same_view=False)
        for source in novel:
            label = f"{name} ({source})"
            scores[label] = {"novel": MethodScores(novel[source])}
            if source in same:
                scores[label]["same"] = MethodScores(same[source])
        extra["seconds"][name] = model.seconds
        extra["iou_train"][name] = mean_iou(model, train, carried=False)
        extra["iou_train_lit"][name] = mean_iou(model, train, carried=False, lit_only=True)
        extra["iou_test_carried"][name] = mean_iou(model, test, carried=True)
    return scores, extra, models


# --------------------------------------------------------------------------------------------
# Table 1: the corpus
# --------------------------------------------------------------------------------------------


def heldout_entries(corpora: list[Path]) -> list[tuple[Path, dict]]:
    """The finished held-out captures of one or more synth-set corpora: (capture folder, entry)."""
    out = [c for corpus in corpora for c in finished_captures(corpus, "heldout", reader="evaluate --table1")]
    if not out:
        raise DamcapError(f"{', '.join(map(str, corpora))}: no rendered held-out captures; render them with damcap synth-set first")
    return out


def table1_rows(corpora: list[Path], opts: TableOptions, predictor, tasks: tuple[str, ...] = TASKS,
                log: Callable[[str], None] = lambda m: None, done: dict[str, dict] | None = None,
                on_capture: Callable[[CaptureRows], None] | None = None, progress: StageProgress | None = None) -> list[CaptureRows]:
    """Every row of Table 1 for every held-out capture (``done``: rows already computed, by
    capture name, reused as they are: the evaluation resumes; ``progress``: each capture's
    training loops, by stage)."""
    from damcap.common.capture_folder import read_capture

    from damcap.appearance.views import load_views

    rows = []
    for path, entry in heldout_entries(corpora):
        name = entry["name"]
        if done and name in done:
            rows.append(rows_from_json(done[name]))
            continue
        m = int(entry.get("materials", 1))
        wanted = [t for t in tasks if (t == "segmentation") == (m > 1)]
        if not wanted:
            continue
        cap = read_capture(path)
        train, test = load_views(cap, "train"), load_views(cap, "test")
        row = CaptureRows(name, entry.get("light_kind", "env"), m)
        each = None if progress is None else (lambda stage, k, n, _name=name: progress(f"{_name}: {stage}", k, n))
        t0 = time.perf_counter()
        if m == 1:
            scores, fitted, fit_s = representation_rows(train, test, opts, each)
            row.extra["fit_seconds"] = fit_s
            if "representation" in wanted:
                row.scores["representation"] = scores
            if "learning-to-learn" in wanted and predictor is not None:
                l2l, extra = learning_to_learn_rows(train, test, predictor, fitted, opts, each)
                row.scores["learning-to-learn"] = l2l
                row.extra["learning-to-learn"] = extra
        else:
            scores, extra, _ = segmentation_rows(train, test, opts, materials=m, progress=each)
            row.scores["segmentation"] = scores
            row.extra["segmentation"] = extra
        row.extra["seconds"] = time.perf_counter() - t0
        log(f"{name}: {row.extra['seconds']:.0f} s")
        rows.append(row)
        if on_capture:
            on_capture(row)
    return rows


def rows_from_json(d: dict) -> CaptureRows:
    scores = {task: {m: {v: MethodScores(s["per_frame"]) for v, s in views.items()} for m, views in methods.items()}
              for task, methods in d["scores"].items()}
    extra = {k: v for k, v in d.items() if k not in ("name", "light_kind", "materials", "scores")}
    return CaptureRows(d["name"], d["light_kind"], d["materials"], scores, extra)


def summarise(rows: list[CaptureRows]) -> dict[str, dict[str, dict[str, dict[str, float]]]]:
    """Cells: {task: {light kind: {method: {view: mean over captures of the per-capture mean}}}}."""
    table: dict = {}
    for row in rows:
        for task, methods in row.scores.items():
            for method, views in methods.items():
                for view, s in views.items():
                    table.setdefault(task, {}).setdefault(row.light_kind, {}).setdefault(method, {}).setdefault(view, []).append(s.mean)
    return {task: {kind: {m: {v: statistics.fmean(xs) for v, xs in views.items() if xs and all(math.isfinite(x) for x in xs)}
                          for m, views in methods.items()} for kind, methods in kinds.items()} for task, kinds in table.items()}


def pooled_scores(rows: list[CaptureRows], task: str, kind: str) -> dict[str, dict[str, MethodScores]]:
    """{view: {method: per-frame DSSIM pooled over the captures ('capture/frame' keys)}} for the plots."""
    out: dict[str, dict[str, MethodScores]] = {}
    for row in rows:
        if row.light_kind != kind or task not in row.scores:
            continue
        for method, views in row.scores[task].items():
            for view, s in views.items():
                pooled = out.setdefault(f"{view} view", {}).setdefault(method, MethodScores())
                pooled.per_frame.update({f"{row.name}/{f}": d for f, d in s.per_frame.items()})
    return out


def _fmt(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.4f}"


def table1_markdown(rows: list[CaptureRows], command: str) -> str:
    """Table 1 as markdown: one section per task, point and env columns, same and novel view."""
    cells = summarise(rows)
    kinds = ("point", "env")
    lines = ["# Table 1 (Maximov et al. 2019), reproduced on the held-out synthetic captures", "",
             f"Command: `{command}`", "", "Mean DSSIM (capture-format.md; lower is better), means over captures.", ""]
    for task in TASKS:
        if task not in cells:
            continue
        n = {k: sum(1 for r in rows if r.light_kind == k and task in r.scores) for k in kinds}
        lines += [f"## {task} ({n['point']} point-light, {n['env']} environment-map captures)", "",
                  "| method | point same | point novel | env same | env novel |", "|---|---|---|---|---|"]
        methods = list(dict.fromkeys(m for k in kinds for m in cells[task].get(k, {})))
        for m in methods:
            vals = [cells[task].get(k, {}).get(m, {}).get(v) for k in kinds for v in VIEWS]
            lines.append(f"| {m} | " + " | ".join(_fmt(x) for x in vals) + " |")
        lines += [""] + ratio_lines(cells, task) + [""]
        if task == "segmentation":
            lines += iou_lines(rows) + [""]
    return "\n".join(lines) + "\n"


def ratio_lines(cells: dict, task: str) -> list[str]:
    """The ratios the paper reports, ours next to the paper's."""
    out = []
    pairs = {"representation": ("DAM (SGD fit)", "RM++", "DAM/RM++ novel"),
             "learning-to-learn": ("predicted", "DAM (SGD fit)", "predicted/SGD novel"),
             "segmentation": ("ours (true weights)", "k-means (true weights)", None)}
    a, b, key = pairs[task]
    for kind in ("point", "env"):
        c = cells[task].get(kind, {})
        if a in c and b in c and "novel" in c[a] and "novel" in c[b]:
            ratio = c[a]["novel"] / c[b]["novel"]
            paper = PAPER[task][kind]
            ref = (f"{paper[key]:.3f}" if key else f"{paper['ours novel'] / paper['k-means novel']:.3f} "
                   f"({paper['ours novel']} vs {paper['k-means novel']})")
            out.append(f"- {kind}: {a} / {b}, novel view: **{ratio:.3f}** (paper: {ref})")
    if task == "learning-to-learn":
        for kind in ("point", "env"):
            c = cells[task].get(kind, {})
            for m in c:
                if m.startswith("predicted +") and "novel" in c[m] and "novel" in c.get("DAM (SGD fit)", {}):
                    out.append(f"- {kind}: {m} / SGD fit, novel view: {c[m]['novel'] / c['DAM (SGD fit)']['novel']:.3f}")
    return out


def iou_lines(rows: list[CaptureRows]) -> list[str]:
    out = ["| capture | light | ours IoU (train, Psi) | ours IoU (test, carried) | k-means IoU (train) | ours s | k-means s |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        e = r.extra.get("segmentation")
        if not e:
            continue
        out.append(f"| {r.name} | {r.light_kind} | {_fmt(e['iou_train']['ours'])} | {_fmt(e['iou_test_carried']['ours'])} | "
                   f"{_fmt(e['iou_train']['k-means'])} | {e['seconds']['ours']:.0f} | {e['seconds']['k-means']:.0f} |")
    return out


def plot_table1(rows: list[CaptureRows], folder: Path) -> list[Path]:
    """One sorted-DSSIM plot per task and light kind (PNG)."""
    from damcap.appearance.evaluate import plot_sorted_dssim

    paths = []
    for task in TASKS:
        for kind in ("point", "env"):
            pooled = pooled_scores(rows, task, kind)
            if pooled:
                p = folder / f"table1_{task}_{kind}.png"
                plot_sorted_dssim(pooled, p, title=f"{task}, {kind}")
                paths.append(p)
    return paths


# --------------------------------------------------------------------------------------------
# Table 2: one real capture
# --------------------------------------------------------------------------------------------


def table2_rows(train: list[ViewData], test: list[ViewData], opts: TableOptions, predictor, name: str,
                materials: int | str = "auto", log: Callable[[str], None] = lambda m: None,
                progress: StageProgress | None = None) -> tuple[CaptureRows, Any]:
    """All three tasks on one (real) capture. ``materials``: n for the segmentation, or 'auto'
    (:func:`.segment.choose_materials` on the test split); ``progress``: the training loops, by
    stage. Returns (rows, our segmentation)."""
    from damcap.appearance.segment.choose import choose_materials

    row = CaptureRows(name, "real", 0)
    t = time.perf_counter()
    scores, fitted, fit_s = representation_rows(train, test, opts, progress)
    row.scores["representation"] = scores
    row.extra["fit_seconds"] = fit_s
    log(f"fit and baselines: {time.perf_counter() - t:.0f} s")
    if predictor is not None:
        t = time.perf_counter()
        row.scores["learning-to-learn"], row.extra["learning-to-learn"] = learning_to_learn_rows(train, test, predictor, fitted, opts, progress)
        log(f"predictor: {time.perf_counter() - t:.0f} s")
    t = time.perf_counter()
    if materials == "auto":
        choice = choose_materials(train, test, opts.segment, log=log, progress=_steps(progress, "segment (--materials auto)"))
        n = choice.materials
        row.extra["materials_auto"] = {"chosen": n, "curve": choice.curve, "margin": choice.margin}
        log(f"--materials auto chose n = {n}")
    else:
        n = int(materials)
    scores, extra, models = segmentation_rows(train, test, opts, materials=n, progress=progress)
    row.materials = n
    row.scores["segmentation"] = scores
    row.extra["segmentation"] = extra
    log(f"segmentation (n = {n}) and k-means: {time.perf_counter() - t:.0f} s")
    return row, models["ours"]


def table2_markdown(row: CaptureRows, command: str, figure: str | None) -> str:
    """Table 2 as markdown: every method, same and novel view, with the paper's real-world figures."""
    lines = [f"# Table 2 (Maximov et al. 2019), reproduced on the real capture {row.name}", "",
             f"Command: `{command}`", "", "Mean DSSIM (capture-format.md; lower is better).", "",
             "| task | method | same view | novel view |", "|---|---|---|---|"]
    for task, methods in row.scores.items():
        for m, views in methods.items():
            lines.append(f"| {task} | {m} | {_fmt(views['same'].mean if 'same' in views else None)} | "
                         f"{_fmt(views['novel'].mean if 'novel' in views else None)} |")
    p = PAPER["real"]
    lines += ["", f"The paper, on its own real spheres (novel view): DAM {p['DAM novel']}, RM++ {p['RM++ novel']}, RM {p['RM novel']}.", ""]
    rep = row.scores["representation"]
    lines.append(f"- DAM / RM++, novel view: **{rep['DAM (SGD fit)']['novel'].mean / rep['RM++']['novel'].mean:.3f}** "
                 f"(paper: {p['DAM novel'] / p['RM++ novel']:.3f})")
    if "materials_auto" in row.extra:
        curve = ", ".join(f"n={c['materials']}: {c['heldout_dssim']:.4f}" for c in row.extra["materials_auto"]["curve"])
        lines.append(f"- segmentation: `--materials auto` chose n = {row.materials} (held-out DSSIM {curve})")
    if figure:
        lines += ["", f"Materials found (false colour, training frames): `{figure}`"]
    return "\n".join(lines) + "\n"


def false_colour_figure(model, views: list[ViewData], path: Path, max_frames: int = 4) -> None:
    """Training frames (tone-mapped photo above, the materials found in false colour below)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from damcap.common.atomic import atomic_path

    from damcap.appearance.segment.preview import false_colour
    from damcap.common.colour import preview_gamma

    pick = views[:: max(1, math.ceil(len(views) / max_frames))][:max_frames]
    fig, axes = plt.subplots(2, len(pick), figsize=(3 * len(pick), 6), squeeze=False)
    scale = max(float(np.percentile(np.concatenate([v.data.radiance_lin[v.data.coverage > 0.5] for v in pick]), 99)), 1e-12)
    for j, v in enumerate(pick):
        axes[0, j].imshow(preview_gamma(v.data.radiance_lin / scale))
        axes[1, j].imshow(false_colour(model.weights_of(v), v.data.coverage))
        axes[0, j].set_title(v.name, fontsize=8)
        for ax in axes[:, j]:
            ax.axis("off")
    fig.suptitle(f"{model.materials} materials found (false colour)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
