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


def test_image_observations_are_the_reprojection_errors(tmp_path):
    """One 3D point seen by two pinhole images: one observation exact, one 3 px off in x."""
    from damcap.reconstruct.colmap.database import import_pycolmap
    from damcap.reconstruct.colmap.model import image_observations

    pycolmap = import_pycolmap()
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 100.0, 64, 48)
    cam.params = [100.0, 100.0, 32.0, 24.0]
    rec.add_camera_with_trivial_rig(cam)
    xyz = np.array([0.1, -0.2, 5.0])
    for k, (shift, dx) in enumerate(((0.0, 0.0), (0.5, 3.0))):
        cfw = np.eye(4)[:3]
        cfw[0, 3] = shift  # camera k at x = -shift (cam_from_world translates by +shift)
        u = 100.0 * (xyz[0] + shift) / xyz[2] + 32.0 + dx
        v = 100.0 * xyz[1] / xyz[2] + 24.0
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"IMG_{k}.jpg", camera_id=1, image_id=k + 1,
                                                        points2D=[pycolmap.Point2D(np.array([u, v]))]), pycolmap.Rigid3d(cfw))
    track = pycolmap.Track()
    track.add_element(1, 0)
    track.add_element(2, 0)
    rec.add_point3D(xyz, track)
    obs = image_observations(rec)
    assert set(obs) == {1, 2}
    assert obs[1].shape == (1, 3) and obs[1][0, 2] == pytest.approx(0.0, abs=1e-9)
    assert obs[2][0, 2] == pytest.approx(3.0, abs=1e-9)
