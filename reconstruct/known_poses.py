"""Known poses from files (``--poses transforms.json``, ``--poses poses_bounds.npy``, ``--poses
colmap:DIR``): :func:`load_known_poses` reads any of them into a :class:`~damcap.reconstruct.poses.Registration`."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from damcap.common.capture_folder import rigid_problem
from damcap.common.errors import DamcapError
from damcap.common.validate import MAX_IMAGE_SIDE, finite_in, load_json_file

from damcap.reconstruct.undistort import PhotoCamera
from damcap.reconstruct.colmap.model import read_colmap_model
from damcap.reconstruct.poses import RegisteredPhoto, Registration, photos_by_stem, finish_registration, orthonormalize_rotation, world_from_cam_of_llff


def _checked(path: Path, what: str, m: np.ndarray) -> np.ndarray:
    try:
        m = orthonormalize_rotation(m)
    except ValueError as e:
        raise DamcapError(f"{path}: {what} is not a rigid camera-to-world ({e})") from None
    problem = rigid_problem(m)
    if problem:
        raise DamcapError(f"{path}: {what} is not a rigid camera-to-world: {problem}")
    return m


def _ngp_camera(path: Path, where: str, obj: dict[str, Any], base: dict[str, Any], size: tuple[int, int]) -> PhotoCamera:
    """Intrinsics of one frame: the frame's keys over the file's shared keys, scaled to the photo."""
    v = {**base, **{k: obj[k] for k in obj if k != "transform_matrix"}}
    model = str(v.get("camera_model", "OPENCV"))
    if "FISHEYE" in model.upper() or model.upper() == "EQUIRECTANGULAR":
        raise DamcapError(f"{path}: {where}: camera_model {model} is not supported (pinhole/OpenCV cameras only)")
    def num(key: str, default: float) -> float:  # finite in float32 (camera math runs in float32 buffers)
        value = v.get(key, default)
        return finite_in(default if value is None else value, "float32", f"'{key}'", f"{path}: {where}")

    w_file = num("w", size[0])
    h_file = num("h", size[1])
    if not (1 <= w_file <= MAX_IMAGE_SIDE and 1 <= h_file <= MAX_IMAGE_SIDE):
        raise DamcapError(f"{path}: {where}: image size must lie in [1, {MAX_IMAGE_SIDE}] pixels, got w={w_file:g}, h={h_file:g}")
    if "fl_x" in v:
        fx = num("fl_x", 0.0)
        fy = num("fl_y", fx)
    elif "camera_angle_x" in v:
        ax = num("camera_angle_x", 0.0)
        ay = num("camera_angle_y", 0.0) if "camera_angle_y" in v else None
        if not (0 < ax < math.pi and (ay is None or 0 < ay < math.pi)):
            raise DamcapError(f"{path}: {where}: camera_angle_x/y must lie in (0, pi) radians, got {ax}, {ay}")
        fx = 0.5 * w_file / math.tan(0.5 * ax)
        fy = 0.5 * h_file / math.tan(0.5 * ay) if ay is not None else fx
    else:
        raise DamcapError(f"{path}: {where}: no focal length (need fl_x or camera_angle_x)")
    cx = num("cx", w_file / 2)
    cy = num("cy", h_file / 2)
    if num("k4", 0.0) != 0.0:
        raise DamcapError(f"{path}: {where}: k4 is a fisheye coefficient; only OpenCV pinhole distortion is supported")
    dist = (num("k1", 0.0), num("k2", 0.0), num("p1", 0.0), num("p2", 0.0), num("k3", 0.0), 0.0, 0.0, 0.0)
    if not (fx > 0 and fy > 0):
        raise DamcapError(f"{path}: {where}: invalid intrinsics {dict(w=w_file, h=h_file, fl_x=fx, fl_y=fy, cx=cx, cy=cy)}")
    cam = PhotoCamera(round(w_file), round(h_file), fx, fy, cx, cy, dist)
    if (cam.width, cam.height) != tuple(size):
        if abs(size[0] / cam.width - size[1] / cam.height) > 0.01:
            raise DamcapError(f"{path}: {where}: intrinsics are for {cam.width}x{cam.height} but the photo is "
                              f"{size[0]}x{size[1]} (a different aspect ratio)")
        cam = cam.scaled(*size)
    return cam


def read_transforms_json(path: str | os.PathLike, photo_sizes: dict[str, tuple[int, int]]) -> Registration:
    """Cameras from a nerfstudio / instant-ngp ``transforms.json`` (OpenGL camera-to-world).

    Frames are matched to photos by base name; frames without a photo are ignored (counted in
    ``stats``), photos without a frame are listed as unregistered. Intrinsics may be shared or
    per frame (``fl_x``/``fl_y`` or ``camera_angle_x``, ``cx``, ``cy``, ``w``, ``h``, OpenCV
    ``k1 k2 k3 p1 p2``) and are scaled to the photos' size.

    Args:
        path: the JSON file.
        photo_sizes: photo file name -> (width, height) pixels.

    Raises:
        DamcapError: unreadable JSON, no frames, non-rigid matrices, unsupported camera model.
    """
    path = Path(path)
    doc = load_json_file(path, "transforms.json")
    frames = doc.get("frames") if isinstance(doc, dict) else None
    if not isinstance(frames, list) or not frames:
        raise DamcapError(f"{path}: expected a JSON object with a non-empty 'frames' list")
    stems = photos_by_stem(list(photo_sizes))
    base = {k: v for k, v in doc.items() if k != "frames"}
    found: dict[str, RegisteredPhoto] = {}
    entry_of: dict[str, int] = {}
    ignored = 0
    for i, fr in enumerate(frames):
        where = f"frames[{i}]"
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise DamcapError(f"{path}: {where} needs 'file_path' and 'transform_matrix'")
        name = stems.get(Path(str(fr["file_path"])).stem)
        if name is None:
            ignored += 1
            continue
        if name in entry_of:  # never resolved silently by the last entry
            raise DamcapError(f"{path}: photo {name} has two pose entries (frames[{entry_of[name]}] and {where}), a "
                              "duplicate entry; keep one")
        entry_of[name] = i
        try:
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise DamcapError(f"{path}: {where}: transform_matrix is not a number matrix") from None
        if m.shape == (3, 4):
            m = np.vstack([m, [0, 0, 0, 1]])
        if m.shape != (4, 4):
            raise DamcapError(f"{path}: {where}: transform_matrix has shape {m.shape}, expected 4x4")
        found[name] = RegisteredPhoto(name, _checked(path, where, m), _ngp_camera(path, where, fr, base, photo_sizes[name]))
    return finish_registration("transforms.json", path, found, list(photo_sizes), f"no frame in {path.name}",
                   {"pose_entries_without_photo": ignored})


def read_llff_poses_bounds(path: str | os.PathLike, photo_sizes: dict[str, tuple[int, int]]) -> Registration:
    """Cameras from an LLFF ``poses_bounds.npy`` (one row of 17 per photo, sorted by name).

    The stored (h, w, f) describe the resolution the poses were made at; the focal length is
    scaled to the photos (principal point at the image centre, no distortion, as LLFF assumes).

    Raises:
        DamcapError: unreadable file, wrong shape, row count different from the photo count,
            aspect ratio different from the photos'.
    """
    path = Path(path)
    try:
        arr = np.load(path, allow_pickle=False, mmap_mode="r")  # header first: the shape is checked before reading
    except (OSError, ValueError, EOFError) as e:
        raise DamcapError(f"{path}: cannot read LLFF poses_bounds.npy ({e})") from None
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise DamcapError(f"{path}: expected an (N, 17) array (3x5 pose + 2 bounds per row), got shape {arr.shape}")
    names = sorted(photo_sizes)
    if len(arr) != len(names):
        raise DamcapError(f"{path}: {len(arr)} rows but {len(names)} photos; LLFF rows follow the sorted photo "
                          "names one to one, so the photo folder must hold exactly the posed photos")
    if arr.dtype.kind not in "fiu":
        raise DamcapError(f"{path}: expected numbers, got dtype {arr.dtype}")
    try:
        arr = np.array(arr, dtype=np.float64)
    except (OSError, ValueError) as e:
        raise DamcapError(f"{path}: cannot read LLFF poses_bounds.npy ({e})") from None
    if not (np.isfinite(arr).all() and np.abs(arr).max() <= np.finfo(np.float32).max):
        raise DamcapError(f"{path}: contains NaN or inf (or values beyond float32)")
    found: dict[str, RegisteredPhoto] = {}
    for i, name in enumerate(names):
        m35 = arr[i, :15].reshape(3, 5)
        h, w, f = m35[:, 4]
        pw, ph = photo_sizes[name]
        if h <= 0 or w <= 0 or f <= 0:
            raise DamcapError(f"{path}: row {i} ({name}): invalid (h, w, f) = {(h, w, f)}")
        if abs(pw / w - ph / h) > 0.01:
            raise DamcapError(f"{path}: row {i} ({name}): poses are for {w:g}x{h:g} but the photo is {pw}x{ph}")
        s = pw / w
        cam = PhotoCamera(pw, ph, f * s, f * ph / h, pw / 2, ph / 2)
        found[name] = RegisteredPhoto(name, _checked(path, f"row {i} ({name})", world_from_cam_of_llff(m35[:, :4])), cam)
    return finish_registration("llff", path, found, names, "", {"bounds_near_far": [float(arr[:, 15].min()), float(arr[:, 16].max())]})


def load_known_poses(spec: str, photo_sizes: dict[str, tuple[int, int]]) -> Registration:
    """Known cameras from ``transforms.json`` (any ``.json``), LLFF ``.npy`` or ``colmap:DIR``.

    Args:
        spec: the ``--poses`` value.
        photo_sizes: photo file name -> (width, height).

    Raises:
        DamcapError: unknown kind, missing file, or what the format reader raises.
    """
    if spec.startswith("colmap:"):
        return read_colmap_model(spec[len("colmap:"):], sorted(photo_sizes))
    path = Path(spec)
    if not path.is_file():
        raise DamcapError(f"{path}: pose file not found (--poses takes transforms.json, poses_bounds.npy or colmap:DIR)")
    if path.suffix.lower() == ".json":
        return read_transforms_json(path, photo_sizes)
    if path.suffix.lower() == ".npy":
        return read_llff_poses_bounds(path, photo_sizes)
    raise DamcapError(f"{path}: unknown pose file kind {path.suffix!r}; use a .json (nerfstudio/instant-ngp), "
                      "an LLFF poses_bounds.npy, or colmap:DIR")
