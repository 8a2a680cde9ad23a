"""The capture folder: round trip and every validation error (docs/capture-format.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from damcap.common.capture_folder import (
    GEOMETRY_CHANNELS, inspect_capture, read_capture, read_frame, rigid_problem, write_frame, write_transforms,
)
from damcap.common.errors import DamcapError
from damcap.common.exr import read_exr, write_exr


def test_round_trip_preserves_arrays_and_unknown_keys(capture_copy):
    cap = read_capture(capture_copy)
    doc = json.loads((capture_copy / "transforms.json").read_text())
    doc["my_tool_key"] = {"a": [1, 2]}
    doc["frames"][0]["my_frame_key"] = "x"
    (capture_copy / "transforms.json").write_text(json.dumps(doc))
    cap = read_capture(capture_copy)
    before = read_frame(cap, cap.frames[0])
    write_transforms(cap)
    again = read_capture(capture_copy)
    out = json.loads((capture_copy / "transforms.json").read_text())
    assert out["my_tool_key"] == {"a": [1, 2]} and out["frames"][0]["my_frame_key"] == "x"
    assert again.train_filenames == cap.train_filenames and again.test_filenames == cap.test_filenames
    np.testing.assert_allclose(again.frames[3].world_from_cam, cap.frames[3].world_from_cam, atol=1e-12)
    after = read_frame(again, again.frames[0])
    for a, b in [(before.radiance_lin, after.radiance_lin), (before.normal_world, after.normal_world), (before.coverage, after.coverage)]:
        np.testing.assert_array_equal(a, b)


def test_exr_round_trip_float_and_half(tmp_path):
    rng = np.random.default_rng(0)
    img = rng.random((5, 7, 3)).astype(np.float32) * 1000
    write_exr(tmp_path / "f.exr", img, ["R", "G", "B"], dtype="float")
    back, names = read_exr(tmp_path / "f.exr")
    assert names == ("R", "G", "B")
    np.testing.assert_array_equal(back, img)
    write_exr(tmp_path / "h.exr", img, ["R", "G", "B"], dtype="half")
    np.testing.assert_allclose(read_exr(tmp_path / "h.exr")[0], img, rtol=1e-3)


def test_summary_reports_frames_and_splits(small_capture):
    s = inspect_capture(small_capture)
    assert (s.frames, s.resolution, s.train, s.test, s.problems) == (12, (32, 32), 4, 8, [])
    assert 0.1 < s.coverage_mean < 0.9 and s.radiance_max > s.radiance_min >= 0


def _geometry(capture_dir, idx=0):
    path = capture_dir / "geometry" / f"{idx:04d}.exr"
    px, names = read_exr(path)
    return path, px, list(names)


def _problems(capture_dir):
    return " | ".join(inspect_capture(capture_dir).problems)


def test_missing_image_file_is_named(capture_copy):
    (capture_copy / "images" / "0002.exr").unlink()
    assert "0002.exr: file not found" in _problems(capture_copy)


def test_wrong_channel_names(capture_copy):
    path, px, names = _geometry(capture_copy)
    names[names.index("N.X")] = "nx"
    write_exr(path, px, names, dtype="float")
    assert "missing channel(s) N.X" in _problems(capture_copy)


def test_non_unit_normals(capture_copy):
    path, px, names = _geometry(capture_copy)
    a = px[..., names.index("A")] > 0
    for c in ("N.X", "N.Y", "N.Z"):
        px[..., names.index(c)][a] *= 1.5
    write_exr(path, px, names, dtype="float")
    assert "normals must be unit length" in _problems(capture_copy)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_inf_named_with_pixel(capture_copy, bad):
    path = capture_copy / "images" / "0001.exr"
    px, names = read_exr(path)
    px[3, 4, 1] = bad
    write_exr(path, px, names, dtype="float")
    assert "0001.exr: radiance has 1 NaN/inf value(s), first at pixel (row 3, col 4)" in _problems(capture_copy)


def test_mismatched_sizes(capture_copy):
    path = capture_copy / "images" / "0005.exr"
    write_exr(path, np.zeros((16, 32, 3)), ["R", "G", "B"])
    assert "0005.exr: image is 32x16 (WxH) but transforms.json says 32x32" in _problems(capture_copy)


def test_non_rigid_camera(capture_copy):
    doc = json.loads((capture_copy / "transforms.json").read_text())
    m = np.array(doc["frames"][2]["transform_matrix"])
    m[:3, :3] *= 2.0
    doc["frames"][2]["transform_matrix"] = m.tolist()
    (capture_copy / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(DamcapError, match=r"frames\[2\].*not a rigid camera-to-world.*not orthonormal"):
        read_capture(capture_copy)


@pytest.mark.parametrize("far, needle", [(1e300, "beyond float32's range"), (1e12, "times farther from the cameras' median centre")])
def test_a_camera_centre_no_scene_can_have_is_refused(capture_copy, far, needle):
    doc = json.loads((capture_copy / "transforms.json").read_text())
    doc["frames"][2]["transform_matrix"][1][3] = far
    (capture_copy / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(DamcapError, match=f"transforms.json: {doc['frames'][2]['file_path']}: camera centre .*{needle}"):
        read_capture(capture_copy)
    with pytest.raises(DamcapError, match=needle):
        inspect_capture(capture_copy)


def test_a_png_named_exr_is_refused_by_its_content(capture_copy):
    from damcap.common.exr import write_png

    frame = json.loads((capture_copy / "transforms.json").read_text())["frames"][1]["file_path"]
    write_png(capture_copy / "x.png", np.zeros((8, 8, 3), np.uint8))
    (capture_copy / "x.png").replace(capture_copy / frame)
    problems = inspect_capture(capture_copy).problems
    assert problems == [f"{capture_copy / frame}: named .exr but its content is PNG, not OpenEXR; convert it to OpenEXR "
                        "(or give it the name of what it is)"]


def test_a_capture_without_a_foreground_pixel_is_a_problem(capture_copy):
    cap = read_capture(capture_copy)
    for f in cap.frames:
        d = read_frame(cap, f)
        d.coverage[:] = d.coverage * 0.4  # covered, but nowhere foreground
        write_frame(cap, f, d)
    problems = inspect_capture(capture_copy).problems
    assert len(problems) == 1 and "no frame has a foreground pixel (largest coverage 0.4" in problems[0]


def test_rigid_problem_cases():
    assert rigid_problem(np.eye(4)) is None
    refl = np.diag([1.0, 1.0, -1.0, 1.0])
    assert "determinant" in rigid_problem(refl)
    bad = np.eye(4)
    bad[3, 0] = 1
    assert "last row" in rigid_problem(bad)


def test_empty_split(capture_copy):
    doc = json.loads((capture_copy / "transforms.json").read_text())
    doc["test_filenames"] = []
    (capture_copy / "transforms.json").write_text(json.dumps(doc))
    assert "the 'test' split is empty" in _problems(capture_copy)
    with pytest.raises(DamcapError, match="'test' split is empty"):
        read_capture(capture_copy).split("test")


def test_split_naming_unknown_frame(capture_copy):
    doc = json.loads((capture_copy / "transforms.json").read_text())
    doc["train_filenames"].append("images/9999.exr")
    (capture_copy / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(DamcapError, match="images/9999.exr"):
        read_capture(capture_copy)


def test_bad_json_and_newer_version(capture_copy):
    tj = capture_copy / "transforms.json"
    doc = json.loads(tj.read_text())
    tj.write_text("{not json")
    with pytest.raises(DamcapError, match="transforms.json: invalid JSON"):
        read_capture(capture_copy)
    doc["damcap_version"] = 99
    tj.write_text(json.dumps(doc))
    with pytest.raises(DamcapError, match="newer than this damcap reads"):
        read_capture(capture_copy)


def test_truncated_exr(capture_copy):
    path = capture_copy / "geometry" / "0000.exr"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    cap = read_capture(capture_copy)
    with pytest.raises(DamcapError, match="0000.exr"):
        read_frame(cap, cap.frames[0])


def test_geometry_channels_constant():
    assert GEOMETRY_CHANNELS == ("N.X", "N.Y", "N.Z", "P.X", "P.Y", "P.Z", "A")


class TestHostileTransforms:
    """Every number in transforms.json is checked (finite in float32, bounded) before it is used."""

    @staticmethod
    def _edit(capture_copy, change):
        tj = capture_copy / "transforms.json"
        doc = json.loads(tj.read_text())
        change(doc)
        tj.write_text(json.dumps(doc))

    def test_huge_material_count_is_refused_quickly(self, capture_copy):
        import time

        self._edit(capture_copy, lambda d: d.update(materials=10 ** 12))
        t0 = time.perf_counter()
        with pytest.raises(DamcapError, match=r"transforms\.json: 'materials' must be an integer in \[1, 64\], got 1000000000000"):
            read_capture(capture_copy)
        assert time.perf_counter() - t0 < 2.0

    def test_a_transforms_json_over_the_bound_is_refused_from_its_size(self, capture_copy):
        """Refused before it is parsed: one line naming the file, its size and the bound (a
        sparse file: its size is all the reader may look at)."""
        import time

        from damcap.common.capture_folder import MAX_TRANSFORMS_BYTES

        tj = capture_copy / "transforms.json"
        with open(tj, "r+b") as f:
            f.truncate(MAX_TRANSFORMS_BYTES + 2 ** 20)
        t0 = time.perf_counter()
        with pytest.raises(DamcapError, match=r"transforms\.json: transforms\.json is 33\.0 MiB, larger than the 32 MiB damcap reads"):
            read_capture(capture_copy)
        assert time.perf_counter() - t0 < 0.5
        with open(tj, "r+b") as f:
            f.truncate(MAX_TRANSFORMS_BYTES)  # at the bound it is parsed (and refused as the JSON it is: NUL padding)
        with pytest.raises(DamcapError, match="invalid JSON"):
            read_capture(capture_copy)

    @pytest.mark.parametrize("value", [0, -2, 2.0, True])
    def test_bad_material_counts(self, capture_copy, value):
        self._edit(capture_copy, lambda d: d.update(materials=value))
        with pytest.raises(DamcapError, match="'materials' must be an integer"):
            read_capture(capture_copy)

    def test_resolution_beyond_memory_names_the_gib(self, capture_copy):
        self._edit(capture_copy, lambda d: d.update(w=60000, h=60000))
        with pytest.raises(DamcapError, match=r"transforms\.json: a frame of 60000x60000 pixels would need [\d.e+]+ GiB"):
            read_capture(capture_copy)
        self._edit(capture_copy, lambda d: d.update(w=10 ** 9, h=4))
        with pytest.raises(DamcapError, match=r"a frame width must be an integer in \[1, 65535\]"):
            read_capture(capture_copy)

    @pytest.mark.parametrize("key", ["fl_x", "fl_y", "cx", "cy"])
    @pytest.mark.parametrize("value", [1e39, float("nan"), float("inf")])
    def test_intrinsics_finite_in_float32(self, capture_copy, key, value):
        self._edit(capture_copy, lambda d: d.update({key: value}))
        with pytest.raises(DamcapError, match=rf"transforms\.json: '{key}' must be a finite"):
            read_capture(capture_copy)

    def test_negative_focal_length(self, capture_copy):
        self._edit(capture_copy, lambda d: d.update(fl_x=-5.0))
        with pytest.raises(DamcapError, match="focal lengths must be positive"):
            read_capture(capture_copy)

    def test_duplicate_frames_are_named(self, capture_copy):
        self._edit(capture_copy, lambda d: d["frames"].append(dict(d["frames"][0])))
        with pytest.raises(DamcapError, match=r"duplicate file_path entries \('images/0000\.exr' appears 2 times\)"):
            read_capture(capture_copy)

    def test_deeply_nested_json_is_one_line(self, capture_copy):
        (capture_copy / "transforms.json").write_text("[" * 100000)
        with pytest.raises(DamcapError, match=r"transforms\.json: transforms\.json is nested too deeply") as e:
            read_capture(capture_copy)
        assert "\n" not in str(e.value)

    def test_exr_header_size_is_bounded_before_reading_pixels(self, tmp_path):
        from damcap.common.exr import check_header_size

        with pytest.raises(DamcapError, match=r"x\.exr: an image of 65535x65535 pixels, 1024 channels would need [\d.e+]+ GiB"):
            check_header_size(tmp_path / "x.exr", 65535, 65535, 1024, 4)
        with pytest.raises(DamcapError, match=r"image channel count \(header\) must be an integer in \[1, 1024\]"):
            check_header_size(tmp_path / "x.exr", 4, 4, 5000, 4)
        check_header_size(tmp_path / "x.exr", 64, 64, 4, 4)


def test_up_world_follows_the_cameras(tmp_path):
    """A ring of cameras turning about +z (a z-up capture) has up +z; the same ring about +y, +y."""
    from damcap.common.cameras import orbit_world_from_cam
    from damcap.common.capture_folder import Capture, Frame, Intrinsics

    for up in ([0.0, 0.0, 1.0], [0.0, 1.0, 0.0]):
        cams = orbit_world_from_cam(8, 3.0, 20.0, up_world=np.array(up))
        frames = [Frame(f"images/{k}.exr", f"geometry/{k}.exr", m, Intrinsics(10.0, 10.0, 4.0, 4.0, 8, 8)) for k, m in enumerate(cams)]
        np.testing.assert_allclose(Capture(tmp_path, frames, [], []).up_world, up, atol=1e-9)
