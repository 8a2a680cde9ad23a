"""Export: frames on a new shape, ONNX (onnxruntime to 1e-5), GLSL, the viewer in a real browser."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, split_weights
from damcap.appearance.dam_file import save_dam
from damcap.appearance.fit import FitOptions, fit_dam
from damcap.appearance.metrics import dssim
from damcap.appearance.views import load_views, samples_of
from damcap.cli.main import main
from damcap.common.capture_folder import read_capture
from damcap.common.exr import read_exr, read_image_u8
from damcap.export.browser import chromium_path, frame_rate, screenshot
from damcap.export.display import display_srgb8, exposure_scale_for
from damcap.export.glsl import glsl_source
from damcap.export.turntable import parts_from_vertex_labels
from tests.conftest import tree_digest


@pytest.fixture(scope="module")
def model_file(sample_capture, tmp_path_factory):
    views = load_views(read_capture(sample_capture), "train")
    model = fit_dam(samples_of(views), FitOptions(steps=300, holdout_views=0)).model
    path = tmp_path_factory.mktemp("model") / "torus.dam"
    save_dam(path, model, colorspace="lin_rec709", made_by="fit")
    return path


@pytest.fixture(scope="module")
def bunny(shared_data):
    return shared_data / "meshes" / "stanford-bunny.obj"


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
    import cv2
    cap = cv2.VideoCapture(str(out / "turntable.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 4
    assert tree_digest(bunny.parent) == before


def test_onnx_matches_onnxruntime(model_file, tmp_path, capsys):
    import onnxruntime as ort

    from damcap.appearance.dam_file import load_dam

    assert main(["export", str(model_file), "--format", "onnx", "-o", str(tmp_path / "m.onnx")]) == 0
    sess = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(3)
    v = rng.normal(size=(1000, 3)).astype(np.float32)
    n = rng.normal(size=(1000, 3)).astype(np.float32)
    got = sess.run(None, {"view_dir_world": v, "normal_world": n})[0]
    with torch.no_grad():
        want = load_dam(model_file)[0](torch.from_numpy(v), torch.from_numpy(n)).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(np.abs(want).max()))


def test_separable_dam_exports_to_onnx(tmp_path):
    import onnxruntime as ort

    from damcap.export.onnx_export import export_onnx

    m = DeepAppearanceMap(DamArchitecture(width=8, depth=3, separable=True), radiance_scale=3.0,
                          generator=torch.Generator().manual_seed(4))
    export_onnx(m, tmp_path / "s.onnx")
    sess = ort.InferenceSession(str(tmp_path / "s.onnx"), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(5)
    v, n = rng.normal(size=(2, 500, 3)).astype(np.float32)
    got = sess.run(None, {"view_dir_world": v, "normal_world": n})[0]
    with torch.no_grad():
        want = m(torch.from_numpy(v), torch.from_numpy(n)).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(np.abs(want).max()))


def test_glsl_of_a_separable_dam_writes_its_block_diagonal_matrices():
    m = DeepAppearanceMap(DamArchitecture(width=6, depth=2, separable=True), generator=torch.Generator().manual_seed(2))
    src = glsl_source(m)
    arrays = [line for line in src.splitlines() if line.startswith("const float")]
    values = np.array([float(x) for line in arrays for x in line.split("(", 1)[1].rstrip(");").split(",")])
    dense = torch.cat([w[0].flatten() for w, _ in split_weights(m.get_flat_weights()[None], m.arch)]).numpy()
    np.testing.assert_allclose(values, dense, rtol=1e-7)
    assert np.count_nonzero(values) == m.arch.num_weights == 6 * 3 + 6 * 6 // 2 + 3 * 6
    first = values[:36].reshape(6, 6)  # units 0-2 see N only, units 3-5 R only
    assert not first[:3, 3:].any() and not first[3:, :3].any()
    assert "separable" in src


def test_glsl_is_self_contained_and_carries_every_weight():
    m = DeepAppearanceMap(DamArchitecture(width=4, depth=2, encoding="vnr", bias=True), radiance_scale=2.0)
    src = glsl_source(m)
    assert "vec3 dam_eval(vec3 view_dir_world, vec3 normal_world)" in src
    arrays = [line for line in src.splitlines() if line.startswith("const float")]
    values = [float(x) for line in arrays for x in line.split("(", 1)[1].rstrip(");").split(",")]
    np.testing.assert_allclose(values, m.get_flat_weights().numpy(), rtol=1e-7)
    assert "* 2.0;" in src


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
    meta = {"format_version": 2, "architecture": DamArchitecture().to_json(), "radiance_scale": 1.0}
    (tmp_path / "new.dam").write_bytes(st_save({"weights": torch.zeros(3360)}, metadata={"damcap": json.dumps(meta)}))
    assert main(["export", str(tmp_path / "new.dam"), "--mesh", str(tmp_path / "tet.obj"), "-o", str(tmp_path / "o2")]) == 2
    assert "newer than this damcap reads" in capsys.readouterr().err
    assert main(["export", str(model_file), str(model_file), "--mesh", str(tmp_path / "tet.obj"), "-o", str(tmp_path / "o3"),
                 "--labels", str(tmp_path / "missing.npy")]) == 2
    assert "label file not found" in capsys.readouterr().err


@pytest.fixture(scope="module")
def browser():
    if chromium_path() is None:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail("chromium is required under CI (make test installs it)")
        pytest.skip("chromium not installed")


def _linear(u8: np.ndarray) -> np.ndarray:
    import colour
    return colour.cctf_decoding(u8[..., :3] / 255.0, function="sRGB")


def test_viewer_matches_cpu_render_in_a_real_browser(browser, model_file, bunny, tmp_path):
    assert main(["view", str(model_file), "--mesh", str(bunny), "-o", str(tmp_path / "view.html"), "--azimuth", "45"]) == 0
    html = (tmp_path / "view.html").read_text()
    assert "<script src" not in html and "http" not in html.split("<script>", 1)[1]  # self-contained
    screenshot(tmp_path / "view.html", tmp_path / "shot.png", 256, fragment="az=45&el=20&caption=0")
    shot = read_image_u8(tmp_path / "shot.png")
    # damcap's own CPU render of the same view (the export's second frame of 8 is at azimuth 45)
    assert main(["export", str(model_file), "--mesh", str(bunny), "-o", str(tmp_path / "cpu"), "--views", "8", "--resolution", "256"]) == 0
    cpu = read_exr(tmp_path / "cpu" / "frames" / "0001.exr")[0]
    scale = float(html.split('"exposure_scale": ')[1].split(",")[0])
    ref = display_srgb8(cpu[..., :3], scale)
    d = dssim(_linear(ref), _linear(shot), cpu[..., 3])
    assert d <= 0.02, d
    # background is black where damcap sees no surface
    assert shot[cpu[..., 3] == 0][:, :3].mean() < 1.0


def test_viewer_frame_rate_is_reported(browser, model_file, tmp_path):
    assert main(["view", str(model_file), "-o", str(tmp_path / "v.html")]) == 0
    fps = frame_rate(tmp_path / "v.html", 128, frames=5)
    assert fps > 0


def test_exposure_scale_rule():
    rad = np.ones((4, 4, 3)) * 2.0
    assert exposure_scale_for(rad, np.ones((4, 4), bool)) == pytest.approx(0.4)
    assert exposure_scale_for(rad * 0, np.ones((4, 4), bool)) == 1.0


def test_several_dams_by_vertex_labels(model_file, bunny, tmp_path):
    from damcap.appearance.dam_file import load_dam
    from damcap.common.mesh import load_mesh

    dam, meta = load_dam(model_file)
    brighter = DeepAppearanceMap(dam.arch, dam.radiance_scale * 2, dam.get_flat_weights())
    save_dam(tmp_path / "b.dam", brighter, colorspace="lin_rec709", made_by="fit")
    verts = load_mesh(bunny).vertices
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


def test_procedural_shapes_are_the_closed_form_surfaces(tmp_path, capsys):
    """The demo's new shapes: every torus vertex lies on (sqrt(x^2 + z^2) - 0.9)^2 + y^2 = 0.4^2
    (axis y, as the capture contract's up), every sphere vertex on |v| = 1; both come back through
    damcap's own mesh reader, and bad requests are refused with a message."""
    from damcap.common.errors import DamcapError
    from damcap.common.shapes import main as shapes_main
    from damcap.common.shapes import torus_mesh, write_shape
    from damcap.common.mesh import load_mesh

    v = np.asarray(torus_mesh(0.9, 0.4).vertices)
    assert np.allclose((np.hypot(v[:, 0], v[:, 2]) - 0.9) ** 2 + v[:, 1] ** 2, 0.16, atol=1e-9)
    assert np.ptp(v[:, 1]) == pytest.approx(0.8, abs=1e-6)  # the tube's height along y
    torus = load_mesh(write_shape("torus", tmp_path / "torus.obj"))
    assert len(torus.vertices) == 60 * 24 and len(torus.triangles) == 2 * 60 * 24
    sphere = load_mesh(write_shape("sphere", tmp_path / "sphere.ply"))
    assert np.allclose(np.linalg.norm(sphere.vertices, axis=1), 1.0, atol=1e-5)
    with pytest.raises(DamcapError, match="0 < minor < major"):
        torus_mesh(0.4, 0.9)
    with pytest.raises(DamcapError, match=r"\.obj or \.ply"):
        write_shape("torus", tmp_path / "torus.stl")
    assert shapes_main(["torus", str(tmp_path / "bad.txt")]) == 2
    assert "error:" in capsys.readouterr().err and not (tmp_path / "bad.txt").exists()
