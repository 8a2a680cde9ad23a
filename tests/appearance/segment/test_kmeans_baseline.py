"""The paper's k-means baseline: hard weights that are exactly the k-means of (RGB, normal) features.

Its accuracy against the joint segmentation is checked in test_score.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from damcap.appearance.segment.cluster import kmeans, kmeans_features
from damcap.appearance.segment.kmeans_baseline import kmeans_baseline
from damcap.appearance.views import load_views, radiance_scale_of
from damcap.common.capture_folder import read_capture


@pytest.fixture(scope="module")
def train(small_capture):
    return load_views(read_capture(small_capture), "train")


def _foreground(views, name):
    return np.concatenate([getattr(v.data, name)[v.data.coverage > 0.5] for v in views])


def test_hard_weights_are_the_kmeans_partition(train):
    model = kmeans_baseline(train, 2, steps=5, seed=0)
    rad, nrm, pos = (_foreground(train, n) for n in ("radiance_lin", "normal_world", "position_world"))
    scale = radiance_scale_of(torch.from_numpy(rad))
    labels = kmeans(kmeans_features(rad, nrm, scale), 2, 0)
    assert model.materials == 2 and not model.has_psi and len(model.dams) == 2
    assert model.radiance_scale == pytest.approx(scale)
    assert model.points_world.shape == (len(pos), 3)  # fewer than 200 000: every pixel kept
    assert set(np.unique(model.point_weights)) == {0.0, 1.0} and np.all(model.point_weights.sum(1) == 1)
    assert sorted(model.point_weights.sum(0).astype(int).tolist()) == sorted(np.bincount(labels, minlength=2).tolist())
    np.testing.assert_array_equal(np.sort(model.points_world, axis=0), np.sort(pos.astype(np.float32), axis=0))
    assert model.seconds > 0


def test_weights_of_a_view_come_from_the_geometry(train):
    model = kmeans_baseline(train, 2, steps=5, seed=1)
    v = train[0]
    w = model.weights_of(v)
    assert w.shape == v.data.coverage.shape + (2,)
    np.testing.assert_allclose(w, model.weights_at(v.data.position_world) * (v.data.coverage > 0)[..., None], atol=1e-7)
    fg = v.data.coverage > 0
    np.testing.assert_allclose(w[fg].sum(-1), 1.0, atol=1e-6)
    assert not w[~fg].any()


def test_one_material_takes_every_pixel(train):
    model = kmeans_baseline(train, 1, steps=5)
    assert model.materials == 1 and np.all(model.point_weights == 1.0)
