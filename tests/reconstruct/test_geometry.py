"""Geometry from silhouettes, points, a sphere or a user mesh, against known shapes."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.capture_folder import Intrinsics
from damcap.common.errors import DamcapError
from damcap.common.cameras import focal_px_from_fov, look_at_world_from_cam
from damcap.reconstruct.geometry import (
    GeometryInputs,
    GeometryOptions,
    align_mesh,
    build_geometry,
    carve,
    fit_sphere_points,
    mask_values_at,
    parse_mode,
    poisson_mesh,
    project_points,
    visual_hull,
)
from damcap.common.mesh import Mesh
from damcap.common.raycast import MeshRaycaster
from damcap.common.shapes import sphere_mesh

SIZE = 64
RADIUS = 0.8
CENTRE = np.array([0.05, -0.03, 0.02])


def _cameras() -> tuple[np.ndarray, list[Intrinsics]]:
    """14 cameras on two rings plus top and bottom, all looking at the origin from distance 3."""
    mats = []
    for el in (-30.0, 30.0):
        for k in range(6):
            az = np.radians(60 * k + (30 if el > 0 else 0))
            e = np.radians(el)
            mats.append(look_at_world_from_cam(3 * np.array([np.cos(e) * np.sin(az), np.sin(e), np.cos(e) * np.cos(az)]),
                                               np.zeros(3), np.array([0.0, 1.0, 0.0])))
    mats.append(look_at_world_from_cam(np.array([0.0, 3.0, 0.01]), np.zeros(3), np.array([0.0, 0.0, -1.0])))
    mats.append(look_at_world_from_cam(np.array([0.0, -3.0, 0.01]), np.zeros(3), np.array([0.0, 0.0, 1.0])))
    f = focal_px_from_fov(50.0, SIZE)
    return np.stack(mats), [Intrinsics(f, f, SIZE / 2, SIZE / 2, SIZE, SIZE)] * len(mats)


def _masks(mesh: Mesh, cams: np.ndarray, intr: list[Intrinsics]) -> list[np.ndarray]:
    rc = MeshRaycaster(mesh)
    return [rc.buffers(m, i.fl_x, i.fl_y, i.cx, i.cy, i.w, i.h, supersample=3).coverage for m, i in zip(cams, intr)]


@pytest.fixture(scope="module")
def sphere_scene() -> GeometryInputs:
    cams, intr = _cameras()
    sphere = sphere_mesh(CENTRE, RADIUS, subdivisions=5)
    return GeometryInputs(cams, intr, _masks(sphere, cams, intr))


def _radial_normal_error_deg(mesh: Mesh, centre: np.ndarray) -> np.ndarray:
    d = mesh.vertices.astype(np.float64) - centre
    cos = np.einsum("ij,ij->i", d / np.linalg.norm(d, axis=1, keepdims=True), mesh.vertex_normals.astype(np.float64))
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def test_project_points_closed_form():
    cams, intr = _cameras()
    uv, front = project_points(np.zeros((1, 3)), cams[0], intr[0])
    assert front[0] and np.allclose(uv[0], [SIZE / 2, SIZE / 2])  # the origin is on the optical axis
    behind = 2 * cams[0][:3, 3]
    assert not project_points(behind[None], cams[0], intr[0])[1][0]


def test_visual_hull_of_a_sphere(sphere_scene):
    mesh, stats = visual_hull(sphere_scene, voxels=48, smooth_iterations=10)
    r = np.linalg.norm(mesh.vertices - CENTRE, axis=1)
    # a visual hull contains the object: never (much) inside it, and close to it from 14 views
    assert np.percentile(r, 2) > RADIUS - 0.04 and np.median(r) < RADIUS * 1.08
    assert np.median(_radial_normal_error_deg(mesh, CENTRE)) < 8.0
    assert not stats["touches_box"]


def test_sphere_fit_from_silhouettes_and_auto_picks_it(sphere_scene):
    res = build_geometry(sphere_scene, GeometryOptions(mode="auto"))
    assert res.mode == "sphere" and "sphere" in res.reason and res.sphere is not None
    centre, radius = res.sphere
    assert np.linalg.norm(centre - CENTRE) < 0.01 and radius == pytest.approx(RADIUS, rel=0.01)
    assert np.median(_radial_normal_error_deg(res.mesh, centre)) < 0.5


def test_auto_picks_the_visual_hull_for_a_non_sphere():
    from damcap.common.shapes import bumpy_blob

    cams, intr = _cameras()
    blob = bumpy_blob(subdivisions=4)
    inputs = GeometryInputs(cams, intr, _masks(blob, cams, intr))
    res = build_geometry(inputs, GeometryOptions(mode="auto", voxels=48))
    assert res.mode == "visual-hull" and "not a sphere" in res.reason


def test_fit_sphere_points_with_noise_and_outliers():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    pts = CENTRE + RADIUS * d / np.linalg.norm(d, axis=1, keepdims=True) + rng.normal(0, 0.002, (500, 3))
    pts[:20] = rng.uniform(-3, 3, (20, 3))  # outliers
    c, r, rms = fit_sphere_points(pts)
    assert np.linalg.norm(c - CENTRE) < 0.003 and r == pytest.approx(RADIUS, abs=0.003) and rms < 0.005


def test_poisson_from_points_on_a_sphere():
    cams, intr = _cameras()
    rng = np.random.default_rng(1)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = CENTRE + RADIUS * d
    seen = np.argmax(d @ (cams[:, :3, 3] / 3).T, axis=1)  # the camera most facing each point
    mesh, stats = poisson_mesh(GeometryInputs(cams, intr, None, pts, seen), depth=6)
    r = np.linalg.norm(mesh.vertices - CENTRE, axis=1)
    assert np.median(np.abs(r - RADIUS)) < 0.02
    assert np.median(_radial_normal_error_deg(mesh, CENTRE)) < 5.0  # oriented outward
    assert stats["points_used"] > 3500


def test_poisson_needs_points():
    cams, intr = _cameras()
    with pytest.raises(DamcapError, match="at least 100 sparse points"):
        build_geometry(GeometryInputs(cams, intr, None, np.zeros((10, 3)), np.zeros(10, np.int64)), GeometryOptions(mode="poisson"))


def test_align_mesh_recovers_a_similarity():
    from damcap.reconstruct.normalize import similarity, transform_points
    from damcap.common.shapes import bumpy_blob

    blob = bumpy_blob(subdivisions=4)
    a = np.radians(35)
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]) @ np.array(
        [[1, 0, 0], [0, np.cos(a / 2), -np.sin(a / 2)], [0, np.sin(a / 2), np.cos(a / 2)]])
    truth = similarity(1.7, rot, np.array([0.3, -0.2, 0.5]))
    target = transform_points(truth, blob.vertices)
    t, rms = align_mesh(blob, target)
    moved = transform_points(t, blob.vertices)
    assert np.sqrt(np.mean(np.sum((moved - target) ** 2, axis=1))) < 0.02 and rms < 0.02


def test_user_mesh_the_cameras_do_not_see(tmp_path, sphere_scene):
    import open3d as o3d

    far = sphere_mesh(np.array([40.0, 0.0, 0.0]), 0.5, subdivisions=2)
    path = tmp_path / "far.ply"
    o3d.io.write_triangle_mesh(str(path), o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(far.vertices.astype(np.float64)), o3d.utility.Vector3iVector(far.triangles)))
    with pytest.raises(DamcapError, match="no camera sees this mesh"):
        build_geometry(GeometryInputs(sphere_scene.world_from_cams, sphere_scene.intrinsics, None),
                       GeometryOptions(mode=f"mesh:{path}", mesh_align="none"))


def test_user_mesh_as_given(tmp_path, sphere_scene):
    import open3d as o3d

    sphere = sphere_mesh(CENTRE, RADIUS, subdivisions=4)
    path = tmp_path / "sphere.ply"
    o3d.io.write_triangle_mesh(str(path), o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(sphere.vertices.astype(np.float64)), o3d.utility.Vector3iVector(sphere.triangles)))
    res = build_geometry(sphere_scene, GeometryOptions(mode=f"mesh:{path}"))
    assert res.mode == "mesh" and "as given" in res.reason and res.stats["silhouette_iou"] > 0.95


def test_parse_mode():
    assert parse_mode("mesh:/a/b.obj")[0] == "mesh" and str(parse_mode("mesh:/a/b.obj")[1]) == "/a/b.obj"
    assert parse_mode("dense") == ("dense", None)
    with pytest.raises(DamcapError, match="use auto, visual-hull, poisson, sphere, dense or mesh:FILE"):
        parse_mode("stereo")
    with pytest.raises(DamcapError, match="needs a file name"):
        parse_mode("mesh:")


@pytest.mark.parametrize("tolerance", [0, 1, 2])
def test_carve_is_the_order_statistic_of_the_mask_values(sphere_scene, tolerance):
    """Carving skips points already carved to 0 by tolerance + 1 views; the result is still the
    (tolerance + 1)-th smallest mask value over all views, computed here view by view."""
    pts = np.random.default_rng(3).uniform(-1.2, 1.2, (4000, 3))
    every = np.stack([mask_values_at(pts.astype(np.float32), m, c, i) for m, c, i in
                      zip(sphere_scene.masks, sphere_scene.world_from_cams, sphere_scene.intrinsics)])
    expected = np.sort(every, axis=0)[tolerance]
    got = carve(sphere_scene.masks, sphere_scene.world_from_cams, sphere_scene.intrinsics, pts, tolerance)
    assert np.array_equal(got, expected)
    assert 0 < (got > 0).mean() < 1  # both carved and kept points are tested


def test_dense_mode_is_built_above_this_module(sphere_scene):
    with pytest.raises(DamcapError, match="dense_geometry, not build_geometry"):
        build_geometry(sphere_scene, GeometryOptions(mode="dense"))
