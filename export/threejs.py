"""A DAM as a three.js material (``export --format threejs``): an ES module exporting
``damcapMaterial(THREE, options)``, which returns a ``THREE.ShaderMaterial`` evaluating the DAM
per fragment (the GLSL of :mod:`.glsl`), exactly as ``damcap view`` does.

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

import json

import numpy as np

from damcap.appearance.dam import DeepAppearanceMap
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


def threejs_module(model: DeepAppearanceMap, exposure_scale: float, dam_from_scene: np.ndarray, note: str = "") -> str:
    """The ES module's text.

    Args:
        model: the DAM.
        exposure_scale: default linear radiance multiplier before sRGB encoding (``options.exposure``).
        dam_from_scene: (3, 3) default rotation from the scene's world to the DAM's (``options.damFromScene``).
        note: a comment line (what the model is).
    """
    rot = np.asarray(dam_from_scene, np.float64)
    if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6):
        raise ValueError("dam_from_scene must be a rotation")
    glsl = glsl_source(model)
    return f"""// damcap deep appearance map as a three.js ShaderMaterial (WebGL 2). {note}
// Usage: import {{ damcapMaterial }} from "./dam_material.js";
//        mesh.material = damcapMaterial(THREE, {{ exposure: {exposure_scale:.6g} }});
// options.exposure: linear radiance multiplier before sRGB encoding; options.damFromScene: a
// THREE.Matrix3 turning scene directions into the DAM's world (default: glTF +y -> the model's up).
const DAM_GLSL = {json.dumps(glsl)};
const VERTEX_SHADER = {json.dumps(VERTEX_SHADER)};
const FRAGMENT_MAIN = {json.dumps(FRAGMENT_MAIN)};
export const DEFAULT_EXPOSURE = {exposure_scale!r};
export const DEFAULT_DAM_FROM_SCENE = {json.dumps([float(x) for x in rot.ravel()])};  // row-major 3x3

export function damcapMaterial(THREE, options = {{}}) {{
  const damFromScene = options.damFromScene || new THREE.Matrix3().set(...DEFAULT_DAM_FROM_SCENE);
  return new THREE.ShaderMaterial({{
    uniforms: {{
      exposure: {{ value: options.exposure ?? DEFAULT_EXPOSURE }},
      damFromScene: {{ value: damFromScene }},
    }},
    vertexShader: VERTEX_SHADER,
    fragmentShader: DAM_GLSL + FRAGMENT_MAIN,
    side: THREE.DoubleSide,  // a back face turns its normal around, as in damcap view
    toneMapped: false,
  }});
}}
"""
