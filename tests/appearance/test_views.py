"""Frames as the appearance tasks see them: the radiance scale, loading a split, its samples."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from damcap.appearance.views import ViewData, load_views, radiance_scale_of, samples_of
from damcap.common.capture_folder import read_capture


def test_radiance_scale_is_the_95th_percentile():
    x = torch.arange(303, dtype=torch.float32).reshape(101, 3)  # pooled channels: 0..302
    assert radiance_scale_of(x) == pytest.approx(0.95 * 302, rel=1e-6)
    # only samples with weight > 0 count: rows 0..10 pool to 0..32
    w = torch.zeros(101)
    w[:11] = 1
    assert radiance_scale_of(x, w) == pytest.approx(0.95 * 32, rel=1e-6)
    assert radiance_scale_of(x.double() * 2) == pytest.approx(2 * 0.95 * 302, rel=1e-6)


@pytest.mark.parametrize("x", [torch.zeros(0, 3), torch.zeros(10, 3), torch.full((4, 3), float("nan")),
                               torch.full((4, 3), float("inf"))])
def test_radiance_scale_falls_back_to_one(x):
    assert radiance_scale_of(x) == 1.0
    assert radiance_scale_of(torch.ones(5, 3), torch.zeros(5)) == 1.0


def test_radiance_scale_of_a_large_array_is_subsampled_evenly():
    x = torch.linspace(0, 1, 3 * 600_000).reshape(-1, 3)
    assert radiance_scale_of(x) == pytest.approx(0.95, abs=1e-4)


def test_load_views_and_samples_of_the_small_capture(small_capture):
    cap = read_capture(small_capture)
    train, test = load_views(cap, "train"), load_views(cap, "test")
    assert len(train) == 4 and len(test) == 8  # 12 views, 4 train (conftest)
    v = train[0]
    assert isinstance(v, ViewData) and v.name == cap.split("train")[0].name
    np.testing.assert_array_equal(v.centre_world, v.world_from_cam[:3, 3])
    assert v.data.radiance_lin.shape == (32, 32, 3)
    s = samples_of(train)
    counts = [int((t.data.coverage > 0.5).sum()) for t in train]
    assert len(s) == sum(counts) and min(counts) > 0
    assert torch.bincount(s.frame_index).tolist() == counts
    np.testing.assert_allclose(s.normal_world.norm(dim=-1).numpy(), 1.0, atol=1e-3)
