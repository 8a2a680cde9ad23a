"""export --format threejs: the ES module's ShaderMaterial in three.js (r111, WebGL 2) in a real
browser, against damcap's own CPU render of the same view."""

from __future__ import annotations

import base64

import numpy as np
import pytest

from damcap.appearance.dam_file import load_dam
from damcap.appearance.metrics import dssim
from damcap.cli.main import main
from damcap.common.colour import display_srgb8
from damcap.common.exr import read_exr, read_image_u8
from damcap.export.browser import page_title, screenshot
from damcap.export.threejs import threejs_module
from damcap.export.turntable import shape_and_parts

SIZE = 256


def _linear(u8: np.ndarray) -> np.ndarray:
    import colour
    return colour.cctf_decoding(u8[..., :3] / 255.0, function="sRGB")


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")


def _page(three, module_js: str, shape, centre) -> str:
    return f"""<!DOCTYPE html><html><head><title>loading</title>
<style>html,body{{margin:0;background:#000;overflow:hidden}}canvas{{display:block}}</style></head><body>
<canvas id="c" width="{SIZE}" height="{SIZE}" style="width:{SIZE}px;height:{SIZE}px"></canvas>
<script>{(three / "three.min.js").read_text()}</script>
<script type="module">
import {{ damcapMaterial }} from "data:text/javascript;base64,{base64.b64encode(module_js.encode()).decode()}";
function arr(s, T) {{ return new T(Uint8Array.from(atob(s), c => c.charCodeAt(0)).buffer); }}
try {{
  const canvas = document.getElementById("c");
  const context = canvas.getContext("webgl2", {{ antialias: false, preserveDrawingBuffer: true }});
  const renderer = new THREE.WebGLRenderer({{ canvas, context }});
  renderer.setPixelRatio(1); renderer.setClearColor(0x000000, 1);
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(arr("{_b64(shape.vertices.astype('<f4'))}", Float32Array), 3));
  geometry.setAttribute("normal", new THREE.BufferAttribute(arr("{_b64(shape.vertex_normals.astype('<f4'))}", Float32Array), 3));
  geometry.setIndex(new THREE.BufferAttribute(arr("{_b64(shape.triangles.astype('<u4'))}", Uint32Array), 1));
  const scene = new THREE.Scene();
  scene.add(new THREE.Mesh(geometry, damcapMaterial(THREE)));
  const camera = new THREE.PerspectiveCamera(45, 1, 0.01, 100);
  camera.position.set({", ".join(repr(float(x)) for x in centre)});
  camera.lookAt(0, 0, 0);
  renderer.render(scene, camera);
  const gl = renderer.getContext();
  document.title = `rendered webgl2=${{gl instanceof WebGL2RenderingContext}} error=${{gl.getError()}}`;
}} catch (e) {{ document.title = "error " + e; }}
</script></body></html>"""


def test_the_module_refuses_a_matrix_that_is_not_a_rotation(model_file):
    dam, _ = load_dam(model_file)
    with pytest.raises(ValueError, match="rotation"):
        threejs_module(dam, 1.0, 2 * np.eye(3))
    js = threejs_module(dam, 0.5, np.eye(3))
    assert "export function damcapMaterial(THREE" in js and "export const DEFAULT_EXPOSURE = 0.5;" in js


def test_three_js_shader_material_matches_cpu_render(browser, three_js, model_file, bunny, tmp_path):
    assert main(["export", str(model_file), "--format", "threejs", "-o", str(tmp_path)]) == 0
    js = (tmp_path / "dam_material.js").read_text()
    scale = float(js.split("export const DEFAULT_EXPOSURE = ")[1].split(";")[0])
    _, shape, _ = shape_and_parts(bunny, None, 1)
    centre = 3.0 * np.array([0.0, np.sin(np.radians(20.0)), np.cos(np.radians(20.0))])  # the orbit's first view
    page = tmp_path / "three.html"
    page.write_text(_page(three_js, js, shape, centre))
    title = page_title(page, SIZE)
    assert title == "rendered webgl2=true error=0", title
    screenshot(page, tmp_path / "shot.png", SIZE, virtual_time_ms=5000)
    shot = read_image_u8(tmp_path / "shot.png")
    assert main(["export", str(model_file), "--mesh", str(bunny), "-o", str(tmp_path / "cpu"), "--views", "1",
                 "--resolution", str(SIZE)]) == 0
    cpu = read_exr(tmp_path / "cpu" / "frames" / "0000.exr")[0]
    d = dssim(_linear(display_srgb8(cpu[..., :3], scale)), _linear(shot), cpu[..., 3])
    print(f"three.js material vs cpu dssim {d:.4f}")
    assert d <= 0.02, d
    assert shot[cpu[..., 3] == 0][:, :3].mean() < 1.0


def test_several_models_need_a_mesh_in_parts(model_file, pot, tmp_path, capsys):
    assert main(["export", str(model_file), str(model_file), "--format", "threejs", "-o", str(tmp_path / "m.js")]) == 2
    assert "2 models were given (one per part of a mesh) but no --mesh" in capsys.readouterr().err
    assert main(["export", *[str(model_file)] * 4, "--mesh", str(pot), "--format", "threejs", "-o", str(tmp_path / "m.js")]) == 2
    assert "its OBJ material groups name 3 part(s), but 4 models were given" in capsys.readouterr().err
    assert not (tmp_path / "m.js").exists()


def _parts_page(three, module_js: str, centre) -> str:
    return f"""<!DOCTYPE html><html><head><title>loading</title>
<style>html,body{{margin:0;background:#000;overflow:hidden}}canvas{{display:block}}</style></head><body>
<canvas id="c" width="{SIZE}" height="{SIZE}" style="width:{SIZE}px;height:{SIZE}px"></canvas>
<script>{(three / "three.min.js").read_text()}</script>
<script type="module">
import {{ damcapGeometry, damcapMaterials, PARTS }} from "data:text/javascript;base64,{base64.b64encode(module_js.encode()).decode()}";
try {{
  const canvas = document.getElementById("c");
  const context = canvas.getContext("webgl2", {{ antialias: false, preserveDrawingBuffer: true }});
  const renderer = new THREE.WebGLRenderer({{ canvas, context }});
  renderer.setPixelRatio(1); renderer.setClearColor(0x000000, 1);
  const scene = new THREE.Scene();
  const geometry = damcapGeometry(THREE);
  scene.add(new THREE.Mesh(geometry, damcapMaterials(THREE)));
  const camera = new THREE.PerspectiveCamera(45, 1, 0.01, 100);
  camera.position.set({", ".join(repr(float(x)) for x in centre)});
  camera.lookAt(0, 0, 0);
  renderer.render(scene, camera);
  const gl = renderer.getContext();
  document.title = `rendered parts=${{PARTS.join("+")}} groups=${{geometry.groups.length}} error=${{gl.getError()}}`;
}} catch (e) {{ document.title = "error " + e; }}
</script></body></html>"""


#: most a part's mean display colour may differ between three.js and damcap's CPU render, 8-bit
#: levels per channel (measured in Chromium's SwiftShader: 0.00, 0.01, 0.06 for body, lid, handle)
PARTS_MEAN_TOL = 0.5


def test_three_js_materials_in_parts_match_cpu_render_per_part(browser, three_js, part_models, pot, tmp_path):
    """Three models on the pot's OBJ groups: damcapGeometry's groups take damcapMaterials' materials,
    each part in its own DAM's colours as damcap's CPU render of the same view gives them."""
    from scipy.ndimage import binary_erosion

    from damcap.export.turntable import OrbitOptions, render_orbit

    assert main(["export", *map(str, part_models), "--mesh", str(pot), "--format", "threejs", "-o", str(tmp_path)]) == 0
    js = (tmp_path / "dam_material.js").read_text()
    assert 'export const PARTS = ["body", "lid", "handle"];' in js and "export function damcapGeometry(THREE)" in js
    scale = float(js.split("export const DEFAULT_EXPOSURE = ")[1].split(";")[0])
    centre = 3.0 * np.array([0.0, np.sin(np.radians(20.0)), np.cos(np.radians(20.0))])  # the orbit's first view
    page = tmp_path / "three.html"
    page.write_text(_parts_page(three_js, js, centre))
    title = page_title(page, SIZE)
    assert title == "rendered parts=body+lid+handle groups=3 error=0", title
    screenshot(page, tmp_path / "shot.png", SIZE, virtual_time_ms=5000)
    shot = read_image_u8(tmp_path / "shot.png")[..., :3].astype(np.float64)
    _, shape, part = shape_and_parts(pot, None, 3)
    dams = [load_dam(m)[0] for m in part_models]
    _, buf, rad = next(render_orbit(dams, shape, part, OrbitOptions(views=1, resolution=SIZE)))
    ref = display_srgb8(rad, scale).astype(np.float64)
    part_px = np.where((buf.coverage > 0.999) & (buf.triangle_id >= 0), part[np.maximum(buf.triangle_id, 0)], -1)
    means = []
    for k in range(3):
        inside = binary_erosion(part_px == k, iterations=2)
        gap = np.abs(shot[inside].mean(0) - ref[inside].mean(0)).max()
        print(f"part {k}: {inside.sum()} px, mean colour three.js {shot[inside].mean(0).round(1)} cpu {ref[inside].mean(0).round(1)}, "
              f"largest mean gap {gap:.2f}, p99 {np.percentile(np.abs(shot[inside] - ref[inside]), 99):.1f} levels")
        assert inside.sum() > 100 and gap <= PARTS_MEAN_TOL, (k, inside.sum(), gap)
        means.append(ref[inside].mean(0))
    assert min(np.abs(means[a] - means[b]).max() for a, b in ((0, 1), (0, 2), (1, 2))) > 10 * PARTS_MEAN_TOL
    assert shot[buf.coverage == 0].mean() < 1.0
