"""Frames of a DAM on a new shape (the export command), one DAM per vertex label, bad inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
from damcap.appearance.dam_file import DAM_FORMAT_VERSION, save_dam
from damcap.cli.main import main
from damcap.common.colour import display_srgb8
from damcap.common.exr import read_exr, read_image_u8
from damcap.export.turntable import parts_from_vertex_labels

from tests.conftest import tree_digest


def test_export_frames_png_video(model_file, bunny, tmp_path, capsys):
    before = tree_digest(bunny.parent)
    out = tmp_path / "out"
    assert main(["export", str(model_file), "--mesh", str(bunny), "-o", str(out), "--views", "4", "--resolution", "64", "--video"]) == 0
    meta = json.loads((out / "export.json").read_text())
    assert len(meta["world_from_cam"]) == 4
    px, names = read_exr(out / "frames" / "0002.exr")
    assert names == ("R", "G", "B", "A") and px.shape == (64, 64, 4)
    fg = px[..., 3] > 0.5
    assert 0.1 < fg.mean() < 0.8 and (px[fg, :3] > 0).all() and (px[~(px[..., 3] > 0), :3] == 0).all()
    png = read_image_u8(out / "display" / "0002.png")
    np.testing.assert_array_equal(png, display_srgb8(px[..., :3], meta["exposure_scale"]))
    assert (out / "turntable.mp4").stat().st_size > 1000
    import av

    with av.open(str(out / "turntable.mp4")) as video:  # H.264, which browsers play (not OpenCV's mp4v)
        stream = video.streams.video[0]
        assert stream.codec_context.name == "h264" and stream.codec_context.pix_fmt == "yuv420p"
        frames = [f.to_ndarray(format="rgb24") for f in video.decode(stream)]
    # 4 views at 8 fps is half a second: the orbit plays 6 times (3 s), its index before its frames (faststart)
    assert len(frames) == 24 and np.abs(frames[2].astype(int) - png.astype(int)).mean() < 6  # lossy, close to the PNG
    assert np.abs(frames[22].astype(int) - png.astype(int)).mean() < 6
    assert meta["video"] == {"file": "turntable.mp4", "fps": 8, "turns": 6, "duration_s": 3.0, "faststart": True}
    from damcap.export.video import mp4_top_level_boxes

    boxes = mp4_top_level_boxes((out / "turntable.mp4").read_bytes())
    assert boxes.index("moov") < boxes.index("mdat")
    assert "turntable.mp4: 3 s at 8 fps, the orbit played 6 times" in capsys.readouterr().out
    assert tree_digest(bunny.parent) == before
    # export.json says how to reproduce a frame: the file's vertices, moved by render_from_mesh into
    # the unit sphere, project through the intrinsics and world_from_cam onto covered pixels
    from damcap.common.mesh import read_mesh

    v = read_mesh(bunny).vertices
    m = np.array(meta["mesh_transform"]["render_from_mesh"])
    p = v @ m[:3, :3].T + m[:3, 3]
    assert abs(np.linalg.norm(p, axis=1).max() - 1.0) < 1e-5
    k = meta["intrinsics"]
    assert k["w"] == k["h"] == 64 and abs(k["fl_x"] - 32 / np.tan(np.radians(45.0) / 2)) < 1e-9
    cam = np.linalg.inv(np.array(meta["world_from_cam"][2]))
    q = p @ cam[:3, :3].T + cam[:3, 3]  # camera space: +z backwards (look_at_world_from_cam)
    j = k["cx"] + k["fl_x"] * q[:, 0] / -q[:, 2]
    i = k["cy"] - k["fl_y"] * q[:, 1] / -q[:, 2]
    inside = (i >= 0) & (i < 64) & (j >= 0) & (j < 64)
    assert inside.all() and px[i.astype(int), j.astype(int), 3].mean() > 0.8  # vertices land on the object


def test_vertex_labels_to_parts():
    tris = np.array([[0, 1, 2], [1, 2, 3], [0, 3, 2]])
    labels = np.array([0, 1, 1, 0])
    assert parts_from_vertex_labels(tris, labels).tolist() == [1, 1, 0]
    assert parts_from_vertex_labels(tris, np.array([2, 0, 1, 1])).tolist() == [2, 1, 1]


def test_bad_meshes_and_models(model_file, tmp_path, capsys):
    (tmp_path / "empty.obj").write_text("# nothing\n")
    assert main(["export", str(model_file), "--mesh", str(tmp_path / "empty.obj"), "-o", str(tmp_path / "o")]) == 2
    assert "no triangles" in capsys.readouterr().err
    (tmp_path / "degen.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    assert main(["export", str(model_file), "--mesh", str(tmp_path / "degen.obj"), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "degen.obj" in err and ("zero area" in err or "degenerate" in err)
    # no normals in the file: recomputed
    (tmp_path / "tet.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    assert main(["export", str(model_file), "--mesh", str(tmp_path / "tet.obj"), "-o", str(tmp_path / "o"), "--views", "1", "--resolution", "32"]) == 0
    # a model from a newer format version
    from safetensors.torch import save as st_save
    meta = {"format_version": DAM_FORMAT_VERSION + 1, "architecture": DamArchitecture().to_json(), "radiance_scale": 1.0}
    (tmp_path / "new.dam").write_bytes(st_save({"weights": torch.zeros(3360)}, metadata={"damcap": json.dumps(meta)}))
    assert main(["export", str(tmp_path / "new.dam"), "--mesh", str(tmp_path / "tet.obj"), "-o", str(tmp_path / "o2")]) == 2
    assert "newer than this damcap reads" in capsys.readouterr().err
    assert main(["export", str(model_file), str(model_file), "--mesh", str(tmp_path / "tet.obj"), "-o", str(tmp_path / "o3"),
                 "--labels", str(tmp_path / "missing.npy")]) == 2
    assert "label file not found" in capsys.readouterr().err


def test_several_dams_by_vertex_labels(model_file, bunny, tmp_path):
    from damcap.appearance.dam_file import load_dam
    from damcap.common.mesh import read_mesh

    dam, meta = load_dam(model_file)
    brighter = DeepAppearanceMap(dam.arch, dam.radiance_scale * 2, dam.get_flat_weights())
    save_dam(tmp_path / "b.dam", brighter, colorspace="lin_rec709", made_by="fit")
    verts = read_mesh(bunny).vertices  # labels follow the file's vertex order
    labels = (verts[:, 0] > np.median(verts[:, 0])).astype(np.int64)
    np.save(tmp_path / "labels.npy", labels)
    out = tmp_path / "two"
    args = ["export", str(model_file), str(tmp_path / "b.dam"), "--mesh", str(bunny), "--labels", str(tmp_path / "labels.npy"),
            "-o", str(out), "--views", "1", "--resolution", "64"]
    assert main(args) == 0
    assert main(["export", str(model_file), "--mesh", str(bunny), "-o", str(tmp_path / "one"), "--views", "1", "--resolution", "64"]) == 0
    two = read_exr(out / "frames" / "0000.exr")[0][..., :3]
    one = read_exr(tmp_path / "one" / "frames" / "0000.exr")[0][..., :3]
    fg = one.sum(-1) > 0
    ratio = two[fg].sum(-1) / one[fg].sum(-1)
    # every covered pixel is rendered by exactly one of the two DAMs: ratio 1 or 2
    assert np.all(np.isclose(ratio, 1.0, rtol=1e-4) | np.isclose(ratio, 2.0, rtol=1e-4))
    assert 0.2 < np.isclose(ratio, 2.0, rtol=1e-4).mean() < 0.8
    np.save(tmp_path / "bad.npy", labels + 5)
    args[args.index(str(tmp_path / "labels.npy"))] = str(tmp_path / "bad.npy")
    assert main(args) == 2


def test_obj_groups_need_one_model_each(tmp_path):
    from damcap.common.errors import DamcapError
    from damcap.export.turntable import shape_and_parts

    from tests.conftest import write_tetra_obj_with_materials

    obj = write_tetra_obj_with_materials(tmp_path)
    assert sorted(shape_and_parts(obj, None, 3)[2].tolist()) == [0, 1, 2, 2]
    with pytest.raises(DamcapError, match="t.obj: part 2 has no model; give 3 .dam files"):
        shape_and_parts(obj, None, 2)


def test_spatial_factor_is_drawn_on_its_own_surface_only(model_file, bunny, tmp_path, capsys):
    """A texture on the bunny's own surface (albedo 2 in red) doubles the red of every export
    pixel; the same texture moved away from it is left out, with a note; GLSL says it carries the
    DAM alone."""
    from damcap.appearance.dam_file import load_dam
    from damcap.appearance.spatial import SpatialAlbedo, trilinear_corners
    from damcap.common.mesh import load_mesh

    dam, _ = load_dam(model_file)
    verts = load_mesh(bunny).vertices.astype(np.float64)
    h = 0.05 * float(np.ptp(verts, axis=0).max())
    origin = verts.min(0) - 2 * h
    keys = np.unique(trilinear_corners(verts, origin, h)[0])
    la = np.tile(np.array([[np.log(2.0), 0.0, 0.0]], np.float32), (keys.size, 1))
    frames = {}
    for name, o in (("own", origin), ("elsewhere", origin + 100.0)):
        save_dam(tmp_path / f"{name}.dam", dam.with_spatial(SpatialAlbedo(o, h, keys, la)), colorspace="lin_rec709", made_by="fit")
    for name in ("plain", "own", "elsewhere"):
        model = model_file if name == "plain" else tmp_path / f"{name}.dam"
        capsys.readouterr()
        assert main(["export", str(model), "--mesh", str(bunny), "-o", str(tmp_path / name), "--views", "2", "--resolution", "48"]) == 0
        frames[name] = (read_exr(tmp_path / name / "frames" / "0001.exr")[0], capsys.readouterr().err,
                        json.loads((tmp_path / name / "export.json").read_text())["spatial"])
    plain, own, away = frames["plain"][0], frames["own"][0], frames["elsewhere"][0]
    fg = plain[..., 3] > 0
    np.testing.assert_allclose(own[fg, 0], 2 * plain[fg, 0], rtol=1e-4)
    np.testing.assert_allclose(own[..., 1:], plain[..., 1:], rtol=1e-5)
    assert frames["own"][2][0]["applied"] and frames["own"][2][0]["surface_share"] > 0.99 and frames["plain"][2] is None
    np.testing.assert_array_equal(away, plain)
    assert not frames["elsewhere"][2][0]["applied"] and "cover 0% of stanford-bunny.obj" in frames["elsewhere"][1]
    assert main(["export", str(tmp_path / "own.dam"), "--format", "glsl", "-o", str(tmp_path / "dam.glsl")]) == 0
    assert "carries the DAM alone" in capsys.readouterr().err


def test_normal_field_is_applied_on_its_own_surface_only(model_file, bunny, tmp_path, capsys):
    """A normal field on the bunny's own surface (one constant offset) changes the shading of
    the export; moved away from it, it is left out with a note and the frame is the DAM alone."""
    from damcap.appearance.dam_file import load_dam
    from damcap.appearance.normal_field import NormalField
    from damcap.appearance.spatial import trilinear_corners
    from damcap.common.mesh import load_mesh

    dam, _ = load_dam(model_file)
    verts = load_mesh(bunny).vertices.astype(np.float64)
    h = 0.05 * float(np.ptp(verts, axis=0).max())
    origin = verts.min(0) - 2 * h
    keys = np.unique(trilinear_corners(verts, origin, h)[0])
    offset = np.tile(np.array([[0.8, 0.0, 0.0]], np.float32), (keys.size, 1))
    frames = {}
    for name, o in (("own", origin), ("elsewhere", origin + 100.0)):
        save_dam(tmp_path / f"{name}.dam", dam.with_normal_field(NormalField(o, h, keys, offset)), colorspace="lin_rec709", made_by="fit")
    for name in ("plain", "own", "elsewhere"):
        model = model_file if name == "plain" else tmp_path / f"{name}.dam"
        capsys.readouterr()
        assert main(["export", str(model), "--mesh", str(bunny), "-o", str(tmp_path / name), "--views", "2", "--resolution", "48"]) == 0
        frames[name] = (read_exr(tmp_path / name / "frames" / "0001.exr")[0], capsys.readouterr().err,
                        json.loads((tmp_path / name / "export.json").read_text())["spatial"])
    plain, own, away = frames["plain"][0], frames["own"][0], frames["elsewhere"][0]
    fg = plain[..., 3] > 0
    assert np.abs(own[fg, :3] - plain[fg, :3]).mean() > 0.02 * np.abs(plain[fg, :3]).mean()
    record = frames["own"][2][0]
    assert record["applied"] and record["surface_share"] > 0.99 and record["factors"] == ["normal_field"]
    np.testing.assert_array_equal(away, plain)
    assert not frames["elsewhere"][2][0]["applied"] and "cover 0% of stanford-bunny.obj" in frames["elsewhere"][1]


def test_orbit_turns_about_the_captures_recorded_up(model_file, bunny, tmp_path, capsys):
    """A model recording up = +z orbits about +z (every camera at the elevation above the xy-plane);
    --up overrides; models that disagree get a note; a bad --up is one line, exit 2."""
    from damcap.appearance.dam_file import load_dam
    from tests.conftest import assert_one_line_error, run_cli

    dam, _ = load_dam(model_file)
    save_dam(tmp_path / "z.dam", dam, colorspace="lin_rec709", made_by="fit", up_world=np.array([0.0, 0.0, 1.0]))
    save_dam(tmp_path / "y.dam", dam, colorspace="lin_rec709", made_by="fit", up_world=np.array([0.0, 1.0, 0.0]))
    common = ["--mesh", bunny, "--views", "4", "--resolution", "32", "--elevation", "30"]

    def export(name, *args):
        code, _, err = run_cli(["export", *args, *common, "-o", tmp_path / name], capsys)
        assert code == 0, err
        return json.loads((tmp_path / name / "export.json").read_text()), err

    rec, _ = export("z", tmp_path / "z.dam")
    cams = np.array(rec["world_from_cam"])
    assert rec["up_world"] == [0.0, 0.0, 1.0] and rec["up_source"] == "model"
    np.testing.assert_allclose(cams[:, 2, 3], 3.0 * np.sin(np.radians(30)), atol=1e-9)
    rec, _ = export("z_over", tmp_path / "z.dam", "--up", "+y")
    assert rec["up_world"] == [0.0, 1.0, 0.0] and rec["up_source"] == "--up"
    np.testing.assert_allclose(np.array(rec["world_from_cam"])[:, 1, 3], 3.0 * np.sin(np.radians(30)), atol=1e-9)
    rec, _ = export("plain", model_file)
    assert rec["up_source"] in ("default", "model")
    from damcap.common.mesh import read_mesh

    labels = np.arange(len(read_mesh(bunny).vertices)) % 2  # the file's vertex order
    np.save(tmp_path / "labels.npy", labels)
    rec, err = export("two", tmp_path / "z.dam", tmp_path / "y.dam", "--labels", tmp_path / "labels.npy")
    assert rec["up_world"] == [0.0, 0.0, 1.0] and "disagree about up" in err
    code, _, err = run_cli(["export", tmp_path / "z.dam", *common, "--up", "sideways", "-o", tmp_path / "bad"], capsys)
    assert_one_line_error(code, err, "--up", "sideways")


def test_export_says_how_much_of_the_shape_faces_normals_the_capture_never_showed(model_file, tmp_path, capsys):
    """A model trained on upward normals only (its recorded histogram: the upper hemisphere),
    exported on a sphere seen from the equator: about half of its pixels face down, export.json
    records that share and stderr warns, naming the model; seen from high above, almost none
    and no warning; a model recording no histogram gets None and no warning. The matcap and
    the GLB record and warn the same way."""
    from damcap.appearance.coverage import normal_histogram
    from damcap.appearance.dam_file import load_dam
    from tests.conftest import run_cli

    dam, _ = load_dam(model_file)
    d = np.random.default_rng(0).normal(size=(50_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    save_dam(tmp_path / "upper.dam", dam, colorspace="lin_rec709", made_by="fit", normal_histogram=normal_histogram(d[d[:, 1] > 0]),
             up_world=np.array([0.0, 1.0, 0.0]))
    save_dam(tmp_path / "none.dam", dam, colorspace="lin_rec709", made_by="fit", up_world=np.array([0.0, 1.0, 0.0]))
    assert main(["shape", "sphere", str(tmp_path / "sphere.obj")]) == 0

    def export(model, elevation):
        code, _, err = run_cli(["export", tmp_path / model, "--mesh", tmp_path / "sphere.obj", "--views", "4", "--resolution", "48",
                                "--elevation", elevation, "-o", tmp_path / f"{model}{elevation}"], capsys)
        assert code == 0, err
        return json.loads((tmp_path / f"{model}{elevation}" / "export.json").read_text())["unobserved_normals"], err

    (rec,), err = export("upper.dam", "0")
    assert rec["model"].endswith("upper.dam") and 0.3 < rec["share"] < 0.5  # the lower half less the bins on the equator
    assert "warning:" in err and "upper.dam" in err and "extrapolated" in err
    (rec,), err = export("upper.dam", "80")
    assert rec["share"] < 0.05 and "warning" not in err
    (rec,), err = export("none.dam", "0")
    assert rec["share"] is None and "warning" not in err
    # the matcap (a sphere seen from the side: its lower half faces down) and the GLB's baked vertices say the same
    from damcap.export.gltf import read_glb

    code, _, err = run_cli(["export", tmp_path / "upper.dam", "--format", "matcap", "--elevation", "0", "--resolution", "48",
                            "-o", tmp_path / "matcap"], capsys)
    assert code == 0 and "of the matcap's pixels" in err and "warning:" in err
    assert 0.3 < json.loads((tmp_path / "matcap" / "matcap.json").read_text())["unobserved_normals"] < 0.5
    code, _, err = run_cli(["export", tmp_path / "upper.dam", "--format", "glb", "--mesh", tmp_path / "sphere.obj",
                            "-o", tmp_path / "s.glb"], capsys)
    (rec,) = read_glb((tmp_path / "s.glb").read_bytes())[0]["asset"]["extras"]["damcap"]["unobserved_normals"]
    assert code == 0 and "of its vertices on sphere.obj" in err and 0.3 < rec["share"] < 0.5
