"""The segmentation model: its weights carried onto frames (weights_on) and onto meshes (mesh_material_weights, through segment-labels)."""

from __future__ import annotations

import numpy as np

from damcap.appearance.segment.score import match_materials

from tests.conftest import assert_one_line_error, run_cli


def _torus_obj(path, scale=1.0, shift=(0.0, 0.0, 0.0)):
    """The closed-form torus (axis y, radii 0.9 and 0.4) as an OBJ, optionally scaled and moved."""
    import open3d as o3d

    from damcap.common.mesh import to_open3d
    from damcap.common.shapes import torus_mesh

    m = to_open3d(torus_mesh(0.9, 0.4))
    v = np.asarray(m.vertices).copy()
    m.vertices = o3d.utility.Vector3dVector(v * scale + np.asarray(shift))
    o3d.io.write_triangle_mesh(str(path), m)
    return v


def test_segmentation_carries_onto_meshes(two_materials, segmented, tmp_path, capsys):
    from scipy.spatial import cKDTree

    from damcap.appearance.segment.file import save_segmentation_folder
    from damcap.synth.closed_form import two_material_weights
    from damcap.common.mesh import load_mesh

    seg = tmp_path / "seg"
    _, train, _ = two_materials
    save_segmentation_folder(seg, segmented, train, [v.name for v in train], colorspace="lin_rec709", provenance={}, summary={})
    same = tmp_path / "torus.obj"
    _torus_obj(same)
    verts = load_mesh(same).vertices  # the vertices as damcap reads them (labels follow this order)
    code, out, err = run_cli(["segment-labels", seg, "--mesh", same, "-o", tmp_path / "l.npy", "--align", "none"], capsys)
    assert code == 0, err
    labels = np.load(tmp_path / "l.npy")
    assert labels.shape == (len(verts),) and "damcap export" in out
    # on the surface the training views saw, the labels are the true materials (labels matched)
    seen = cKDTree(segmented.points_world).query(verts)[0] < 0.02 * segmented.scene_radius
    assert seen.mean() > 0.3
    iou = match_materials(np.eye(2)[labels[seen]], two_material_weights(verts[seen]))[1]
    assert iou > 0.85, iou
    # a new shape elsewhere and 100x larger: 'sphere' alignment puts the materials back in place
    moved = tmp_path / "moved.ply"
    _torus_obj(moved, scale=100.0, shift=(5.0, -3.0, 40.0))
    code, _, err = run_cli(["segment-labels", seg, "--mesh", moved, "-o", tmp_path / "m.txt", "--weights", tmp_path / "w.npy"], capsys)
    assert code == 0, err
    moved_labels = np.loadtxt(tmp_path / "m.txt", dtype=np.int64)
    assert len(moved_labels) == len(verts) and np.load(tmp_path / "w.npy").shape == (len(verts), 2)
    assert (moved_labels[seen] == labels[seen]).mean() > 0.9
    code, _, err = run_cli(["segment-labels", seg, "--mesh", same, "-o", tmp_path / "l.csv"], capsys)
    assert_one_line_error(code, err, "l.csv", ".npy")
    code, _, err = run_cli(["segment-labels", seg, "--mesh", same, "-o", tmp_path / "l2.npy", "--align", "box"], capsys)
    assert_one_line_error(code, err, "'box'")
    # the folder is one unit: a damaged segment.json or missing weight maps are refused, naming them
    summary = (seg / "segment.json").read_text()
    (seg / "segment.json").write_text(summary.replace('"materials": 2', '"materials": 3'))
    code, _, err = run_cli(["segment-labels", seg, "--mesh", same, "-o", tmp_path / "l3.npy"], capsys)
    assert_one_line_error(code, err, "segment.json", "materials = 3")
    (seg / "segment.json").write_text(summary)
    first = sorted((seg / "weights").glob("*.exr"))[0]
    first.write_bytes(b"not an exr")
    code, _, err = run_cli(["segment-labels", seg, "--mesh", same, "-o", tmp_path / "l3.npy"], capsys)
    assert_one_line_error(code, err, first.name)
    assert not (tmp_path / "l3.npy").exists()


def test_weights_on_a_frame_are_the_carried_weights_on_its_object(two_materials, segmented):
    _, _, test = two_materials
    v = test[0]
    cov = v.data.coverage > 0
    assert 0 < cov.mean() < 1
    w = segmented.weights_on(v)
    assert w.shape == cov.shape + (2,) and w.dtype == np.float32
    np.testing.assert_allclose(w[cov], segmented.weights_at(v.data.position_world[cov]), atol=1e-7)
    np.testing.assert_allclose(w[cov].sum(-1), 1.0, atol=1e-5)
    assert not w[~cov].any()
