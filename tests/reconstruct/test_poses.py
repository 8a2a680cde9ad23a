"""Axis conventions: COLMAP and LLFF camera matrices to OpenGL camera-to-world and back."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.reconstruct.poses import colmap_of_world_from_cam, llff_of_world_from_cam, world_from_cam_of_colmap, world_from_cam_of_llff

from tests.reconstruct.conftest import ATOL, _cameras


def test_colmap_axes_closed_form():
    # a COLMAP camera at the origin looking down +z, y down: OpenGL looks down -z with y up
    m = world_from_cam_of_colmap(np.eye(4)[:3])
    assert np.allclose(m[:3, 2], [0, 0, -1]) and np.allclose(m[:3, 1], [0, -1, 0]) and np.allclose(m[:3, 0], [1, 0, 0])
    # a point in front of the OpenGL camera has negative camera z, positive COLMAP z
    wfc = _cameras(1)[0]
    p_world = wfc[:3, 3] - 2.0 * wfc[:3, 2]
    cfw = colmap_of_world_from_cam(wfc)
    assert (cfw[:, :3] @ p_world + cfw[:, 3])[2] == pytest.approx(2.0)


def test_colmap_and_llff_round_trip():
    for wfc in _cameras(4):
        assert np.allclose(world_from_cam_of_colmap(colmap_of_world_from_cam(wfc)), wfc, atol=ATOL)
        assert np.allclose(world_from_cam_of_llff(llff_of_world_from_cam(wfc)), wfc, atol=ATOL)
