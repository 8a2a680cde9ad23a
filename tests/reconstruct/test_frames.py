"""Per-frame buffers: coverage limited to the mask, background zeroed, clipped pixels kept out.

Writing whole frames from photos (write_frames) runs end to end in test_reconstruct.py."""

from __future__ import annotations

import numpy as np

from damcap.common.capture_folder import Intrinsics
from damcap.reconstruct.frames import frame_data_from_buffers, unclipped_fraction
from damcap.reconstruct.undistort import PhotoCamera


def _buffers(h: int = 4, w: int = 5):
    rng = np.random.default_rng(0)
    radiance = rng.uniform(-0.5, 2.0, (h, w, 3))
    normal = rng.normal(size=(h, w, 3))
    position = rng.normal(size=(h, w, 3))
    return radiance, normal, position


def test_background_is_zeroed_and_radiance_clamped_at_zero():
    radiance, normal, position = _buffers()
    coverage = np.zeros((4, 5))
    coverage[1:3, 1:4] = 1.0
    coverage[0, 0] = 0.4
    coverage[3, 4] = 5e-4  # at or below 1e-3: no coverage at all
    d = frame_data_from_buffers(radiance, normal, position, coverage)
    on = np.zeros((4, 5), bool)
    on[1:3, 1:4] = True
    on[0, 0] = True
    for a in (d.radiance_lin, d.normal_world, d.position_world, d.coverage):
        assert a.dtype == np.float32
    np.testing.assert_array_equal(d.coverage, np.where(on, coverage, 0).astype(np.float32))
    np.testing.assert_allclose(d.radiance_lin[on], np.maximum(radiance[on], 0), rtol=1e-7)
    np.testing.assert_allclose(d.normal_world[on], normal[on], rtol=1e-7)
    np.testing.assert_allclose(d.position_world[on], position[on], rtol=1e-7)
    for a in (d.radiance_lin, d.normal_world, d.position_world):
        assert not a[~on].any()
    assert d.weights is None


def test_coverage_is_limited_to_the_mask():
    radiance, normal, position = _buffers()
    coverage = np.full((4, 5), 0.8)
    mask = np.zeros((4, 5))
    mask[:, :2] = 1.0
    mask[:, 2] = 0.5
    mask[0, 3] = 1.7  # clipped to 1
    mask[1, 3] = -2.0  # clipped to 0
    d = frame_data_from_buffers(radiance, normal, position, coverage, mask)
    expected = np.zeros((4, 5), np.float32)
    expected[:, :2] = 0.8
    expected[:, 2] = 0.5
    expected[0, 3] = 0.8
    np.testing.assert_allclose(d.coverage, expected, rtol=1e-7)
    assert not d.radiance_lin[expected == 0].any() and d.radiance_lin[expected > 0].shape == (13, 3)
    # without a mask the same buffers cover everything
    assert (frame_data_from_buffers(radiance, normal, position, coverage).coverage == np.float32(0.8)).all()


def test_unclipped_fraction_of_an_identical_pinhole():
    cam = PhotoCamera(8, 6, 10.0, 10.0, 4.0, 3.0)
    target = Intrinsics(10.0, 10.0, 4.0, 3.0, 8, 6)
    clipped = np.zeros((6, 8), bool)
    clipped[2, 3] = clipped[5, 7] = True
    keep = unclipped_fraction(clipped, cam, target)
    assert keep.shape == (6, 8) and keep.dtype == np.float32
    np.testing.assert_array_equal(keep, (~clipped).astype(np.float32))


def test_unclipped_fraction_is_conservative_when_resampled():
    """At half the resolution every target pixel that any clipped photo pixel touches is dropped."""
    cam = PhotoCamera(16, 16, 20.0, 20.0, 8.0, 8.0)
    target = Intrinsics(10.0, 10.0, 4.0, 4.0, 8, 8)
    clipped = np.zeros((16, 16), bool)
    clipped[6:8, 10:12] = True  # photo pixels (6..7, 10..11) -> target pixel (3, 5)
    keep = unclipped_fraction(clipped, cam, target)
    assert set(np.unique(keep)) <= {0.0, 1.0}
    assert keep[3, 5] == 0 and keep.sum() >= 64 - 4  # the clipped target pixel, and at most its neighbours
    assert unclipped_fraction(np.zeros((16, 16), bool), cam, target).min() == 1.0
