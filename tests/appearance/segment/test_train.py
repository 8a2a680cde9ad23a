"""Joint material estimation and segmentation (segment_materials) on a closed-form capture with known materials."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from damcap.appearance.segment.cluster import chromaticity_features, kmeans
from damcap.appearance.segment.options import SegmentOptions
from damcap.appearance.segment.score import match_materials
from damcap.appearance.segment.train import segment_materials
from damcap.appearance.views import radiance_scale_of


def _iou(model, views):
    fgs = [v.data.coverage > 0.5 for v in views]
    pw = np.concatenate([model.weights_of(v)[fg] for v, fg in zip(views, fgs)])
    tw = np.concatenate([v.data.weights[fg] for v, fg in zip(views, fgs)])
    return match_materials(pw, tw)[1]


def test_recovers_the_true_partition(two_materials, segmented):
    _, train, test = two_materials
    assert _iou(segmented, train) > 0.85
    # carried onto the geometry, the segmentation also holds in views it never saw, on the part
    # of the surface the training views saw (within 2 % of the scene radius of a training pixel)
    from scipy.spatial import cKDTree
    tree = cKDTree(segmented.points_world)
    pos = np.concatenate([v.data.position_world[v.data.coverage > 0.5] for v in test])
    seen = tree.query(pos)[0] < 0.02 * segmented.scene_radius
    tw = np.concatenate([v.data.weights[v.data.coverage > 0.5] for v in test])
    assert seen.mean() > 0.3
    assert match_materials(segmented.weights_at(pos[seen]), tw[seen])[1] > 0.85


def test_prior_weight_keeps_the_initial_labels(two_materials):
    """The joint phase's prior term pulls Psi toward the chromaticity k-means labels it started from."""
    _, train, _ = two_materials
    fgs = [v.data.coverage > 0.5 for v in train]
    rad = np.concatenate([v.data.radiance_lin[fg] for v, fg in zip(train, fgs)])
    chroma, bright = chromaticity_features(rad, radiance_scale_of(torch.from_numpy(rad)))
    init = kmeans(chroma[bright], 2, seed=0)
    agreement = {}
    for prior in (0.0, 50.0):  # a short initialisation: without the prior, the joint phase drifts away
        model = segment_materials(train, SegmentOptions(materials=2, steps=150, init_steps=20, batch_pixels=2048, prior_weight=prior,
                                                        illumination_degree=0, init_colour="pixel",  # starts from exactly `init`
                                                        prior="off"))  # DAMs from random weights, free to drift
        assert "prior_ce" in model.history[-1]
        pw = np.concatenate([model.weights_of(v)[fg] for v, fg in zip(train, fgs)])[bright]
        agreement[prior] = match_materials(pw, np.eye(2)[init])[1]
    assert agreement[50.0] > 0.85 and agreement[50.0] > agreement[0.0] + 0.1, agreement
    with pytest.raises(Exception, match="prior-weight"):
        segment_materials(train, SegmentOptions(materials=2, prior_weight=-1.0))
