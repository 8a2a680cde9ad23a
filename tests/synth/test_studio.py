"""Studio photo sets (Mitsuba): a multi-material object on a textured board, photographed."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from damcap.capture.exif import read_exposure
from damcap.common.data_dir import shared_data_dir
from damcap.common.errors import DamcapError
from damcap.common.exr import read_image_u8
from damcap.synth.studio import PARTIAL_MARKER, STUDIO_MATERIALS, StudioOptions, board_albedo, make_studio_photos, studio_object


@pytest.fixture(scope="module")
def inputs():
    data = shared_data_dir()
    return str(data / "meshes" / "stanford-bunny.obj"), str(data / "envmaps" / "studio.hdr")


def test_board_albedo_range_and_saturation():
    full = board_albedo(2.0, 1.0, seed=1, texels=64)
    grey = board_albedo(2.0, 0.0, seed=1, texels=64)
    assert full.shape == (64, 64, 3) and full.dtype == np.float32
    assert full.min() >= 0.02 and full.max() <= 0.95 and full.std() > 0.05  # a pattern, not a flat colour
    np.testing.assert_allclose(grey[..., 0], grey[..., 1], atol=1e-6)
    np.testing.assert_allclose(grey[..., 1], grey[..., 2], atol=1e-6)
    assert not np.allclose(board_albedo(2.0, 1.0, seed=2, texels=64), full)


def test_options_name_what_is_wrong(inputs, tmp_path):
    obj, env = inputs
    with pytest.raises(DamcapError, match="--materials 'gold,velvet'.*velvet unknown"):
        StudioOptions(object=obj, env=env, materials="gold,velvet").validate()
    with pytest.raises(DamcapError, match="--env 'nope.hdr': file not found"):
        StudioOptions(object=obj, env="nope.hdr").validate()
    with pytest.raises(DamcapError, match="--object '': file not found"):
        StudioOptions(env=env).validate()
    assert set(StudioOptions(object=obj, env=env).material_names()) <= set(STUDIO_MATERIALS)
    with pytest.raises(DamcapError, match="puts rings at 65, 95 deg"):
        StudioOptions(object=obj, env=env, elevation_deg=80.0).validate()


def test_a_small_set_is_photographed_with_masks_cameras_and_materials(inputs, tmp_path):
    """3 photos of 48 px: JPEGs with EXIF exposure, masks that are the object's silhouette (not
    the board's), the true cameras and the materials recorded; the folder is refused afterwards,
    and a folder of another interrupted run is refused."""
    from damcap.common.capture_folder import Intrinsics
    from damcap.common.raycast import MeshRaycaster
    from damcap.synth.photos import default_intrinsics

    obj, env = inputs
    opts = StudioOptions(object=obj, env=env, materials="blue-plastic,copper", views=3, size=48, spp=4, seed=2)
    names = make_studio_photos(tmp_path / "set", opts)
    assert names == ["IMG_0000.jpg", "IMG_0001.jpg", "IMG_0002.jpg"]
    t = json.loads((tmp_path / "set" / "transforms.json").read_text())
    assert [m["name"] for m in t["damcap_studio"]["materials"]] == ["blue-plastic", "copper"]
    assert all(s > 0 for s in t["damcap_studio"]["face_share"]) and not (tmp_path / "set" / PARTIAL_MARKER).exists()
    assert t["damcap_studio"]["exposure_gain"] > 0 and t["damcap_studio"]["median_exposure_factor"] > 0
    mesh, normals, labels = studio_object(opts)
    assert np.bincount(labels).tolist() == t["damcap_studio"]["face_share"]
    intr: Intrinsics = default_intrinsics(48)
    rc = MeshRaycaster(replace(mesh, vertex_normals=normals))
    for k, frame in enumerate(t["frames"]):
        photo = read_image_u8(tmp_path / "set" / frame["file_path"])
        mask = read_image_u8(tmp_path / "set" / frame["mask_path"])[..., 0]
        assert photo.shape == (48, 48, 3) and set(np.unique(mask)) <= {0, 255}
        cover = rc.buffers(np.array(frame["transform_matrix"]), intr.fl_x, intr.fl_y, intr.cx, intr.cy, 48, 48, supersample=4).coverage
        assert ((mask > 0) == (cover > 0.5)).mean() > 0.99
        assert 0.02 < (mask > 0).mean() < 0.6  # the object, not the whole frame (the board is not masked)
        assert photo[mask == 0].mean() > 5  # the board is lit and seen around the object
        assert read_exposure(tmp_path / "set" / frame["file_path"]).time_s is not None
    with pytest.raises(DamcapError, match="not empty"):
        make_studio_photos(tmp_path / "set", opts)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / PARTIAL_MARKER).write_text("{}")
    with pytest.raises(DamcapError, match="interrupted synth-studio run with other options"):
        make_studio_photos(tmp_path / "other", opts)


def test_an_interrupted_run_resumes_keeping_its_photos(inputs, tmp_path, monkeypatch):
    import damcap.synth.mitsuba_render as mr

    obj, env = inputs
    opts = StudioOptions(object=obj, env=env, materials="gold", views=3, size=48, spp=4)
    real, calls = mr.render_view, []

    def stop_on_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(mr, "render_view", stop_on_second)
    with pytest.raises(KeyboardInterrupt):
        make_studio_photos(tmp_path / "set", opts)
    first = (tmp_path / "set" / "images" / "IMG_0000.jpg").read_bytes()
    assert (tmp_path / "set" / PARTIAL_MARKER).is_file() and not (tmp_path / "set" / "transforms.json").exists()
    monkeypatch.setattr(mr, "render_view", real)
    calls.clear()
    assert len(make_studio_photos(tmp_path / "set", opts)) == 3
    assert (tmp_path / "set" / "images" / "IMG_0000.jpg").read_bytes() == first  # kept, not rendered again


def test_a_folder_left_by_a_run_killed_while_writing_its_marker_counts_as_new(inputs, tmp_path, monkeypatch):
    """kill -9 inside the marker's atomic write leaves only its temporary file: the rerun starts
    (the marker is the first thing written), where any other file makes the folder 'not empty'."""
    import damcap.synth.mitsuba_render as mr

    obj, env = inputs
    opts = StudioOptions(object=obj, env=env, materials="gold", views=3, size=48, spp=4)
    (tmp_path / "set").mkdir()
    (tmp_path / "set" / f".{PARTIAL_MARKER[:-len('.json')]}.k1ll3d.tmp.json").write_text('{"half')

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(mr, "render_view", stop)
    with pytest.raises(KeyboardInterrupt):
        make_studio_photos(tmp_path / "set", opts)
    assert json.loads((tmp_path / "set" / PARTIAL_MARKER).read_text())["views"] == 3
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(DamcapError, match="not empty"):
        make_studio_photos(tmp_path / "other", opts)
