"""Known poses: the three formats read back to known OpenGL camera-to-world matrices."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from damcap.common.errors import DamcapError
from damcap.common.cameras import look_at_world_from_cam
from damcap.reconstruct.poses import (
    colmap_of_world_from_cam,
    llff_of_world_from_cam,
    load_known_poses,
    world_from_cam_of_colmap,
    world_from_cam_of_llff,
)

#: float64 round trips through text files (JSON keeps 17 digits, .npy is exact)
ATOL = 1e-9


def _cameras(n: int = 5, seed: int = 0) -> np.ndarray:
    """(n, 4, 4) OpenGL camera-to-world, random centres looking near the origin."""
    rng = np.random.default_rng(seed)
    mats = []
    for _ in range(n):
        c = rng.normal(size=3)
        c = 3.0 * c / np.linalg.norm(c)
        mats.append(look_at_world_from_cam(c, 0.1 * rng.normal(size=3), np.array([0.0, 1.0, 0.2])))
    return np.stack(mats)


def _sizes(n: int, w: int = 64, h: int = 48) -> dict[str, tuple[int, int]]:
    return {f"IMG_{k:02d}.jpg": (w, h) for k in range(n)}


# ---- axis conversions ------------------------------------------------------------------------

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


# ---- transforms.json ---------------------------------------------------------------------------

def test_transforms_json_round_trip(tmp_path):
    cams = _cameras(5)
    sizes = _sizes(4)  # 5 frames, 4 photos: one frame without photo, one photo... all 4 have frames
    frames = [{"file_path": f"images/IMG_{k:02d}", "transform_matrix": cams[k].tolist()} for k in range(5)]
    doc = {"camera_model": "OPENCV", "fl_x": 70.0, "fl_y": 71.0, "cx": 33.0, "cy": 23.5, "w": 64, "h": 48,
           "k1": 0.05, "k2": -0.01, "p1": 0.001, "p2": -0.002, "frames": frames}
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps(doc))
    reg = load_known_poses(str(path), sizes)
    assert [p.name for p in reg.photos] == sorted(sizes)
    for p in reg.photos:
        k = int(p.name[4:6])
        assert np.allclose(p.world_from_cam, cams[k], atol=ATOL)
        assert (p.camera.fx, p.camera.fy, p.camera.cx, p.camera.cy) == (70.0, 71.0, 33.0, 23.5)
        assert p.camera.distortion[:4] == (0.05, -0.01, 0.001, -0.002)
    assert reg.stats["pose_entries_without_photo"] == 1


def test_transforms_json_angle_and_scaling(tmp_path):
    # instant-ngp / Blender style: camera_angle_x only, file at 2x the photos' resolution
    cams = _cameras(2)
    doc = {"camera_angle_x": math.radians(60), "w": 128, "h": 96,
           "frames": [{"file_path": f"./train/IMG_{k:02d}.png", "transform_matrix": cams[k].tolist()} for k in range(2)]}
    path = tmp_path / "t.json"
    path.write_text(json.dumps(doc))
    reg = load_known_poses(str(path), _sizes(3))
    f = 0.5 * 64 / math.tan(math.radians(30))  # at the photos' 64 px width
    assert reg.photos[0].camera.fx == pytest.approx(f) and reg.photos[0].camera.cx == pytest.approx(32.0)
    assert reg.unregistered == {"IMG_02.jpg": "no frame in t.json"}


def test_transforms_json_rejects_non_rigid(tmp_path):
    m = _cameras(1)[0]
    m[:3, :3] *= 2.0
    (tmp_path / "t.json").write_text(json.dumps({"fl_x": 50, "frames": [{"file_path": "IMG_00.jpg", "transform_matrix": m.tolist()}]}))
    with pytest.raises(DamcapError, match="not a rigid camera-to-world"):
        load_known_poses(str(tmp_path / "t.json"), _sizes(1))


# ---- LLFF poses_bounds.npy ---------------------------------------------------------------------

def test_llff_round_trip(tmp_path):
    cams = _cameras(3)
    rows = []
    for m in cams:
        # LLFF's definition, written independently: columns (down, right, backwards), then (h, w, f)
        down, right, back = -m[:3, 1], m[:3, 0], m[:3, 2]
        pose = np.stack([down, right, back, m[:3, 3], [96.0, 128.0, 140.0]], axis=1)
        rows.append(np.concatenate([pose.ravel(), [0.5, 6.0]]))
    np.save(tmp_path / "poses_bounds.npy", np.array(rows))
    reg = load_known_poses(str(tmp_path / "poses_bounds.npy"), _sizes(3))
    for k, p in enumerate(reg.photos):
        assert np.allclose(p.world_from_cam, cams[k], atol=ATOL)
        assert p.camera.fx == pytest.approx(70.0) and (p.camera.cx, p.camera.cy) == (32.0, 24.0)


def test_llff_row_count_must_match(tmp_path):
    np.save(tmp_path / "poses_bounds.npy", np.zeros((2, 17)))
    with pytest.raises(DamcapError, match="2 rows but 3 photos"):
        load_known_poses(str(tmp_path / "poses_bounds.npy"), _sizes(3))


# ---- colmap:DIR --------------------------------------------------------------------------------

def test_colmap_model_round_trip(tmp_path):
    from damcap.reconstruct.sfm import import_pycolmap

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


def test_unknown_pose_file(tmp_path):
    (tmp_path / "poses.txt").write_text("x")
    with pytest.raises(DamcapError, match="unknown pose file kind"):
        load_known_poses(str(tmp_path / "poses.txt"), _sizes(1))
    with pytest.raises(DamcapError, match="not found"):
        load_known_poses(str(tmp_path / "missing.json"), _sizes(1))
