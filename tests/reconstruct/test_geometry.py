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
    mask_touches_border,
    mask_values_and_judged,
    mask_values_at,
    parse_mode,
    points_box,
    poisson_mesh,
    project_points,
    views_judging,
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


# --------------------------------------------------------------------------------------------
# An object the photos cut: a long box (a tool) that leaves the frame
# --------------------------------------------------------------------------------------------

TOOL_HALF = np.array([1.1, 0.12, 0.25])


def box_mesh(half: np.ndarray) -> Mesh:
    """A closed box centred on the origin, outward-facing."""
    from damcap.common.mesh import vertex_normals_area_weighted

    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64) * half
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    t = np.array([tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))], np.int32)
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    inward = (n * v[t].mean(1)).sum(1) < 0
    t[inward] = t[inward][:, ::-1]
    return Mesh(v.astype(np.float32), t, vertex_normals_area_weighted(v, t).astype(np.float32), np.zeros(len(t), np.int32))


def tool_scene(fov_deg: float) -> GeometryInputs:
    """Exact masks of a 2.2 x 0.24 x 0.5 box from 40 cameras on two rings above it (elevations 25
    and 50 deg, distance 3), 96 x 72 px with a ``fov_deg`` horizontal field of view: at 30 deg every
    photo cuts the box, at 36 deg 3 photos (looking along it) hold it whole."""
    from damcap.synth.photos import orbit_cameras

    cams = orbit_cameras(40, 3.0, (25.0, 50.0), jitter_deg=3, seed=2)
    w, h = 96, 72
    f = focal_px_from_fov(fov_deg, w)
    intr = [Intrinsics(f, f, w / 2, h / 2, w, h)] * len(cams)
    return GeometryInputs(cams, intr, _masks(box_mesh(TOOL_HALF), cams, intr))


@pytest.fixture(scope="module")
def cut_tool() -> GeometryInputs:
    return tool_scene(30.0)


def test_the_tool_is_cut_by_every_photo(cut_tool):
    assert all(mask_touches_border(m) for m in cut_tool.masks)


def test_a_hull_cut_by_every_photo_stays_near_the_object_and_says_it_touches(cut_tool):
    """Carving only where the photos judge: before, the hull filled its search cube ([-2.86, 2.86]
    on every axis here); now it ends near the box's ends (x = +-1.1) where too few photos hold the
    voxels, and says that it ends at its bounds there."""
    mesh, stats = visual_hull(cut_tool, voxels=64, smooth_iterations=5)
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    assert np.all(lo < -TOOL_HALF + 0.05) and np.all(hi > TOOL_HALF - 0.05)  # contains the object
    assert hi[0] < 1.4 and lo[0] > -1.4  # not the cube
    assert np.all(np.abs(lo[1:]) < 0.35) and np.all(np.abs(hi[1:]) < 0.35)
    assert stats["touches_box"]


def test_photos_that_hold_the_whole_object_close_the_hull():
    mesh, stats = visual_hull(tool_scene(36.0), voxels=64, smooth_iterations=5)
    assert np.all(np.abs(mesh.vertices[:, 0]) < TOOL_HALF[0] + 0.06)
    assert not stats["touches_box"]


def test_sparse_points_bound_the_hull(cut_tool):
    """Points on the box's middle part bound the grid: their robust box plus its margin."""
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (400, 3)) * np.array([0.5, 0.12, 0.25])
    cams, intr, masks = cut_tool.world_from_cams, cut_tool.intrinsics, cut_tool.masks
    mesh, stats = visual_hull(GeometryInputs(cams, intr, masks, pts, np.zeros(len(pts), np.int64)), voxels=64,
                              smooth_iterations=0)
    lo_p, hi_p = points_box(pts)
    assert np.all(mesh.vertices.min(0) > lo_p - 0.05) and np.all(mesh.vertices.max(0) < hi_p + 0.05)
    assert stats["points_box"] is not None and stats["touches_box"]


def test_a_mask_that_stops_short_of_the_border_still_reaches_it():
    """A photo whose object mask stops 1 px short of the edge does not carve outside itself."""
    m = np.zeros((72, 96), np.float32)
    m[30:40, 1:50] = 1.0
    assert mask_touches_border(m)
    m[30:40, :5] = 0.0
    assert not mask_touches_border(m)


def test_outside_a_photo_is_unknown_when_the_object_leaves_it(sphere_scene):
    """Outside a photo: background for a photo that holds the whole object, unknown (1) for one
    the object leaves; behind the camera: unknown."""
    cam, intr = sphere_scene.world_from_cams[0], sphere_scene.intrinsics[0]
    far_off = 5.0 * cam[:3, 0]  # beside the origin, to the camera's right: in front, outside its photo
    behind = 2.0 * cam[:3, 3]
    pts = np.stack([far_off, behind]).astype(np.float32)
    whole = sphere_scene.masks[0]
    assert not mask_touches_border(whole)
    vals, judged = mask_values_and_judged(pts, whole, cam, intr)
    assert vals.tolist() == [0.0, 1.0] and judged.tolist() == [True, False]
    cut = whole.copy()
    cut[:, -1] = 1.0
    vals, judged = mask_values_and_judged(pts, cut, cam, intr)
    assert vals.tolist() == [1.0, 1.0] and judged.tolist() == [False, False]
    assert views_judging(pts, [whole, cut], np.stack([cam, cam]), [intr, intr]).tolist() == [1, 0]
