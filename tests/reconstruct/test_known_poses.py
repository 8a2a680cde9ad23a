"""Known poses: transforms.json and LLFF poses_bounds.npy read back to known OpenGL camera-to-world matrices."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from damcap.common.errors import DamcapError
from damcap.reconstruct.known_poses import load_known_poses

from tests.reconstruct.conftest import ATOL, _cameras, _sizes


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


def test_unknown_pose_file(tmp_path):
    (tmp_path / "poses.txt").write_text("x")
    with pytest.raises(DamcapError, match="unknown pose file kind"):
        load_known_poses(str(tmp_path / "poses.txt"), _sizes(1))
    with pytest.raises(DamcapError, match="not found"):
        load_known_poses(str(tmp_path / "missing.json"), _sizes(1))
