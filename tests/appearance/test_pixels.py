"""From a frame's arrays to the DAM's per-pixel inputs: V, camera-space normals, foreground samples."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from damcap.appearance.pixels import FOREGROUND_COVERAGE, gather_samples, normal_cam, view_dir_world
from damcap.common.capture_folder import FrameData
from damcap.common.cameras import look_at_world_from_cam


def _frame(coverage: np.ndarray, value: float) -> FrameData:
    h, w = coverage.shape
    j, i = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    pos = np.stack([j, i, np.zeros_like(j)], -1)
    nrm = np.zeros((h, w, 3), np.float32)
    nrm[..., 2] = 1
    return FrameData(np.full((h, w, 3), value, np.float32), nrm, pos, coverage.astype(np.float32))


def test_view_dir_closed_form_unit_and_batch_shapes():
    v = view_dir_world(np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 2.0], [0.0, 4.0, -1.0]]), np.array([0.0, 0.0, 2.0]))
    assert v.dtype == np.float32
    np.testing.assert_allclose(v, [[0, 0, 1], [-1, 0, 0], [0, -0.8, 0.6]], atol=1e-7)
    p = np.random.default_rng(0).normal(size=(2, 5, 7, 3))
    out = view_dir_world(p, np.array([1.0, 2.0, 3.0]))
    assert out.shape == (2, 5, 7, 3)
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, atol=1e-6)


def test_view_dir_at_the_camera_centre_is_zero_not_nan():
    v = view_dir_world(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 3.0]))
    assert v.tolist() == [0.0, 0.0, 0.0]
    assert np.isnan(view_dir_world(np.array([np.nan, 0.0, 0.0]), np.zeros(3))).all()  # NaN is not hidden


def test_normal_cam_closed_form_and_round_trip():
    # a camera on +x looking at the origin: world +x is camera +z (backwards), world -z is camera +x
    wfc = look_at_world_from_cam(np.array([2.0, 0.0, 0.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    n = normal_cam(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]), wfc)
    np.testing.assert_allclose(n, [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-7)
    nw = np.random.default_rng(1).normal(size=(4, 6, 3))
    wfc2 = look_at_world_from_cam(np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.0, -0.2]), np.array([0.0, 1.0, 0.0]))
    nc = normal_cam(nw, wfc2)
    assert nc.shape == (4, 6, 3) and nc.dtype == np.float32
    np.testing.assert_allclose(nc @ wfc2[:3, :3].T, nw, atol=1e-5)


def test_gather_samples_takes_the_foreground_of_every_frame():
    cov0 = np.array([[1.0, 0.6, 0.5], [0.0, 0.9, 0.2]])  # 3 pixels above 0.5 (0.5 itself is not)
    cov1 = np.array([[0.51, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 2
    frames = [_frame(cov0, 1.0), _frame(cov1, 2.0)]
    centres = [np.array([0.0, 0.0, 10.0]), np.array([5.0, 5.0, 5.0])]
    s = gather_samples(frames, centres)
    assert FOREGROUND_COVERAGE == 0.5 and len(s) == 5
    assert s.frame_index.tolist() == [0, 0, 0, 1, 1] and s.frame_index.dtype == torch.int64
    assert s.radiance_lin[:, 0].tolist() == [1.0, 1.0, 1.0, 2.0, 2.0]
    assert torch.equal(s.weight, torch.ones(5))
    # row-major order of the foreground pixels: (0,0), (0,1), (1,1) of frame 0
    np.testing.assert_allclose(s.view_dir_world[1].numpy(), view_dir_world(np.array([1.0, 0.0, 0.0]), centres[0]), atol=1e-7)
    np.testing.assert_allclose(s.view_dir_world[2].numpy(), view_dir_world(np.array([1.0, 1.0, 0.0]), centres[0]), atol=1e-7)
    assert torch.equal(s.normal_world, torch.tensor([[0.0, 0.0, 1.0]]).expand(5, 3))
    # per-pixel weights and another threshold
    w = [np.full(cov0.shape, 0.25), np.arange(6, dtype=np.float64).reshape(2, 3)]
    sw = gather_samples(frames, centres, weights=w, threshold=0.15)
    assert len(sw) == 7 and sw.weight.dtype == torch.float32
    assert sw.weight.tolist() == [0.25] * 5 + [0.0, 5.0]
    sub = sw.subset(sw.frame_index == 1)
    assert len(sub) == 2 and sub.radiance_lin[:, 1].tolist() == [2.0, 2.0]


def test_gather_samples_of_empty_frames_and_mismatched_centres():
    s = gather_samples([_frame(np.zeros((2, 2)), 1.0)], [np.zeros(3)])
    assert len(s) == 0 and s.view_dir_world.shape == (0, 3)
    with pytest.raises(ValueError, match="zip"):
        gather_samples([_frame(np.ones((2, 2)), 1.0)] * 2, [np.zeros(3)])
