"""Scoring a segmentation: matching predicted to true materials (IoU), novel-view DSSIM, shares."""

from __future__ import annotations


import numpy as np
from scipy.optimize import linear_sum_assignment


from damcap.appearance.views import ViewData
from damcap.appearance.pixels import FOREGROUND_COVERAGE
from damcap.appearance.segment.model import SegmentationModel


def match_materials(pred_weights: np.ndarray, true_weights: np.ndarray) -> tuple[np.ndarray, float]:
    """Match predicted to true materials by maximum total IoU of the arg-max labels (Hungarian).

    Args:
        pred_weights: (P, n_pred) weights on foreground pixels.
        true_weights: (P, n_true) weights on the same pixels.

    Returns:
        perm: (n_true,) predicted material index for each true material (-1 = none),
        mean IoU over the true materials.
    """
    p = pred_weights.argmax(1)
    t = true_weights.argmax(1)
    n_p, n_t = pred_weights.shape[1], true_weights.shape[1]
    iou = np.zeros((n_t, n_p))
    for i in range(n_t):
        for j in range(n_p):
            inter = np.sum((t == i) & (p == j))
            union = np.sum((t == i) | (p == j))
            iou[i, j] = inter / union if union else 0.0
    rows, cols = linear_sum_assignment(-iou)
    perm = np.full(n_t, -1)
    perm[rows] = cols
    return perm, float(np.mean([iou[i, perm[i]] if perm[i] >= 0 else 0.0 for i in range(n_t)]))


def novel_view_dssim(model: SegmentationModel, views: list[ViewData], seen_only: bool = False, seen_radius: float = 0.02) -> float:
    """Mean DSSIM of the model on views, weights carried from the geometry (no ground truth).

    Args:
        seen_only: score only the pixels whose surface point the training views saw (within
            ``seen_radius`` x the scene radius of a training pixel's position). Elsewhere the
            weights are extrapolated by nearest neighbour and the DAMs' inputs were never
            observed, so errors there mostly measure extrapolation luck, not the materials.
    """
    from damcap.appearance.evaluate import score_view
    from damcap.appearance.metrics import dssim

    scores = []
    tree = model.point_tree() if seen_only else None
    for v in views:
        pred = model.render(v, model.weights_on(v))
        if tree is None:
            scores.append(score_view(v, pred))
            continue
        cov = v.data.coverage > 0
        seen = np.zeros(cov.shape, bool)
        seen[cov] = tree.query(v.data.position_world[cov])[0] < seen_radius * model.scene_radius
        scores.append(dssim(v.data.radiance_lin, pred, v.data.coverage * seen))
    vals = [s for s in scores if s is not None]
    return float(np.mean(vals)) if vals else float("nan")


def material_shares(model: SegmentationModel, views: list[ViewData]) -> np.ndarray:
    """(n,) fraction of the views' foreground pixels whose largest weight is each material's."""
    labels = np.concatenate([model.weights_of(v)[v.data.coverage > FOREGROUND_COVERAGE].argmax(-1) for v in views])
    return np.bincount(labels, minlength=model.materials) / max(len(labels), 1)


def segmentation_scores(model: SegmentationModel, train: list[ViewData], targets: list[ViewData], same_view: bool) -> dict[str, dict[str, float | None]]:
    """Per-frame DSSIM of a segmentation on targets, by where the weights come from.

    Returns:
        ``{"estimated weights": {...}}`` always (Psi's weights on training frames when
        ``same_view``), plus ``{"true weights": {...}}`` when the targets carry ground-truth
        weights (materials matched to the truth on the training frames by IoU).
    """
    from damcap.appearance.evaluate import score_view

    out: dict[str, dict[str, float | None]] = {"estimated weights": {}}
    for v in targets:
        w = model.weights_of(v) if same_view else model.weights_on(v)
        out["estimated weights"][v.name] = score_view(v, model.render(v, w))
    if all(v.data.weights is not None for v in train + targets):
        fgs = [v.data.coverage > FOREGROUND_COVERAGE for v in train]
        pw = np.concatenate([model.weights_at(v.data.position_world[fg]) for v, fg in zip(train, fgs)])
        tw = np.concatenate([v.data.weights[fg] for v, fg in zip(train, fgs)])
        perm, _ = match_materials(pw, tw)
        out["true weights"] = {}
        for v in targets:
            w = np.zeros(v.data.weights.shape[:-1] + (model.materials,), np.float32)
            for i, j in enumerate(perm):
                if j >= 0:
                    w[..., j] += v.data.weights[..., i]
            out["true weights"][v.name] = score_view(v, model.render(v, w))
    return out
