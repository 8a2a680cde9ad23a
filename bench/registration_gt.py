"""Registration against ground-truth cameras (issue 26): damcap, its principal-point option, plain
pycolmap and GLOMAP, side by side on Strecha's scenes, rendered sets and real captures.

Scenes (``--scenes``): ``herz-jesus-p8`` (8 photos) and ``castle-p19`` (19 photos) of Strecha et
al. 2008 (``real/strecha``, 1536x1024, ground-truth cameras read by ``--poses strecha:DIR``);
``turntable`` and ``orbit`` (:data:`RENDERED`: an object in a textured room, turning before the
camera or orbited by it, rendered into the cache with ground-truth cameras and masks); ``cape``
(``real/mold_gold_cape``, 119 photos, 912 px, masks; its reference is the LLFF poses, COLMAP with
the principal point at the image centre: a reference, not ground truth) and ``fox``
(``real/fox``, 50 phone photos; its reference is instant-ngp's COLMAP run). Methods, side by side
in one run of a scene (a rerun of some methods keeps the others' rows, each with its command):

- ``damcap reconstruct``: the whole ``damcap reconstruct`` at its defaults, with the scene's masks
  when it has them (as a user runs it): registered, the frames it wrote, its self-check, its
  stage times; the errors are those of the frames' cameras;
- ``damcap``: ``register_photos`` with ``SfmOptions(principal_point="centre")`` (no masks; the
  default before the 'auto' rule, COLMAP's convention);
- ``damcap refined pp``: ``SfmOptions(principal_point="refine")``; the default 'auto' picks one
  of the two by :func:`~damcap.reconstruct.colmap.principal_point.photos_support_offset`, whose
  decision the report lists per run;
- ``pycolmap incremental``: plain pycolmap 4.2.1 as a new user runs it: ``extract_features``,
  ``match_exhaustive`` and ``incremental_mapping``, all at their defaults;
- ``pycolmap global``: ``global_mapping`` (GLOMAP) at its defaults on the same database (its
  time = the shared extraction and matching + its own mapping);
- ``pycolmap masked`` (scenes with masks): plain pycolmap with its features inside the masks.

``--known-intrinsics`` maps the cached pycolmap database again with the reference intrinsics held
fixed: the rotation error that intrinsics cannot lower.

Reported per method (:func:`gt_errors`, :func:`intrinsics_vs_gt`): registered / total; rotation
error (median, max) after the similarity that best aligns the camera centres with the reference
(Umeyama), and after only the best common rotation (chordal mean, independent of the centres);
camera-centre error after the similarity, relative to the reference centres' extent; focal length
and principal point against the reference's, at the photos' resolution; damcap's own principal
point estimate (``SfmReport.principal_point``); wall time. Results:
``bench/results/registration_gt.json`` (scenes merge across runs) and ``bench/registration_gt.md``.

``--first N`` registers only the scene's first N photos (sorted names; a window of neighbouring
views), to see how few photos still fix the principal point; such runs are kept under the key
``SCENE (first N)`` and reported in one table of their own.

Run (from the repository root)::

    .venv/bin/python -m bench.registration_gt [--scenes herz-jesus-p8 castle-p19 turntable orbit cape fox] [--first N ...] [--methods ...]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import CACHE, REPO, RESULTS, command_line, log, machine_info, rows_not_rerun, shared_data_dir

REPORT = Path(__file__).with_name("registration_gt.md")
RESULT = RESULTS / "registration_gt.json"
WORK = CACHE / "registration_gt"
GEOMETRY_SETS = {**{obj: (obj, 320) for obj in ("bunny", "dragon", "armadillo")},
                 **{f"{obj}-800": (obj, 800) for obj in ("bunny", "dragon", "armadillo")}}
"""bench/reconstruct's geometry sets of the shared meshes (:func:`bench.reconstruct.geometry_photos`:
36 photos of the textured object alone, masks, true cameras): (mesh, photo size in px) by scene. The
geometry bench's 320 px is a thumbnail; 800 px is what a phone photo downsized for registration
still has"""
SCENES = ("herz-jesus-p8", "castle-p19", "cape", "fox", "turntable", "orbit", *GEOMETRY_SETS)
METHODS = ("damcap reconstruct", "damcap", "damcap refined pp", "pycolmap incremental", "pycolmap global", "pycolmap masked")
#: what each scene's reference cameras are
REFERENCES = {"strecha": "Strecha ground truth (gt_cameras, K scaled from 3072x2048)",
              "cape": "LLFF poses_bounds.npy (COLMAP, principal point at the image centre): a reference, not ground truth",
              "fox": ("instant-ngp's transforms.json (colmap2nerf: COLMAP with an OPENCV camera and a refined principal "
                      "point): a reference, not ground truth"),
              "turntable": "the renderer's cameras, in the object's frame (ground truth)",
              "orbit": "the renderer's cameras (ground truth)",
              **{scene: "the renderer's cameras (ground truth)" for scene in GEOMETRY_SETS}}
#: the rendered sets: an object in a textured room, photographed while it turns before a (2 deg
#: shaky) camera, or by a camera orbiting it; ground-truth cameras and masks from the renderer
RENDERED = {"turntable": dict(views=36, size=800, motion="turntable"), "orbit": dict(views=24, size=800, motion="orbit")}


def scene_key(scene: str, first: int | None) -> str:
    """The results' key of a scene, or of its first ``first`` photos.

    >>> scene_key("castle-p19", 8)
    'castle-p19 (first 8)'
    """
    return scene if first is None else f"{scene} (first {first})"


def geometry_set_root(scene: str) -> Path:
    """The folder of one of :data:`GEOMETRY_SETS` (photos, masks, transforms.json), rendered once."""
    from bench.reconstruct import geometry_photos

    obj, size = GEOMETRY_SETS[scene]
    return geometry_photos(obj, photo_size=size)


def scene_paths(scene: str, data: Path) -> tuple[Path, str]:
    """(photo folder, ``--poses`` spec of its reference cameras); a rendered set is rendered into
    the cache first when it is not there."""
    if scene == "cape":
        root = data / "real" / "mold_gold_cape"
        return root / "images", str(root / "poses_bounds.npy")
    if scene == "fox":
        root = data / "real" / "fox"
        return root / "images", str(root / "transforms.json")
    if scene in RENDERED:
        root = rendered_set(scene)
        return root / "images", str(root / "transforms.json")
    if scene in GEOMETRY_SETS:
        root = geometry_set_root(scene)
        return root / "images", str(root / "transforms.json")
    root = data / "real" / "strecha" / scene
    return root / "images", f"strecha:{root / 'gt_cameras'}"


def scene_masks(scene: str, data: Path) -> Path | None:
    """The scene's object masks folder, or None (Strecha and the fox have none)."""
    if scene == "cape":
        return data / "real" / "mold_gold_cape" / "masks"
    if scene in GEOMETRY_SETS:
        return geometry_set_root(scene) / "masks"
    return rendered_set(scene) / "masks" if scene in RENDERED else None


def rendered_set(scene: str) -> Path:
    """The rendered photo set of ``scene`` (:data:`RENDERED`) in the cache, rendered once."""
    from damcap.synth.photos import PhotoSetOptions, make_photo_set

    root = WORK / f"photos-{scene}"
    if not (root / "transforms.json").is_file():
        shutil.rmtree(root, ignore_errors=True)
        log(f"{scene}: rendering {RENDERED[scene]}")
        make_photo_set(root, PhotoSetOptions(room=True, jitter_deg=2.0, **RENDERED[scene]))  # type: ignore[arg-type]
    return root


# --------------------------------------------------------------------------------------------
# Pure parts: errors against the reference, intrinsics, the report
# --------------------------------------------------------------------------------------------

def centres_extent(centres: np.ndarray) -> float:
    """Largest distance between two of the (N, 3) camera centres (their units).

    >>> centres_extent(np.array([[0.0, 0, 0], [3.0, 4.0, 0], [1.0, 0, 0]]))
    5.0
    """
    c = np.asarray(centres, np.float64)
    return float(np.max(np.linalg.norm(c[:, None] - c[None], axis=-1)))


def scored(row: dict, reg, ref) -> dict:
    """``row`` with ``errors`` (:func:`gt_errors`) and ``intrinsics`` (:func:`intrinsics_vs_gt`)
    of a registration against the reference registration, when it has cameras."""
    if reg is not None and reg.photos:
        row["errors"] = gt_errors({p.name: p.world_from_cam for p in reg.photos}, {p.name: p.world_from_cam for p in ref.photos})
        if reg.photos[0].camera is not None:
            row["intrinsics"] = intrinsics_vs_gt([p.camera for p in reg.photos], ref.photos[0].camera)
    return row


def gt_errors(est: dict[str, np.ndarray], ref: dict[str, np.ndarray]) -> dict:
    """How far estimated cameras lie from reference cameras of the same photos.

    Args:
        est: photo name -> (4, 4) estimated world_from_cam (any world frame and scale, OpenGL axes).
        ref: photo name -> (4, 4) reference world_from_cam, same axes.

    Returns:
        ``compared`` (photos in both) and, with at least 3 of them: ``rot_sim_median_deg`` /
        ``rot_sim_max_deg`` (angle of R_ref^T R_sim R_est, R_sim the rotation of the Umeyama
        similarity taking the estimated centres onto the reference's), ``rot_common_median_deg`` /
        ``rot_common_max_deg`` (after the best common rotation only), ``centre_median_rel`` /
        ``centre_max_rel`` (|s R c + t - c_ref| over ``extent``), ``extent`` (largest distance
        between two reference centres, reference units).
    """
    from damcap.reconstruct.normalize import (rotation_aligned_errors_deg, rotation_angle_deg, similarity_scale,
                                              transform_points, umeyama_similarity)

    names = sorted(n for n in est if n in ref)
    if len(names) < 3:
        return {"compared": len(names)}
    e = np.stack([est[n] for n in names]).astype(np.float64)
    r = np.stack([ref[n] for n in names]).astype(np.float64)
    ref_from_est = umeyama_similarity(e[:, :3, 3], r[:, :3, 3])
    r_sim = ref_from_est[:3, :3] / similarity_scale(ref_from_est)
    rot_sim = rotation_angle_deg(np.swapaxes(r[:, :3, :3], -1, -2) @ r_sim @ e[:, :3, :3])
    rot_common = rotation_aligned_errors_deg(e, r)
    c_ref = r[:, :3, 3]
    extent = centres_extent(c_ref)
    centre = np.linalg.norm(transform_points(ref_from_est, e[:, :3, 3]) - c_ref, axis=1) / extent
    return {"compared": len(names), "rot_sim_median_deg": float(np.median(rot_sim)), "rot_sim_max_deg": float(np.max(rot_sim)),
            "rot_common_median_deg": float(np.median(rot_common)), "rot_common_max_deg": float(np.max(rot_common)),
            "centre_median_rel": float(np.median(centre)), "centre_max_rel": float(np.max(centre)), "extent": extent}


def intrinsics_vs_gt(cams: list, ref) -> dict:
    """Focal length and principal point of the registered photos' cameras against the reference's.

    Args:
        cams: the estimated :class:`~damcap.reconstruct.undistort.PhotoCamera` of every registered
            photo (one shared camera or one each), all at the reference's resolution.
        ref: the reference camera (:class:`PhotoCamera`) at the same resolution.

    Returns:
        ``cameras`` (distinct estimates), ``focal_px`` (mean of (fx + fy) / 2 over the photos),
        ``focal_err_px`` (minus the reference's (fx + fy) / 2), ``focal_spread_px`` (max - min over
        the photos), ``pp_px`` (mean (cx, cy)), ``pp_err_px`` (minus the reference's), all in
        pixels (centres at +0.5).
    """
    if not cams:
        return {}
    f = np.array([(c.fx + c.fy) / 2 for c in cams])
    pp = np.array([(c.cx, c.cy) for c in cams]).mean(0)
    f_ref = (ref.fx + ref.fy) / 2
    return {"cameras": len({(c.fx, c.fy, c.cx, c.cy) for c in cams}), "focal_px": float(f.mean()),
            "focal_err_px": float(f.mean() - f_ref), "focal_spread_px": float(f.max() - f.min()),
            "pp_px": [float(pp[0]), float(pp[1])], "pp_err_px": [float(pp[0] - ref.cx), float(pp[1] - ref.cy)]}


def pp_rule_refines(estimate: dict | None, photos: int) -> tuple[bool, str]:
    """What damcap's 'auto' principal point decides for a report's estimate
    (:func:`~damcap.reconstruct.colmap.principal_point.photos_support_offset`).

    Args:
        estimate: ``SfmReport.principal_point`` (``offset_px``, ``sd_px``, ``tilt_deg``) or None.
        photos: registered photos.

    Returns:
        (refine, why).
    """
    from damcap.reconstruct.colmap.principal_point import PrincipalPointEstimate, photos_support_offset

    if not estimate:
        return False, "no estimate"
    return photos_support_offset(PrincipalPointEstimate(estimate["offset_px"], estimate["sd_px"], estimate["tilt_deg"], False,
                                                        coverage=estimate.get("coverage")), photos)


def discussion_lines(res: dict) -> list[str]:
    """What the measurements say, computed from them: the principal-point rule's decision per
    run against what refining did, and what global mapping did against incremental mapping."""
    from damcap.reconstruct.colmap.principal_point import PP_GRID, PP_MAX_TILT_DEG, PP_MIN_COVERAGE, PP_MIN_PHOTOS, PP_MIN_SIGMAS

    lines = [(f"Principal-point rule (damcap's 'auto', `photos_support_offset`: refine when the offset is >= {PP_MIN_SIGMAS:g} sigma, >= "
             f"{PP_MIN_PHOTOS} photos registered, tilt <= {PP_MAX_TILT_DEG:g} deg, and the median photo's points on >= "
             f"{100 * PP_MIN_COVERAGE:.0f} % of a {PP_GRID}x{PP_GRID} grid, where the run measured it), against what refining measured "
             "(rotation sim median, centred -> refined; principal point minus the reference's):"), ""]
    for key, sc in res.get("scenes", {}).items():
        rows = {r["method"]: r for r in sc["rows"]}
        d, r = rows.get("damcap"), rows.get("damcap refined pp")
        if not d or not d.get("principal_point"):
            continue
        refine, why = pp_rule_refines(d["principal_point"], d["registered"])
        text = f"- {key}: {why}"
        if r and "errors" in d and "errors" in r:
            de, re_ = d["errors"], r["errors"]
            text += (f"; measured {de['rot_sim_median_deg']:.3f} -> {re_['rot_sim_median_deg']:.3f} deg, centre "
                     f"{100 * de['centre_median_rel']:.2f} -> {100 * re_['centre_median_rel']:.2f} % (median); pp "
                     f"({d['intrinsics']['pp_err_px'][0]:+.1f}, {d['intrinsics']['pp_err_px'][1]:+.1f}) -> "
                     f"({r['intrinsics']['pp_err_px'][0]:+.1f}, {r['intrinsics']['pp_err_px'][1]:+.1f}) px")
        lines.append(text)
    lines += ["", ("`damcap reconstruct` at its defaults against the issue's targets (>= 95 % registered, rotation sim "
              "median <= 0.1 deg and max <= 1 deg), next to plain pycolmap's best row (most registered, then lowest "
              "median):"), ""]
    for key, sc in res.get("scenes", {}).items():
        rows = {r["method"]: r for r in sc["rows"]}
        d = rows.get("damcap reconstruct")
        if not d:
            continue
        note = " (against a reference, not ground truth)" if "not ground truth" in sc["reference"]["what"] else ""
        lines.append(f"- {key}{note}: {target_verdict(d)}" + (f"; plain pycolmap ({p['method']}) {target_verdict(p)}"
                                                             if (p := best_pycolmap(sc["rows"])) else ""))
    lines += ["", ("With the reference intrinsics fixed (the same matches; the floor intrinsics cannot lower), against "
              "damcap with the principal point refined (rotation sim median / max; common median / max; the reference "
              "centres' singular values over the largest: a path close to a line or a plane leaves the centre-based "
              "similarity's rotation loosely determined):"), ""]
    for key, sc in res.get("scenes", {}).items():
        k = sc.get("known_intrinsics")
        d = {r["method"]: r for r in sc["rows"]}.get("damcap refined pp")
        if not (k and "errors" in k):
            continue
        ke = k["errors"]
        text = (f"- {key}: reference intrinsics {ke['rot_sim_median_deg']:.3f} / {ke['rot_sim_max_deg']:.3f} deg sim, "
                f"{ke['rot_common_median_deg']:.3f} / {ke['rot_common_max_deg']:.3f} deg common")
        if d and "errors" in d:
            de = d["errors"]
            text += (f"; damcap refined pp {de['rot_sim_median_deg']:.3f} / {de['rot_sim_max_deg']:.3f} sim, "
                     f"{de['rot_common_median_deg']:.3f} / {de['rot_common_max_deg']:.3f} common")
        spread = sc["reference"].get("centre_spread")
        if spread:
            text += f"; centres {' : '.join(f'{v:.3f}' for v in spread)}"
        lines.append(text)
    lines += ["", ("Global (GLOMAP) against incremental mapping on the same database (mapping stage alone; rotation sim "
              "median / max; centre max):"), ""]
    for key, sc in res.get("scenes", {}).items():
        rows = {r["method"]: r for r in sc["rows"]}
        i, g = rows.get("pycolmap incremental"), rows.get("pycolmap global")
        if not (i and g and "errors" in i and "errors" in g):
            continue
        ie, ge = i["errors"], g["errors"]
        lines.append(f"- {key}: registered {i['registered']} / {g['registered']} of {i['photos']}; mapping "
                     f"{i['stage_wall_s']['mapping']:.1f} s / {g['stage_wall_s']['mapping']:.1f} s; rotation "
                     f"{ie['rot_sim_median_deg']:.3f} / {ie['rot_sim_max_deg']:.3f} deg against "
                     f"{ge['rot_sim_median_deg']:.3f} / {ge['rot_sim_max_deg']:.3f} deg; centre max "
                     f"{100 * ie['centre_max_rel']:.2f} % against {100 * ge['centre_max_rel']:.2f} %")
    return lines


def target_verdict(row: dict, min_fraction: float = 0.95, max_median_deg: float = 0.1, max_max_deg: float = 1.0) -> str:
    """One row against the registration targets, in words.

    >>> target_verdict({"registered": 36, "photos": 36, "errors": {"rot_sim_median_deg": 0.104, "rot_sim_max_deg": 0.231}})
    '36/36 (100 %), 0.104 / 0.231 deg: median above 0.1'
    >>> target_verdict({"registered": 3, "photos": 8})
    '3/8 (38 %): fewer than 95 % registered'
    """
    frac = row["registered"] / row["photos"]
    head = f"{row['registered']}/{row['photos']} ({100 * frac:.0f} %)"
    e = row.get("errors", {})
    if "rot_sim_median_deg" not in e:
        return head + (": fewer than 95 % registered" if frac < min_fraction else ": no errors")
    head += f", {e['rot_sim_median_deg']:.3f} / {e['rot_sim_max_deg']:.3f} deg"
    missed = ([f"fewer than {100 * min_fraction:.0f} % registered"] if frac < min_fraction else []) + \
             ([f"median above {max_median_deg:g}"] if e["rot_sim_median_deg"] > max_median_deg else []) + \
             ([f"max above {max_max_deg:g}"] if e["rot_sim_max_deg"] > max_max_deg else [])
    return head + (": " + ", ".join(missed) if missed else ": met")


WRONG_DEG = 5.0
"""a registration whose median rotation error is above this is wrong, not a registration: plain
pycolmap's best row is chosen among the others first (GLOMAP registers every photo of the mesh
sets, 35 to 89 deg off)"""


def best_pycolmap(rows: list[dict]) -> dict | None:
    """Plain pycolmap's best row of a scene: the most photos registered, then the lowest median,
    among rows that are not wrong (:data:`WRONG_DEG`) when there are such rows.

    >>> rows = [{"method": "pycolmap global", "registered": 36, "errors": {"rot_sim_median_deg": 35.0}},
    ...         {"method": "pycolmap incremental", "registered": 33, "errors": {"rot_sim_median_deg": 2.0}}]
    >>> best_pycolmap(rows)["method"]
    'pycolmap incremental'
    """
    cands = [r for r in rows if r["method"] in ("pycolmap incremental", "pycolmap global", "pycolmap masked")]
    median = lambda r: r.get("errors", {}).get("rot_sim_median_deg", float("inf"))  # noqa: E731
    return min(cands, key=lambda r: (not median(r) <= WRONG_DEG, -r["registered"], median(r)), default=None)


def _num(v, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def row_cells(row: dict) -> list[str]:
    """One method's table cells (see :func:`write_report` for the columns)."""
    e = row.get("errors", {})
    i = row.get("intrinsics", {})
    pp = row.get("principal_point")
    rot_sim = f"{_num(e.get('rot_sim_median_deg'), '.3f')} / {_num(e.get('rot_sim_max_deg'), '.3f')}"
    rot_common = f"{_num(e.get('rot_common_median_deg'), '.3f')} / {_num(e.get('rot_common_max_deg'), '.3f')}"
    centre = (f"{100 * e['centre_median_rel']:.2f} / {100 * e['centre_max_rel']:.2f}" if "centre_median_rel" in e else "- / -")
    focal = f"{i['focal_px']:.1f} ({i['focal_err_px']:+.1f})" if i else "-"
    if i and i.get("cameras", 1) > 1:
        focal += f", {i['cameras']} cameras, spread {i['focal_spread_px']:.1f}"
    ppt = f"({i['pp_err_px'][0]:+.1f}, {i['pp_err_px'][1]:+.1f})" if i else "-"
    est = (f"({pp['offset_px'][0]:+.1f}, {pp['offset_px'][1]:+.1f}) +- ({pp['sd_px'][0]:.1f}, {pp['sd_px'][1]:.1f})"
           if pp else "-")
    reg = f"{row['registered']}/{row['photos']}" + (f" ({row['error'].split(': ', 1)[-1][:90]})" if row.get("error") else "") \
        + (f", {row['points']} points" if row.get("points") else "") \
        + (f" (SIFT peak {row['sift_peak_threshold']:.4f})" if row.get("sift_peak_threshold") else "")
    mapping = row.get("stage_wall_s", {}).get("mapping")
    wall = f"{row['wall_s']:.1f}" + (f" ({mapping:.1f})" if mapping is not None else "")
    sc = row.get("self_check")
    check = "-" if not sc else (f"{sc['verdict']}" + (f", recall min {sc['recall_min']:.3f}" if sc.get("recall_min") is not None else "")
                                + (f", flagged {len(sc['flagged'])}" if sc.get("flagged") else ""))
    return [row["method"], reg, rot_sim, rot_common, centre, focal, ppt, est, check, wall]


def write_report(res: dict, path: Path = REPORT) -> None:
    """The markdown report: one table per scene, each with the command and machine that made it."""
    lines = ["# Registration against ground-truth cameras (issue 26)", "",
             ("Generated by `bench/registration_gt.py` from `bench/results/registration_gt.json`. Up to six methods per "
             "scene, side by side in one run (the machine is shared: compare times within a scene's run only); `damcap "
             "reconstruct` is the whole command at its defaults (with the scene's masks when it has them), the others "
             "register only."), "",
             ("Columns: registered / photos; rotation error (deg, median / max) after the similarity that aligns the camera "
             "centres with the reference (`sim`), and after only the best common rotation (`common`); camera-centre error "
             "after the similarity, % of the reference centres' extent (median / max); focal length (px, mean over photos; "
             "in brackets minus the reference's (fx + fy) / 2); principal point minus the reference's (px); the principal "
             "point damcap estimates (offset from the image centre +- 1 sigma, px; `SfmReport.principal_point`); wall time "
             "(s; in brackets the mapping stage alone; `pycolmap global` includes the extraction and matching it "
             "shares with `pycolmap incremental`). All "
             "pixels at the photos' resolution, pixel centres at +0.5."), ""]
    for scene in [s for s in SCENES if s in res.get("scenes", {})]:
        sc = res["scenes"][scene]
        m = sc["machine"]
        ref = sc["reference"]
        lines += [f"## {scene}", "",
                  (f"Command: `{sc['command']}` ({m['date_utc']}, {m['nproc']} cores, {m['cpu_model']}; pycolmap "
                  f"{sc.get('pycolmap', '?')})."), "",
                  (f"Reference: {ref['what']}; focal {ref['focal_px']:.2f} px, principal point ({ref['pp_px'][0]:.2f}, "
                  f"{ref['pp_px'][1]:.2f}) px = ({ref['pp_offset_px'][0]:+.2f}, {ref['pp_offset_px'][1]:+.2f}) from the "
                  f"image centre (tilt {ref['pp_tilt_deg']:.3f} deg); {ref['photos']} photos of {ref['width']}x{ref['height']}; "
                  f"centres' extent {ref['extent']:.3g} units."), "",
                  ("| method | registered | rotation sim (deg) | rotation common (deg) | centre (% extent) | focal (px) | "
                  "pp - ref (px) | damcap pp estimate (px) | self-check | wall (s) |"),
                  "|---|---|---|---|---|---|---|---|---|---|"]
        lines += ["| " + " | ".join(row_cells(r)) + " |" for r in sc["rows"]]
        lines += ["| " + " | ".join(row_cells(r)) + " |" for r in sc.get("global_reruns", [])]
        if sc.get("known_intrinsics"):
            lines.append("| " + " | ".join(row_cells(sc["known_intrinsics"])) + " |")
        lines += ["| " + " | ".join(row_cells(r)) + " |" for r in sc.get("variants", []) + sc.get("masked_variants", [])]
        lines.append("")
        earlier: dict[tuple[str, str], list[str]] = {}
        for r in sc["rows"]:
            if r.get("command", sc["command"]) != sc["command"]:
                earlier.setdefault((r["command"], r.get("date_utc", "?")), []).append(f"*{r['method']}*")
        lines += [f"Rows {', '.join(methods)} measured earlier by `{cmd}` ({date})." for (cmd, date), methods in earlier.items()]
        if sc.get("known_intrinsics_command"):
            lines += [f"Incremental mapping again with the reference intrinsics fixed: `{sc['known_intrinsics_command']}`.", ""]
        if sc.get("variants_command"):
            lines += [f"damcap's registration with one option changed: `{sc['variants_command']}`.", ""]
        if sc.get("masked_variants_command"):
            lines += [f"damcap's masked registration (the features inside the masks) with SIFT's contrast threshold or the "
                      f"seed changed: `{sc['masked_variants_command']}`.", ""]
        lines += sorted({f"Global mapping again on the same database: `{c}`." for c in sc.get("global_rerun_commands", [])})
        if sc.get("global_rerun_commands"):
            lines.append("")
    subsets = [k for k in res.get("scenes", {}) if k not in SCENES]
    if subsets:
        lines += ["## Fewer photos", "",
                  ("The first N photos of a scene (sorted names: neighbouring views), same columns; the command of each run "
                  "below the table."), "",
                  ("| photos | method | registered | rotation sim (deg) | rotation common (deg) | centre (% extent) | focal (px) | "
                  "pp - ref (px) | damcap pp estimate (px) | self-check | wall (s) |"),
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for key in sorted(subsets, key=lambda k: (k.split(" ")[0], res["scenes"][k]["photos"])):
            lines += [f"| {key} | " + " | ".join(row_cells(r)) + " |" for r in res["scenes"][key]["rows"]]
        lines += ["", *(f"- `{c}`" for c in sorted({res["scenes"][k]["command"] for k in subsets})), ""]
    lines += ["## What the measurements say", "", *discussion_lines(res), ""]
    path.write_text("\n".join(lines), encoding="utf-8")


# --------------------------------------------------------------------------------------------
# The runs
# --------------------------------------------------------------------------------------------

def run_damcap(images: Path, names: list[str], work: Path, refine_pp: bool, **sfm: Any) -> dict:
    """damcap's registration with the principal point kept at the centre or refined (``sfm``:
    other :class:`SfmOptions` fields changed, for :data:`VARIANTS`)."""
    from damcap.common.errors import DamcapError
    from damcap.reconstruct.colmap.register import SfmOptions, register_photos

    shutil.rmtree(work, ignore_errors=True)
    opts = replace(SfmOptions(), principal_point="refine" if refine_pp else "centre", **sfm)
    t0 = time.perf_counter()
    try:
        reg, rep = register_photos(images, names, work, opts)
    except DamcapError as e:
        return {"registered": 0, "error": str(e)[:300], "wall_s": time.perf_counter() - t0, "options": asdict(opts)}
    return {"registered": rep.registered, "wall_s": time.perf_counter() - t0, "stage_wall_s": rep.seconds,
            "features": rep.features, "retry": rep.retry, "principal_point": rep.principal_point,
            "mean_reprojection_error_px": rep.mean_reprojection_error_px, "options": asdict(opts), "registration": reg}


def run_reconstruct(images: Path, masks: Path | None, work: Path) -> dict:
    """``damcap reconstruct`` as a user runs it (every option at its default, the masks when the
    scene has them): what it registered, kept and dropped, its self-check, its stage times, and the
    cameras of the frames it wrote (a similarity of the photos' frame, which the errors align)."""
    from damcap.common.capture_folder import read_capture
    from damcap.common.errors import DamcapError
    from damcap.reconstruct.pipeline import ReconstructOptions, reconstruct_capture
    from damcap.reconstruct.poses import Registration, RegisteredPhoto

    shutil.rmtree(work, ignore_errors=True)
    t0 = time.perf_counter()
    try:
        _, rep = reconstruct_capture(images, work, ReconstructOptions(), masks_dir=masks)
    except DamcapError as e:
        return {"registered": 0, "error": str(e)[:300], "wall_s": time.perf_counter() - t0}
    wall = time.perf_counter() - t0
    cap = read_capture(work)
    check = rep.self_check or {}
    recall = [p["silhouette_recall"] for p in check.get("photos", {}).values() if p.get("silhouette_recall") is not None]
    # the frames' cameras (normalised frame); their intrinsics are the capture's pinhole targets, not compared
    reg = Registration([RegisteredPhoto(f.extra["photo"], f.world_from_cam, None) for f in cap.frames])  # type: ignore[arg-type]
    return {"registered": rep.registered, "frames": rep.frames, "dropped": sorted(rep.dropped),
            "unregistered": sorted(rep.unregistered), "wall_s": wall,
            "stage_wall_s": {**rep.registration.get("seconds", {}), **{k: v for k, v in rep.seconds.items() if k != "total"}},
            "self_check": {"verdict": check.get("verdict"), "flagged": check.get("flagged", []),
                           "recall_min": min(recall) if recall else None},
            "features_used": rep.registration.get("features_used"), "masks": masks is not None, "registration": reg}


def _best(recs: dict, names: list[str], where: str):
    from damcap.reconstruct.colmap.model import registration_of_reconstruction

    if not recs:
        return None, 0
    best = max(recs.values(), key=lambda r: r.num_reg_images())
    return registration_of_reconstruction(best, names, "pycolmap", where), len(recs)


def run_pycolmap(images: Path, names: list[str], work: Path) -> tuple[dict, dict]:
    """Plain pycolmap, every call at its defaults: (incremental row, global row)."""
    import pycolmap

    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    db = work / "database.db"
    t0 = time.perf_counter()
    pycolmap.extract_features(db, images, image_names=names)
    t_extract = time.perf_counter() - t0
    t0 = time.perf_counter()
    pycolmap.match_exhaustive(db)
    t_match = time.perf_counter() - t0
    shared = t_extract + t_match
    rows = []
    for method, mapper, out in (("pycolmap incremental", pycolmap.incremental_mapping, work / "incremental"),
                                ("pycolmap global", pycolmap.global_mapping, work / "global")):
        out.mkdir()
        t0 = time.perf_counter()
        try:
            recs = mapper(db, images, out)
            error = None
        except Exception as e:  # noqa: BLE001  (a mapper failure is a result of the study, recorded)
            recs, error = {}, f"{type(e).__name__}: {e}"
        t_map = time.perf_counter() - t0
        reg, models = _best(recs, names, str(out))
        row = {"registered": len(reg.photos) if reg else 0, "models": models, "wall_s": shared + t_map,
               "stage_wall_s": {"extract": t_extract, "match": t_match, "mapping": t_map}, "registration": reg}
        if error:
            row["error"] = error[:300]
        rows.append(row)
    return rows[0], rows[1]


def run_pycolmap_masked(images: Path, names: list[str], masks: Path, work: Path) -> dict:
    """Plain pycolmap with its features restricted to the object masks (``ImageReaderOptions.mask_path``,
    the masks as given, not eroded), otherwise at its defaults: extraction, exhaustive matching,
    incremental mapping."""
    import pycolmap

    from damcap.reconstruct.colmap.database import write_colmap_masks
    from damcap.reconstruct.photos import match_masks

    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    write_colmap_masks(match_masks(names, masks), work / "masks", erode_fraction=0.0)
    reader = pycolmap.ImageReaderOptions()
    reader.mask_path = str(work / "masks")
    db = work / "database.db"
    t0 = time.perf_counter()
    pycolmap.extract_features(db, images, image_names=names, reader_options=reader)
    t_extract = time.perf_counter() - t0
    t0 = time.perf_counter()
    pycolmap.match_exhaustive(db)
    t_match = time.perf_counter() - t0
    out = work / "incremental"
    out.mkdir()
    t0 = time.perf_counter()
    recs = pycolmap.incremental_mapping(db, images, out)
    t_map = time.perf_counter() - t0
    reg, models = _best(recs, names, str(out))
    return {"registered": len(reg.photos) if reg else 0, "models": models, "wall_s": t_extract + t_match + t_map,
            "stage_wall_s": {"extract": t_extract, "match": t_match, "mapping": t_map}, "registration": reg}


def rerun_global(scene: str, data: Path, seed: int) -> dict:
    """``global_mapping`` again on the database the scene's last ``pycolmap`` run left in the cache,
    with every random seed of its options set to ``seed`` (-1: its default, a random seed); a
    row like :func:`run_scene`'s, ``wall_s`` the mapping alone."""
    import pycolmap

    from damcap.reconstruct.known_poses import load_known_poses
    from damcap.reconstruct.photos import image_size, list_photos

    images, spec = scene_paths(scene, data)
    names = list_photos(images)
    work = WORK / scene / "pycolmap"
    db = work / "database.db"
    if not db.is_file():
        raise SystemExit(f"error: {db} not found; run the scene with the pycolmap methods first")
    opts = pycolmap.GlobalPipelineOptions()
    m = opts.mapper
    for o in (opts, m, m.rotation_averaging, m.global_positioning):
        o.random_seed = seed
    out = work / f"global-seed{seed}"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    log(f"{scene}: pycolmap global, seed {seed}, on {db}")
    t0 = time.perf_counter()
    recs = pycolmap.global_mapping(db, images, out, opts)
    wall = time.perf_counter() - t0
    reg, models = _best(recs, names, str(out))
    ref = load_known_poses(spec, {n: image_size(images / n) for n in names})
    row = {"method": f"pycolmap global, seed {seed} (mapping only)", "photos": len(names),
           "registered": len(reg.photos) if reg else 0, "models": models, "wall_s": wall, "stage_wall_s": {"mapping": wall},
           "seed": seed}
    scored(row, reg, ref)
    log(f"  -> {json.dumps(row)}")
    return row


def rerun_known_intrinsics(scene: str, data: Path) -> tuple[dict, list[float]]:
    """Incremental mapping again on the database the scene's last ``pycolmap`` run left in the
    cache, every camera set to the reference's pinhole intrinsics and held fixed (focal length,
    principal point and distortion not refined): what the matches give with perfect intrinsics, the
    floor of the rotation error that intrinsics cannot lower. A row like :func:`run_scene`'s
    (``wall_s`` the mapping alone) and the reference centres' :func:`centre_spread`."""
    import pycolmap

    from damcap.reconstruct.known_poses import load_known_poses
    from damcap.reconstruct.photos import image_size, list_photos

    images, spec = scene_paths(scene, data)
    names = list_photos(images)
    ref = load_known_poses(spec, {n: image_size(images / n) for n in names})
    src = WORK / scene / "pycolmap" / "database.db"
    if not src.is_file():
        raise SystemExit(f"error: {src} not found; run the scene with the pycolmap methods first")
    out = WORK / scene / "pycolmap-known-intrinsics"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    db_path = out / "database.db"
    shutil.copy(src, db_path)
    c = ref.photos[0].camera
    db = pycolmap.Database.open(str(db_path))
    try:
        for cam in db.read_all_cameras():
            known = pycolmap.Camera(model="PINHOLE", width=c.width, height=c.height, params=[c.fx, c.fy, c.cx, c.cy])
            known.camera_id = cam.camera_id
            known.has_prior_focal_length = True
            db.update_camera(known)
    finally:
        db.close()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.ba_refine_focal_length = opts.ba_refine_principal_point = opts.ba_refine_extra_params = False
    log(f"{scene}: pycolmap incremental with the reference intrinsics fixed, on {db_path}")
    t0 = time.perf_counter()
    recs = pycolmap.incremental_mapping(str(db_path), str(images), str(out), options=opts)
    wall = time.perf_counter() - t0
    reg, models = _best(recs, names, str(out))
    row = {"method": "pycolmap incremental, reference intrinsics fixed (mapping only)", "photos": len(names),
           "registered": len(reg.photos) if reg else 0, "models": models, "wall_s": wall, "stage_wall_s": {"mapping": wall}}
    scored(row, reg, ref)
    log(f"  -> {json.dumps(row)}")
    return row, centre_spread(ref.world_from_cams[:, :3, 3])


def centre_spread(centres: np.ndarray) -> list[float]:
    """Singular values of the (N, 3) camera centres about their mean, over the largest: how far
    the path is from a line (second) and a plane (third). A centre-based similarity determines the
    rotation about the path's long axis only as well as the second and third allow.

    >>> centre_spread(np.array([[0.0, 0, 0], [4.0, 0, 0], [2.0, 1.0, 0], [2.0, -1.0, 0]]))
    [1.0, 0.5, 0.0]
    """
    c = np.asarray(centres, np.float64)
    sv = np.linalg.svd(c - c.mean(0), compute_uv=False)
    return [round(float(v / sv[0]), 6) for v in sv]


def reference_summary(ref, what: str) -> dict:
    from damcap.reconstruct.colmap.principal_point import principal_point_tilt_deg

    c = ref.photos[0].camera
    c_ref = ref.world_from_cams[:, :3, 3]
    off = [c.cx - c.width / 2, c.cy - c.height / 2]
    return {"what": what, "photos": len(ref.photos), "width": c.width, "height": c.height, "focal_px": (c.fx + c.fy) / 2,
            "fx_px": c.fx, "fy_px": c.fy, "pp_px": [c.cx, c.cy], "pp_offset_px": off,
            "pp_tilt_deg": principal_point_tilt_deg(off, (c.fx + c.fy) / 2),
            "extent": centres_extent(c_ref), "centre_spread": centre_spread(c_ref)}


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def run_scene(scene: str, data: Path, methods: tuple[str, ...], first: int | None = None) -> dict:
    import pycolmap

    from damcap.reconstruct.known_poses import load_known_poses
    from damcap.reconstruct.photos import image_size, list_photos

    images, spec = scene_paths(scene, data)
    names = list_photos(images)[:first]
    ref = load_known_poses(spec, {n: image_size(images / n) for n in names})
    what = REFERENCES.get(scene, REFERENCES["strecha"])
    out = {"photos": len(names), "reference": reference_summary(ref, what), "pycolmap": pycolmap.__version__,
           "register_py_sha256": _sha(REPO / "reconstruct" / "colmap" / "register.py"), "rows": []}
    work = WORK / scene_key(scene, first).replace(" ", "-").replace("(", "").replace(")", "")
    results: dict[str, dict] = {}
    masks = scene_masks(scene, data)
    methods = tuple(m for m in methods if masks is not None or m != "pycolmap masked")
    for method in methods:
        log(f"{scene_key(scene, first)}: {method} on {len(names)} photos")
        if method == "damcap reconstruct":
            results[method] = run_reconstruct(images, masks, work / "damcap-reconstruct")
        elif method == "pycolmap masked":
            results[method] = run_pycolmap_masked(images, names, masks, work / "pycolmap-masked")  # type: ignore[arg-type]
        elif method == "damcap":
            results[method] = run_damcap(images, names, work / "damcap", refine_pp=False)
        elif method == "damcap refined pp":
            results[method] = run_damcap(images, names, work / "damcap-refined-pp", refine_pp=True)
        elif method == "pycolmap incremental" or (method == "pycolmap global" and method not in results):
            inc, glo = run_pycolmap(images, names, work / "pycolmap")
            results["pycolmap incremental"], results["pycolmap global"] = inc, glo
    for method in methods:
        r = dict(results[method])
        reg = r.pop("registration", None)
        row = {"method": method, "photos": len(names), **r}
        if scored(row, reg, ref).get("intrinsics") is not None:
            row["distortion_k1"] = float(np.mean([p.camera.distortion[0] for p in reg.photos]))
        log(f"  -> {json.dumps({k: v for k, v in row.items() if k not in ('options', 'retry', 'stage_wall_s')})}")
        out["rows"].append(row)
    return out


VARIANTS: dict[str, dict[str, Any]] = {
    "damcap refined pp, features at 1536 px": {"max_image_size": 1536},
    "damcap refined pp, SIMPLE_PINHOLE": {"camera_model": "SIMPLE_PINHOLE"},
    "damcap refined pp, RADIAL": {"camera_model": "RADIAL"},
}
"""``--variants``: damcap's registration (principal point refined) with one option changed: the
photos' full resolution for the features (Strecha's are 1536 px; the default caps them at
1024), and no or two radial terms instead of SIMPLE_RADIAL's one"""


MASKED_VARIANTS: dict[str, dict[str, Any]] = {
    "damcap masked (its probe picks the threshold)": {},
    "damcap masked, probe, seed 1": {"seed": 1},
    "damcap masked, SIFT peak 0.0067 (COLMAP's default)": {"sift_peak_threshold": 0.02 / 3, "low_contrast_peak_threshold": None},
    "damcap masked, SIFT peak 0.0067, seed 1": {"sift_peak_threshold": 0.02 / 3, "low_contrast_peak_threshold": None, "seed": 1},
    "damcap masked, SIFT peak 0.0045": {"sift_peak_threshold": 0.0045, "low_contrast_peak_threshold": None},
    "damcap masked, SIFT peak 0.003": {"sift_peak_threshold": 0.003, "low_contrast_peak_threshold": None},
    "damcap masked, SIFT peak 0.002": {"sift_peak_threshold": 0.002, "low_contrast_peak_threshold": None},
}
"""``--masked-variants``: damcap's registration with features inside the masks
(:func:`~damcap.reconstruct.colmap.register.masked_options`, every other option at its default):
as it runs (a probe of 4 photos picks SIFT's contrast threshold, :func:`peak_threshold_for`), and
with the threshold fixed or the seed changed: what chose ``MASKED_PEAK_THRESHOLD``"""


def run_masked(images: Path, names: list[str], masks_dir: Path, work: Path, **sfm: Any) -> dict:
    """damcap's masked registration (``sfm``: :class:`SfmOptions` fields changed after
    :func:`masked_options`), as :func:`run_damcap` reports it."""
    from damcap.reconstruct.colmap.register import SfmOptions, masked_options, register_photos
    from damcap.reconstruct.photos import image_size, match_masks
    from damcap.reconstruct.pipeline import check_masks

    masks = match_masks(names, masks_dir)
    fraction = check_masks(masks, {n: image_size(images / n) for n in names})  # as reconstruct measures it
    opts = replace(masked_options(SfmOptions(), fraction), **sfm)
    shutil.rmtree(work, ignore_errors=True)
    t0 = time.perf_counter()
    reg, rep = register_photos(images, names, work, opts, masks)
    return {"registered": rep.registered, "wall_s": time.perf_counter() - t0, "stage_wall_s": rep.seconds,
            "points": rep.points, "sift_peak_threshold": rep.sift_peak_threshold, "principal_point": rep.principal_point,
            "options": asdict(opts), "registration": reg}


def rerun_masked_variants(scene: str, data: Path) -> list[dict]:
    """:data:`MASKED_VARIANTS` on one scene with masks, scored like the study's rows."""
    from damcap.reconstruct.known_poses import load_known_poses
    from damcap.reconstruct.photos import image_size, list_photos

    images, spec = scene_paths(scene, data)
    masks = scene_masks(scene, data)
    if masks is None:
        raise SystemExit(f"{scene} has no masks: --masked-variants needs a scene with masks")
    names = list_photos(images)
    ref = load_known_poses(spec, {n: image_size(images / n) for n in names})
    rows = []
    for method, sfm in MASKED_VARIANTS.items():
        log(f"{scene}: {method}")
        r = run_masked(images, names, masks, WORK / scene / "masked-variant", **sfm)
        reg = r.pop("registration", None)
        rows.append(scored({"method": method, "photos": len(names), **r}, reg, ref))
        log(f"  -> {rows[-1]['registered']} registered, {rows[-1].get('points')} points at SIFT peak "
            f"{rows[-1].get('sift_peak_threshold')}, {rows[-1].get('errors')}")
    return rows


def rerun_variants(scene: str, data: Path) -> list[dict]:
    """:data:`VARIANTS` on one scene, scored like the study's rows."""
    from damcap.reconstruct.known_poses import load_known_poses
    from damcap.reconstruct.photos import image_size, list_photos

    images, spec = scene_paths(scene, data)
    names = list_photos(images)
    ref = load_known_poses(spec, {n: image_size(images / n) for n in names})
    rows = []
    for method, sfm in VARIANTS.items():
        log(f"{scene}: {method}")
        r = run_damcap(images, names, WORK / scene / "variant", refine_pp=True, **sfm)
        reg = r.pop("registration", None)
        rows.append(scored({"method": method, "photos": len(names), **r}, reg, ref))
    return rows


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["herz-jesus-p8", "castle-p19"], choices=list(SCENES))
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    ap.add_argument("--first", nargs="+", type=int, default=[None], help="register only the first N photos (each N in turn)")
    ap.add_argument("--global-seeds", nargs="+", type=int, default=None,
                    help="instead of the study: global_mapping again on each scene's cached database, once per seed")
    ap.add_argument("--known-intrinsics", action="store_true",
                    help="instead of the study: incremental mapping again on each scene's cached database with the "
                         "reference intrinsics fixed")
    ap.add_argument("--variants", action="store_true",
                    help="instead of the study: damcap's registration with one option changed (VARIANTS) on each scene")
    ap.add_argument("--masked-variants", action="store_true",
                    help="instead of the study: damcap's masked registration with SIFT's contrast threshold or the seed "
                         "changed (MASKED_VARIANTS) on each scene")
    args = ap.parse_args(argv)
    import damcap.reconstruct.colmap.register  # noqa: F401  (imports pycolmap after OpenImageIO/OpenCV)

    data = shared_data_dir()
    if args.variants or args.masked_variants:
        key = "masked_variants" if args.masked_variants else "variants"
        for scene in args.scenes:
            rows = rerun_masked_variants(scene, data) if args.masked_variants else rerun_variants(scene, data)
            res = json.loads(RESULT.read_text(encoding="utf-8"))
            sc = res["scenes"][scene]
            sc[key], sc[f"{key}_command"] = rows, command_line("registration_gt", argv)
            RESULT.write_text(json.dumps(res, indent=1), encoding="utf-8")
            write_report(res)
        return 0
    if args.global_seeds is not None:
        for scene in args.scenes:
            rows = [rerun_global(scene, data, seed) for seed in args.global_seeds]
            res = json.loads(RESULT.read_text(encoding="utf-8"))
            sc = res["scenes"][scene]
            kept = [r for r in sc.get("global_reruns", []) if r["seed"] not in args.global_seeds]
            sc["global_reruns"] = kept + rows
            sc["global_rerun_commands"] = sorted(set(sc.get("global_rerun_commands", [])) | {command_line("registration_gt", argv)})
            RESULT.write_text(json.dumps(res, indent=1), encoding="utf-8")
            write_report(res)
        return 0
    if args.known_intrinsics:
        for scene in args.scenes:
            row, spread = rerun_known_intrinsics(scene, data)
            res = json.loads(RESULT.read_text(encoding="utf-8"))
            sc = res["scenes"][scene]
            sc["known_intrinsics"] = row
            sc["known_intrinsics_command"] = command_line("registration_gt", argv)
            sc["reference"]["centre_spread"] = spread
            RESULT.write_text(json.dumps(res, indent=1), encoding="utf-8")
            write_report(res)
        return 0
    for scene in args.scenes:
        for first in args.first:
            sc = run_scene(scene, data, tuple(args.methods), first)
            sc["command"] = command_line("registration_gt", argv)
            sc["machine"] = machine_info()
            for row in sc["rows"]:
                row["command"], row["date_utc"] = sc["command"], sc["machine"]["date_utc"]
            # read again just before writing: scenes measured by other runs meanwhile are kept
            res = json.loads(RESULT.read_text(encoding="utf-8")) if RESULT.is_file() else {}
            key = scene_key(scene, first)
            res.setdefault("scenes", {})[key] = merged_scene(res["scenes"].get(key), sc)
            RESULT.write_text(json.dumps(res, indent=1), encoding="utf-8")
            write_report(res)
    return 0


def merged_scene(prev: dict | None, new: dict) -> dict:
    """A scene's new results with the rows of the methods it did not rerun kept from ``prev``
    (each row keeps the command and date that measured it), in :data:`METHODS` order, and the
    reruns (global seeds, reference intrinsics) kept.

    >>> prev = {"command": "a", "machine": {"date_utc": "d0"}, "rows": [{"method": "damcap"}, {"method": "pycolmap masked"}]}
    >>> new = {"command": "b", "rows": [{"method": "damcap", "command": "b"}]}
    >>> [(r["method"], r["command"]) for r in merged_scene(prev, new)["rows"]]
    [('damcap', 'b'), ('pycolmap masked', 'a')]
    """
    if not prev:
        return new
    kept = rows_not_rerun(prev, new["rows"], lambda r: r["method"])
    out = {**new, "rows": sorted(new["rows"] + kept, key=lambda r: METHODS.index(r["method"]) if r["method"] in METHODS else len(METHODS))}
    for k in ("global_reruns", "global_rerun_commands", "known_intrinsics", "known_intrinsics_command", "variants", "variants_command",
              "masked_variants", "masked_variants_command"):
        if k in prev and k not in out:
            out[k] = prev[k]
    return out


def rewrite_report() -> None:
    """The markdown report again from the saved results (no registration is rerun)."""
    write_report(json.loads(RESULT.read_text(encoding="utf-8")))


if __name__ == "__main__":
    raise SystemExit(main())
