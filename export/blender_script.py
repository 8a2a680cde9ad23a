"""The script ``damcap export --format blender`` writes as ``damcap_materials.py``: run inside
Blender (Text editor > Run Script, or ``blender --python damcap_materials.py``), it makes one
material per DAM from the OSL shaders beside it, and with a mesh, the mesh with those materials.

This file is the script's template: :func:`damcap.export.blender.materials_script` copies it with
:data:`CONFIG` filled in. It imports ``bpy`` only inside :func:`main`, so damcap (which has no
Blender) can import and test it.

Per material: a node group ``damcap <name>`` (Script node running ``<name>.osl`` -> Emission, whose
strength is the group's ``exposure`` input) in a material ``<name>``. The Script node holds the
shader as an internal text, so a saved .blend keeps it. OSL runs in Cycles on the CPU only: the
script sets the scene's render engine to Cycles, the device to CPU and Open Shading Language on,
and the view transform to Standard (the display sRGB of damcap's PNGs).
"""

from __future__ import annotations

import glob
import importlib.util
import json  # noqa: F401  (the CONFIG line damcap export writes reads JSON)
import os
import sys

CONFIG: dict = {}  # damcap export fills this in: {"materials": [...], "mesh": ... or None}
SCRIPT_NAME = "damcap_materials.py"


def script_folder(file: str | None, texts=()) -> str:
    """The folder this script was run from: its ``__file__``, or (run from Blender's Text editor
    without one) the file path of the text block named like it.

    Args:
        file: ``__file__`` as Blender set it (None when unset).
        texts: ``bpy.data.texts``.
    """
    candidates = [file] if file else []
    candidates += [bpy_abspath(t.filepath) for t in texts if t.filepath and os.path.basename(t.filepath) == SCRIPT_NAME]
    for c in candidates:
        folder = os.path.dirname(os.path.abspath(c))
        if all(os.path.isfile(os.path.join(folder, m["osl"])) for m in CONFIG["materials"]):
            return folder
    raise RuntimeError(f"damcap: cannot find the .osl files beside {SCRIPT_NAME}; run it from the folder damcap export wrote "
                       f"(blender --python DIR/{SCRIPT_NAME}, or open DIR/{SCRIPT_NAME} in the Text editor and run it)")


def bpy_abspath(path: str) -> str:
    """A Blender path ('//' = the .blend's folder) as an absolute path."""
    import bpy

    return bpy.path.abspath(path)


def ensure_oslquery() -> None:
    """Make Blender's bundled ``oslquery`` importable: Cycles needs it to compile a Script node.

    Blender's own Python has it on ``sys.path``; the ``bpy`` module from PyPI keeps it in
    ``<version>/python/lib/python3.x/site-packages`` without adding that folder.
    """
    if importlib.util.find_spec("oslquery") is not None:
        return
    import bpy

    root = bpy.utils.system_resource("PYTHON")
    for site in sorted(glob.glob(os.path.join(root, "lib", "python3*", "site-packages"))):
        if os.path.isdir(os.path.join(site, "oslquery")) and site not in sys.path:
            sys.path.append(site)
    if importlib.util.find_spec("oslquery") is None:
        raise RuntimeError(f"damcap: Blender's oslquery module (which compiles OSL Script nodes) is not under {root}")


def setup_scene(scene) -> None:
    """Cycles on the CPU with Open Shading Language, view transform Standard."""
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.shading_system = True
    scene.view_settings.view_transform = "Standard"


def owned(collection, name: str, *args):
    """The datablock ``name`` in ``collection`` (``bpy.data.texts``, ``.node_groups``, ``.materials``)
    that an earlier run of this script made (tagged ``damcap`` = name), to be refilled; else a new
    one, tagged (Blender adds a suffix to its name when the file already has one of that name: a
    datablock of the user's is never overwritten)."""
    old = next((b for b in collection if b.get("damcap") == name), None)
    if old is not None:
        return old
    block = collection.new(name, *args)
    block["damcap"] = name
    return block


def dam_node_group(name: str, osl_text: str, shader_text_name: str, exposure: float):
    """The node group ``damcap <name>``: Script node (the DAM's linear radiance) -> Emission, its
    strength the group's ``exposure`` input."""
    import bpy

    text = owned(bpy.data.texts, shader_text_name)
    text.from_string(osl_text)
    group = owned(bpy.data.node_groups, f"damcap {name}", "ShaderNodeTree")
    group.nodes.clear()
    group.interface.clear()
    sock = group.interface.new_socket("exposure", in_out="INPUT", socket_type="NodeSocketFloat")
    sock.default_value, sock.min_value = exposure, 0.0
    group.interface.new_socket("Shader", in_out="OUTPUT", socket_type="NodeSocketShader")
    nodes, links = group.nodes, group.links
    inp, out = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    script = nodes.new("ShaderNodeScript")
    script.mode = "INTERNAL"
    script.script = text  # Cycles compiles it here (its outputs appear)
    if "radiance" not in script.outputs:
        import cycles.osl

        cycles.osl.update_script_node(script, lambda kind, msg: print(f"damcap: {msg}"))
    if "radiance" not in script.outputs:
        raise RuntimeError(f"damcap: the OSL shader {text.name} did not compile (Blender's console says why)")
    emission = nodes.new("ShaderNodeEmission")
    links.new(script.outputs["radiance"], emission.inputs["Color"])
    links.new(inp.outputs["exposure"], emission.inputs["Strength"])
    links.new(emission.outputs["Emission"], out.inputs["Shader"])
    inp.location, script.location, emission.location, out.location = (-400, -150), (-400, 100), (-100, 0), (150, 0)
    return group


def dam_material(name: str, group):
    """The material ``name``: the node group into the material output, its ``exposure`` the group's default."""
    import bpy

    mat = owned(bpy.data.materials, name)
    if mat.node_tree is None:  # Blender before 5.0 makes materials without nodes
        mat.use_nodes = True
    tree = mat.node_tree
    tree.nodes.clear()
    node = tree.nodes.new("ShaderNodeGroup")
    node.node_tree = group
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    tree.links.new(node.outputs["Shader"], out.inputs["Surface"])
    node.location, out.location = (-200, 0), (100, 0)
    return mat


def add_mesh(path: str, name: str, materials: list, collection):
    """The mesh ``damcap export`` wrote (an .npz of Blender-frame vertices, triangles, normals and
    each triangle's part) as an object whose slot k holds material k."""
    import bpy
    import numpy as np

    data = np.load(path, allow_pickle=False)
    vertices, triangles = data["vertices"], data["triangles"]
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(vertices))
    mesh.vertices.foreach_set("co", vertices.astype(np.float32).ravel())
    mesh.loops.add(3 * len(triangles))
    mesh.loops.foreach_set("vertex_index", triangles.astype(np.int32).ravel())
    mesh.polygons.add(len(triangles))
    mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * len(triangles), 3, dtype=np.int32))
    mesh.polygons.foreach_set("material_index", data["part"].astype(np.int32))
    mesh.update(calc_edges=True)
    if mesh.validate():  # degenerate triangles (a vertex twice) are dropped, as Blender's importers do
        print(f"damcap: {name}: dropped {len(triangles) - len(mesh.polygons)} degenerate triangle(s)")
    mesh.shade_smooth()
    if "normals" in data:  # the normals damcap renders with
        mesh.normals_split_custom_set_from_vertices([tuple(n) for n in data["normals"].astype(np.float64)])
    for mat in materials:
        mesh.materials.append(mat)
    obj = bpy.data.objects.new(name, mesh)
    collection.objects.link(obj)
    return obj


def main() -> None:
    import bpy

    folder = script_folder(globals().get("__file__"), bpy.data.texts)
    ensure_oslquery()
    scene = bpy.context.scene
    setup_scene(scene)
    made = []
    for m in CONFIG["materials"]:
        with open(os.path.join(folder, m["osl"]), encoding="utf-8") as f:
            group = dam_node_group(m["name"], f.read(), m["osl"], m["exposure"])
        made.append(dam_material(m["name"], group))
    print(f"damcap: {len(made)} material(s) from {folder}: "
          + ", ".join(f"{mat.name} (exposure {m['exposure']:.4g})" for mat, m in zip(made, CONFIG["materials"])))
    print("damcap: scene set to Cycles on the CPU with Open Shading Language (the materials run OSL), view transform Standard")
    mesh = CONFIG.get("mesh")
    if mesh:
        obj = add_mesh(os.path.join(folder, mesh["file"]), mesh["name"], made, bpy.context.collection or scene.collection)
        print(f"damcap: added {obj.name} ({len(obj.data.polygons)} triangles) with material slots "
              + ", ".join(m.name for m in made))


if __name__ == "__main__":
    main()
