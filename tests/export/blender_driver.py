"""Runs inside Blender's Python (the bpy module of .venv-blender), started by test_blender.py.

Usage: python blender_driver.py JOBS.json. Each job: reset the scene, run an export's
damcap_materials.py, then render with Cycles (CPU, OSL, no denoiser; by default 1 sample and a box
filter of width 0.01 px: each pixel is its centre ray's radiance; a job may set "samples" and
"filter_width") either a sphere of radius 1 at the origin (an
exact sphere: a one-point point cloud) carrying one of the materials, or the mesh the script
added. bpy is imported inside the functions (pytest collects this file). Writes per job the linear RGBA pixels (top row first) as .npy and a JSON report of the
camera, the render time and the materials and objects the script made.
"""

from __future__ import annotations

import json
import runpy
import sys
import time

import numpy as np


def sphere_object(material):
    """An exact sphere (radius 1 at the origin): a point cloud of one point, made by geometry nodes."""
    import bpy

    obj = bpy.data.objects.new("sphere", bpy.data.meshes.new("empty"))
    bpy.context.scene.collection.objects.link(obj)
    tree = bpy.data.node_groups.new("one point", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    points = tree.nodes.new("GeometryNodePoints")
    points.inputs["Count"].default_value = 1
    points.inputs["Radius"].default_value = 1.0
    setmat = tree.nodes.new("GeometryNodeSetMaterial")
    setmat.inputs["Material"].default_value = material
    out = tree.nodes.new("NodeGroupOutput")
    tree.links.new(points.outputs["Points"], setmat.inputs["Geometry"])
    tree.links.new(setmat.outputs["Geometry"], out.inputs[0])
    obj.modifiers.new("one point", "NODES").node_group = tree
    return obj


def camera(spec: dict):
    import bpy
    from mathutils import Vector

    cam = bpy.data.cameras.new("camera")
    cam.lens, cam.sensor_width, cam.sensor_fit = spec["lens_mm"], 36.0, "HORIZONTAL"
    obj = bpy.data.objects.new("camera", cam)
    bpy.context.scene.collection.objects.link(obj)
    obj.location = Vector(spec["location"])
    obj.rotation_euler = (Vector(spec["target"]) - obj.location).to_track_quat("-Z", "Y").to_euler()
    bpy.context.scene.camera = obj
    bpy.context.view_layer.update()
    return obj


def run(job: dict) -> dict:
    import bpy
    from mathutils import Matrix

    bpy.ops.wm.read_factory_settings(use_empty=True)
    if job.get("user_material"):  # a material of the user's that happens to have a model's name
        bpy.data.materials.new(job["user_material"])["mine"] = 1
    for _ in range(job.get("runs", 1)):  # a second run refills what the first made
        runpy.run_path(job["script"], run_name="__main__")
    scene = bpy.context.scene
    report = {"engine": scene.render.engine, "device": scene.cycles.device, "osl": bool(scene.cycles.shading_system),
              "view_transform": scene.view_settings.view_transform,
              "materials": {m.name: [n.node_tree.name for n in m.node_tree.nodes if n.type == "GROUP"] for m in bpy.data.materials},
              "user_materials": [m.name for m in bpy.data.materials if m.get("mine") and len(m.node_tree.nodes) <= 2],
              "texts": sorted(t.name for t in bpy.data.texts),
              "groups": {g.name: {"exposure": g.interface.items_tree["exposure"].default_value,
                                  "script_outputs": [s.name for n in g.nodes if n.type == "SCRIPT" for s in n.outputs]}
                         for g in bpy.data.node_groups if g.bl_idname == "ShaderNodeTree"},
              "objects": {o.name: {"slots": [s.material.name for s in o.material_slots],
                                   "material_index": np.bincount([p.material_index for p in o.data.polygons],
                                                                 minlength=len(o.material_slots)).tolist(),
                                   "vertices": [list(v.co) for v in o.data.vertices][:4]}
                          for o in scene.objects if o.type == "MESH"}}
    if job.get("sphere_material"):
        sphere_object(bpy.data.materials[job["sphere_material"]])
    if job.get("exposure") is not None:
        for g in bpy.data.node_groups:
            if g.bl_idname == "ShaderNodeTree" and "exposure" in g.interface.items_tree:
                g.interface.items_tree["exposure"].default_value = job["exposure"]
        for m in bpy.data.materials:  # the group node's own input (the material's exposure)
            for n in m.node_tree.nodes:
                if n.type == "GROUP":
                    n.inputs["exposure"].default_value = job["exposure"]
    cam = camera(job["camera"])
    scene.cycles.samples = job.get("samples", 1)
    scene.cycles.use_denoising = False
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = job.get("filter_width", 0.01)
    scene.cycles.max_bounces = 0
    scene.render.resolution_x = scene.render.resolution_y = job["resolution"]
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = True
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = job["out"] + ".exr"
    t0 = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    report["render_s"] = time.perf_counter() - t0
    img = bpy.data.images.load(job["out"] + ".exr")
    n = job["resolution"]
    np.save(job["out"] + ".npy", np.array(img.pixels[:], np.float32).reshape(n, n, 4)[::-1])
    report["world_from_cam"] = [list(r) for r in Matrix(cam.matrix_world)]
    return report


def main() -> None:
    jobs = json.loads(open(sys.argv[-1]).read())
    reports = [run(job) for job in jobs]
    with open(sys.argv[-1] + ".out.json", "w") as f:
        json.dump(reports, f)


if __name__ == "__main__":
    main()
