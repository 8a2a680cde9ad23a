"""Photo consistency: photos of a textured sphere agree through the true sphere, not a wrong one."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.cameras import orbit_world_from_cam
from damcap.common.capture_folder import Intrinsics
from damcap.common.raycast import MeshRaycaster
from damcap.common.shapes import sphere_mesh
from damcap.reconstruct.photo_consistency import Consistency, nearest_view, photo_consistency, prefer_dense, windowed_ncc


def _texture(p: np.ndarray) -> np.ndarray:
    """(..., 3) a print-like pattern on the surface."""
    g = np.sin(11 * p[..., 0]) * np.cos(13 * p[..., 1]) + 0.5 * np.sin(17 * p[..., 2] + 5 * p[..., 0])
    return np.stack([0.5 + 0.4 * g, 0.5 - 0.3 * g, 0.4 + 0.2 * np.sign(g)], -1).astype(np.float32)


@pytest.fixture(scope="module")
def photos():
    truth = sphere_mesh(np.zeros(3), 1.0, subdivisions=5)
    cams = orbit_world_from_cam(12, 4.0, 20.0)
    intr = Intrinsics(90.0, 90.0, 48.0, 48.0, 96, 96)
    caster = MeshRaycaster(truth)
    images, masks = [], []
    for m in cams:
        b = caster.buffers(m, intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h, supersample=1)
        hit = b.triangle_id >= 0
        images.append(np.where(hit[..., None], _texture(b.position_world), 0).astype(np.float32))
        masks.append(hit.astype(np.float32))
    return truth, cams, [intr] * len(cams), images, masks


def test_the_true_surface_agrees_and_a_wrong_one_does_not(photos):
    truth, cams, intr, images, masks = photos
    good = photo_consistency(truth, cams, intr, images, masks, views=6)
    assert good.pairs == 6 and good.ncc > 0.8 and good.compared_fraction > 0.6
    for wrong in (sphere_mesh(np.array([0.08, 0.0, 0.0]), 1.0, 5), sphere_mesh(np.zeros(3), 0.9, 5)):
        bad = photo_consistency(wrong, cams, intr, images, masks, views=6)
        assert bad.ncc < good.ncc - 0.2, (good, bad)
        assert prefer_dense(bad, good, 0.02) and not prefer_dense(good, bad, 0.02)


def test_without_masks_every_hit_pixel_counts(photos):
    truth, cams, intr, images, _ = photos
    c = photo_consistency(truth, cams, intr, images, None, views=4)
    assert c.pairs == 4 and c.ncc > 0.8


def test_nothing_to_compare_gives_zero():
    truth = sphere_mesh(np.zeros(3), 1.0, subdivisions=3)
    cams = orbit_world_from_cam(1, 4.0, 20.0)
    intr = Intrinsics(30.0, 30.0, 16.0, 16.0, 32, 32)
    assert photo_consistency(truth, cams, [intr], [np.zeros((32, 32, 3), np.float32)], None) == Consistency(0.0, 0.0, 0)


def test_windowed_ncc_ignores_invalid_pixels_and_gain():
    rng = np.random.default_rng(1)
    a = rng.random((20, 20))
    valid = np.ones((20, 20), bool)
    valid[:, 10:] = False
    b = np.where(valid, 2.5 * a + 3.0, rng.random((20, 20)) * 100)  # garbage where invalid
    ncc = windowed_ncc(a, b, valid, 5)
    np.testing.assert_allclose(ncc[2:18, 2:8], 1.0, atol=1e-4)
    assert (ncc[:, 13:] == 0).all()  # windows with less than half valid pixels


def test_nearest_view_skips_views_too_close():
    centres = np.array([[0, 0, 4.0], [0.01, 0, 4.0], [0.5, 0, 4.0], [-4.0, 0, 0]])
    assert nearest_view(centres, np.zeros(3), 0) == 2
    assert nearest_view(centres[:2], np.zeros(3), 0) is None
