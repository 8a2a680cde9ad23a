"""DAMs into Blender (``damcap export --format blender``): one OSL shader per model and a script
that makes the materials (and, with ``--mesh``, the mesh with them) inside Blender.

``<name>.osl`` defines a Cycles Script-node shader whose output ``radiance`` is the model's linear
radiance (its radiance scale applied) for the shading point's world normal ``N`` and view
direction ``I``. In a Cycles Script node ``I`` points from the surface toward the camera, as
damcap's ``view_dir_world`` (measured on Blender 5.0.1). The DAM works in its capture's world,
whose up axis the ``.dam`` records (``up_world``); Blender's is +Z, so the shader reads Blender's
directions through the smallest rotation taking the model's up onto +Z, baked into the first
layer's weights (:func:`damcap.appearance.dam.rotated_world_weights`). For a +Y-up model that is
(x, y, z) -> (x, -z, y), what Blender's OBJ and glTF importers do to a +Y-up mesh. Every other
weight, the encoding, the activation and the radiance scale are written as constants, evaluated
as :func:`damcap.appearance.dam.dam_forward` does.

``damcap_materials.py`` (:mod:`.blender_script` with its configuration filled in) builds the
materials: Script node -> Emission, its strength an ``exposure`` input.
"""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from damcap.appearance.dam import LN2, DeepAppearanceMap, rotated_world_weights, split_weights
from damcap.common.atomic import atomic_path, write_text_atomic
from damcap.common.cameras import rotation_between
from damcap.common.colour import exposure_scale_for
from damcap.common.mesh import Mesh, vertex_normals_area_weighted
from damcap.common.shapes import shape_mesh
from damcap.export.turntable import OrbitOptions, render_orbit, shape_and_parts

#: Blender's up axis
BLENDER_UP = np.array([0.0, 0.0, 1.0])
SCRIPT_NAME = "damcap_materials.py"
#: the line of :mod:`.blender_script` that the export replaces with the configuration
CONFIG_LINE = "CONFIG: dict = {}"
#: softplus(x) = x above this (torch's threshold), exp(x) below ``SOFTPLUS_LOW`` (float32's log(1 + tiny) is 0)
SOFTPLUS_HIGH = 20.0
SOFTPLUS_LOW = -15.0


def blender_from_world(up_world: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation taking the model's up direction onto Blender's +Z.

    Args:
        up_world: (3,) the model's up direction (any length > 0).

    >>> blender_from_world(np.array([0.0, 1.0, 0.0])).round(12).tolist()  # (x, y, z) -> (x, -z, y)
    [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
    """
    return rotation_between(np.asarray(up_world, np.float64), BLENDER_UP)


def shader_name(stem: str) -> str:
    """An OSL / Blender identifier made of a model file's stem.

    >>> shader_name("material-0.v2"), shader_name("3 gold")
    ('material_0_v2', 'm3_gold')
    """
    name = re.sub(r"[^A-Za-z0-9_]", "_", stem) or "dam"
    return name if not name[0].isdigit() else "m" + name


def unique_names(stems: list[str]) -> list[str]:
    """:func:`shader_name` of each stem, a suffix added where two would be the same.

    >>> unique_names(["gold", "gold", "a-b", "a_b"])
    ['gold', 'gold_2', 'a_b', 'a_b_2']
    """
    out: list[str] = []
    for s in stems:
        base = name = shader_name(s)
        k = 2
        while name in out:
            name, k = f"{base}_{k}", k + 1
        out.append(name)
    return out


def _lit(x: float) -> str:
    s = f"{float(x):.9g}"
    return s if any(c in s for c in ".en") else s + ".0"


ACTIVATION_OSL = {
    "leaky_relu": "return x > 0.0 ? x : 0.01 * x;",
    "relu": "return max(x, 0.0);",
    "softplus": "return damcap_softplus(x);",
    "shifted_softplus": f"return damcap_softplus(x) - {LN2!r};",
    "tanh": "return tanh(x);",
}


def osl_source(model: DeepAppearanceMap, blender_from_dam: np.ndarray, name: str, note: str = "") -> str:
    """OSL source of the shader ``damcap_<name>`` with one output, ``color radiance``.

    Args:
        model: the DAM (its surface factors, if any, are not part of the shader).
        blender_from_dam: (3, 3) rotation from the model's world to Blender's (:func:`blender_from_world`).
        name: an identifier (:func:`shader_name`).
        note: a comment line (which model, which up).

    Returns:
        the shader's text: weights as constant arrays, (out, in) row-major per layer (a separable
        DAM's structural zeros written out), evaluated in float like ``dam_forward``.
    """
    arch = model.arch
    rot = np.asarray(blender_from_dam, np.float64)
    if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-9) or np.linalg.det(rot) < 0:
        raise ValueError("blender_from_dam must be a rotation")
    # f_blender(V, N) = f(R^T V, R^T N): the first layer reads Blender's vectors through R^T
    weights = rotated_world_weights(model.get_flat_weights().double(), arch, torch.from_numpy(rot.T.copy()))
    layers = split_weights(weights[None], arch)
    dims = [arch.layer_shapes[0][1]] + [o for o, _ in arch.layer_shapes]
    comps = {"vn": ["V", "Nw"], "nr": ["Nw", "R"], "vnr": ["V", "Nw", "R"]}[arch.encoding]
    lines = [
        f"// damcap deep appearance map (damcap export --format blender). {note}".rstrip(),
        f"// {arch.depth} hidden layers of {arch.width} ({arch.activation}{', separable' if arch.separable else ''}"
        f"{', biases' if arch.bias else ''}), input '{arch.encoding}', {arch.num_weights} weights, radiance scale {model.radiance_scale:.9g}.",
        "// Output 'radiance': linear radiance in the capture's units for Cycles' world normal N and view direction I",
        "// (in a Cycles Script node I points from the surface toward the camera). The model's world is turned",
        "// into Blender's by this rotation (rows), baked into the first layer's weights:",
        *[f"//   {' '.join(f'{v: .9f}' for v in row)}" for row in rot],
        "",
        "float damcap_softplus(float x)",
        "{",
        f"    if (x > {_lit(SOFTPLUS_HIGH)}) return x;",
        f"    if (x < {_lit(SOFTPLUS_LOW)}) return exp(x);",
        "    return log(1.0 + exp(x));",
        "}",
        "",
        f"float damcap_act(float x) {{ {ACTIVATION_OSL[arch.activation]} }}",
        "",
        f"shader damcap_{name}(",
        '    output color radiance = 0 [[ string help = "linear radiance of the DAM (times exposure: Emission strength)" ]])',
        "{",
    ]
    for li, ((o, i), (w, b)) in enumerate(zip(arch.layer_shapes, layers)):
        lines.append(f"    float W{li}[{o * i}] = {{{','.join(_lit(v) for v in w[0].flatten().tolist())}}};")
        if b is not None:
            lines.append(f"    float B{li}[{o}] = {{{','.join(_lit(v) for v in b[0].tolist())}}};")
    lines += [
        "    vector V = normalize(I);",
        "    vector Nw = normalize(N);",
        "    vector R = 2.0 * dot(Nw, V) * Nw - V;",
        f"    float x0[{dims[0]}];",
    ]
    for j, c in enumerate(comps):
        for a in range(3):
            lines.append(f"    x0[{3 * j + a}] = {c}[{a}];")
    last = len(arch.layer_shapes) - 1
    for li, (o, i) in enumerate(arch.layer_shapes):
        lines += [
            f"    float x{li + 1}[{o}];",
            f"    for (int r = 0; r < {o}; r++) {{",
            f"        float s = {f'B{li}[r]' if arch.bias else '0.0'};",
            f"        for (int c = 0; c < {i}; c++) s += W{li}[r * {i} + c] * x{li}[c];",
            f"        x{li + 1}[r] = {'damcap_softplus(s)' if li == last else 'damcap_act(s)'};",
            "    }",
        ]
    n = len(arch.layer_shapes)
    lines += [f"    radiance = color(x{n}[0], x{n}[1], x{n}[2]) * {_lit(model.radiance_scale)};", "}"]
    return "\n".join(lines) + "\n"


def materials_script(materials: list[dict], mesh: dict | None) -> str:
    """The text of ``damcap_materials.py``: :mod:`.blender_script` with its configuration.

    Args:
        materials: per model ``{"name", "osl", "exposure", "model"}`` (material name, shader file
            beside the script, default exposure, the model's file name).
        mesh: ``{"file", "name"}`` of the mesh file beside the script, or None.
    """
    template = (Path(__file__).parent / "blender_script.py").read_text(encoding="utf-8")
    if template.count(CONFIG_LINE) != 1:
        raise RuntimeError("export/blender_script.py: its configuration line is missing")
    config = json.dumps({"materials": materials, "mesh": mesh}, indent=1)
    header = ('"""damcap\'s materials for Blender, written by damcap export --format blender.\n\n'
              "Run inside Blender: Text editor > Open this file > Run Script, or blender --python damcap_materials.py.\n"
              "It needs the .osl files beside it.\n")
    text = template.replace(CONFIG_LINE, f"CONFIG: dict = json.loads({config!r})", 1)
    return header + '"""' + text.split('"""', 2)[2]  # the template's docstring replaced by the header


def mesh_arrays(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray | None, part: np.ndarray,
                blender_from_dam: np.ndarray) -> dict[str, np.ndarray]:
    """The mesh for ``damcap_materials.py``, turned into Blender's frame.

    Args:
        vertices: (V, 3) positions in the model's world (the mesh file's own coordinates).
        triangles: (T, 3) vertex indices.
        normals: (V, 3) unit vertex normals, or None.
        part: (T,) part (model index) per triangle.
        blender_from_dam: (3, 3) rotation (:func:`blender_from_world`).

    Returns:
        ``vertices`` (V, 3) float32, ``triangles`` (T, 3) int32, ``part`` (T,) int32 and, when
        given, ``normals`` (V, 3) float32, all in Blender's frame.
    """
    rot = np.asarray(blender_from_dam, np.float64)
    out = {"vertices": (np.asarray(vertices, np.float64) @ rot.T).astype(np.float32),
           "triangles": np.asarray(triangles, np.int32), "part": np.asarray(part, np.int32)}
    if normals is not None:
        out["normals"] = (np.asarray(normals, np.float64) @ rot.T).astype(np.float32)
    return out


def first_view_exposure(dams: list[DeepAppearanceMap], mesh: Mesh, part: np.ndarray, orbit: OrbitOptions, up_world: np.ndarray) -> float:
    """The default ``exposure``: the display key at the 95th percentile of a 128 px render of the
    orbit's first view (the rule of damcap export's PNGs, the GLB and the three.js material)."""
    small = replace(orbit, views=1, resolution=128, supersample=1)
    _, buf, rad = next(render_orbit(dams, mesh, part, small, up_world=up_world))
    return exposure_scale_for(rad, buf.coverage > 0.5)


def export_blender(dams: list[DeepAppearanceMap], model_paths: list[Path], up_world: np.ndarray, out_dir: Path,
                   orbit: OrbitOptions, mesh_path: Path | None = None, labels_path: Path | None = None) -> dict:
    """Write ``<name>.osl`` per model, ``damcap_materials.py`` and, with a mesh, ``<mesh>.npz`` into ``out_dir``.

    Args:
        dams: the models (DAMs alone: surface factors are not exported).
        model_paths: their files (names the materials).
        up_world: (3,) the models' up direction (turned onto Blender's +Z).
        out_dir: an existing folder.
        orbit: the orbit whose first view sets the default exposure.
        mesh_path: the mesh to carry the materials, or None.
        labels_path: its per-vertex labels, or None (OBJ material groups; one model: one part).

    Returns:
        what was written: ``names``, ``exposures``, ``mesh`` (file name or None), ``triangles``.
    """
    rot = blender_from_world(up_world)
    names = unique_names([Path(p).stem for p in model_paths])
    mesh_entry, triangles = None, 0
    if mesh_path is not None:
        raw, shape, part = shape_and_parts(mesh_path, labels_path, len(dams))
        scale = first_view_exposure(dams, shape, part, orbit, up_world)
        exposures = [scale] * len(dams)
        mesh_name = shader_name(Path(mesh_path).stem)
        with atomic_path(out_dir / f"{mesh_name}.npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **mesh_arrays(raw.vertices, shape.triangles, shape.vertex_normals, part, rot))
        mesh_entry, triangles = {"file": f"{mesh_name}.npz", "name": mesh_name}, len(shape.triangles)
    else:
        sphere = shape_mesh("sphere")
        tri = np.asarray(sphere.triangles, np.int32)
        ball = Mesh(np.asarray(sphere.vertices, np.float32), tri,
                    vertex_normals_area_weighted(np.asarray(sphere.vertices, np.float32), tri).astype(np.float32))
        exposures = [first_view_exposure([d], ball, np.zeros(len(tri), np.int64), orbit, up_world) for d in dams]
    up_text = (np.round(np.asarray(up_world, np.float64), 4) + 0.0).tolist()  # no -0.0
    materials = []
    for d, path, name, exposure in zip(dams, model_paths, names, exposures):
        note = f"Model {Path(path).name}, up {up_text}."
        write_text_atomic(out_dir / f"{name}.osl", osl_source(d, rot, name, note))
        materials.append({"name": name, "osl": f"{name}.osl", "exposure": float(exposure), "model": Path(path).name})
    write_text_atomic(out_dir / SCRIPT_NAME, materials_script(materials, mesh_entry))
    return {"names": names, "exposures": exposures, "mesh": None if mesh_entry is None else mesh_entry["file"], "triangles": triangles}
