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


class TestHostilePoseFiles:
    @staticmethod
    def _doc(n=4, **shared):
        cams = _cameras(n)
        frames = [{"file_path": f"images/IMG_{k:02d}", "transform_matrix": cams[k].tolist()} for k in range(n)]
        return {"camera_model": "OPENCV", "fl_x": 70.0, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48, **shared, "frames": frames}

    def test_duplicate_entries_for_one_photo_are_refused_naming_photo_and_file(self, tmp_path):
        doc = self._doc()
        doc["frames"].append(dict(doc["frames"][1]))
        path = tmp_path / "transforms.json"
        path.write_text(json.dumps(doc))
        with pytest.raises(DamcapError, match=r"transforms\.json: photo IMG_01\S* has two pose entries \(frames\[1\] and frames\[4\]\)") as e:
            load_known_poses(str(path), _sizes(4))
        assert "\n" not in str(e.value)

    def test_duplicate_by_base_name_with_another_suffix(self, tmp_path):
        doc = self._doc()
        doc["frames"].append({**doc["frames"][2], "file_path": "other/IMG_02.png"})
        path = tmp_path / "t.json"
        path.write_text(json.dumps(doc))
        with pytest.raises(DamcapError, match=r"t\.json: photo IMG_02\S* has two pose entries"):
            load_known_poses(str(path), _sizes(4))

    @pytest.mark.parametrize("key, value", [("fl_x", float("nan")), ("fl_x", float("inf")), ("fl_x", 1e39), ("cx", 1e39),
                                            ("k1", float("nan")), ("w", 10 ** 9), ("w", 0), ("fl_x", "x"),
                                            ("camera_angle_x", 4.0)])
    def test_nan_inf_and_out_of_range_intrinsics(self, tmp_path, key, value):
        doc = self._doc()
        if key == "camera_angle_x":
            del doc["fl_x"]
        doc[key] = value
        path = tmp_path / "transforms.json"
        path.write_text(json.dumps(doc))  # json.dumps writes NaN / Infinity, which json.loads reads back
        with pytest.raises(DamcapError, match=r"transforms\.json"):
            load_known_poses(str(path), _sizes(4))

    def test_nan_matrix_is_refused(self, tmp_path):
        doc = self._doc()
        doc["frames"][0]["transform_matrix"][0][3] = float("nan")
        path = tmp_path / "transforms.json"
        path.write_text(json.dumps(doc))
        with pytest.raises(DamcapError, match=r"transforms\.json: frames\[0\]"):
            load_known_poses(str(path), _sizes(4))

    def test_deeply_nested_json_is_one_line(self, tmp_path):
        path = tmp_path / "transforms.json"
        path.write_text("[" * 100000)
        with pytest.raises(DamcapError, match=r"transforms\.json: transforms\.json is nested too deeply") as e:
            load_known_poses(str(path), _sizes(4))
        assert "\n" not in str(e.value)

    def test_llff_values_beyond_float32_are_refused(self, tmp_path):
        arr = np.zeros((4, 17))
        arr[0, 0] = 1e39
        np.save(tmp_path / "poses_bounds.npy", arr)
        with pytest.raises(DamcapError, match=r"poses_bounds\.npy: contains NaN or inf"):
            load_known_poses(str(tmp_path / "poses_bounds.npy"), _sizes(4))

    def test_llff_huge_array_is_refused_by_its_header(self, tmp_path):
        path = tmp_path / "poses_bounds.npy"
        np.lib.format.open_memmap(path, mode="w+", dtype=np.float64, shape=(10 ** 6, 17)).flush()
        path.write_bytes(path.read_bytes()[:4096])  # the header claims 136 MB, the file holds 4 KB
        with pytest.raises(DamcapError, match=r"poses_bounds\.npy"):
            load_known_poses(str(path), _sizes(4))
