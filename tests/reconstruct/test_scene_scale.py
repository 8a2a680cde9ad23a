"""``damcap reconstruct`` with known poses in any unit: the capture does not depend on the scene's scale.

Users' poses come in millimetres, metres or kilometres. The same photos (a textured blob made by
:mod:`damcap.synth.photos`) are reconstructed with the ground-truth poses'
translations, and the user mesh, multiplied by k from 1e-20 to 1e20 (1e-3 / 1e3 are millimetres /
kilometres against metres lie within 1e-4..1e4; the decades beyond show that no absolute
epsilon is left).

The contract (:mod:`damcap.reconstruct.normalize`, pipeline step 3 and 5): reconstruct maps the input
world by one similarity ``norm_from_input_world`` (the cameras' focus to the origin, their distance
to a radius of about 1, then the geometry's bounding sphere to the unit sphere), recorded in
``damcap_source``. So the capture of a run at scale k is the unit run's capture (cameras, normals,
positions, coverage, view directions, radiance), ``norm_from_input_world`` carries 1/k, and the
positions mapped back to the input world are k times the unit run's.

Before the fixes these tests go with, a mesh of size 1e-11 or below got non-unit vertex normals
(an absolute 1e-12 floor on area-weighted sums, in square scene units, and on ``inverse(s R)``
normals), and cameras 1e-12 units from their focus or closer were normalised with an absolute
1e-12 floor on the radius, so the visual hull and the sphere were built in a frame of the wrong
scale (the sphere's coverage fell to a quarter at k = 1e-20). Degenerate poses (every camera at one
position: translations scaled by 0, one matrix repeated, a panorama) wrote a meaningless capture
with exit code 0.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from damcap.common.capture_folder import read_capture, read_frame
from damcap.common.errors import DamcapError
from damcap.reconstruct.normalize import normalization_transform, similarity_scale, transform_points
from damcap.reconstruct.geometry import GeometryOptions
from damcap.reconstruct.pipeline import ReconstructOptions, reconstruct_capture
from damcap.reconstruct.poses import llff_of_world_from_cam
from damcap.common.mesh import vertex_normals_area_weighted
from damcap.common.shapes import bumpy_blob
from damcap.synth.photos import default_intrinsics, orbit_cameras, write_photo_set

from tests.conftest import assert_one_line_error, run_cli

N_PHOTOS = 8
PHOTO_SIZE = 96
SCALES = (1e-20, 1e-12, 1e-8, 1e-4, 1e4, 1e8, 1e12, 1e20)
FAST = dict(capture_size=48, train_views=4, supersample=2, dtype="float")
#: Tolerances in the normalised frame (object radius 1). The only scale-dependent rounding left is
#: float32: the user mesh is stored as float32 in the input's units and again after each similarity
#: (3 roundings of 6e-8 relative), and Open3D intersects rays in float32, ill-conditioned near
#: grazing hits. Measured: normals and positions within 1.1e-5, cameras within 1e-7, coverage and
#: radiance bit-identical. 1e-4 is 0.006 degrees of normal, far below what a DAM resolves.
GEOMETRY_ATOL = 1e-4
CAMERA_ATOL = 1e-6
#: a pixel whose centre ray passes within ~1e-7 of a silhouette edge may flip between runs
COVERAGE_MISMATCH_MAX = 1e-3


@pytest.fixture(scope="module")
def photo_set(tmp_path_factory) -> dict:
    """Photos and masks of the blob from 8 cameras at distance 3.2 (unit scale), its mesh, its poses."""
    root = tmp_path_factory.mktemp("scale")
    mesh = bumpy_blob(subdivisions=4)
    cams = orbit_cameras(N_PHOTOS, 3.2, (25.0,), jitter_deg=4, seed=0)
    write_photo_set(root, mesh, cams, default_intrinsics(PHOTO_SIZE), seed=0)
    return {"root": root, "mesh": mesh, "poses": json.loads((root / "transforms.json").read_text()), "runs": {}}


def _scaled_poses(doc: dict, k: float, path: Path) -> Path:
    """The transforms.json with every camera centre multiplied by k (rotations kept)."""
    out = json.loads(json.dumps(doc))
    for f in out["frames"]:
        m = np.asarray(f["transform_matrix"], dtype=np.float64)
        m[:3, 3] *= k
        f["transform_matrix"] = m.tolist()
    path.write_text(json.dumps(out))
    return path


def _write_mesh(vertices: np.ndarray, triangles: np.ndarray, path: Path) -> Path:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices.astype(np.float64)), o3d.utility.Vector3iVector(triangles))
    assert o3d.io.write_triangle_mesh(str(path), m)
    return path


def _run(photo_set: dict, mode: str, k: float) -> tuple[Path, object]:
    """reconstruct at scale k (memoised per module): poses and, for mode 'mesh', the mesh times k."""
    key = (mode, k)
    if key not in photo_set["runs"]:
        root = photo_set["root"]
        tag = f"{mode}_{k:g}"
        poses = _scaled_poses(photo_set["poses"], k, root / f"poses_{tag}.json")
        geometry = mode
        if mode == "mesh":
            mesh = photo_set["mesh"]
            (root / tag).mkdir()  # one file name for all scales: the report quotes it
            geometry = f"mesh:{_write_mesh(mesh.vertices.astype(np.float64) * k, mesh.triangles, root / tag / 'blob.ply')}"
        out = root / f"capture_{tag}"
        # mesh_align auto: with masks it judges the mesh against a visual hull (silhouette IoU)
        _, report = reconstruct_capture(root / "images", out, ReconstructOptions(geometry=GeometryOptions(mode=geometry, voxels=48), **FAST),  # type: ignore[arg-type]
                                        masks_dir=root / "masks", poses=str(poses))
        photo_set["runs"][key] = (out, report)
    return photo_set["runs"][key]


def _norm_from_input_world(capture_root: Path) -> np.ndarray:
    doc = json.loads((capture_root / "transforms.json").read_text())
    return np.asarray(doc["damcap_source"]["norm_from_input_world"], dtype=np.float64)


@pytest.mark.parametrize("k", SCALES)
@pytest.mark.parametrize("mode", ["mesh", "visual-hull", "sphere"])
def test_the_capture_does_not_depend_on_the_scene_scale(photo_set, mode, k):
    ref_root, ref_report = _run(photo_set, mode, 1.0)
    root, report = _run(photo_set, mode, k)
    # the same decisions: geometry (its reason quotes fit residuals and "as given"), frames, split
    assert report.geometry_reason == ref_report.geometry_reason
    if mode == "mesh":
        assert "as given" in report.geometry_reason
    assert (report.train, report.test, report.dropped) == (ref_report.train, ref_report.test, {})
    ref, cap = read_capture(ref_root), read_capture(root)
    assert [f.file_path for f in cap.frames] == [f.file_path for f in ref.frames] and len(cap.frames) == N_PHOTOS

    # norm_from_input_world carries the unit: norm_k = norm_1 diag(1/k, 1/k, 1/k, 1)
    norm_1, norm_k = _norm_from_input_world(ref_root), _norm_from_input_world(root)
    assert similarity_scale(norm_k) * k == pytest.approx(similarity_scale(norm_1), rel=CAMERA_ATOL)
    np.testing.assert_allclose(norm_k @ np.diag([k, k, k, 1.0]), norm_1, rtol=0, atol=CAMERA_ATOL)

    mismatched = covered = 0
    for f_ref, f in zip(ref.frames, cap.frames):
        np.testing.assert_allclose(f.world_from_cam, f_ref.world_from_cam, rtol=0, atol=CAMERA_ATOL)
        a, b = read_frame(ref, f_ref), read_frame(cap, f)
        mismatched += int(np.count_nonzero(np.abs(b.coverage - a.coverage) > 1e-6))
        both = (a.coverage > 0) & (b.coverage > 0)
        covered += int(both.sum())
        np.testing.assert_allclose(b.normal_world[both], a.normal_world[both], rtol=0, atol=GEOMETRY_ATOL)
        # positions: the same in the capture, k times the unit run's in the input world
        np.testing.assert_allclose(b.position_world[both], a.position_world[both], rtol=0, atol=GEOMETRY_ATOL)
        p_in_1 = transform_points(np.linalg.inv(norm_1), a.position_world[both])
        p_in_k = transform_points(np.linalg.inv(norm_k), b.position_world[both])
        np.testing.assert_allclose(p_in_k / k, p_in_1, rtol=0, atol=GEOMETRY_ATOL / similarity_scale(norm_1))
        # view directions V = normalize(camera centre - P), derived as docs/capture-format.md defines them
        v_1 = f_ref.world_from_cam[:3, 3] - a.position_world[both]
        v_k = f.world_from_cam[:3, 3] - b.position_world[both]
        v_1 /= np.linalg.norm(v_1, axis=1, keepdims=True)
        v_k /= np.linalg.norm(v_k, axis=1, keepdims=True)
        np.testing.assert_allclose(v_k, v_1, rtol=0, atol=GEOMETRY_ATOL)
        # coverage: the same on all but silhouette pixels within rounding of an edge; radiance
        # comes from the same photos through the same pinhole resampling
        same = np.abs(b.coverage - a.coverage) <= 1e-6
        np.testing.assert_array_equal(b.radiance_lin[same], a.radiance_lin[same])
    assert covered > 0.3 * N_PHOTOS * 48 * 48  # the blob fills about 40% of each frame
    assert mismatched <= COVERAGE_MISMATCH_MAX * N_PHOTOS * 48 * 48


# ---- the pure functions the invariance rests on ------------------------------------------------

@pytest.mark.parametrize("k", (1e-30, 1e-12, 1e-3, 1.0, 1e3, 1e12, 1e30))
def test_normalization_transform_carries_the_unit(k):
    """norm(k x) = norm(x) / k, for cameras alone (radius from their distance) and with points
    (radius from the points), for cameras on a ring and for a forward-facing capture with points."""
    cams = orbit_cameras(8, 3.2, (25.0,), jitter_deg=4, seed=0)
    pts = np.random.default_rng(0).normal(size=(200, 3)) * 0.5
    forward = cams.copy()
    forward[:, :3, :3] = cams[0, :3, :3]  # parallel optical axes: the focus comes from the points
    for m, p in ((cams, None), (cams, pts), (forward, pts)):
        mk = m.copy()
        mk[:, :3, 3] *= k
        expected = normalization_transform(m, p) @ np.diag([1 / k, 1 / k, 1 / k, 1.0])
        got = normalization_transform(mk, None if p is None else p * k)
        np.testing.assert_allclose(got[:3, :3] * k, expected[:3, :3] * k, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got[:3, 3], expected[:3, 3], rtol=0, atol=1e-9)


def test_normalization_of_cameras_at_their_focus_is_an_error():
    """Cameras at the point they look at have no radius; no floor turns 0 into a scale of 1e12."""
    cams = orbit_cameras(4, 3.2, (25.0,))
    cams[:, :3, 3] = 0.0
    with pytest.raises(DamcapError, match=r"the object's radius is 0\.0"):
        normalization_transform(cams)


@pytest.mark.parametrize("k", (1e-30, 1e-15, 1e-6, 1.0, 1e6, 1e15, 1e30))
def test_vertex_normals_are_unit_at_any_mesh_scale(k):
    """An octahedron: by symmetry the area-weighted normal at vertex +-e_i is +-e_i, at any size
    (the sums are 1e-60 square units at k = 1e-30); an unreferenced vertex gets a zero normal."""
    v = np.concatenate([np.eye(3), -np.eye(3), [[0.0, 0.0, 0.0]]]) * k
    x, y, z, mx, my, mz = range(6)
    t = np.array([[x, y, z], [y, mx, z], [mx, my, z], [my, x, z], [y, x, mz], [mx, y, mz], [my, mx, mz], [x, my, mz]])
    n = vertex_normals_area_weighted(v, t)
    np.testing.assert_allclose(n[:6], np.concatenate([np.eye(3), -np.eye(3)]), rtol=0, atol=1e-12)
    assert (n[6] == 0).all()


# ---- degenerate poses and meshes: one-line errors, exit code 2 ---------------------------------

def _degenerate(doc: dict, kind: str) -> dict:
    out = json.loads(json.dumps(doc))
    first = np.asarray(doc["frames"][0]["transform_matrix"])
    for f in out["frames"]:
        m = np.asarray(f["transform_matrix"])
        if kind == "scale 0":
            m[:3, 3] = 0.0
        elif kind == "one matrix repeated":
            m = first
        else:  # a panorama: turned about one centre
            m[:3, 3] = first[:3, 3]
        f["transform_matrix"] = m.tolist()
    return out


@pytest.mark.parametrize("kind", ["scale 0", "one matrix repeated", "panorama"])
def test_cameras_at_one_position_are_a_clear_error(photo_set, tmp_path, capsys, kind):
    """Before, these wrote a capture (exit 0) or failed later with a misleading message."""
    root = photo_set["root"]
    poses = tmp_path / "transforms.json"
    poses.write_text(json.dumps(_degenerate(photo_set["poses"], kind)))
    code, _, err = run_cli(["reconstruct", root / "images", "-o", tmp_path / "out", "--masks", root / "masks",
                            "--poses", poses, "--capture-size", "48", "--voxels", "48"], capsys)
    assert_one_line_error(code, err, str(poses), f"all {N_PHOTOS} cameras are at the same position", "(spread 0)")
    if kind == "scale 0":
        assert "[0.0, 0.0, 0.0]" in err
    assert not (tmp_path / "out" / "transforms.json").exists()


def test_llff_cameras_at_one_position_are_a_clear_error(photo_set, tmp_path, capsys):
    """The same check for poses_bounds.npy (rows follow the sorted photo names)."""
    rows = []
    for f in photo_set["poses"]["frames"]:
        m = np.asarray(f["transform_matrix"])
        m[:3, 3] = 0.0
        hwf = [[PHOTO_SIZE], [PHOTO_SIZE], [photo_set["poses"]["fl_x"]]]
        rows.append(np.concatenate([np.concatenate([llff_of_world_from_cam(m), hwf], axis=1).ravel(), [0.1, 10.0]]))
    poses = tmp_path / "poses_bounds.npy"
    np.save(poses, np.array(rows))
    code, _, err = run_cli(["reconstruct", photo_set["root"] / "images", "-o", tmp_path / "out", "--poses", poses,
                            "--geometry", "sphere", "--masks", photo_set["root"] / "masks"], capsys)
    assert_one_line_error(code, err, str(poses), f"all {N_PHOTOS} cameras are at the same position [0.0, 0.0, 0.0]")


@pytest.mark.parametrize("k", [float("inf"), float("nan")])
def test_non_finite_pose_scale_is_a_clear_error(photo_set, tmp_path, capsys, k):
    poses = _scaled_poses(photo_set["poses"], k, tmp_path / "transforms.json")
    code, _, err = run_cli(["reconstruct", photo_set["root"] / "images", "-o", tmp_path / "out", "--poses", poses], capsys)
    assert_one_line_error(code, err, str(poses), "frames[0]", "contains NaN or inf")


def test_a_mesh_scaled_by_zero_is_a_clear_error(photo_set, tmp_path, capsys):
    mesh = _write_mesh(photo_set["mesh"].vertices * 0.0, photo_set["mesh"].triangles, tmp_path / "flat.ply")
    code, _, err = run_cli(["reconstruct", photo_set["root"] / "images", "-o", tmp_path / "out", "--poses",
                            photo_set["root"] / "transforms.json", "--geometry", f"mesh:{mesh}", "--mesh-align", "none"], capsys)
    assert_one_line_error(code, err, str(mesh), "degenerate")
