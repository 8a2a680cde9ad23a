"""Scene normalisation: closed-form values and round trips."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.capture_folder import rigid_problem
from damcap.common.cameras import look_at_world_from_cam, up_direction
from damcap.reconstruct.normalize import (
    normalization_transform,
    optical_axes_focus,
    rotation_agreement_deg,
    similarity,
    similarity_scale,
    transform_points,
    transform_world_from_cam,
    umeyama_similarity,
)


def _orbit(centre: np.ndarray, up: np.ndarray, n: int = 12, radius: float = 5.0, elevation_deg: float = 20.0) -> np.ndarray:
    """Cameras on a tilted ring around ``centre`` with ring normal ``up``, looking at the centre."""
    up = up / np.linalg.norm(up)
    a = np.cross(up, [1.0, 0, 0]) if abs(up[0]) < 0.9 else np.cross(up, [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    e = np.radians(elevation_deg)
    mats = []
    for k in range(n):
        t = 2 * np.pi * k / n
        c = centre + radius * (np.cos(e) * (np.cos(t) * a + np.sin(t) * b) + np.sin(e) * up)
        mats.append(look_at_world_from_cam(c, centre, up))
    return np.stack(mats)


def test_normalization_puts_focus_at_origin_up_on_y():
    centre, up = np.array([3.0, -1.0, 7.0]), np.array([0.3, 0.2, 1.0])
    cams = _orbit(centre, up)
    focus, cond = optical_axes_focus(cams)
    assert np.allclose(focus, centre, atol=1e-9) and cond > 0.01
    assert np.allclose(up_direction(cams), up / np.linalg.norm(up), atol=1e-9)
    t = normalization_transform(cams)
    assert np.allclose(transform_points(t, centre[None])[0], 0, atol=1e-9)
    new = transform_world_from_cam(t, cams)
    assert all(rigid_problem(m) is None for m in new)
    assert np.allclose(up_direction(new), [0, 1, 0], atol=1e-9)
    assert new[0, 0, 3] == pytest.approx(0.0, abs=1e-9) and new[0, 2, 3] > 0  # first camera on +z
    # no points: object radius = 0.35 x camera distance -> 1, so cameras sit at 1 / 0.35
    assert np.linalg.norm(new[:, :3, 3], axis=1) == pytest.approx(np.full(12, 1 / 0.35))
    # cameras still look at the object: the origin projects to the image centre direction (-z)
    to_origin = -new[:, :3, 3] / np.linalg.norm(new[:, :3, 3], axis=1, keepdims=True)
    assert np.allclose(np.einsum("ij,ij->i", to_origin, -new[:, :3, 2]), 1.0, atol=1e-9)


def test_normalization_radius_from_points():
    cams = _orbit(np.zeros(3), np.array([0.0, 1, 0]))
    rng = np.random.default_rng(0)
    d = rng.normal(size=(300, 3))
    pts = 0.5 * d / np.linalg.norm(d, axis=1, keepdims=True)
    t = normalization_transform(cams, pts)
    assert similarity_scale(t) == pytest.approx(2.0, rel=1e-6)


def test_umeyama_and_rotation_agreement():
    cams = _orbit(np.zeros(3), np.array([0.0, 1, 0]))
    a = np.radians(40)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    t = similarity(0.3, rot, np.array([1.0, 2, 3]))
    moved = transform_world_from_cam(t, cams)
    assert np.allclose(umeyama_similarity(cams[:, :3, 3], moved[:, :3, 3]), t, atol=1e-9)
    absolute, relative = rotation_agreement_deg(moved, cams)
    assert absolute.max() < 1e-6 and relative.max() < 1e-6 and len(relative) == 66
    # one camera turned by 1 degree about its optical axis
    bad = moved.copy()
    c, s = np.cos(np.radians(1)), np.sin(np.radians(1))
    bad[3, :3, :3] = bad[3, :3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    absolute, relative = rotation_agreement_deg(bad, cams)
    assert absolute[3] == pytest.approx(1.0, abs=1e-6) and np.median(absolute) < 1e-6
