"""DAMs as three.js materials (``export --format threejs``): an ES module exporting
``damcapMaterial(THREE, options)``, which returns a ``THREE.ShaderMaterial`` evaluating a DAM
per fragment (the GLSL of :mod:`.glsl`), exactly as ``damcap view`` does, and, for a mesh in
parts (one model per part), ``damcapMaterials(THREE)`` (one material per part) and
``damcapGeometry(THREE)`` (the mesh with one group per part, for ``new THREE.Mesh(geometry,
materials)``).

three.js is passed in rather than imported, so the module works with whichever copy a page or a
bundler provides (it needs a WebGL 2 renderer: the DAM's constant arrays are GLSL ES 3.00).
The material writes display sRGB itself (exposure, clip, sRGB encoding), so it sets
``toneMapped: false`` and three.js's output colour conversion does not apply to it. The DAM
works in the world frame of the capture it was fitted in; ``options.damFromScene`` (a
``THREE.Matrix3``) turns the scene's world directions into that frame when the object is placed
otherwise (default: the rotation taking glTF's +y back onto the model's up axis, the inverse of
the root transform of ``--format glb``, so both exports line up).
"""

from __future__ import annotations

import base64
import json
from typing import Sequence

import numpy as np

from damcap.appearance.dam import DeepAppearanceMap
from damcap.common.mesh import Mesh
from damcap.export.glsl import glsl_source

VERTEX_SHADER = """varying vec3 vPosWorld;
varying vec3 vNrmWorld;
void main() {
  vec4 p = modelMatrix * vec4(position, 1.0);
  vPosWorld = p.xyz;
  vNrmWorld = mat3(modelMatrix) * normal;  // uniform scale assumed
  gl_Position = projectionMatrix * viewMatrix * p;
}"""

FRAGMENT_MAIN = """uniform float exposure;
uniform mat3 damFromScene;
varying vec3 vPosWorld;
varying vec3 vNrmWorld;
vec3 damcap_srgb(vec3 x) {
  x = clamp(x, 0.0, 1.0);
  return mix(12.92 * x, 1.055 * pow(x, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, x));
}
void main() {
  vec3 V = normalize(cameraPosition - vPosWorld);
  vec3 N = normalize(vNrmWorld);
  if (!gl_FrontFacing) N = -N;
  if (dot(N, V) <= 0.0) discard;
  gl_FragColor = vec4(damcap_srgb(dam_eval(damFromScene * V, damFromScene * N) * exposure), 1.0);
}"""


def threejs_module(models: DeepAppearanceMap | Sequence[DeepAppearanceMap], exposure_scale: float, dam_from_scene: np.ndarray,
                   note: str = "", part_names: Sequence[str] | None = None, mesh: Mesh | None = None,
                   triangle_part: np.ndarray | None = None, scene_from_world: np.ndarray | None = None) -> str:
    """The ES module's text: one ShaderMaterial per model (part), and the mesh when given.

    Args:
        models: the DAM, or one DAM per part (``damcapMaterial(THREE, {part: k})``, ``damcapMaterials``).
        exposure_scale: default linear radiance multiplier before sRGB encoding (``options.exposure``), one for all parts.
        dam_from_scene: (3, 3) default rotation from the scene's world to the DAMs' (``options.damFromScene``).
        note: a comment line (what the models are).
        part_names: a name per part (``PARTS``); default 'part k'.
        mesh: the shape in damcap's world (the unit sphere), or None; given, ``damcapGeometry(THREE)``
            returns it as a BufferGeometry with one group per part (``materialIndex`` k), turned into
            the scene by ``scene_from_world``.
        triangle_part: (T,) part (model index) per triangle of ``mesh``; None: all part 0.
        scene_from_world: (3, 3) rotation from damcap's world to the scene's (default: the inverse of
            ``dam_from_scene``).
    """
    from damcap.export.viewer import part_ranges

    dams = [models] if isinstance(models, DeepAppearanceMap) else list(models)
    if not dams:
        raise ValueError("threejs_module needs at least one model")
    rot = np.asarray(dam_from_scene, np.float64)
    if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6):
        raise ValueError("dam_from_scene must be a rotation")
    names = [f"part {k}" for k in range(len(dams))] if part_names is None else [str(n) for n in part_names]
    if len(names) != len(dams):
        raise ValueError(f"{len(names)} part names for {len(dams)} models")
    geometry = ""
    if mesh is not None:
        part = np.zeros(len(mesh.triangles), np.int64) if triangle_part is None else np.asarray(triangle_part)
        if part.shape != (len(mesh.triangles),):
            raise ValueError(f"one part index per triangle expected, got shape {part.shape} for {len(mesh.triangles)} triangles")
        order, ranges = part_ranges(part, len(dams))
        to_scene = rot.T if scene_from_world is None else np.asarray(scene_from_world, np.float64)
        data = {"positions": _b64((np.asarray(mesh.vertices, np.float64) @ to_scene.T).astype("<f4")),
                "normals": _b64((np.asarray(mesh.vertex_normals, np.float64) @ to_scene.T).astype("<f4")),
                "indices": _b64(mesh.triangles[order].astype("<u4")),
                "groups": [[3 * f, 3 * c, k] for k, (f, c) in enumerate(ranges) if c > 0]}  # index start, index count, material
        geometry = f"""
// The mesh (centred and scaled into the unit sphere, as damcap renders it), one group per part.
const GEOMETRY = {json.dumps(data)};
function damcapArray(s, T) {{ return new T(Uint8Array.from(atob(s), c => c.charCodeAt(0)).buffer); }}

export function damcapGeometry(THREE) {{
  const g = new THREE.BufferGeometry();
  g.setAttribute("position", new THREE.BufferAttribute(damcapArray(GEOMETRY.positions, Float32Array), 3));
  g.setAttribute("normal", new THREE.BufferAttribute(damcapArray(GEOMETRY.normals, Float32Array), 3));
  g.setIndex(new THREE.BufferAttribute(damcapArray(GEOMETRY.indices, Uint32Array), 1));
  for (const [start, count, k] of GEOMETRY.groups) g.addGroup(start, count, k);
  return g;
}}
"""
    usage = ('//        const mesh = new THREE.Mesh(damcapGeometry(THREE), damcapMaterials(THREE));  // one material per part\n'
             if mesh is not None else
             "//        mesh.material = damcapMaterial(THREE, { exposure: %.6g });\n" % exposure_scale if len(dams) == 1 else
             "//        mesh.material = damcapMaterials(THREE);  // with geometry.addGroup(start, count, k) for part k\n")
    imports = "damcapMaterial, damcapMaterials" + (", damcapGeometry" if mesh is not None else "")
    return f"""// damcap deep appearance map{'s' if len(dams) > 1 else ''} as three.js ShaderMaterial{'s' if len(dams) > 1 else ''} (WebGL 2). {note}
// Usage: import {{ {imports} }} from "./dam_material.js";
{usage}// options.exposure: linear radiance multiplier before sRGB encoding; options.damFromScene: a
// THREE.Matrix3 turning scene directions into the DAM's world (default: glTF +y -> the model's up);
// options.part: which part's DAM (index into PARTS, default 0).
const DAM_GLSL = {json.dumps([glsl_source(d) for d in dams])};
const VERTEX_SHADER = {json.dumps(VERTEX_SHADER)};
const FRAGMENT_MAIN = {json.dumps(FRAGMENT_MAIN)};
export const PARTS = {json.dumps(names)};
export const DEFAULT_EXPOSURE = {exposure_scale!r};
export const DEFAULT_DAM_FROM_SCENE = {json.dumps([float(x) for x in rot.ravel()])};  // row-major 3x3

export function damcapMaterial(THREE, options = {{}}) {{
  const part = options.part ?? 0;
  if (!(part in DAM_GLSL)) throw new RangeError(`part ${{part}}: the module has parts 0..${{DAM_GLSL.length - 1}} (${{PARTS.join(", ")}})`);
  const damFromScene = options.damFromScene || new THREE.Matrix3().set(...DEFAULT_DAM_FROM_SCENE);
  return new THREE.ShaderMaterial({{
    uniforms: {{
      exposure: {{ value: options.exposure ?? DEFAULT_EXPOSURE }},
      damFromScene: {{ value: damFromScene }},
    }},
    vertexShader: VERTEX_SHADER,
    fragmentShader: DAM_GLSL[part] + FRAGMENT_MAIN,
    side: THREE.DoubleSide,  // a back face turns its normal around, as in damcap view
    toneMapped: false,
  }});
}}

export function damcapMaterials(THREE, options = {{}}) {{
  return DAM_GLSL.map((_, part) => damcapMaterial(THREE, {{ ...options, part }}));
}}
{geometry}"""


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")
