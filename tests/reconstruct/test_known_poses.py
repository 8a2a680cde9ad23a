"""Known poses: transforms.json, LLFF poses_bounds.npy and Strecha .camera files read back to known OpenGL camera-to-world matrices."""

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


def test_transforms_json_fisheye_is_colmaps_opencv_fisheye(tmp_path):
    cams = _cameras(2)
    frames = [{"file_path": f"images/IMG_{k:02d}", "transform_matrix": cams[k].tolist()} for k in range(2)]
    doc = {"camera_model": "OPENCV_FISHEYE", "fl_x": 40.0, "fl_y": 41.0, "cx": 32.0, "cy": 24.0, "w": 128, "h": 96,
           "k1": 0.05, "k2": -0.01, "k3": 0.002, "k4": -0.001, "frames": frames}
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps(doc))
    cam = load_known_poses(str(path), _sizes(2)).photos[0].camera  # the photos are 64 x 48: half the file's size
    assert cam.model == "OPENCV_FISHEYE" and cam.params == (20.0, 20.5, 16.0, 12.0, 0.05, -0.01, 0.002, -0.001)
    path.write_text(json.dumps({**doc, "p1": 0.01}))
    with pytest.raises(DamcapError, match="p1/p2 are not parameters of camera_model OPENCV_FISHEYE"):
        load_known_poses(str(path), _sizes(2))
    path.write_text(json.dumps({**doc, "camera_model": "EQUIRECTANGULAR"}))
    with pytest.raises(DamcapError, match="camera_model EQUIRECTANGULAR is not supported"):
        load_known_poses(str(path), _sizes(2))


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


# --- Strecha .camera files (strecha:DIR) ---------------------------------------------------------

def _strecha_text(k: np.ndarray, world_from_cam_gl: np.ndarray, size: tuple[int, int], dist=(0, 0, 0)) -> str:
    """A .camera file written from Strecha's definition: x ~ K R^T (X - C), R camera-to-world with
    OpenCV axes (x right, y down, +z forward), here from an OpenGL camera (y up, looking down -z)."""
    r_cv = world_from_cam_gl[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    rows = [*k.tolist(), list(dist), *r_cv.tolist(), world_from_cam_gl[:3, 3].tolist(), list(size)]
    return "\n".join(" ".join(repr(float(v)) if not isinstance(v, int) else str(v) for v in row) + " " for row in rows) + "\n"


def _project_strecha_file_pixels(k: np.ndarray, world_from_cam_gl: np.ndarray, x_world: np.ndarray) -> np.ndarray:
    """Strecha's projection K R^T (X - C) in the file's pixels (pixel centres at integers)."""
    r_cv = world_from_cam_gl[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    p = k @ r_cv.T @ (x_world - world_from_cam_gl[:3, 3])
    return p[:2] / p[2]


def _project_damcap(cam, world_from_cam_gl: np.ndarray, x_world: np.ndarray) -> np.ndarray:
    """damcap's projection: OpenGL camera (looks down -z, y up), pixel centres at +0.5."""
    x_cam = np.linalg.inv(world_from_cam_gl) @ np.append(x_world, 1.0)
    depth = -x_cam[2]
    return np.array([cam.fx * x_cam[0] / depth + cam.cx, cam.fy * -x_cam[1] / depth + cam.cy])


K_FILE = np.array([[150.0, 0.0, 61.25], [0.0, 152.0, 49.5], [0.0, 0.0, 1.0]])  # for 128x96 images


def test_strecha_round_trip_projects_a_point_the_same_both_ways(tmp_path):
    cams = _cameras(4)
    for k in range(4):
        (tmp_path / f"IMG_{k:02d}.jpg.camera").write_text(_strecha_text(K_FILE, cams[k], (128, 96)))
    reg = load_known_poses(f"strecha:{tmp_path}", _sizes(4, 128, 96))
    assert [p.name for p in reg.photos] == sorted(_sizes(4)) and reg.source == "strecha"
    x_world = np.array([0.2, -0.1, 0.3])
    for k, p in enumerate(reg.photos):
        assert np.allclose(p.world_from_cam, cams[k], atol=ATOL)
        # same resolution: damcap's coordinates are the file's plus half a pixel
        expected = _project_strecha_file_pixels(K_FILE, cams[k], x_world) + 0.5
        assert np.allclose(_project_damcap(p.camera, p.world_from_cam, x_world), expected, atol=1e-9)


def test_strecha_intrinsics_scale_to_the_photo_with_the_half_pixel_shift(tmp_path):
    cams = _cameras(2)
    for k in range(2):
        (tmp_path / f"IMG_{k:02d}.jpg.camera").write_text(_strecha_text(K_FILE, cams[k], (128, 96)))
    reg = load_known_poses(f"strecha:{tmp_path}", _sizes(2, 64, 48))  # photos downscaled by 2
    c = reg.photos[0].camera
    assert (c.width, c.height, c.fx, c.fy) == (64, 48, 75.0, 76.0)
    assert (c.cx, c.cy) == (30.875, 25.0)  # (61.25 + 0.5) / 2, (49.5 + 0.5) / 2: not 61.25 / 2
    # a point seen at file pixel (u, v) (centres at integers) lies at ((u + 0.5) / 2, (v + 0.5) / 2) in the photo
    x_world = np.array([-0.3, 0.25, 0.1])
    u_file = _project_strecha_file_pixels(K_FILE, cams[1], x_world)
    assert np.allclose(_project_damcap(reg.photos[1].camera, cams[1], x_world), (u_file + 0.5) / 2, atol=1e-9)


def test_strecha_matches_by_name_then_base_name_and_counts_files_without_photo(tmp_path):
    cams = _cameras(3)
    for k in range(3):
        (tmp_path / f"IMG_{k:02d}.png.camera").write_text(_strecha_text(K_FILE, cams[k], (128, 96)))
    (tmp_path / "notes.txt").write_text("not a camera")
    sizes = {"IMG_00.jpg": (128, 96), "IMG_01.jpg": (128, 96), "IMG_05.jpg": (128, 96)}
    reg = load_known_poses(f"strecha:{tmp_path}", sizes)
    assert [p.name for p in reg.photos] == ["IMG_00.jpg", "IMG_01.jpg"]
    assert reg.unregistered == {"IMG_05.jpg": f"no .camera file in {tmp_path.name}"}
    assert reg.stats["pose_entries_without_photo"] == 1


@pytest.mark.parametrize("edit, message", [
    (lambda rows: rows.__setitem__(0, "abc 0 61.25"), r"IMG_00\.jpg\.camera: line 1: 'abc' is not a number"),
    (lambda rows: rows.__setitem__(0, "nan 0 61.25"), r"IMG_00\.jpg\.camera: line 1 value must be a finite float32 number"),
    (lambda rows: rows.__setitem__(0, "-150 0 61.25"), r"IMG_00\.jpg\.camera: focal lengths .* must be > 0, got -150"),
    (lambda rows: rows.__setitem__(0, "150 3 61.25"), r"IMG_00\.jpg\.camera: K has skew 3"),
    (lambda rows: rows.__setitem__(2, "0 0 2"), r"IMG_00\.jpg\.camera: K must be upper triangular with K\[2,2\] = 1"),
    (lambda rows: rows.__setitem__(3, "0.1 0 0"), r"IMG_00\.jpg\.camera: radial distortion \[0\.1, 0\.0, 0\.0\] is not zero"),
    (lambda rows: rows.__setitem__(4, "2 0 0"), r"IMG_00\.jpg\.camera: R is not a rigid camera-to-world"),
    (lambda rows: rows.__setitem__(8, "128.5 96"), r"IMG_00\.jpg\.camera: image size must be two whole numbers"),
    (lambda rows: rows.__setitem__(8, "128 128"), r"IMG_00\.jpg\.camera: the camera is for 128x128 but the photo is 128x96"),
    (lambda rows: rows.__setitem__(8, "128"), r"IMG_00\.jpg\.camera: line 9 needs 2 numbers, got 1"),
    (lambda rows: rows.pop(), r"IMG_00\.jpg\.camera: a Strecha camera file has 9 lines .* got 8"),
])
def test_strecha_malformed_file_is_one_line_naming_file_and_value(tmp_path, edit, message):
    rows = _strecha_text(K_FILE, _cameras(1)[0], (128, 96)).splitlines()
    edit(rows)
    (tmp_path / "IMG_00.jpg.camera").write_text("\n".join(rows) + "\n")
    with pytest.raises(DamcapError, match=message) as e:
        load_known_poses(f"strecha:{tmp_path}", _sizes(1, 128, 96))
    assert "\n" not in str(e.value)


def test_strecha_folder_errors(tmp_path):
    with pytest.raises(DamcapError, match="Strecha camera folder not found"):
        load_known_poses(f"strecha:{tmp_path / 'missing'}", _sizes(1))
    with pytest.raises(DamcapError, match=r"no \*\.camera file"):
        load_known_poses(f"strecha:{tmp_path}", _sizes(1))
    text = _strecha_text(K_FILE, _cameras(1)[0], (128, 96))
    (tmp_path / "IMG_00.jpg.camera").write_text(text)
    (tmp_path / "IMG_00.png.camera").write_text(text)
    with pytest.raises(DamcapError, match=r"photo IMG_00\.jpg has two camera files \(IMG_00\.jpg\.camera and IMG_00\.png\.camera\)"):
        load_known_poses(f"strecha:{tmp_path}", _sizes(1, 128, 96))


def test_strecha_real_herz_jesus_cameras_face_one_scene(shared_data):
    from damcap.reconstruct.normalize import optical_axes_focus
    from damcap.reconstruct.photos import image_size

    root = shared_data / "real" / "strecha" / "herz-jesus-p8"
    names = sorted(p.name for p in (root / "images").iterdir())
    reg = load_known_poses(f"strecha:{root / 'gt_cameras'}", {n: image_size(root / "images" / n) for n in names})
    assert len(reg.photos) == 8 and not reg.unregistered
    c = reg.photos[0].camera
    # 0000.jpg.camera: K = [[2759.48, 0, 1520.69], [0, 2764.16, 1006.81], [0, 0, 1]] at 3072x2048
    assert (c.width, c.height) == (1536, 1024)
    assert (c.fx, c.fy) == pytest.approx((2759.48 / 2, 2764.16 / 2))
    assert (c.cx, c.cy) == pytest.approx(((1520.69 + 0.5) / 2, (1006.81 + 0.5) / 2))
    assert np.allclose(reg.photos[0].world_from_cam[:3, 3], [-6.71999, -14.2551, 0.279539])
    # the point nearest every optical axis lies in front of every camera and projects into every photo
    focus, cond = optical_axes_focus(reg.world_from_cams)
    assert cond > 1e-3
    for p in reg.photos:
        u, v = _project_damcap(p.camera, p.world_from_cam, focus)
        depth = -(np.linalg.inv(p.world_from_cam) @ np.append(focus, 1.0))[2]
        assert depth > 0 and 0 < u < p.camera.width and 0 < v < p.camera.height


def test_transforms_json_ply_file_path_gives_the_sparse_points(tmp_path):
    import open3d as o3d

    cams = _cameras(2)
    doc = {"fl_x": 70.0, "w": 64, "h": 48, "ply_file_path": "sparse_pc.ply",
           "frames": [{"file_path": f"images/IMG_{k:02d}", "transform_matrix": cams[k].tolist()} for k in range(2)]}
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(DamcapError, match="ply_file_path: .*sparse_pc.ply not found"):
        load_known_poses(str(path), _sizes(2))
    pts = np.random.default_rng(0).normal(size=(50, 3))
    o3d.io.write_point_cloud(str(tmp_path / "sparse_pc.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    reg = load_known_poses(str(path), _sizes(2))
    np.testing.assert_allclose(reg.points_world, pts)
    assert reg.points_seen_from.shape == (50,) and set(reg.points_seen_from.tolist()) <= {0, 1}
