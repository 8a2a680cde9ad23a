"""The paper's k-means baseline: clusters in RGB + normal space, one DAM fitted per cluster."""

from __future__ import annotations

import time

import numpy as np
import torch


from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, Encoding
from damcap.appearance.views import ViewData, radiance_scale_of
from damcap.appearance.pixels import FOREGROUND_COVERAGE, view_dir_world
from damcap.appearance.segment.cluster import kmeans, kmeans_features
from damcap.appearance.segment.model import SegmentationModel, SegmentationNet, scene_bounds


def kmeans_baseline(views: list[ViewData], materials: int, steps: int = 1500, seed: int = 0, encoding: Encoding = "nr") -> SegmentationModel:
    """The paper's baseline as a :class:`SegmentationModel` (hard weights; Psi unused)."""
    from damcap.appearance.fit import FitOptions, fit_dam
    from damcap.appearance.pixels import PixelSamples

    t0 = time.perf_counter()
    fgs = [v.data.coverage > FOREGROUND_COVERAGE for v in views]
    rad = np.concatenate([v.data.radiance_lin[fg] for v, fg in zip(views, fgs)])
    nrm = np.concatenate([v.data.normal_world[fg] for v, fg in zip(views, fgs)])
    pos = np.concatenate([v.data.position_world[fg] for v, fg in zip(views, fgs)])
    vd = np.concatenate([view_dir_world(v.data.position_world[fg], v.centre_world) for v, fg in zip(views, fgs)])
    fidx = np.concatenate([np.full(int(fg.sum()), k) for k, fg in enumerate(fgs)])
    scale = radiance_scale_of(torch.from_numpy(rad))
    labels = kmeans(kmeans_features(rad, nrm, scale), materials, seed)
    dams = []
    for k in range(materials):
        w = torch.from_numpy((labels == k).astype(np.float32))
        samples = PixelSamples(torch.from_numpy(vd), torch.from_numpy(nrm), torch.from_numpy(rad), w, torch.from_numpy(fidx))
        if w.sum() == 0:
            dams.append(DeepAppearanceMap(DamArchitecture(encoding=encoding), scale))
            continue
        # the same DAM architecture as the joint segmentation's
        opts = FitOptions(steps=steps, seed=seed, holdout_views=0).for_architecture(DamArchitecture(encoding=encoding))
        dams.append(fit_dam(samples, opts).model)
    centre, radius = scene_bounds(views)
    onehot = np.eye(materials, dtype=np.float32)[labels]
    keep = np.random.default_rng(seed).choice(len(pos), min(len(pos), 200_000), replace=False)
    model = SegmentationModel(dams, SegmentationNet(materials), scale, centre, radius, pos[keep].astype(np.float32), onehot[keep], has_psi=False)
    model.seconds = time.perf_counter() - t0
    return model
