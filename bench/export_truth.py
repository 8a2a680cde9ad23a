"""Benchmark: the demo's export against the truth (issue 29).

``make demo`` exports the three materials it segments from the bundled studio photos
(``samples/photos_studio``) onto a new shape (one model per part of the mesh: its OBJ material
groups, as the demo's pot, or ``--labels``; the report's run: a torus). Those photos were path traced from known materials,
light and cameras (``transforms.json``'s ``damcap_studio`` record), so the truth of that export can
be rendered: the same shape, posed as the export posed it, each part made of the studio material
its segment covers in the photos, under the same environment map and board, by Mitsuba
(:func:`damcap.synth.studio.render_on_shape`). Per material region: DSSIM of the export's frames
against the truth next to a constant-colour baseline (the region painted with its mean truth
colour over all frames), each scored on its region alone (elsewhere both images are the truth).
Target (issue 29): the export at most 0.5x the baseline.

What a DAM can reach at all: per region, a DAM of the export's own architecture fitted to the
truth frames themselves (:func:`best_dam_on_truth`, in-sample, so an optimistic bound). Whatever
it misses (self-shadowing, the board's reflection, anything not a function of view and normal) no
DAM carried from the photos can recover; a ratio above the target there means the target lies
beyond the model, not beyond the capture.

What a DAM of the photographed object can carry to the new shape (``--transfer-bound``): per
material, a DAM fitted to path-traced HDR renders of the studio's own object from every photo's
true camera, with its exact normals and material labels (:func:`object_dams`: no clipping, no
JPEG, no reconstruction or segmentation error), drawn on the shape. It is a reference, not a
strict bound: it is one fit (``fit``'s 2000 steps, nothing held out), and another fit of the
same data may extrapolate differently to the shape's normals that no photo saw. Where it misses
the target, the photos do not carry the shape's appearance (the board beside the object,
occlusion that differs between the two shapes, normals no camera saw). It is fitted twice: to
every photo's render, and to the renders of the photos the capture trained on alone (the views
the export learnt from; the others are the demo's novel views).

How the frames are matched:
- the capture's world is a similarity of the studio's (``damcap reconstruct`` registered the photos
  itself and normalised the result); it is estimated from the camera centres (Umeyama) and
  reported with its residuals;
- a segment's material is the studio material most of its pixels show in the training photos
  (the studio object ray cast from each photo's camera mapped into the studio world), reported
  with its purity;
- truth radiance is in the capture's units (:func:`damcap.synth.studio.capture_radiance_scale`).

Run (from the repository root)::

    make demo DEMO_OUT=demo_out
    .venv/bin/python -m bench.export_truth --demo demo_out --transfer-bound

(``make export-truth`` runs both.) It writes bench/results/export_truth.json, bench/export_truth.md and bench/export_truth.png.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import statistics
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
from damcap.appearance.coverage import observed_at
from damcap.appearance.dam_file import load_dam, recorded_normal_histogram
from damcap.appearance.fit import FitOptions, fit_dam
from damcap.appearance.metrics import dssim
from damcap.appearance.pixels import gather_samples
from damcap.common.atomic import atomic_path
from damcap.common.capture_folder import FrameData, Intrinsics, read_capture
from damcap.common.exr import read_exr, write_png
from damcap.common.colour import display_srgb8, exposure_scale_for
from damcap.common.mesh import Mesh
from damcap.common.raycast import MeshRaycaster, SurfaceBuffers
from damcap.export.turntable import shade_buffers, shape_and_parts
from damcap.reconstruct.normalize import similarity_scale, umeyama_similarity
from damcap.synth.studio import StudioOptions, capture_radiance_scale, render_on_shape, studio_object

from bench.common import BENCH, CACHE, RESULTS, command_line, log, machine_info

INTERIOR = 0.99
"""a pixel belongs to a region when its coverage in both images is above this (no silhouette mixing)"""
TARGET_RATIO = 0.5


def studio_from_capture(capture_c2w: np.ndarray, studio_c2w: np.ndarray) -> tuple[np.ndarray, dict]:
    """The similarity taking capture-world points to the studio world, from matched cameras.

    Args:
        capture_c2w: (N, 4, 4) cameras in the capture's world.
        studio_c2w: (N, 4, 4) the same photos' ground-truth cameras.

    Returns:
        (4, 4) studio_from_capture ``[s R | t]`` and its residuals: camera centres (RMS, in studio
        units) and camera orientations (median and largest angle, degrees).
    """
    t = umeyama_similarity(capture_c2w[:, :3, 3], studio_c2w[:, :3, 3])
    s = similarity_scale(t)
    rot = t[:3, :3] / s
    centres = capture_c2w[:, :3, 3] @ t[:3, :3].T + t[:3, 3]
    angles = []
    for a, b in zip(capture_c2w, studio_c2w):
        r = (rot @ a[:3, :3]).T @ b[:3, :3]
        angles.append(float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))))
    return t, {"scale": s, "centre_rms": float(np.sqrt(((centres - studio_c2w[:, :3, 3]) ** 2).sum(1).mean())),
               "rotation_median_deg": float(np.median(angles)), "rotation_max_deg": float(np.max(angles))}


def camera_to_studio(c2w: np.ndarray, studio_from_capture: np.ndarray, move_centre: bool = True) -> np.ndarray:
    """A capture-world camera (OpenGL axes) in the studio world: turned by the similarity's
    rotation; its centre mapped by the similarity (``move_centre``) or only turned (a camera of
    the export, whose unit-sphere frame differs from the capture's by the rotation alone)."""
    rot = studio_from_capture[:3, :3] / similarity_scale(studio_from_capture)
    out = np.eye(4)
    out[:3, :3] = rot @ c2w[:3, :3]
    out[:3, 3] = studio_from_capture[:3, :3] @ c2w[:3, 3] + studio_from_capture[:3, 3] if move_centre else rot @ c2w[:3, 3]
    return out


def segment_materials(demo: Path, studio_from_capture: np.ndarray, opts: StudioOptions) -> tuple[list[int], np.ndarray]:
    """Each segment's studio material: (material index per segment, confusion counts (segments, materials))."""
    cap = read_capture(demo / "capture")
    mesh, normals, face_label = studio_object(opts)
    caster = MeshRaycaster(replace(mesh, vertex_normals=normals))
    counts = None
    for f in cap.split("train"):
        weights_file = demo / "segmentation" / "weights" / (Path(f.file_path).stem + ".exr")
        if not weights_file.is_file():
            continue
        w, _ = read_exr(weights_file)
        if counts is None:
            counts = np.zeros((w.shape[2], len(opts.material_names())), np.int64)
        i = f.intrinsics
        b = caster.buffers(camera_to_studio(f.world_from_cam, studio_from_capture), i.fl_x, i.fl_y, i.cx, i.cy, i.w, i.h, supersample=1)
        hit = b.triangle_id >= 0
        np.add.at(counts, (w.argmax(2)[hit], face_label[b.triangle_id[hit]]), 1)
    if counts is None:
        raise SystemExit(f"{demo / 'segmentation'}: no weights/*.exr for the capture's training frames")
    return [int(k) for k in counts.argmax(1)], counts


def model_segments(models: list[str]) -> list[int]:
    """The segment each exported model is (``.../segmentation/material_K.dam`` is segment K), in the export's part order."""
    out = []
    for m in models:
        found = re.fullmatch(r"material_(\d+)", Path(m).stem)
        if found is None:
            raise SystemExit(f"{m}: the export's models must be the segmentation's material_K.dam files, one per part")
        out.append(int(found.group(1)))
    return out


def region_scores(truth: np.ndarray, pred: np.ndarray, mask: np.ndarray, constant: np.ndarray) -> tuple[float, float] | None:
    """(DSSIM of ``pred``, DSSIM of the constant colour) against ``truth`` on ``mask`` alone (elsewhere both are the truth)."""
    if mask.sum() < 50:
        return None
    p = np.where(mask[..., None], pred, truth)
    c = np.where(mask[..., None], constant[None, None, :], truth)
    a, b = dssim(truth, p, mask.astype(np.float32)), dssim(truth, c, mask.astype(np.float32))
    return (a, b) if a is not None and b is not None else None


def best_dam_on_truth(radiance_lin: list[np.ndarray], masks: list[np.ndarray], buffers: list[SurfaceBuffers],
                      camera_centres_world: list[np.ndarray], arch: DamArchitecture, steps: int = 2000, seed: int = 0) -> DeepAppearanceMap | None:
    """A DAM fitted to the truth frames' pixels on their region (every frame, none held out).

    Args:
        radiance_lin: per frame (H, W, 3) truth radiance.
        masks: per frame (H, W) bool, the region's pixels.
        buffers: per frame, the ray-cast surface (normal_world, position_world).
        camera_centres_world: per frame (3,).
        arch: the DAM's architecture (the export's, so the bound is of the same model).
        steps: optimiser steps (2000, ``damcap fit``'s default).
        seed: the fit's seed.

    Returns:
        the fitted DAM, or None when no frame has a pixel of the region.
    """
    if not any(m.any() for m in masks):
        return None
    samples = gather_samples([FrameData(np.asarray(rad, np.float32), b.normal_world, b.position_world, m.astype(np.float32))
                              for rad, m, b in zip(radiance_lin, masks, buffers, strict=True)], camera_centres_world)
    opts = FitOptions(steps=steps, width=arch.width, depth=arch.depth, activation=arch.activation, encoding=arch.encoding,
                      separable=arch.separable, holdout_views=0, checkpoint_every=0, seed=seed)
    return fit_dam(samples, opts).model


def rendered_on_shape(opts: StudioOptions, mesh: Mesh, face_material: np.ndarray, world_from_cam: np.ndarray, intr: Intrinsics,
                      spp: int, seed: int | None = None, cache: Path | None = CACHE / "export_truth") -> tuple[np.ndarray, np.ndarray, bool]:
    """:func:`damcap.synth.studio.render_on_shape`, kept in ``cache`` under the SHA-256 of
    everything it depends on (options, mesh, materials, cameras, pinhole, spp, seed), so a rerun
    on another export of the same shape and cameras renders nothing (None: no cache). Returns
    (radiance, alpha, whether they came from the cache)."""
    h = hashlib.sha256(json.dumps([asdict(opts), asdict(intr), spp, seed]).encode())
    for a in (mesh.vertices, mesh.triangles, face_material, world_from_cam):
        h.update(np.ascontiguousarray(a).tobytes())
    path = cache / f"{h.hexdigest()[:24]}.npz" if cache is not None else None
    if path is not None and path.is_file():
        z = np.load(path)
        return z["radiance"], z["alpha"], True
    radiance, alpha = render_on_shape(opts, mesh, face_material, world_from_cam, intr, spp=spp, seed=seed)
    if path is not None:
        with atomic_path(path) as tmp:
            np.savez(tmp, radiance=radiance, alpha=alpha)
    return radiance, alpha, False


def object_dams(opts: StudioOptions, record: dict, world_from_cam: np.ndarray, intr: Intrinsics, arch: DamArchitecture,
                spp: int, cache: Path | None = None, photos: np.ndarray | None = None) -> list[DeepAppearanceMap | None]:
    """Per studio material, a DAM fitted to HDR renders of the studio's object (:func:`best_dam_on_truth`).

    Args:
        opts, record: the studio set (``transforms.json``'s ``damcap_studio``).
        world_from_cam: (N, 4, 4) the photos' true cameras, studio world, OpenGL axes.
        intr: the photos' pinhole.
        arch: the DAMs' architecture.
        spp: path-tracing samples per pixel.
        cache: the render cache (:func:`rendered_on_shape`); every camera is rendered (and cached)
            whatever ``photos`` picks.
        photos: (N,) bool, the cameras whose renders the DAMs are fitted to (None: all).

    Returns:
        one DAM per material of the set (studio axes), None for a material no render shows.
    """
    mesh, normals, face = studio_object(opts)
    radiance, alpha, _ = rendered_on_shape(opts, mesh, face, world_from_cam, intr, spp, cache=cache)
    if photos is not None:
        radiance, alpha, world_from_cam = radiance[photos], alpha[photos], world_from_cam[photos]
    radiance = radiance * capture_radiance_scale(record)
    caster = MeshRaycaster(replace(mesh, vertex_normals=normals))
    bufs = [caster.buffers(m, intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h, supersample=1) for m in world_from_cam]
    labels = [np.where(b.triangle_id >= 0, face[np.maximum(b.triangle_id, 0)], -1) for b in bufs]
    return [best_dam_on_truth(list(radiance), [(lab == k) & (a > INTERIOR) for lab, a in zip(labels, alpha)], bufs,
                              [m[:3, 3] for m in world_from_cam], arch) for k in range(len(opts.material_names()))]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--demo", type=Path, required=True, help="make demo's output folder (DEMO_OUT)")
    ap.add_argument("--photos", type=Path, default=Path("samples/photos_studio"), help="the studio photo set the demo ran on")
    ap.add_argument("--spp", type=int, default=256, help="samples per pixel of the truth")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--render-cache", type=Path, default=CACHE / "export_truth",
                    help="folder of path-traced renders kept between runs (rendered_on_shape)")
    ap.add_argument("--transfer-bound", action="store_true",
                    help="also fit DAMs to HDR renders of the photographed object itself and draw them on the new shape (object_dams)")
    args = ap.parse_args(argv)
    t_start = time.perf_counter()
    studio = json.loads((args.photos / "transforms.json").read_text())
    record = studio["damcap_studio"]
    opts = StudioOptions(**record["options"])
    names = opts.material_names()
    gt = {Path(fr["file_path"]).name: np.array(fr["transform_matrix"], np.float64) for fr in studio["frames"]}
    cap_json = json.loads((args.demo / "capture" / "transforms.json").read_text())
    pairs = [(np.array(fr["transform_matrix"], np.float64), gt[fr["photo"]]) for fr in cap_json["frames"] if fr.get("photo") in gt]
    sim, residual = studio_from_capture(np.stack([a for a, _ in pairs]), np.stack([b for _, b in pairs]))
    log(f"capture -> studio: {len(pairs)} cameras, centre RMS {residual['centre_rms']:.4f}, rotation median {residual['rotation_median_deg']:.3f} deg")
    export = json.loads((args.demo / "export" / "export.json").read_text())
    _, shape, part = shape_and_parts(export["mesh"], Path(export["labels"]) if export["labels"] else None, len(export["models"]))
    if export["labels"] or len(export["models"]) > 1:  # parts by labels or by the mesh's OBJ groups: part k shows models[k]
        seg_material, confusion = segment_materials(args.demo, sim, opts)
        part_segment = model_segments(export["models"])
        seg_material, confusion = [seg_material[j] for j in part_segment], confusion[part_segment]
    elif len(names) == 1:  # one DAM of a one-material set
        seg_material, confusion, part_segment = [0], np.ones((1, 1), np.int64), [0]
    else:
        raise SystemExit(f"{args.demo / 'export'}: an export of one model of a {len(names)}-material set; export the segmentation's "
                         "materials, one per part of the mesh (its OBJ groups or --labels)")
    region = [f"segment {j}" for j in part_segment]  # part k's region is named after the segment its model is
    purity = (confusion.max(1) / np.maximum(confusion.sum(1), 1)).tolist()
    log("segments: " + ", ".join(f"{region[k]} (part {k}) -> {names[m]} ({p:.0%})" for k, (m, p) in enumerate(zip(seg_material, purity))))
    i = export["intrinsics"]
    intr = Intrinsics(i["fl_x"], i["fl_y"], i["cx"], i["cy"], int(i["w"]), int(i["h"]))
    cams = np.array(export["world_from_cam"], np.float64)
    rot = sim[:3, :3] / similarity_scale(sim)
    torus_studio = Mesh(shape.vertices @ rot.T, shape.triangles)  # same size (unit sphere), turned into the studio's axes
    cams_studio = np.stack([camera_to_studio(m, sim, move_centre=False) for m in cams])
    t = time.perf_counter()
    truth, truth_alpha, truth_cached = rendered_on_shape(opts, torus_studio, np.array(seg_material)[part], cams_studio, intr, args.spp, cache=args.render_cache)
    truth = truth * capture_radiance_scale(record)
    truth_s = time.perf_counter() - t
    again, _, _ = rendered_on_shape(opts, torus_studio, np.array(seg_material)[part], cams_studio, intr, args.spp, seed=opts.seed + 1, cache=args.render_cache)
    again = again * capture_radiance_scale(record)
    caster = MeshRaycaster(shape)
    frames, buffers = [], []
    for k, m in enumerate(cams):
        px, _ = read_exr(args.demo / "export" / "frames" / f"{k:04d}.exr")
        b = caster.buffers(m, intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h, supersample=1)
        part_px = np.where(b.triangle_id >= 0, part[np.maximum(b.triangle_id, 0)], -1)
        frames.append((px[..., :3], px[..., 3], part_px))
        buffers.append(b)
    region_masks = {seg: [(fp == seg) & (a > INTERIOR) & (truth_alpha[k] > INTERIOR) for k, (_, a, fp) in enumerate(frames)]
                    for seg in range(len(export["models"]))}
    # the best a DAM of the export's architecture can do on these frames: fitted to the truth itself
    t = time.perf_counter()
    export_models = [load_dam(p) for p in export["models"]]  # (model, metadata) each
    first_export_dam = export_models[0][0]
    arch = first_export_dam.arch
    best = [best_dam_on_truth(list(truth), region_masks[seg], buffers, [m[:3, 3] for m in cams], arch) for seg in range(len(export["models"]))]
    any_dam = next((d for d in best if d is not None), first_export_dam)  # draws regions no frame shows (never scored)
    best_frames = [shade_buffers([d if d is not None else any_dam for d in best], b, m[:3, 3], part) for b, m in zip(buffers, cams)]
    best_s = time.perf_counter() - t
    transfer_frames, transfer_s = {}, None  # "object_dam": from every photo; "object_dam_train": from the capture's train photos
    train_names = {fr.get("photo") for fr in cap_json["frames"] if fr["file_path"] in set(cap_json["train_filenames"])}
    train_photos = np.array([name in train_names for name in gt])
    if args.transfer_bound:
        t = time.perf_counter()
        photo_intr = Intrinsics(*(studio[k] for k in ("fl_x", "fl_y", "cx", "cy")), int(studio["w"]), int(studio["h"]))
        caster_studio = MeshRaycaster(replace(torus_studio, vertex_normals=shape.vertex_normals @ rot.T))  # the export's normals, turned
        studio_buffers = [caster_studio.buffers(c, intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h, supersample=1) for c in cams_studio]
        for key, photos in (("object_dam", None), ("object_dam_train", train_photos)):
            by_material = object_dams(opts, record, np.stack(list(gt.values())), photo_intr, arch, args.spp, args.render_cache, photos)
            dams = [by_material[m] if by_material[m] is not None else any_dam for m in seg_material]
            transfer_frames[key] = [shade_buffers(dams, b, c[:3, 3], part) for b, c in zip(studio_buffers, cams_studio)]
        transfer_s = time.perf_counter() - t
    constants = {}
    for seg in range(len(export["models"])):
        vals = [truth[k][m] for k, m in enumerate(region_masks[seg])]
        vals = [v for v in vals if len(v)]
        constants[seg] = np.concatenate(vals).mean(0) if vals else np.zeros(3, np.float32)
    per_region = {}
    for seg in range(len(export["models"])):
        # the region's pixels whose normal the segment's capture did not show it at (damcap export's unobserved_normals)
        hist = recorded_normal_histogram(export_models[seg][1])
        observed = None if hist is None else [observed_at(hist, b.normal_world) for b in buffers]
        abs_err = {True: [], False: []}  # mean |export - truth| over RGB per pixel: observed, unobserved
        ours, base, floor, bound = [], [], [], []
        transfer: dict[str, list[float]] = {key: [] for key in transfer_frames}
        sums = {"truth": 0.0, "export": 0.0, **{key: 0.0 for key in transfer_frames}}  # summed radiance on the scored pixels
        for k, (rad, a, fp) in enumerate(frames):
            mask = region_masks[seg][k]
            r = region_scores(truth[k], rad, mask, constants[seg])
            if r is not None:
                sums["truth"] += float(truth[k][mask].sum())
                sums["export"] += float(rad[mask].sum())
                ours.append(r[0])
                base.append(r[1])
                floor.append(region_scores(truth[k], again[k], mask, constants[seg])[0])
                bound.append(region_scores(truth[k], best_frames[k], mask, constants[seg])[0])
                for key, tf in transfer_frames.items():
                    sums[key] += float(tf[k][mask].sum())
                    transfer[key].append(region_scores(truth[k], tf[k], mask, constants[seg])[0])
                if observed is not None:
                    err = np.abs(rad - truth[k]).mean(-1)
                    for flag in (True, False):
                        abs_err[flag].append(err[mask & (observed[k] == flag)])
        per_region[region[seg]] = {"material": names[seg_material[seg]], "purity": purity[seg], "frames": len(ours),
                                        "export": statistics.mean(ours) if ours else None, "constant": statistics.mean(base) if base else None,
                                        "noise_floor": statistics.mean(floor) if floor else None,
                                        "best_dam": statistics.mean(bound) if bound else None,
                                        **{key: statistics.mean(v) if v else None for key, v in transfer.items()}}
        if ours:
            per_region[region[seg]]["brightness"] = sums["export"] / sums["truth"]
            if observed is not None:
                e_obs, e_not = np.concatenate(abs_err[True]), np.concatenate(abs_err[False])
                per_region[region[seg]]["unobserved_share"] = len(e_not) / max(len(e_obs) + len(e_not), 1)
                per_region[region[seg]]["abs_error_observed"] = float(e_obs.mean()) if len(e_obs) else None
                per_region[region[seg]]["abs_error_unobserved"] = float(e_not.mean()) if len(e_not) else None
            per_region[region[seg]]["ratio"] = statistics.mean(ours) / statistics.mean(base)
            per_region[region[seg]]["best_dam_ratio"] = statistics.mean(bound) / statistics.mean(base)
            for key, v in transfer.items():
                per_region[region[seg]][f"{key}_ratio"] = statistics.mean(v) / statistics.mean(base)
                per_region[region[seg]][f"{key}_brightness"] = sums[key] / sums["truth"]
    whole = [dssim(truth[k], np.where((truth_alpha[k] > INTERIOR)[..., None] & (a > INTERIOR)[..., None], rad, truth[k]),
                   ((truth_alpha[k] > INTERIOR) & (a > INTERIOR)).astype(np.float32)) for k, (rad, a, _) in enumerate(frames)]
    # side by side for one frame: truth | export | constant colours (one display exposure)
    k = 0
    rad, a, fp = frames[k]
    flat = truth[k].copy()
    for seg, c in constants.items():
        flat[(fp == seg) & (a > INTERIOR)] = c
    scale = exposure_scale_for(truth[k], truth_alpha[k] > 0.5)
    out_png = (args.out or BENCH) / "export_truth.png"
    write_png(out_png, display_srgb8(np.concatenate([truth[k], np.where(a[..., None] > 0.5, rad, truth[k]), flat], 1), scale))
    res = {"command": command_line("export_truth", argv if argv is not None else __import__("sys").argv[1:]),
           "machine": machine_info(), "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
           "demo": str(args.demo), "photos": str(args.photos), "spp": args.spp, "frames": len(frames), "resolution": intr.w,
           "capture_to_studio": residual, "segment_material": [names[m] for m in seg_material], "part_segment": part_segment, "confusion": confusion.tolist(),
           "per_region": per_region, "whole_object_export_dssim": float(np.mean([w for w in whole if w is not None])),
           "truth_seconds": truth_s, "truth_cached": truth_cached, "best_dam_seconds": best_s, "object_dam_seconds": transfer_s,
           "object_dam_train_photos": int(train_photos.sum()), "best_dam_arch": asdict(arch), "seconds": time.perf_counter() - t_start, "target_ratio": TARGET_RATIO}
    out_json = (args.out or RESULTS) / "export_truth.json"
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(res, indent=1, default=float))
    write_markdown(res, (args.out or BENCH) / "export_truth.md")
    log(f"wrote {out_json}")
    return 0


def write_markdown(res: dict, path: Path) -> None:
    r = res["capture_to_studio"]
    lines = ["# The demo's export against the truth (issue 29)", "",
             f"Command (from the repository root): `{res['command']}` (after `make demo DEMO_OUT={res['demo']}`)", "",
             f"Machine: {res['machine']['cpu_model']} ({res['machine']['nproc']} cores); {res['date']}. Truth: Mitsuba, "
             f"{res['spp']} spp, {res['frames']} frames of {res['resolution']} px, "
             + ("read from the render cache (bench/.cache/export_truth)" if res.get("truth_cached") else f"rendered in {res['truth_seconds']:.0f} s")
             + "; the whole "
             f"bench took {res['seconds']:.0f} s.", "",
             f"The capture's world against the studio's: camera centres {r['centre_rms']:.4f} RMS "
             f"(studio units, object radius 1), orientations {r['rotation_median_deg']:.3f} deg median, {r['rotation_max_deg']:.3f} deg at most.", "",
             "DSSIM against the truth on each material region of the new shape (interior pixels; elsewhere both images are the truth), "
             "mean over the frames. Constant colour: the region painted with its mean truth colour. Target: export at most "
             f"{res['target_ratio']}x the constant colour.", "",
             "Noise floor: a second truth render with another seed against the first (what path-tracing noise alone costs).", "",
             "Best DAM: a DAM of the export's architecture fitted to these truth frames themselves, on the region, every frame "
             f"(in-sample: an optimistic bound on what any DAM can reach here; fitted in {res['best_dam_seconds']:.0f} s).", ""]
    transfer = res.get("object_dam_seconds") is not None
    if transfer:
        lines += ["Object's DAM: per material, a DAM fitted to path-traced HDR renders of the photographed object itself from every "
                  "photo's true camera, with its exact normals and material labels (no clipping, no JPEG, no reconstruction or "
                  "segmentation error), fitted as `fit` fits (2000 steps, nothing held out) and drawn on the new shape: what a DAM of the "
                  "object carries to this shape (a reference, not a strict bound). *Train photos*: the "
                  f"same from the {res['object_dam_train_photos']} photos the demo trained on, the information the export had "
                  f"(both {res['object_dam_seconds']:.0f} s).", ""]
    lines += ["Brightness: the region's radiance summed over its scored pixels, drawn over the truth's (1: as bright on the whole).", ""]
    keys = ("object_dam", "object_dam_train") if transfer else ()
    lines += ["| segment | its material (purity in the photos) | frames | export | constant colour | ratio | brightness | noise floor | best DAM | its ratio |"
              + (" object's DAM | its ratio | its brightness | train photos: object's DAM | its ratio | its brightness |" if transfer else ""),
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|" + "---:|---:|---:|" * len(keys)]
    for name, d in res["per_region"].items():
        if d["export"] is None:
            lines.append(f"| {name} | {d['material']} ({d['purity']:.0%}) | 0 | | | | | | | |" + " | | |" * len(keys))
            continue
        lines.append(f"| {name} | {d['material']} ({d['purity']:.0%}) | {d['frames']} | {d['export']:.4f} | {d['constant']:.4f} | "
                     f"x{d['ratio']:.2f} | {d['brightness']:.2f} | {d['noise_floor']:.4f} | {d['best_dam']:.4f} | x{d['best_dam_ratio']:.2f} |"
                     + "".join(f" {d[k]:.4f} | x{d[k + '_ratio']:.2f} | {d[k + '_brightness']:.2f} |" for k in keys))
    rows = [(name, d) for name, d in res["per_region"].items() if d.get("unobserved_share") is not None]
    if rows:
        lines += ["", "Normals the capture did not show: the share of each region's scored pixels whose normal falls in a direction "
                  "the segment's training pixels did not show that material at (`damcap export`'s *unobserved_normals*, "
                  "appearance/coverage.py), and the export's mean absolute error against the truth (linear radiance, mean over RGB) "
                  "on those pixels and on the others.", "",
                  "| segment | its material | unobserved | mean abs error: observed | unobserved | ratio |", "|---|---|---:|---:|---:|---:|"]
        for name, d in rows:
            o, u = d["abs_error_observed"], d["abs_error_unobserved"]
            lines.append(f"| {name} | {d['material']} | {d['unobserved_share']:.1%} | " + (f"{o:.4f}" if o is not None else "") + " | "
                         + (f"{u:.4f}" if u is not None else "") + " | " + (f"x{u / o:.1f}" if o and u is not None else "") + " |")
    lines += ["", f"Whole shape: export DSSIM {res['whole_object_export_dssim']:.4f}.", "",
              "`export_truth.png`: the first frame, truth | export | constant colours."]
    path.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
