"""Textured photo sets' building blocks: exposures, camera rings, intrinsics, albedo, JPEG EXIF;
the textured room, the turntable motion and the principal point offset.

Whole photo sets (render_textured, write_photo_set) are registered end to end in
tests/reconstruct/test_reconstruct.py."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from damcap.capture.exif import read_exposure
from damcap.common.errors import DamcapError
from damcap.common.exr import read_image_u8
from damcap.common.raycast import MeshRaycaster
from damcap.common.shapes import bumpy_blob
from damcap.synth.photos import (
    PhotoExposure,
    PhotoSetOptions,
    cube_room,
    default_intrinsics,
    exposure_series,
    lambert_ambient,
    make_photo_set,
    orbit_cameras,
    procedural_albedo,
    render_textured,
    room_albedo,
    turntable_cameras,
    write_jpeg,
    y_rotation,
)

LIGHT = np.array([0.4, 0.8, 0.45]) / np.linalg.norm([0.4, 0.8, 0.45])


def test_exposure_factor_closed_form():
    assert PhotoExposure(1 / 50, 200.0, 4.0).factor == pytest.approx(0.25)
    assert PhotoExposure(2.0, 100.0, 8.0).factor == pytest.approx(3.125)


def test_exposure_series_stays_near_the_target_factor():
    series = exposure_series(200, seed=3, target_factor=0.25)
    assert len(series) == 200 and series == exposure_series(200, seed=3, target_factor=0.25)
    assert {e.iso for e in series} == {100.0, 200.0, 400.0} and all(e.f_number == 4.0 for e in series)
    for e in series:
        assert 1 / e.time_s == pytest.approx(round(1 / e.time_s))  # 1/N s, as cameras show it
        assert 0.25 * 0.7 < e.factor < 0.25 * 1.4
    assert exposure_series(5, seed=4) != exposure_series(5, seed=3)


def test_default_intrinsics_closed_form():
    intr = default_intrinsics(256, fov_deg=90.0)
    assert (intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h) == (pytest.approx(128.0), pytest.approx(128.0), 128.0, 128.0, 256, 256)
    assert default_intrinsics(100).fl_x == pytest.approx(50 / math.tan(math.radians(22.5)))


def test_orbit_cameras_on_rings_looking_at_the_origin():
    cams = orbit_cameras(12, 3.0, elevations_deg=(10.0, 40.0))
    assert cams.shape == (12, 4, 4)
    centres = cams[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(centres, axis=1), 3.0, atol=1e-12)
    el = np.degrees(np.arcsin(centres[:, 1] / 3.0))
    np.testing.assert_allclose(el, [10.0] * 6 + [40.0] * 6, atol=1e-9)
    np.testing.assert_allclose(-cams[:, :3, 2], -centres / 3.0, atol=1e-12)  # optical axis through the origin
    az = np.degrees(np.arctan2(centres[:6, 0], centres[:6, 2])) % 360
    np.testing.assert_allclose(az, np.arange(6) * 60.0, atol=1e-9)
    jittered = orbit_cameras(12, 3.0, elevations_deg=(10.0, 40.0), jitter_deg=4.0, seed=1)
    el_j = np.degrees(np.arcsin(jittered[:, 1, 3] / 3.0))
    assert np.all(np.abs(el_j - el) <= 4.0 + 1e-9) and np.abs(el_j - el).max() > 0.1


def test_procedural_albedo_is_a_bounded_function_of_the_point():
    p = np.random.default_rng(0).uniform(-1, 1, (5000, 3))
    a = procedural_albedo(p, seed=2)
    assert a.shape == (5000, 3) and a.dtype == np.float32
    assert a.min() >= 0.05 - 1e-6 and a.max() <= 0.9 + 1e-6
    assert a.std(axis=0).min() > 0.1  # texture, not a flat colour
    np.testing.assert_array_equal(procedural_albedo(p[::-1], seed=2), a[::-1])  # per point, order-free
    assert np.abs(procedural_albedo(p, seed=3) - a).mean() > 0.05
    top = procedural_albedo(p[:10], seed=2 ** 31 - 1)  # the largest --seed (value_noise hashes in int64)
    assert top.min() >= 0.05 - 1e-6 and np.abs(top - a[:10]).mean() > 0.01


def test_write_jpeg_carries_the_exposure_in_exif(tmp_path):
    j, i = np.meshgrid(np.arange(32), np.arange(24))
    img = np.stack([j * 8, i * 10, 255 - j * 4], -1).astype(np.uint8)  # smooth: JPEG keeps it within a few levels
    write_jpeg(tmp_path / "a.jpg", img, PhotoExposure(1 / 60, 400.0, 4.0), quality=95)
    ex = read_exposure(tmp_path / "a.jpg")
    assert ex.time_s == pytest.approx(1 / 60, rel=1e-4) and ex.iso == 400 and ex.f_number == pytest.approx(4.0)
    back = read_image_u8(tmp_path / "a.jpg")
    assert back.shape == (24, 32, 3) and np.abs(back.astype(int) - img).mean() < 3
    write_jpeg(tmp_path / "b.jpg", img, None)
    assert read_exposure(tmp_path / "b.jpg").time_s is None


def test_lambert_ambient_closed_form():
    albedo = np.array([[0.5, 0.2, 0.8], [0.5, 0.2, 0.8]], np.float32)
    normal = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], np.float32)
    light = np.array([0.0, 0.6, 0.8])
    np.testing.assert_allclose(lambert_ambient(albedo, normal, light, 0.25), [[0.425, 0.17, 0.68], [0.125, 0.05, 0.2]], rtol=1e-6)


def test_cube_room_is_seen_from_inside_at_the_closed_form_distance():
    room = cube_room(5.0)
    v, t = room.vertices.astype(np.float64), room.triangles
    assert v.shape == (24, 3) and t.shape == (12, 3) and np.abs(v).max() == 5.0
    face_n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    centroid = v[t].mean(1)
    assert np.all(np.einsum("ti,ti->t", face_n, centroid) < 0)  # counter-clockwise seen from inside
    np.testing.assert_allclose(room.vertex_normals[t[:, 0]], -np.round(centroid / 5.0), atol=0)  # inward face normals
    d = np.random.default_rng(0).normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origin = np.array([0.5, -1.0, 2.0])
    hit = MeshRaycaster(room).cast(origin, d)
    t_ref = np.min(np.where(d > 0, (5.0 - origin) / d, (-5.0 - origin) / d), axis=1)  # exit distance of the box
    np.testing.assert_allclose(hit["t_hit"], t_ref, rtol=1e-5)


def test_room_albedo_is_a_scaled_procedural_albedo_with_its_own_pattern():
    p = np.random.default_rng(1).uniform(-6, 6, (3000, 3))
    a = room_albedo(p, 0.25, seed=2)
    assert a.shape == (3000, 3) and a.min() >= 0.05 - 1e-6 and a.max() <= 0.9 + 1e-6
    assert np.abs(a - procedural_albedo(p * 0.25, seed=2)).mean() > 0.05  # not the object's pattern
    np.testing.assert_array_equal(room_albedo(p * 2, 0.125, seed=2), a)


def test_y_rotation_composes_and_turns_z_toward_x():
    np.testing.assert_allclose(y_rotation(30.0) @ y_rotation(60.0), y_rotation(90.0), atol=1e-12)
    np.testing.assert_allclose(y_rotation(90.0)[:3, :3] @ [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], atol=1e-12)
    r = y_rotation(-37.0)
    np.testing.assert_allclose(r @ r.T, np.eye(4), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_turntable_cameras_are_the_orbit_seen_from_the_object():
    obj_from_cam, room_from_obj = turntable_cameras(8, 3.0, 20.0, jitter_deg=0.0, seed=4)
    np.testing.assert_array_equal(obj_from_cam, orbit_cameras(8, 3.0, (20.0,), jitter_deg=0.0, seed=4))
    room_from_cam = room_from_obj @ obj_from_cam
    np.testing.assert_allclose(room_from_cam, room_from_cam[:1].repeat(8, 0), atol=1e-12)  # one fixed camera
    el = math.radians(20.0)
    np.testing.assert_allclose(room_from_cam[0, :3, 3], 3.0 * np.array([0.0, math.sin(el), math.cos(el)]), atol=1e-12)
    np.testing.assert_allclose(room_from_obj[2], y_rotation(-90.0))  # -360 / 8 degrees per photo
    obj_j, room_j = turntable_cameras(8, 3.0, 20.0, jitter_deg=3.0, seed=4)
    c = (room_j @ obj_j)[:, :3, 3]
    az, el_j = np.degrees(np.arctan2(c[:, 0], c[:, 2])), np.degrees(np.arcsin(c[:, 1] / 3.0))
    assert np.abs(az).max() <= 3.0 + 1e-9 and np.abs(el_j - 20.0).max() <= 3.0 + 1e-9 and np.abs(az).max() > 0.1


def _turntable_photo(rc, room_rc, k: int, n: int, size: int, exposure: PhotoExposure):
    obj_from_cam, room_from_obj = turntable_cameras(n, 3.2, 25.0, jitter_deg=0.0, seed=0)
    return render_textured(rc, obj_from_cam[k], default_intrinsics(size), room_from_obj[k][:3, :3].T @ LIGHT, exposure,
                           room=room_rc, room_from_obj=room_from_obj[k], room_texture_scale=0.25)


def test_turntable_room_stands_still_while_the_object_turns():
    rc, room_rc = MeshRaycaster(bumpy_blob(subdivisions=4)), MeshRaycaster(cube_room(6.4))
    ex = PhotoExposure(1 / 50, 200.0, 4.0)
    photo_a, mask_a, _ = _turntable_photo(rc, room_rc, 0, 8, 64, ex)
    photo_b, mask_b, _ = _turntable_photo(rc, room_rc, 1, 8, 64, ex)
    room_only = (mask_a == 0) & (mask_b == 0)
    assert room_only.mean() > 0.25
    np.testing.assert_array_equal(photo_a[room_only], photo_b[room_only])  # the trap: a static background
    both = (mask_a == 255) & (mask_b == 255)
    assert np.abs(photo_a[both].astype(int) - photo_b[both]).mean() > 15  # the object turned 45 degrees
    assert photo_a[room_only].min() > 5  # lit walls, never black


def test_room_is_textured_and_the_mask_is_the_object_alone():
    rc = MeshRaycaster(bumpy_blob(subdivisions=4))
    cam = orbit_cameras(1, 3.2, (25.0,))[0]
    ex = PhotoExposure(1 / 50, 200.0, 4.0)
    plain, mask_plain, rad_plain = render_textured(rc, cam, default_intrinsics(96), LIGHT, ex)
    photo, mask, rad = render_textured(rc, cam, default_intrinsics(96), LIGHT, ex, room=MeshRaycaster(cube_room(6.4)),
                                       room_texture_scale=0.25)
    np.testing.assert_array_equal(mask, mask_plain)  # the room is behind the object everywhere
    np.testing.assert_array_equal(rad, rad_plain)  # the object's radiance alone
    np.testing.assert_array_equal(photo[mask == 255], plain[mask == 255])
    background = mask == 0
    assert np.all(plain[background] == 0)
    grey = photo.astype(np.float64).mean(-1)
    gx = np.abs(np.diff(grey, axis=1))[background[:, 1:] & background[:, :-1]]
    assert photo[background].min() > 5 and gx.mean() > 3.0 and gx.std() > 3.0  # non-black, textured


def test_principal_point_offset_moves_the_image_by_the_offset():
    rc = MeshRaycaster(bumpy_blob(subdivisions=4))
    cam = orbit_cameras(1, 4.5, (25.0,))[0]
    ex = PhotoExposure(1 / 50, 200.0, 4.0)
    _, centred, _ = render_textured(rc, cam, default_intrinsics(64), LIGHT, ex)
    _, shifted, _ = render_textured(rc, cam, default_intrinsics(64, principal_dx_px=5.0, principal_dy_px=-3.0), LIGHT, ex)
    assert centred[:, :6].max() == 0 and centred[-4:].max() == 0  # the object stays inside either way
    np.testing.assert_array_equal(shifted[:-3, 5:], centred[3:, :-5])  # integer offsets: an exact shift

    def centroid(mask_u8):
        w = mask_u8.astype(np.float64)
        i, j = np.indices(w.shape)
        return np.array([(w * j).sum(), (w * i).sum()]) / w.sum()

    _, frac, _ = render_textured(rc, cam, default_intrinsics(64, principal_dx_px=2.5, principal_dy_px=1.25), LIGHT, ex)
    np.testing.assert_allclose(centroid(frac) - centroid(centred), [2.5, 1.25], atol=0.05)


def _project(obj_from_cam: np.ndarray, doc: dict, points: np.ndarray) -> np.ndarray:
    """(P, 2) pixel (x, y) of object points under an OpenGL camera-to-object and transforms.json's intrinsics."""
    cam = (np.linalg.inv(obj_from_cam) @ np.c_[points, np.ones(len(points))].T).T[:, :3]
    return np.stack([doc["fl_x"] * cam[:, 0] / -cam[:, 2] + doc["cx"], doc["fl_y"] * -cam[:, 1] / -cam[:, 2] + doc["cy"]], 1)


def test_photo_sets_ground_truth_is_the_objects_camera(tmp_path):
    opts = {"views": 3, "size": 48, "jitter_deg": 4.0, "seed": 1, "principal_dx_px": 3.0, "principal_dy_px": -2.0}
    make_photo_set(tmp_path / "tt", PhotoSetOptions(**opts, motion="turntable", room=True))
    make_photo_set(tmp_path / "orbit", PhotoSetOptions(**opts))
    make_photo_set(tmp_path / "orbit_room", PhotoSetOptions(**opts, room=True))
    docs = {k: json.loads((tmp_path / k / "transforms.json").read_text()) for k in ("tt", "orbit", "orbit_room")}
    gt = orbit_cameras(3, 3.2, (25.0,), jitter_deg=4.0, seed=1)
    for doc in docs.values():
        assert (doc["cx"], doc["cy"], doc["w"], doc["h"]) == (27.0, 22.0, 48, 48)
        np.testing.assert_array_equal([f["transform_matrix"] for f in doc["frames"]], gt)  # the same cameras for every motion
    assert all("room_from_cam" not in f for f in docs["orbit_room"]["frames"])
    room_from_cam = np.array([f["room_from_cam"] for f in docs["tt"]["frames"]])
    np.testing.assert_allclose(room_from_cam, turntable_cameras(3, 3.2, 25.0, 4.0, 1)[1] @ gt, atol=1e-12)
    vertices = bumpy_blob(seed=1).vertices.astype(np.float64)
    for n in range(3):
        mask = read_image_u8(tmp_path / "tt" / "masks" / f"IMG_{n:04d}.png")
        mask = mask[..., 0] if mask.ndim == 3 else mask
        np.testing.assert_array_equal(mask, read_image_u8(tmp_path / "orbit" / "masks" / f"IMG_{n:04d}.png").reshape(mask.shape))
        xy = _project(gt[n], docs["tt"], vertices)
        ij = np.floor(xy[:, ::-1]).astype(int)
        near = np.pad(mask > 0, 1)
        near = np.any([near[1 + di:1 + di + 48, 1 + dj:1 + dj + 48] for di in (-1, 0, 1) for dj in (-1, 0, 1)], axis=0)
        assert np.all(near[ij[:, 0], ij[:, 1]])  # the silhouette is the projection of the object (to a pixel)
        assert (mask[ij[:, 0], ij[:, 1]] > 0).mean() > 0.9  # (pixels whose centre misses it have coverage 0)
        rows, cols = np.nonzero(mask)
        np.testing.assert_allclose([cols.min(), cols.max() + 1, rows.min(), rows.max() + 1],
                                   [xy[:, 0].min(), xy[:, 0].max(), xy[:, 1].min(), xy[:, 1].max()], atol=1.0)
        photo = read_image_u8(tmp_path / "orbit_room" / "images" / f"IMG_{n:04d}.jpg")
        assert photo[mask == 0].mean() > 20  # a room, not black


def test_principal_point_beyond_a_quarter_of_the_size_is_refused():
    PhotoSetOptions(size=64, principal_dx_px=16.0, principal_dy_px=-16.0).validate()
    with pytest.raises(DamcapError, match=r"--principal-dx 16.5 --principal-dy 0: .*quarter of --size 64 \(16 px\)"):
        PhotoSetOptions(size=64, principal_dx_px=16.5).validate()
    with pytest.raises(DamcapError, match="--principal-dy -20"):
        PhotoSetOptions(size=64, principal_dy_px=-20.0).validate()
    with pytest.raises(DamcapError, match="--principal-dx"):
        PhotoSetOptions(principal_dx_px=math.nan).validate()
    with pytest.raises(DamcapError, match="--motion must be one of orbit, turntable, got 'spin'"):
        PhotoSetOptions(motion="spin").validate()
