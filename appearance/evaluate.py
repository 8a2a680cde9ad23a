"""Evaluation: mean DSSIM per split for a model, RM and RM++ (docs/capture-format.md), and the plot."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from damcap.appearance.views import ViewData
from damcap.appearance.baselines import rm_oracle, rm_plus_plus
from damcap.appearance.dam import DeepAppearanceMap
from damcap.appearance.metrics import dssim
from damcap.appearance.render import render_frame


@dataclass
class MethodScores:
    """Per-frame DSSIM of one method on one split (None = frame without foreground)."""

    per_frame: dict[str, float | None] = field(default_factory=dict)
    note: str = ""
    per_source: dict[str, float] = field(default_factory=dict)
    """RM only: every candidate source's mean DSSIM (RM keeps the lowest)"""

    @property
    def mean(self) -> float:
        vals = [v for v in self.per_frame.values() if v is not None]
        return float(np.mean(vals)) if vals else float("nan")


def score_view(view: ViewData, prediction_lin: np.ndarray) -> float | None:
    """DSSIM of a prediction against the view's radiance."""
    return dssim(view.data.radiance_lin, prediction_lin, view.data.coverage)


def rm_source_spread(per_source: dict[str, float]) -> dict | None:
    """How RM's candidate sources score: count, min, median and max of their finite mean DSSIMs
    (None with fewer than two; RM keeps the min, so its win over the median is selection)."""
    finite = sorted(v for v in per_source.values() if np.isfinite(v))
    if len(finite) < 2:
        return None
    return {"n": len(finite), "min": finite[0], "median": float(np.median(finite)), "max": finite[-1], "scores": finite}


def evaluate_split(train: list[ViewData], targets: list[ViewData], models: dict[str, DeepAppearanceMap], baselines: bool = True,
                   progress: Callable[[str, int, int], None] | None = None, split: str = "") -> dict[str, MethodScores]:
    """DSSIM of every model and of RM / RM++ on ``targets``, with ``train`` as the baselines' sources
    (``progress(stage, done, total)``: each model's frames, then each baseline; stages named
    after ``split``)."""
    say = progress or (lambda stage, done, total: None)
    where = f"{split}: " if split else ""
    out: dict[str, MethodScores] = {}
    for name, model in models.items():
        scores = {}
        for k, t in enumerate(targets):
            scores[t.name] = score_view(t, render_frame(model, t.data, t.centre_world))
            say(f"{where}{name}", k + 1, len(targets))
        out[name] = MethodScores(scores)
    if baselines and len(train) >= 2:
        say(f"{where}RM++ and RM", 0, 2)
        preds = rm_plus_plus(train, targets)
        out["RM++"] = MethodScores({t.name: score_view(t, p) for t, p in zip(targets, preds)})
        say(f"{where}RM++ and RM", 1, 2)
        preds, chosen, per_source = rm_oracle(train, targets, score_view)
        say(f"{where}RM++ and RM", 2, 2)
        sp = rm_source_spread(per_source)
        spread = f"; best of {sp['n']} single sources, which score {sp['min']:.3f}-{sp['max']:.3f} (median {sp['median']:.3f})" if sp else ""
        out["RM"] = MethodScores({t.name: score_view(t, p) for t, p in zip(targets, preds)}, note=f"source {chosen}{spread}",
                                 per_source=per_source)
    return out


def plot_sorted_dssim(results: dict[str, dict[str, MethodScores]], path: str | Path, title: str = "") -> None:
    """The paper-style plot: per-frame DSSIM sorted, one curve per method, one panel per split."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from damcap.common.atomic import atomic_path

    splits = list(results)
    fig, axes = plt.subplots(1, len(splits), figsize=(5 * len(splits), 3.6), squeeze=False)
    for ax, split in zip(axes[0], splits):
        for method, scores in results[split].items():
            vals = sorted(v for v in scores.per_frame.values() if v is not None)
            ax.plot(np.arange(1, len(vals) + 1), vals, marker="o", ms=3, label=f"{method} ({scores.mean:.3f})")
        ax.set_title(f"{title} {split}".strip())
        ax.set_xlabel("frames, sorted")
        ax.set_ylabel("DSSIM (lower is better)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
