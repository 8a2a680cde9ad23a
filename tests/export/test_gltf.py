"""export --format glb: the container read back by hand, and three.js's GLTFLoader in a real browser
against damcap's own CPU render of the baked view."""

from __future__ import annotations

import base64

import numpy as np

from damcap.appearance.dam_file import load_dam
from damcap.appearance.metrics import dssim
from damcap.cli.main import main
from damcap.common.cameras import orbit_world_from_cam
from damcap.common.exr import read_exr, read_image_u8
from damcap.export.browser import page_title, screenshot
from damcap.export.gltf import accessor_array, glb_bytes, gltf_from_world, read_glb, split_parts, vertex_radiance
from damcap.export.turntable import shape_and_parts

SIZE = 256


def _cube_parts():
    from damcap.common.mesh import Mesh, vertex_normals_area_weighted

    v = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], np.float32)
    t = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.int32)
    m = Mesh(v, t, vertex_normals_area_weighted(v, t).astype(np.float32))
    return m, split_parts(m, np.arange(12) // 6, 2)


def test_the_container_reads_back_exactly():
    mesh, parts = _cube_parts()
    colours = [np.full((len(p.positions), 3), 0.25, np.float32) * (k + 1) for k, p in enumerate(parts)]
    colours[1][0] = 7.0  # clipped to 1 in the file
    up = np.array([0.0, 0.0, 1.0])
    cam = orbit_world_from_cam(1, 3.0, 20.0, 0.0, up)[0]
    data = glb_bytes(parts, colours, gltf_from_world(up), cam, 45.0, {"note": "test"})
    assert len(data) % 4 == 0
    doc, blob = read_glb(data)
    assert doc["asset"]["version"] == "2.0" and doc["asset"]["extras"] == {"note": "test"}
    assert doc["extensionsUsed"] == ["KHR_materials_unlit"] and "KHR_materials_unlit" in doc["materials"][0]["extensions"]
    for k, part in enumerate(parts):
        prim = doc["meshes"][k]["primitives"][0]
        pos = accessor_array(doc, blob, prim["attributes"]["POSITION"])
        np.testing.assert_array_equal(pos, part.positions)
        acc = doc["accessors"][prim["attributes"]["POSITION"]]
        assert acc["min"] == pos.min(0).tolist() and acc["max"] == pos.max(0).tolist()  # required by the spec
        np.testing.assert_array_equal(accessor_array(doc, blob, prim["indices"]).reshape(-1, 3), part.triangles)
        np.testing.assert_array_equal(accessor_array(doc, blob, prim["attributes"]["COLOR_0"]), np.clip(colours[k], 0, 1))
    for v in doc["bufferViews"]:
        assert v["byteOffset"] % 4 == 0
    # the camera node holds world_from_cam; the root turns the orbit's up (+z here) onto glTF's +y
    cam_node = next(n for n in doc["nodes"] if "camera" in n)
    np.testing.assert_allclose(np.array(cam_node["matrix"]).reshape(4, 4).T, cam)
    root = np.array(doc["nodes"][doc["scenes"][0]["nodes"][0]]["matrix"]).reshape(4, 4).T
    np.testing.assert_allclose(root[:3, :3] @ up, [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(doc["cameras"][0]["perspective"]["yfov"], np.radians(45.0))


def test_read_glb_refuses_other_files():
    import pytest

    with pytest.raises(ValueError, match="glTF 2.0"):
        read_glb(b"\0" * 64)


def _page(three, glb: bytes) -> str:
    return f"""<!DOCTYPE html><html><head><title>loading</title>
<style>html,body{{margin:0;background:#000;overflow:hidden}}canvas{{display:block}}</style></head><body>
<canvas id="c" width="{SIZE}" height="{SIZE}" style="width:{SIZE}px;height:{SIZE}px"></canvas>
<script>{(three / "three.min.js").read_text()}</script>
<script>{(three / "examples" / "js" / "loaders" / "GLTFLoader.js").read_text()}</script>
<script>
const bytes = Uint8Array.from(atob("{base64.b64encode(glb).decode()}"), c => c.charCodeAt(0));
const canvas = document.getElementById("c");
const context = canvas.getContext("webgl2", {{ antialias: false, preserveDrawingBuffer: true }});
const renderer = new THREE.WebGLRenderer({{ canvas, context }});
renderer.setPixelRatio(1); renderer.setClearColor(0x000000, 1);
new THREE.GLTFLoader().parse(bytes.buffer, "", gltf => {{
  gltf.scene.updateMatrixWorld(true);
  const cam = gltf.cameras[0];
  const unlit = gltf.scene.getObjectByName("part_0").material;
  renderer.render(gltf.scene, cam);
  document.title = `rendered ${{gltf.cameras.length}} ${{unlit.type}} ${{unlit.vertexColors}}`;
}}, err => {{ document.title = "error " + err; }});
</script></body></html>"""


def test_three_js_gltf_loader_shows_what_damcap_renders(browser, three_js, model_file, bunny, tmp_path):
    assert main(["export", str(model_file), "--format", "glb", "--mesh", str(bunny), "-o", str(tmp_path / "bunny.glb")]) == 0
    glb = (tmp_path / "bunny.glb").read_bytes()
    doc, blob = read_glb(glb)
    # the baked colours are the DAM's radiance at each vertex, seen from the file's camera
    dam, _ = load_dam(model_file)
    _, shape, part = shape_and_parts(bunny, None, 1)
    (one,) = split_parts(shape, part, 1)
    scale = doc["asset"]["extras"]["damcap"]["exposure_scale"]
    cam = np.array(next(n for n in doc["nodes"] if "camera" in n)["matrix"]).reshape(4, 4).T
    want = np.clip(vertex_radiance(dam, one.positions, one.normals, cam[:3, 3]) * scale, 0, 1)
    got = accessor_array(doc, blob, doc["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"])
    np.testing.assert_allclose(got, want, atol=1e-6)

    page = tmp_path / "glb.html"
    page.write_text(_page(three_js, glb))
    title = page_title(page, SIZE)
    assert title.startswith("rendered 1 MeshBasicMaterial"), title  # loaded, with its camera, unlit
    screenshot(page, tmp_path / "shot.png", SIZE, virtual_time_ms=5000)
    shot = read_image_u8(tmp_path / "shot.png")[..., :3] / 255.0  # no output encoding: linear, as baked
    # damcap's CPU render of the same view (the orbit's first frame)
    assert main(["export", str(model_file), "--mesh", str(bunny), "-o", str(tmp_path / "cpu"), "--views", "1",
                 "--resolution", str(SIZE)]) == 0
    cpu = read_exr(tmp_path / "cpu" / "frames" / "0000.exr")[0]
    ref = np.clip(cpu[..., :3] * scale, 0, 1)
    d = dssim(ref, shot, cpu[..., 3])
    print(f"glb vs cpu dssim {d:.4f}")
    assert d <= 0.05, d
    assert shot[cpu[..., 3] == 0].mean() < 1 / 255  # background where damcap sees no surface


def _browser_dssim(three, glb_path, model_file, mesh, tmp_path) -> float:
    """DSSIM of three.js's render of the GLB from its camera against damcap's render of the view."""
    page = tmp_path / f"{glb_path.stem}.html"
    page.write_text(_page(three, glb_path.read_bytes()))
    screenshot(page, tmp_path / f"{glb_path.stem}.png", SIZE, virtual_time_ms=5000)
    shot = read_image_u8(tmp_path / f"{glb_path.stem}.png")[..., :3] / 255.0
    if not (tmp_path / "cpu").is_dir():
        assert main(["export", str(model_file), "--mesh", str(mesh), "-o", str(tmp_path / "cpu"), "--views", "1",
                     "--resolution", str(SIZE)]) == 0
    cpu = read_exr(tmp_path / "cpu" / "frames" / "0000.exr")[0]
    doc, _ = read_glb(glb_path.read_bytes())
    return dssim(np.clip(cpu[..., :3] * doc["asset"]["extras"]["damcap"]["exposure_scale"], 0, 1), shot, cpu[..., 3])


def test_a_coarse_mesh_is_subdivided_so_the_baked_colours_follow_the_dam(browser, three_js, tmp_path):
    """The torus damcap makes has 2880 triangles. A DAM with random weights (radiance that changes
    fast with view and normal, like a glossy material) baked on it as given is far from damcap's
    render in three.js (colours interpolated across large triangles); subdivided to >= 40,000
    triangles it is close (measured 0.032 and 0.0022)."""
    import torch

    from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
    from damcap.appearance.dam_file import save_dam

    arch = DamArchitecture()
    torch.manual_seed(0)
    save_dam(tmp_path / "glossy.dam", DeepAppearanceMap(arch, radiance_scale=1.0, weights_flat=0.5 * torch.randn(arch.num_weights)),
             colorspace="lin_rec709", made_by="fit")
    model = tmp_path / "glossy.dam"
    assert main(["shape", "torus", str(tmp_path / "torus.obj")]) == 0
    torus = tmp_path / "torus.obj"
    for name, extra in (("fine", []), ("coarse", ["--glb-min-triangles", "0"])):
        assert main(["export", str(model), "--format", "glb", "--mesh", str(torus), "-o", str(tmp_path / f"{name}.glb"), *extra]) == 0
    fine = read_glb((tmp_path / "fine.glb").read_bytes())[0]["asset"]["extras"]["damcap"]["triangles"]
    coarse = read_glb((tmp_path / "coarse.glb").read_bytes())[0]["asset"]["extras"]["damcap"]["triangles"]
    assert coarse == {"mesh": 2880, "baked": 2880, "subdivided_to_at_least": 0}
    assert fine["mesh"] == 2880 and fine["baked"] == 2880 * 16  # two subdivisions reach 40,000
    d_fine = _browser_dssim(three_js, tmp_path / "fine.glb", model, torus, tmp_path)
    d_coarse = _browser_dssim(three_js, tmp_path / "coarse.glb", model, torus, tmp_path)
    assert d_fine <= 0.005 and d_coarse > 5 * d_fine, (d_fine, d_coarse)


def test_glb_needs_a_mesh_and_one_model_per_part(model_file, bunny, tmp_path, capsys):
    assert main(["export", str(model_file), "--format", "glb", "-o", str(tmp_path / "a.glb")]) == 2
    assert "--format glb needs --mesh" in capsys.readouterr().err
    labels = tmp_path / "labels.npy"
    from damcap.common.mesh import file_vertex_order, load_mesh

    np.save(labels, np.arange(file_vertex_order(bunny, load_mesh(bunny).vertices)[1]) % 2)
    assert main(["export", str(model_file), "--format", "glb", "--mesh", str(bunny), "--labels", str(labels),
                 "-o", str(tmp_path / "b.glb")]) == 2
    err = capsys.readouterr().err
    assert "labels.npy: label 1" in err and "1 model(s) were given" in err and "Traceback" not in err, err
    assert not (tmp_path / "a.glb").exists() and not (tmp_path / "b.glb").exists()


def _strings(node):
    """Every string in a JSON document (keys and values)."""
    if isinstance(node, str):
        yield node
    elif isinstance(node, dict):
        for k, v in node.items():
            yield k
            yield from _strings(v)
    elif isinstance(node, list):
        for v in node:
            yield from _strings(v)


def test_glb_carries_no_paths_of_the_machine_and_says_it_is_one_view(model_file, bunny, tmp_path, capsys):
    import hashlib
    import re

    from damcap.export.gltf import VIEW_DEPENDENCE_NOTE

    labels = tmp_path / "labels.npy"
    from damcap.common.mesh import file_vertex_order, load_mesh

    np.save(labels, np.zeros(file_vertex_order(bunny, load_mesh(bunny).vertices)[1], np.int64))
    out = tmp_path / "bunny.glb"
    assert main(["export", str(model_file), "--format", "glb", "--mesh", str(bunny), "--labels", str(labels),
                 "--glb-min-triangles", "0", "--resolution", "64", "-o", str(out)]) == 0
    glb = out.read_bytes()
    doc, _ = read_glb(glb)
    absolute = [s for s in _strings(doc) if s.startswith(("/", "\\")) or re.match(r"[A-Za-z]:[\\/]", s)]
    assert absolute == []
    for folder in {model_file.parent, bunny.parent, tmp_path}:
        assert str(folder).encode() not in glb  # not in the JSON chunk, nor anywhere else in the file
    extras = doc["asset"]["extras"]["damcap"]
    assert extras["models"] == [{"file": "torus.dam", "sha256": hashlib.sha256(model_file.read_bytes()).hexdigest()}]
    assert extras["mesh"] == {"file": "stanford-bunny.obj", "sha256": hashlib.sha256(bunny.read_bytes()).hexdigest()}
    assert extras["labels"]["file"] == "labels.npy" and extras["unobserved_normals"][0]["model"] == "torus.dam"
    assert extras["view_dependence"] == VIEW_DEPENDENCE_NOTE and "one view's radiance" in VIEW_DEPENDENCE_NOTE
    assert f"note: {VIEW_DEPENDENCE_NOTE}" in capsys.readouterr().out
