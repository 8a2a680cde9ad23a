"""The predictor as each material's start and prior (``damcap segment --prior predictor``).

After the initial clustering (:func:`.cluster.initial_labels`), each material k gets the shipped
predictor's DAM for the pixels first assigned to it (:func:`material_views`, then
:func:`.hyper.predict.predict_views`): its DAM starts from those weights, and the joint training
adds, per material, the L1 distance between its DAM and the prediction on (view, normal)
samples drawn once over its pixels' normals and their hemispheres, each weighted by how far it
lies from every pixel of the material (:func:`damcap.appearance.prior.prior_samples`, the
mechanism of ``damcap fit --prior``): 0 where the material's pixels decide, towards 1 where
they say nothing.

Units: the segmentation's DAMs share the capture's radiance scale s (their outputs, and the
data cost, are radiance / s). A prediction has its own scale s_k; its weights are kept as they
are and DAM k's output is multiplied by the gain s_k / s (exactly 1 for a DAM that did not
start from a prediction), so that DAM k with those weights is the prediction exactly.

Pure but for :func:`predict_material_priors`, which reads the shipped predictor.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, dam_forward
from damcap.appearance.fit import PriorSamples
from damcap.appearance.pixels import FOREGROUND_COVERAGE
from damcap.appearance.views import ViewData


def material_views(views: list[ViewData], labels: list[np.ndarray], material: int) -> list[ViewData]:
    """The views with only ``material``'s pixels covered.

    Args:
        views: the training views.
        labels: per view, (P_f,) int labels of its foreground pixels (coverage above
            FOREGROUND_COVERAGE, row-major order), -1 = unlabelled (:func:`.cluster.initial_labels`).
        material: k.

    Returns:
        views sharing every array but coverage, which is 0 outside the pixels labelled k.
    """
    out = []
    for v, lab in zip(views, labels, strict=True):
        fg = v.data.coverage > FOREGROUND_COVERAGE
        keep = np.zeros(fg.shape, bool)
        keep[fg] = np.asarray(lab) == material
        out.append(ViewData(v.name, replace(v.data, coverage=np.where(keep, v.data.coverage, 0).astype(v.data.coverage.dtype)),
                            v.world_from_cam))
    return out


def label_shares(labels: list[np.ndarray], materials: int) -> torch.Tensor:
    """(n,) float32 each material's share of the labelled pixels (labels >= 0); uniform when none is.

    >>> label_shares([np.array([0, 0, 1, -1]), np.array([1, 1])], 2).tolist()
    [0.4000000059604645, 0.6000000238418579]
    """
    lab = np.concatenate([np.asarray(x) for x in labels]) if labels else np.zeros(0, np.int64)
    counts = np.bincount(lab[lab >= 0], minlength=materials)[:materials].astype(np.float64)
    return torch.from_numpy(counts / counts.sum() if counts.sum() > 0 else np.full(materials, 1.0 / materials)).float()


@dataclass
class MaterialPriors:
    """Per material, the prediction it starts from and is pulled towards."""

    predictions: list[DeepAppearanceMap]
    """the predictor's DAM for each material's pixels"""
    inputs: torch.Tensor
    """(n, M, C) the prior samples' encoded DAM inputs"""
    target: torch.Tensor
    """(n, M, 3) the prediction's radiance / the capture's radiance scale"""
    weight: torch.Tensor
    """(n, M) in [0, 1]: how little material k's pixels constrain each sample"""
    share: torch.Tensor
    """(n,) each material's share of the initially labelled pixels (its prior cost's weight, as
    its share of the pixels weighs its data cost)"""
    seconds: float = 0.0
    """predictions and samples, wall clock"""

    def start(self, arch: DamArchitecture, radiance_scale: float) -> tuple[list[torch.Tensor | None], torch.Tensor]:
        """Each material's initial weights (None where the prediction's architecture is not
        ``arch``) and (n,) output gains s_k / s (1 where there is no initial weight)."""
        weights = [p.get_flat_weights().float() if p.arch == arch else None for p in self.predictions]
        gain = [p.radiance_scale / radiance_scale if w is not None else 1.0 for p, w in zip(self.predictions, weights)]
        return weights, torch.tensor(gain, dtype=torch.float32)


def stack_samples(samples: list[PriorSamples], share: torch.Tensor, predictions: list[DeepAppearanceMap], seconds: float = 0.0) -> MaterialPriors:
    """:class:`MaterialPriors` of per-material :class:`.fit.PriorSamples` of one count M."""
    return MaterialPriors(predictions, torch.stack([s.inputs for s in samples]), torch.stack([s.target for s in samples]),
                          torch.stack([s.weight for s in samples]), share, seconds)


def prior_cost(weights_flat: torch.Tensor, gain: torch.Tensor, priors: MaterialPriors, index: torch.Tensor, arch: DamArchitecture) -> torch.Tensor:
    """The prior's cost: sum_k share_k mean_j w_kj |gain_k DAM_k(x_kj) - t_kj| (L1 averaged over channels).

    Args:
        weights_flat: (n, P) the materials' DAM weights.
        gain: (n,) their output gains (:meth:`MaterialPriors.start`).
        priors: the samples (on the weights' device).
        index: (n, B) int64, the samples of this step (each row indexes material k's M samples).
        arch: the DAMs' architecture.

    Returns:
        () in units of radiance / the capture's radiance scale.
    """
    rows = torch.arange(index.shape[0], device=index.device)[:, None]
    x, t, w = priors.inputs[rows, index], priors.target[rows, index], priors.weight[rows, index]
    pred = dam_forward(weights_flat, x, arch) * gain[:, None, None]
    per = ((pred - t).abs().mean(-1) * w).mean(1)  # (n,)
    return (priors.share * per).sum()


def predict_material_priors(views: list[ViewData], labels: list[np.ndarray], materials: int, radiance_scale: float, arch: DamArchitecture,
                            count: int, sigma: float, seed: int = 0, device: str = "cpu") -> MaterialPriors:
    """The shipped predictor's DAM for each material's pixels and its prior samples.

    Args:
        views, labels: the training views and their initial labels (:func:`material_views`).
        materials: n.
        radiance_scale: the capture's (the segmentation's DAMs').
        arch: the segmentation's DAM architecture (its input encoding is the samples').
        count: prior samples per material; sigma: :func:`damcap.appearance.prior.unconstrained_weight`'s distance.
        seed: seeds the samples (material k: seed + k).

    Raises:
        DamcapError: the predictor cannot predict a material (no view shows enough of it, an
            unreadable predictor).
    """
    from damcap.appearance.hyper.predict import predict_views
    from damcap.appearance.prior import prior_samples
    from damcap.appearance.views import samples_of

    t0 = time.perf_counter()
    predictions, samples = [], []
    for k in range(materials):
        mine = material_views(views, labels, k)
        predicted = predict_views(mine, device=device)
        predictions.append(predicted)
        samples.append(prior_samples(predicted, samples_of(mine), arch.encoding, radiance_scale, count, sigma, seed + k))
    return stack_samples(samples, label_shares(labels, materials), predictions, time.perf_counter() - t0)
