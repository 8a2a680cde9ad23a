"""A COLMAP reconstruction (pycolmap) as a :class:`~damcap.reconstruct.poses.Registration`."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from damcap.common.errors import DamcapError

from damcap.reconstruct.undistort import camera_from_colmap
from damcap.reconstruct.poses import RegisteredPhoto, Registration, photos_by_stem, finish_registration, nearest_facing_camera, world_from_cam_of_colmap


def image_observations(rec: Any) -> dict[int, np.ndarray]:
    """Per registered image of a ``pycolmap.Reconstruction``: its observations of 3D points with
    their reprojection errors.

    Returns:
        image id -> (M, 3) float64 rows (x, y, |projection - observation|), image pixels.
    """
    xyz_of = {int(pid): p.xyz for pid, p in rec.points3D.items()}
    out: dict[int, np.ndarray] = {}
    for image_id in rec.reg_image_ids():
        img = rec.image(image_id)
        cam = rec.camera(img.camera_id)
        obs = [(p.xy, xyz_of[int(p.point3D_id)]) for p in img.points2D if p.has_point3D()]
        if not obs:
            out[image_id] = np.zeros((0, 3))
            continue
        xy = np.array([o[0] for o in obs], np.float64)
        xyz = np.array([o[1] for o in obs], np.float64)
        cam_from_world = np.asarray(img.cam_from_world().matrix(), np.float64)
        p_cam = xyz @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        uv = np.asarray(cam.img_from_cam(p_cam), np.float64).reshape(-1, 2)
        out[image_id] = np.column_stack([xy, np.linalg.norm(uv - xy, axis=1)])
    return out


def registration_of_reconstruction(rec: Any, photo_names: list[str], source: str, where: str) -> Registration:
    """Cameras and points of a ``pycolmap.Reconstruction``, in OpenGL camera axes.

    Images are matched to photos by name, then by base name; points keep one observing photo.
    """
    stems = photos_by_stem(photo_names)
    found: dict[str, RegisteredPhoto] = {}
    id_to_name: dict[int, str] = {}
    observations = image_observations(rec)
    for image_id in rec.reg_image_ids():
        img = rec.image(image_id)
        name = img.name if img.name in photo_names else stems.get(Path(img.name).stem)
        if name is None:
            continue
        if name in found:  # never resolved silently by the last entry
            raise DamcapError(f"{where}: photo {name} has two pose entries (images {img.name!r} and another with its "
                              "base name); keep one")
        cam = rec.camera(img.camera_id)
        params = np.asarray(cam.params, dtype=np.float64)
        m = np.asarray(img.cam_from_world().matrix(), dtype=np.float64)
        if not (np.isfinite(params).all() and np.isfinite(m).all()):
            raise DamcapError(f"{where}: image {img.name!r} has a NaN or infinite camera or pose")
        pc = camera_from_colmap(cam.model.name, cam.width, cam.height, params)
        m = world_from_cam_of_colmap(m)
        found[name] = RegisteredPhoto(name, m, pc, observations.get(image_id))
        id_to_name[image_id] = name
    reg = finish_registration(source, Path(where), found, photo_names, "", {})
    index = {p.name: k for k, p in enumerate(reg.photos)}
    pts, seen, trackless = [], [], []
    for _, p3d in rec.points3D.items():
        if len(p3d.track.elements) == 0:  # a model written without observations (a 3DGS tool's, damcap's export)
            trackless.append(p3d.xyz)
        for el in p3d.track.elements:
            n = id_to_name.get(el.image_id)
            if n is not None:
                pts.append(p3d.xyz)
                seen.append(index[n])
                break
    if trackless and reg.photos:
        pts.extend(trackless)
        seen.extend(nearest_facing_camera(np.asarray(trackless, np.float64), reg.world_from_cams).tolist())
        reg.stats["points_without_track"] = len(trackless)
    if pts:
        reg.points_world = np.asarray(pts, dtype=np.float64)
        reg.points_seen_from = np.asarray(seen, dtype=np.int64)
    return reg


def read_colmap_model(folder: str | os.PathLike, photo_names: list[str]) -> Registration:
    """Cameras and sparse points from a COLMAP model folder (``cameras/images/points3D`` .bin or .txt).

    Raises:
        DamcapError: the folder is missing or holds no readable model.
    """
    from damcap.reconstruct.colmap.database import import_pycolmap

    folder = Path(folder)
    if not folder.is_dir():
        raise DamcapError(f"{folder}: COLMAP model folder not found")
    have = {p.name for p in folder.iterdir()}
    if not ({"cameras.bin", "images.bin"} <= have or {"cameras.txt", "images.txt"} <= have):
        sub = sorted(p for p in folder.iterdir() if p.is_dir() and (p / "images.bin").is_file())
        if len(sub) >= 1:
            folder = sub[0]
        else:
            raise DamcapError(f"{folder}: no COLMAP model here (need cameras.bin + images.bin or the .txt files)")
    pycolmap = import_pycolmap()
    try:
        rec = pycolmap.Reconstruction(str(folder))
    except (RuntimeError, ValueError) as e:
        raise DamcapError(f"{folder}: cannot read the COLMAP model ({e})") from None
    reg = registration_of_reconstruction(rec, photo_names, "colmap", str(folder))
    for n in reg.unregistered:
        reg.unregistered[n] = f"not registered in {folder}"
    return reg
