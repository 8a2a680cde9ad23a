"""Commands that take appearance out of damcap: export (frames, ONNX, GLSL) and view (HTML)."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, List, Optional

import numpy as np
import typer

from damcap.common.errors import DamcapError

from damcap.cli.app import command, progress_bar
from damcap.cli.options import parse_int
from damcap.cli.paths import Interrupted, Output, Terminated, check_paths, file_out, folder_out, holds, staged_folder

if TYPE_CHECKING:
    from damcap.export.capture_export import CaptureExportOptions
    from damcap.export.turntable import ExportOptions, OrbitOptions
    from damcap.export.viewer import ViewerCamera


def _load_mesh(mesh: Optional[Path]):
    from damcap.common.mesh import Mesh, load_mesh, normalise_to_unit_sphere, vertex_normals_area_weighted

    if mesh is None:
        from damcap.common.shapes import shape_mesh

        s = shape_mesh("sphere")
        v, t = np.asarray(s.vertices, np.float32), np.asarray(s.triangles, np.int32)
        return Mesh(v, t, vertex_normals_area_weighted(v, t).astype(np.float32), np.zeros(len(t), np.int32))
    return normalise_to_unit_sphere(load_mesh(mesh))


@command(opts="damcap.export.turntable:ExportOptions", orbit="damcap.export.turntable:OrbitOptions")
def export(
    models: List[Path] = typer.Argument(..., help="model file(s) (.dam); several = one per mesh part"),
    output: Path = typer.Option(..., "-o", "--output", help="output folder (frames) or file (onnx, glsl)"),
    mesh: Optional[Path] = typer.Option(None, "--mesh", help="OBJ/PLY shape to render the appearance on"),
    labels: Optional[Path] = typer.Option(None, "--labels", help="per-vertex part labels (.npy or .txt), instead of OBJ material groups"),
    *,
    opts: ExportOptions,
    orbit: OrbitOptions,
) -> None:
    """Render a DAM on a new shape, or write it for other tools.

    --format frames: an orbit of linear EXR + sRGB PNG frames (and an MP4 with --video); glb: the
    mesh with the radiance of one view baked per vertex; threejs: three.js ShaderMaterials that
    evaluate the DAMs (one per part, with --mesh the mesh in parts); matcap: the DAM on a sphere for matcap shaders; onnx / glsl: the DAM as an
    ONNX model or a fragment-shader function; blender: an OSL shader per model and a script that
    makes Blender materials of them (and the mesh with them, with --mesh).
    """
    from damcap.appearance.dam_file import load_dam

    opts.validate()
    if opts.format == "onnx":
        target: Output = file_out(output if output.suffix == ".onnx" else output / "model.onnx")  # type: ignore[assignment]
    elif opts.format == "glsl":
        target = file_out(output if output.suffix in (".glsl", ".frag") else output / "dam.glsl")  # type: ignore[assignment]
    elif opts.format == "matcap":
        target = folder_out(output, replaces=holds("matcap.json"))  # type: ignore[assignment]
    elif opts.format == "glb":
        target = file_out(output if output.suffix == ".glb" else output / "model.glb")  # type: ignore[assignment]
    elif opts.format == "threejs":
        target = file_out(output if output.suffix in (".js", ".mjs") else output / "dam_material.js")  # type: ignore[assignment]
    elif opts.format == "blender":
        target = folder_out(output, replaces=holds("damcap_materials.py"))  # type: ignore[assignment]
    else:
        target = folder_out(output, replaces=holds("export.json"))  # type: ignore[assignment]
    check_paths([*models, mesh, labels], [target])
    if opts.format == "threejs":
        _check_parts_given(models, mesh, labels)
    loaded = [load_dam(m) for m in models]
    dams = [m for m, _ in loaded]
    if opts.format != "frames" and any(d.has_surface_factors for d in dams):
        typer.echo(f"note: --format {opts.format} carries the DAM alone; the surface factors of the model's capture (albedo "
                   "texture, normal field) are left out", err=True)
    if opts.format == "onnx":
        if len(dams) != 1:
            raise DamcapError("--format onnx takes one model")
        _export_onnx(dams[0], target.path)
        return
    if opts.format == "glsl":
        from damcap.common.atomic import write_text_atomic
        from damcap.export.glsl import glsl_source

        path = target.path
        write_text_atomic(path, "".join(glsl_source(d, prefix=f"dam{k}" if len(dams) > 1 else "dam") for k, d in enumerate(dams)))
        typer.echo(f"wrote {path}")
        return
    if opts.format == "matcap":
        if len(dams) != 1:
            raise DamcapError("--format matcap takes one model")
        with staged_folder(output, replace=True) as stage:
            _export_matcap(dams[0], loaded[0][1], models[0], stage, orbit)
        typer.echo(f"wrote {output}/matcap.exr (linear), matcap.png (sRGB) and matcap.json ({orbit.resolution} px, seen from "
                   f"elevation {orbit.elevation_deg:g} deg, azimuth {orbit.azimuth0_deg:g} deg)")
        return
    if opts.format == "threejs":
        _export_threejs([d.dam_alone() if d.has_surface_factors else d for d in dams], [meta for _, meta in loaded], models, mesh,
                        labels, target.path, orbit)
        return
    if opts.format == "blender":
        _export_blender([d.dam_alone() if d.has_surface_factors else d for d in dams], [meta for _, meta in loaded], models,
                        mesh, labels, output, orbit)
        return
    if mesh is None:
        raise DamcapError(f"--format {opts.format} needs --mesh SHAPE.obj|ply")
    if opts.format == "glb":
        _export_glb([d.dam_alone() if d.has_surface_factors else d for d in dams], [meta for _, meta in loaded], models,
                    mesh, labels, target.path, orbit, opts.glb_min_triangles)
        return
    with staged_folder(output, replace=True) as stage:  # frames, PNGs, video and export.json move into OUTPUT at the end
        timing = _export_frames(dams, [meta for _, meta in loaded], models, mesh, labels, stage, orbit, opts)
    video = "" if timing is None else (f", turntable.mp4: {timing.duration_s:g} s at {timing.fps} fps"
                                       + (f", the orbit played {timing.turns} times" if timing.turns > 1 else ""))
    typer.echo(f"wrote {orbit.views} frames to {output} (frames/*.exr linear, display/*.png sRGB{video})")


def _export_matcap(dam, meta: dict, model_path: Path, output: Path, orbit: OrbitOptions) -> None:
    from damcap.appearance.coverage import normal_histogram
    from damcap.appearance.dam_file import recorded_normal_histogram, recorded_up
    from damcap.common.atomic import write_json_atomic
    from damcap.common.cameras import orbit_world_from_cam
    from damcap.common.capture_folder import RADIANCE_CHANNELS
    from damcap.common.colour import display_srgb8, exposure_scale_for
    from damcap.common.exr import write_exr, write_png
    from damcap.export.matcap import matcap_normals_world, render_matcap
    from damcap.export.turntable import orbit_up

    orbit.validate()
    up, up_source, _ = orbit_up(orbit.up, [recorded_up(meta)])
    cam = orbit_world_from_cam(1, orbit.distance, orbit.elevation_deg, orbit.azimuth0_deg, up)[0]
    rad, cover = render_matcap(dam, orbit.resolution, cam)
    hist = recorded_normal_histogram(meta)
    shown = None if hist is None else normal_histogram(matcap_normals_world(orbit.resolution, cam)[0], k=len(hist))
    (unobserved,) = _unobserved_normals([model_path], [hist], [shown], "of the matcap's pixels", "matcap.json 'unobserved_normals'")
    scale = exposure_scale_for(rad, cover > 0.5)
    write_exr(output / "matcap.exr", np.concatenate([rad, cover[..., None]], -1), RADIANCE_CHANNELS + ("A",), dtype="float")
    write_png(output / "matcap.png", np.concatenate([display_srgb8(rad, scale), np.round(cover * 255).astype(np.uint8)[..., None]], -1))
    write_json_atomic(output / "matcap.json", {
        "model": str(model_path.resolve()), "resolution": orbit.resolution, "exposure_scale": scale,
        # the one view the matcap is exact for: pixels look back along view_dir_world
        "view_dir_world": cam[:3, 2].tolist(), "world_from_cam": cam.tolist(), "up_world": up.tolist(), "up_source": up_source,
        "projection": "orthographic: pixel (x, y) of the unit disk shows camera-space normal (x, y, sqrt(1 - x^2 - y^2))",
        # the share of the disk's pixels whose normal the model's capture never showed it (None: not recorded)
        "unobserved_normals": unobserved["share"]})


def _first_view_exposure(dams, shape, part, orbit: OrbitOptions, up) -> float:
    """The exposure of ``damcap view``, the GLB and the three.js material: the display key at the
    95th percentile of a 128 px render of the orbit's first view (the export PNGs' rule)."""
    from dataclasses import replace

    from damcap.common.colour import exposure_scale_for
    from damcap.export.turntable import render_orbit

    small = replace(orbit, views=1, resolution=128, supersample=1)
    _, buf, rad = next(render_orbit(dams, shape, part, small, up_world=up))
    return exposure_scale_for(rad, buf.coverage > 0.5)


def _export_glb(dams, metas, model_paths, mesh_path: Path, labels, path: Path, orbit: OrbitOptions, min_triangles: int) -> None:
    from damcap.appearance.coverage import normal_histogram
    from damcap.appearance.dam_file import recorded_normal_histogram, recorded_up
    from damcap.common.atomic import atomic_path
    from damcap.common.cameras import orbit_world_from_cam
    from damcap.common.fingerprint import file_digest
    from damcap.export.gltf import VIEW_DEPENDENCE_NOTE, glb_bytes, gltf_from_world, split_parts, subdivide_midpoint, vertex_radiance
    from damcap.export.turntable import orbit_up, shape_and_parts

    orbit.validate()
    _, shape, part = shape_and_parts(mesh_path, labels, len(dams))
    up, up_source, up_note = orbit_up(orbit.up, [recorded_up(m) for m in metas])
    if up_note:
        typer.echo(f"note: {up_note}", err=True)
    cam = orbit_world_from_cam(1, orbit.distance, orbit.elevation_deg, orbit.azimuth0_deg, up)[0]
    scale = _first_view_exposure(dams, shape, part, orbit, up)
    given = len(shape.triangles)
    while len(shape.triangles) < min_triangles:
        shape, part = subdivide_midpoint(shape, part)
    parts = split_parts(shape, part, len(dams))
    colours = [vertex_radiance(d, p.positions, p.normals, cam[:3, 3]) * scale for d, p in zip(dams, parts)]
    histograms = [recorded_normal_histogram(m) for m in metas]
    unobserved = _unobserved_normals(model_paths, histograms, [None if h is None else normal_histogram(p.normals, k=len(h))
                                                               for h, p in zip(histograms, parts)],
                                     f"of its vertices on {mesh_path.name}", "the GLB's extras 'unobserved_normals'")
    values = np.concatenate([c.ravel() for c in colours])
    clipped = float((values > 1.0).mean()) if values.size else 0.0
    # the file travels: its inputs by base name and content hash, never this machine's paths
    extras = {"damcap": {
        "what": "linear radiance of the DAM(s) seen from the camera 'baked_view', times exposure_scale, clipped to [0, 1], per vertex",
        "view_dependence": VIEW_DEPENDENCE_NOTE,
        "models": [{"file": m.name, "sha256": file_digest(m)} for m in model_paths],
        "mesh": {"file": mesh_path.name, "sha256": file_digest(mesh_path)},
        "labels": None if labels is None else {"file": Path(labels).name, "sha256": file_digest(labels)},
        "exposure_scale": scale, "clipped_fraction": clipped, "up_world": up.tolist(), "up_source": up_source,
        "unobserved_normals": [{**u, "model": Path(m).name} for u, m in zip(unobserved, model_paths)],
        "triangles": {"mesh": given, "baked": len(shape.triangles), "subdivided_to_at_least": min_triangles},
        "view": {"elevation_deg": orbit.elevation_deg, "azimuth_deg": orbit.azimuth0_deg, "distance": orbit.distance,
                 "fov_deg": orbit.fov_deg},
        "world": "the mesh centred and scaled into the unit sphere (as damcap export renders it), turned so that up is +y"}}
    data = glb_bytes(parts, colours, gltf_from_world(up), cam, orbit.fov_deg, extras)
    with atomic_path(path) as staged:
        staged.write_bytes(data)
    typer.echo(f"wrote {path} ({len(shape.triangles)} triangles" + (f", the mesh's {given} subdivided" if len(shape.triangles) > given else "")
               + ", radiance baked for elevation "
               f"{orbit.elevation_deg:g} deg, azimuth {orbit.azimuth0_deg:g} deg; exposure x{scale:.4g}, "
               f"{clipped:.1%} of the colour values clipped at 1)")
    typer.echo(f"note: {VIEW_DEPENDENCE_NOTE}")


def _export_threejs(dams, metas, model_paths, mesh_path: Optional[Path], labels: Optional[Path], path: Path, orbit: OrbitOptions) -> None:
    from damcap.appearance.dam_file import recorded_up
    from damcap.common.atomic import write_text_atomic
    from damcap.export.gltf import gltf_from_world
    from damcap.export.threejs import threejs_module
    from damcap.export.turntable import orbit_up

    orbit.validate()
    up, _, up_note = orbit_up(orbit.up, [recorded_up(m) for m in metas])
    if up_note:
        typer.echo(f"note: {up_note}", err=True)
    shape, part, names = _parts_of_shape(model_paths, mesh_path, labels)
    scale = _first_view_exposure(dams, shape, part, orbit, up)
    gltf_rot = gltf_from_world(up)[:3, :3]
    note = "Models: " + _parts_caption(model_paths, names, mesh_path) + "." if len(dams) > 1 else f"Model: {model_paths[0].name}."
    write_text_atomic(path, threejs_module(dams, scale, gltf_rot.T, note=note, part_names=names,
                                           mesh=shape if mesh_path is not None else None, triangle_part=part, scene_from_world=gltf_rot))
    use = "import { damcapMaterial } from it" if mesh_path is None else \
        "new THREE.Mesh(damcapGeometry(THREE), damcapMaterials(THREE)): " + _parts_caption(model_paths, names, mesh_path)
    typer.echo(f"wrote {path} ({use}; exposure x{scale:.4g} on {mesh_path.name if mesh_path else 'a sphere'} seen from the orbit's first view)")


def _export_blender(dams, metas, model_paths, mesh_path, labels, output: Path, orbit: OrbitOptions) -> None:
    from damcap.appearance.dam_file import recorded_up
    from damcap.export.blender import SCRIPT_NAME, export_blender
    from damcap.export.turntable import orbit_up

    orbit.validate()
    up, up_source, up_note = orbit_up(orbit.up, [recorded_up(m) for m in metas])
    if up_note:
        typer.echo(f"note: {up_note}", err=True)
    with staged_folder(output, replace=True) as stage:
        done = export_blender(dams, model_paths, up, stage, orbit, mesh_path, labels)
    shaders = ", ".join(f"{n}.osl" for n in done["names"])
    mesh = "" if done["mesh"] is None else f", the mesh {done['mesh']} ({done['triangles']} triangles, slot k = model k)"
    typer.echo(f"wrote {output}: {shaders}, {SCRIPT_NAME}{mesh}; up {(np.round(up, 4) + 0.0).tolist()} ({up_source}) turned onto "
               f"Blender's +Z. In Blender run {output / SCRIPT_NAME} (Text editor > Run Script, or blender --python); "
               "the materials render in Cycles on the CPU (Open Shading Language)")


def _export_onnx(dam, path: Path) -> None:
    from damcap.common.atomic import atomic_path
    from damcap.common.optional import require

    ort = require("onnxruntime", "damcap export --format onnx")

    from damcap.export.onnx_export import export_onnx

    with atomic_path(path) as staged:  # a file that fails the check below is never left behind
        export_onnx(dam, staged)
        checked = _check_onnx(ort, dam, staged, path)
    typer.echo(f"wrote {path} (checked against onnxruntime: max relative difference {checked:.1e})")


def _check_onnx(ort, dam, staged: Path, path: Path) -> float:
    import torch

    rng = np.random.default_rng(0)
    v = rng.normal(size=(4096, 3)).astype(np.float32)
    n = rng.normal(size=(4096, 3)).astype(np.float32)
    got = ort.InferenceSession(str(staged), providers=["CPUExecutionProvider"]).run(None, {"view_dir_world": v, "normal_world": n})[0]
    with torch.no_grad():
        want = dam(torch.from_numpy(v), torch.from_numpy(n)).numpy()
    err = float(np.abs(got - want).max() / max(float(np.abs(want).max()), 1e-12))
    if err > 1e-5:
        raise DamcapError(f"{path}: onnxruntime disagrees with damcap by {err:.2e} (relative); the export is wrong")
    return err


def _surface_factors_on_shape(dams, model_paths, mesh_path, vertices):
    """Keep each model's surface factors (spatial factor, normal field) only where the shape is its
    capture's own surface (:data:`.turntable.SURFACE_MIN_SHARE`); say which are dropped and why.
    ``vertices``: the mesh file's own (before the export's centring and scaling)."""
    from damcap.common.mesh import bounding_sphere
    from damcap.export.turntable import SURFACE_MIN_SHARE, surface_share

    if not any(d.has_surface_factors for d in dams):
        return dams, {"capture_from_render": None, "record": None}
    centre, radius = bounding_sphere(vertices)
    kept, record = [], []
    for d, path in zip(dams, model_paths):
        share = surface_share(d, vertices)
        applied = share is not None and share >= SURFACE_MIN_SHARE
        if share is not None and not applied:
            typer.echo(f"note: {path}: its surface factors (albedo texture, normal field of its capture's surface) cover {share:.0%} "
                       f"of {mesh_path.name}, so the DAM alone is drawn; they apply to the capture's own mesh", err=True)
        kept.append(d if applied or share is None else d.dam_alone())
        record.append({"model": str(path), "surface_share": share, "applied": applied,
                       "factors": [k for k, f in (("spatial", d.spatial), ("normal_field", d.normal_field)) if f is not None]})
    return kept, {"capture_from_render": (centre, radius), "record": record}


def _export_frames(dams, metas, model_paths, mesh_path, labels, output, opts, export_opts):
    """Render the orbit into ``output``; returns the video's :class:`.video.TurntableTiming` (None without --video)."""
    from damcap.cli.app import make_bar

    from damcap.common.atomic import atomic_path, write_json_atomic
    from damcap.common.capture_folder import RADIANCE_CHANNELS
    from damcap.common.exr import write_exr, write_png
    from damcap.common.version import package_version
    from damcap.common.colour import display_srgb8, exposure_scale_for
    from damcap.appearance.coverage import normal_histogram
    from damcap.appearance.dam_file import recorded_normal_histogram, recorded_up
    from damcap.export.turntable import orbit_intrinsics, orbit_up, render_orbit, shape_and_parts

    opts.validate()
    views, video, fps = opts.views, export_opts.video, export_opts.fps
    from damcap.common.mesh import unit_sphere_transform

    raw, shape, part = shape_and_parts(mesh_path, labels, len(dams))  # read once: rendered centred and scaled, textured in its own frame
    centre, radius = unit_sphere_transform(raw.vertices)
    centre = [float(x) for x in centre]
    dams, spatial = _surface_factors_on_shape(dams, model_paths, mesh_path, raw.vertices)
    up, up_source, up_note = orbit_up(opts.up, [recorded_up(m) for m in metas])
    if up_note:
        typer.echo(f"note: {up_note}", err=True)
    (output / "frames").mkdir(parents=True, exist_ok=True)
    (output / "display").mkdir(parents=True, exist_ok=True)
    writer, tmp_video, scale, cams = None, None, None, []
    histograms = [recorded_normal_histogram(m) for m in metas]  # each model's training normals (None: not recorded)
    shown = [None if h is None else np.zeros(len(h)) for h in histograms]  # the normals the frames show of each model
    video_ctx = atomic_path(output / "turntable.mp4") if video else None
    timing, held = None, []  # held: the frames of an orbit the video plays more than once
    try:
        if video_ctx is not None:
            from damcap.export.video import H264Writer, turntable_timing

            timing = turntable_timing(views, fps)
            tmp_video = video_ctx.__enter__()
            writer = H264Writer(tmp_video, timing.fps)
        for k, (m, buf, rad) in enumerate(make_bar(views, "export", "frame", render_orbit(dams, shape, part, opts, spatial["capture_from_render"], up))):
            if scale is None:  # one exposure for the whole turntable, from the first frame
                scale = exposure_scale_for(rad, buf.coverage > 0.5)
            write_exr(output / "frames" / f"{k:04d}.exr", np.concatenate([rad, buf.coverage[..., None]], -1), RADIANCE_CHANNELS + ("A",), dtype="float")
            png = display_srgb8(rad, scale)
            write_png(output / "display" / f"{k:04d}.png", png)
            if writer is not None:
                writer.write(png)
                if timing.turns > 1:
                    held.append(png)
            cams.append(m.tolist())
            part_px = np.where((buf.coverage > 0.5) & (buf.triangle_id >= 0), part[np.maximum(buf.triangle_id, 0)], -1)
            for i, counts in enumerate(shown):
                if counts is not None:
                    counts += normal_histogram(buf.normal_world[part_px == i], k=len(counts))
        if writer is not None:
            for _ in range(timing.turns - 1):
                for png in held:
                    writer.write(png)
            writer.close()
            writer = None
            video_ctx.__exit__(None, None, None)
            video_ctx = None
    finally:
        if writer is not None:
            writer.close()
        if video_ctx is not None:
            video_ctx.__exit__(RuntimeError, RuntimeError("aborted"), None)
    unobserved = _unobserved_normals(model_paths, histograms, shown, f"of its pixels on {mesh_path.name}", "export.json 'unobserved_normals'")
    write_json_atomic(output / "export.json", {
        "damcap_package_version": package_version(), "models": [str(p.resolve()) for p in model_paths],
        "mesh": str(mesh_path.resolve()), "labels": str(labels.resolve()) if labels else None,
        "options": asdict(opts), "export_options": asdict(export_opts), "exposure_scale": scale, "colorspace": metas[0].get("colorspace"),
        "world_from_cam": cams, "spatial": spatial["record"],
        "up_world": up.tolist(), "up_source": up_source,  # the orbit's axis: --up, the first model's capture, or +y
        # what reproduces a frame: the mesh file's vertices v are rendered at (v - centre) / radius,
        # seen by pinholes with these intrinsics from world_from_cam
        "mesh_transform": {"centre": centre, "radius": radius,
                           "render_from_mesh": [[1 / radius, 0, 0, -centre[0] / radius], [0, 1 / radius, 0, -centre[1] / radius],
                                                [0, 0, 1 / radius, -centre[2] / radius], [0, 0, 0, 1]]},
        "intrinsics": dict(zip(("fl_x", "fl_y", "cx", "cy", "w", "h"), orbit_intrinsics(opts))),
        # per model: the share of its pixels in these frames whose normal its capture never showed it (None: not recorded)
        "unobserved_normals": unobserved,
        # the MP4 (None without --video): the orbit played `turns` times at `fps`, its index (moov) before its frames
        "video": None if timing is None else {"file": "turntable.mp4", "fps": timing.fps, "turns": timing.turns,
                                              "duration_s": timing.duration_s, "faststart": True},
    })
    return timing


def _unobserved_normals(model_paths, histograms, shown, what: str, record: str) -> list[dict]:
    """Per model, the share of what the export shows of it that faces directions its training
    normals did not observe (:func:`damcap.appearance.coverage.unobserved_share`); warns above
    ``UNOBSERVED_WARNING``.

    Args:
        histograms: per model, its recorded training-normal histogram (None: not recorded).
        shown: per model, the histogram of the normals the export shows of it (same directions).
        what: what was counted, for the warning ("of its pixels on torus.obj").
        record: where the shares are written, for the warning.
    """
    from damcap.appearance.coverage import UNOBSERVED_WARNING, unobserved_share

    out = []
    for path, h, seen in zip(model_paths, histograms, shown):
        share = None if h is None else unobserved_share(h, seen)
        out.append({"model": str(Path(path).resolve()), "share": share})
        if share is not None and share > UNOBSERVED_WARNING:
            typer.echo(f"warning: {path}: {share:.0%} {what} face normals its capture never showed this material at; its appearance "
                       f"there is extrapolated, not measured ({record})", err=True)
    return out


@command(cam="damcap.export.viewer:ViewerCamera")
def view(
    models: List[Path] = typer.Argument(..., help="model file(s) (.dam); several = one per mesh part"),
    output: Path = typer.Option(..., "-o", "--output", help="HTML file to write"),
    mesh: Optional[Path] = typer.Option(None, "--mesh", help="OBJ/PLY shape (default: a sphere)"),
    labels: Optional[Path] = typer.Option(None, "--labels", help="per-vertex part labels (.npy or .txt), instead of OBJ material groups"),
    serve: bool = typer.Option(False, "--serve/--no-serve", help="serve the page (only it) on 127.0.0.1 until Ctrl-C"),
    port: int = typer.Option(8765, parser=parse_int("--port", (0, 65535)), metavar="INTEGER",
                             help="port for --serve: 1-65535, or 0 for any free port"),
    *,
    cam: ViewerCamera,
) -> None:
    """Write an HTML page showing DAMs on a mesh in real time.

    Self-contained, WebGL 2. Several models: one per part of the mesh (its OBJ material groups, or
    --labels), each drawn with its own shader.
    """
    from damcap.appearance.dam_file import load_dam
    from damcap.common.atomic import write_text_atomic
    from damcap.export.turntable import OrbitOptions
    from damcap.export.viewer import viewer_html

    # the page's exposure: the same rule as damcap export's PNGs, on a CPU render of the first view
    opts = OrbitOptions(views=1, elevation_deg=cam.elevation_deg, azimuth0_deg=cam.azimuth_deg, resolution=128, distance=cam.distance,
                        fov_deg=cam.fov_deg)
    opts.validate()
    check_paths([*models, mesh, labels], [file_out(output)])
    _check_parts_given(models, mesh, labels)
    dams = [load_dam(m)[0] for m in models]
    if any(d.has_surface_factors for d in dams):
        typer.echo("note: the viewer draws the DAM alone; the surface factors of the model's capture (albedo texture, normal "
                   "field) are left out", err=True)
        dams = [d.dam_alone() if d.has_surface_factors else d for d in dams]
    shape, part, names = _parts_of_shape(models, mesh, labels)
    scale = _first_view_exposure(dams, shape, part, opts, None)
    html = viewer_html(dams, shape, scale, cam, title=_parts_caption(models, names, mesh), triangle_part=part,
                       part_names=names or [f"part {k}" for k in range(len(models))])
    write_text_atomic(output, html)
    typer.echo(f"wrote {output}" + (f" ({_parts_caption(models, names, mesh)})" if len(models) > 1 else ""))
    if serve:
        from urllib.parse import quote

        from damcap.export.viewer import page_server

        with page_server(html.encode("utf-8"), output.name, port) as httpd:  # this page only, never the folder
            typer.echo(f"serving http://127.0.0.1:{httpd.server_address[1]}/{quote(output.name)} (Ctrl-C to stop)")
            try:
                httpd.serve_forever()
            except KeyboardInterrupt as e:
                raise Interrupted(f"{output} is kept; the server stopped", isinstance(e, Terminated)) from None


def _check_parts_given(models: List[Path], mesh: Optional[Path], labels: Optional[Path]) -> None:
    """Several models need a mesh with parts; labels need a mesh (checked before any file is read)."""
    if labels is not None and mesh is None:
        raise DamcapError(f"{labels}: --labels needs --mesh (the labels are one per vertex of that mesh)")
    if len(models) > 1 and mesh is None:
        raise DamcapError(f"{len(models)} models were given (one per part of a mesh) but no --mesh: give --mesh SHAPE.obj with one OBJ "
                          "material group per model, or --mesh with --labels")


def _parts_of_shape(models: List[Path], mesh: Optional[Path], labels: Optional[Path]):
    """The shape in the unit sphere, each triangle's part (model index) and the parts' names
    (the OBJ's material names; None when unknown). A mesh whose labels or OBJ material groups
    name fewer parts than there are models is refused, as is one naming more (a part without a
    model, :func:`damcap.export.turntable.shape_and_parts`)."""
    from damcap.export.shapes import obj_part_names
    from damcap.export.turntable import shape_and_parts

    if mesh is None:
        shape = _load_mesh(None)
        return shape, np.zeros(len(shape.triangles), np.int64), None
    _, shape, part = shape_and_parts(mesh, labels, len(models))
    found = int(part.max()) + 1 if len(part) else 0
    if len(models) > 1 and found < len(models):
        where = (f"{labels}: its labels name parts 0..{found - 1}" if labels is not None
                 else f"{mesh}: {'its OBJ material groups name' if found > 1 else 'the mesh has no OBJ material groups, so'} {found} part(s)")
        raise DamcapError(f"{where}, but {len(models)} models were given; give one .dam per part"
                          + ("" if labels is not None else " (or --labels)"))
    names = obj_part_names(mesh) if labels is None and len(models) > 1 else None
    return shape, part, names if names is not None and len(names) == len(models) else None


def _parts_caption(models: List[Path], names, mesh: Optional[Path]) -> str:
    """'body: a.dam, lid: b.dam on pot.obj' (one model: 'a.dam on pot.obj')."""
    shape = mesh.name if mesh else "a sphere"
    if len(models) == 1:
        return f"{models[0].name} on {shape}"
    names = names or [f"part {k}" for k in range(len(models))]
    return ", ".join(f"{n}: {m.name}" for n, m in zip(names, models)) + f" on {shape}"


@command("export-capture", opts="damcap.export.capture_export:CaptureExportOptions")
def export_capture_cmd(
    capture: Path = typer.Argument(..., help="capture folder"),
    output: Path = typer.Option(..., "-o", "--output", help="output folder (a new one, or this command's earlier output)"),
    *,
    opts: CaptureExportOptions,
) -> None:
    """The capture for other tools: nerfstudio or COLMAP.

    The capture for other tools: a nerfstudio dataset (PNG frames, masks, transforms.json with
    train/val/test lists, the surface as points.ply) or a COLMAP text model of the undistorted
    capture (sparse/0 + images/, what 3D Gaussian splatting tools start from) with the
    registration's points and their tracks (surface samples without tracks where it has none).
    """
    from damcap.common.capture_folder import read_capture
    from damcap.export.capture_export import export_capture

    opts.validate()
    record = "transforms.json" if opts.format == "nerfstudio" else "sparse/0/images.txt"
    check_paths([capture], [folder_out(output, replaces=holds(record))])
    cap = read_capture(capture)
    bar = progress_bar(len(cap.frames), "export-capture")
    with staged_folder(output, replace=True) as stage:
        summary = export_capture(cap, stage, opts, progress=lambda k, n: bar(k, n, {}))
    if summary["points_source"] == "registration":
        points = (f"{summary['points']} sparse points with their tracks (from {summary['model']}; mean track length "
                  f"{summary['mean_track_length']:.2f}, mean reprojection error {summary['mean_reprojection_error_px']:.2f} px)")
    else:
        points = f"{summary['points']} surface points" + ("" if opts.format == "nerfstudio" else " without tracks (the capture keeps no sparse points with tracks)")
    typer.echo(f"wrote {summary['frames']} frames and {points} to {output} as a {opts.format} "
               f"{'dataset' if opts.format == 'nerfstudio' else 'model'} (one display exposure for all frames: x{summary['exposure_scale']:.4g})")
