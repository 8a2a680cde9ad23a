"""A COLMAP model (colmap:DIR) read back to known OpenGL camera-to-world matrices."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.reconstruct.known_poses import load_known_poses

from tests.reconstruct.conftest import _cameras, _sizes


def test_colmap_model_round_trip(tmp_path):
    from damcap.reconstruct.colmap.database import import_pycolmap

    pycolmap = import_pycolmap()
    cams = _cameras(3)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 60.0, 64, 48)
    cam.params = [60.0, 32.0, 24.0, 0.02]
    rec.add_camera_with_trivial_rig(cam)
    for k, m in enumerate(cams):
        # COLMAP's cam_from_world, written independently: inverse of camera-to-world with y, z flipped
        cfw = np.linalg.inv(m @ np.diag([1.0, -1.0, -1.0, 1.0]))[:3]
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"IMG_{k:02d}.jpg", camera_id=1, image_id=k + 1),
                                         pycolmap.Rigid3d(cfw))
    (tmp_path / "model").mkdir()
    rec.write_binary(str(tmp_path / "model"))
    reg = load_known_poses(f"colmap:{tmp_path / 'model'}", _sizes(4))
    assert len(reg.photos) == 3 and list(reg.unregistered) == ["IMG_03.jpg"]
    for k, p in enumerate(reg.photos):
        assert np.allclose(p.world_from_cam, cams[k], atol=1e-6)
        assert p.camera.distortion[0] == pytest.approx(0.02) and p.camera.fx == pytest.approx(60.0)
