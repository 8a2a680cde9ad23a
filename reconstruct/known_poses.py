"""Known poses from files (``--poses transforms.json``, ``--poses poses_bounds.npy``, ``--poses
colmap:DIR``, ``--poses strecha:DIR``): :func:`load_known_poses` reads any of them into a
:class:`~damcap.reconstruct.poses.Registration`."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from damcap.common.capture_folder import rigid_problem
from damcap.common.errors import DamcapError
from damcap.common.validate import MAX_IMAGE_SIDE, finite_in, load_json_file
from damcap.reconstruct.colmap.model import read_colmap_model
from damcap.reconstruct.poses import (
    GL_FROM_CV_CAM,
    RegisteredPhoto,
    Registration,
    finish_registration,
    nearest_facing_camera,
    orthonormalize_rotation,
    photos_by_stem,
    world_from_cam_of_llff,
)
from damcap.reconstruct.undistort import PhotoCamera


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
    model = str(v.get("camera_model", "OPENCV")).upper()
    if model not in ("OPENCV", "PINHOLE", "OPENCV_FISHEYE"):
        raise DamcapError(f"{path}: {where}: camera_model {model} is not supported (nerfstudio's OPENCV, PINHOLE or OPENCV_FISHEYE)")
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
    if not (fx > 0 and fy > 0):
        raise DamcapError(f"{path}: {where}: invalid intrinsics {dict(w=w_file, h=h_file, fl_x=fx, fl_y=fy, cx=cx, cy=cy)}")
    if model == "OPENCV_FISHEYE":  # nerfstudio's fisheye: k1..k4 of OpenCV's (and COLMAP's) equidistant model
        if num("p1", 0.0) or num("p2", 0.0):
            raise DamcapError(f"{path}: {where}: p1/p2 are not parameters of camera_model OPENCV_FISHEYE (k1..k4 are)")
        params = (fx, fy, cx, cy, num("k1", 0.0), num("k2", 0.0), num("k3", 0.0), num("k4", 0.0))
        cam = PhotoCamera(round(w_file), round(h_file), fx, fy, cx, cy, model="OPENCV_FISHEYE", params=params)
    else:
        if num("k4", 0.0) != 0.0:
            raise DamcapError(f"{path}: {where}: k4 is a fisheye coefficient; give camera_model OPENCV_FISHEYE for a fisheye")
        dist = (num("k1", 0.0), num("k2", 0.0), num("p1", 0.0), num("p2", 0.0), num("k3", 0.0), 0.0, 0.0, 0.0)
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
    reg = finish_registration("transforms.json", path, found, list(photo_sizes), f"no frame in {path.name}",
                              {"pose_entries_without_photo": ignored})
    if doc.get("ply_file_path") and reg.photos:
        ply = path.parent / str(doc["ply_file_path"])
        reg.points_world = read_point_cloud(ply, f"{path}: ply_file_path")
        reg.points_seen_from = nearest_facing_camera(reg.points_world, reg.world_from_cams)
        reg.stats["points_from"] = str(ply)
    return reg


def read_point_cloud(path: Path, where: str) -> np.ndarray:
    """(P, 3) float64 points of a point-cloud file (PLY and the formats Open3D reads).

    Raises:
        DamcapError: the file is missing, unreadable, or holds no finite point.
    """
    import open3d as o3d

    if not path.is_file():
        raise DamcapError(f"{where}: {path} not found; restore it or remove the key (the points seed the geometry)")
    pts = np.asarray(o3d.io.read_point_cloud(str(path)).points, np.float64)
    pts = pts[np.isfinite(pts).all(1)]
    if len(pts) == 0:
        raise DamcapError(f"{where}: {path} holds no readable point (a PLY point cloud with x, y, z expected)")
    return pts


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


#: numbers on each line of a Strecha ``.camera`` file: K (3 rows), radial distortion, R (3 rows), C, image size
STRECHA_ROWS = (3, 3, 3, 3, 3, 3, 3, 3, 2)
#: |K's skew| allowed, as a fraction of its focal length (PhotoCamera has no skew)
STRECHA_MAX_SKEW_REL = 1e-6


def photo_camera_of_strecha(k: np.ndarray, file_size: tuple[int, int], photo_size: tuple[int, int]) -> PhotoCamera:
    """The :class:`PhotoCamera` of a Strecha camera matrix, for the photo as it is.

    Strecha's K (as openMVG and OpenCV read it) puts pixel (i, j)'s centre at (j, i); damcap puts
    it at (j + 0.5, i + 0.5) (:mod:`damcap.reconstruct.undistort`). In damcap's convention the
    image spans [0, w] x [0, h], so a resize by s maps every coordinate to s times itself:
    ``c_photo = s (c_file + 0.5)``, ``f_photo = s f_file``. A factor-2 downscale thus puts the
    principal point at ``c_file / 2 + 0.25``, not ``c_file / 2``.

    Args:
        k: (3, 3) float64 upper-triangular intrinsic matrix, K[2, 2] = 1, zero skew, pixels at
            ``file_size``.
        file_size: (width, height) the file's K refers to, pixels.
        photo_size: (width, height) of the photo, pixels (same aspect ratio).

    Returns:
        pinhole camera at ``photo_size`` (no distortion).

    >>> c = photo_camera_of_strecha(np.array([[2000.0, 0, 1535.5], [0, 2000, 1023.5], [0, 0, 1]]), (3072, 2048), (1536, 1024))
    >>> (c.fx, c.fy, c.cx, c.cy)
    (1000.0, 1000.0, 768.0, 512.0)
    """
    sx, sy = photo_size[0] / file_size[0], photo_size[1] / file_size[1]
    return PhotoCamera(int(photo_size[0]), int(photo_size[1]), float(k[0, 0] * sx), float(k[1, 1] * sy),
                       float((k[0, 2] + 0.5) * sx), float((k[1, 2] + 0.5) * sy))


def world_from_cam_of_strecha(rotation_world_from_cam: np.ndarray, centre_world: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world of a Strecha camera (a world point X projects as K R^T (X - C)).

    Args:
        rotation_world_from_cam: (3, 3) R, camera-to-world, OpenCV camera axes (x right, y down,
            looking down +z).
        centre_world: (3,) C, the camera centre, world units.

    Returns:
        (4, 4) float64 world_from_cam, OpenGL camera axes (x right, y up, looking down -z).

    >>> world_from_cam_of_strecha(np.eye(3), np.array([1.0, 2.0, 3.0]))[:3].tolist()
    [[1.0, 0.0, 0.0, 1.0], [0.0, -1.0, 0.0, 2.0], [0.0, 0.0, -1.0, 3.0]]
    """
    m = np.eye(4)
    m[:3, :3] = rotation_world_from_cam
    m[:3, 3] = centre_world
    return m @ GL_FROM_CV_CAM + 0.0


def _strecha_rows(path: Path) -> list[list[float]]:
    """The rows of numbers of one ``.camera`` file, checked against :data:`STRECHA_ROWS`."""
    try:
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as e:
        raise DamcapError(f"{path}: cannot read the Strecha camera file ({e})") from None
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if len(lines) != len(STRECHA_ROWS):
        raise DamcapError(f"{path}: a Strecha camera file has {len(STRECHA_ROWS)} lines (3 of K, distortion, 3 of R, C, "
                          f"width height), got {len(lines)}")
    rows = []
    for i, (line, n) in enumerate(zip(lines, STRECHA_ROWS)):
        words = line.split()
        if len(words) != n:
            raise DamcapError(f"{path}: line {i + 1} needs {n} numbers, got {len(words)} ({line.strip()[:60]!r})")
        row = []
        for w in words:
            try:
                v = float(w)
            except ValueError:
                raise DamcapError(f"{path}: line {i + 1}: {w[:40]!r} is not a number") from None
            row.append(finite_in(v, "float32", f"line {i + 1} value", path))
        rows.append(row)
    return rows


def read_strecha_camera(path: str | os.PathLike, photo_size: tuple[int, int]) -> tuple[np.ndarray, PhotoCamera]:
    """One Strecha ``.camera`` file: (world_from_cam OpenGL (4, 4), the camera at ``photo_size``).

    The file (Strecha et al. 2008, as openMVG reads it): 3 rows of K, 1 row of radial distortion
    (must be zero: the images are undistorted), 3 rows of R (camera-to-world, OpenCV axes), 1 row
    of C (centre, world units), 1 row ``width height`` (the image K refers to).

    Raises:
        DamcapError: wrong layout, non-numbers, NaN/inf, K not of the form ``[[f, 0, c], [0, f, c],
            [0, 0, 1]]`` with f > 0, non-zero distortion, R not a rotation, size out of range or of
            another aspect ratio than the photo's. One line naming the file and the value.
    """
    path = Path(path)
    rows = _strecha_rows(path)
    k = np.array(rows[0:3], dtype=np.float64)
    dist, rot, centre, size = rows[3], np.array(rows[4:7]), np.array(rows[7]), rows[8]
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise DamcapError(f"{path}: focal lengths K[0,0], K[1,1] must be > 0, got {k[0, 0]:g}, {k[1, 1]:g}")
    if k[2, 2] != 1.0 or k[1, 0] != 0.0 or k[2, 0] != 0.0 or k[2, 1] != 0.0:
        raise DamcapError(f"{path}: K must be upper triangular with K[2,2] = 1, got last rows {k[1:].tolist()}")
    if abs(k[0, 1]) > STRECHA_MAX_SKEW_REL * k[0, 0]:
        raise DamcapError(f"{path}: K has skew {k[0, 1]:g}; only cameras without skew are supported")
    if any(dist):
        raise DamcapError(f"{path}: radial distortion {dist} is not zero; only undistorted Strecha cameras are supported")
    if not all(float(v).is_integer() and 1 <= v <= MAX_IMAGE_SIDE for v in size):
        raise DamcapError(f"{path}: image size must be two whole numbers in [1, {MAX_IMAGE_SIDE}], got {size}")
    w, h = int(size[0]), int(size[1])
    if abs(photo_size[0] / w - photo_size[1] / h) > 0.01:
        raise DamcapError(f"{path}: the camera is for {w}x{h} but the photo is {photo_size[0]}x{photo_size[1]} "
                          "(a different aspect ratio)")
    world_from_cam = _checked(path, "R", world_from_cam_of_strecha(rot, centre))
    return world_from_cam, photo_camera_of_strecha(k, (w, h), photo_size)


def read_strecha_cameras(folder: str | os.PathLike, photo_sizes: dict[str, tuple[int, int]]) -> Registration:
    """Cameras from a folder of Strecha ``.camera`` files (``NNNN.jpg.camera`` for ``NNNN.jpg``).

    Files are matched to photos by name without ``.camera`` (then by base name, so ``0000.jpg.camera``
    also serves ``0000.png``); files without a photo are ignored (counted in ``stats``), photos
    without a file are listed as unregistered. Intrinsics are scaled to each photo
    (:func:`photo_camera_of_strecha`).

    Args:
        folder: the folder of ``*.camera`` files (Strecha's ``gt_cameras``).
        photo_sizes: photo file name -> (width, height) pixels.

    Raises:
        DamcapError: no such folder, no ``.camera`` file, two files for one photo, or what
            :func:`read_strecha_camera` raises.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DamcapError(f"{folder}: Strecha camera folder not found (--poses strecha:DIR takes a folder of *.camera files)")
    files = sorted(p for p in folder.iterdir() if p.name.endswith(".camera") and p.is_file())
    if not files:
        raise DamcapError(f"{folder}: no *.camera file (Strecha's NNNN.jpg.camera) in the folder")
    stems = photos_by_stem(list(photo_sizes))
    found: dict[str, RegisteredPhoto] = {}
    file_of: dict[str, str] = {}
    ignored = 0
    for f in files:
        image = f.name[: -len(".camera")]
        name = image if image in photo_sizes else stems.get(Path(image).stem)
        if name is None:
            ignored += 1
            continue
        if name in file_of:  # never resolved silently by the last file
            raise DamcapError(f"{folder}: photo {name} has two camera files ({file_of[name]} and {f.name}); keep one")
        file_of[name] = f.name
        world_from_cam, cam = read_strecha_camera(f, photo_sizes[name])
        found[name] = RegisteredPhoto(name, world_from_cam, cam)
    return finish_registration("strecha", folder, found, list(photo_sizes), f"no .camera file in {folder.name}",
                               {"pose_entries_without_photo": ignored})


def load_known_poses(spec: str, photo_sizes: dict[str, tuple[int, int]]) -> Registration:
    """Known cameras from ``transforms.json`` (any ``.json``), LLFF ``.npy``, ``colmap:DIR`` or
    ``strecha:DIR`` (a folder of Strecha ``.camera`` files).

    Args:
        spec: the ``--poses`` value.
        photo_sizes: photo file name -> (width, height).

    Raises:
        DamcapError: unknown kind, missing file, or what the format reader raises.
    """
    if spec.startswith("colmap:"):
        return read_colmap_model(spec[len("colmap:"):], sorted(photo_sizes))
    if spec.startswith("strecha:"):
        return read_strecha_cameras(spec[len("strecha:"):], photo_sizes)
    path = Path(spec)
    if not path.is_file():
        raise DamcapError(f"{path}: pose file not found (--poses takes transforms.json, poses_bounds.npy, colmap:DIR or "
                          "strecha:DIR)")
    if path.suffix.lower() == ".json":
        return read_transforms_json(path, photo_sizes)
    if path.suffix.lower() == ".npy":
        return read_llff_poses_bounds(path, photo_sizes)
    raise DamcapError(f"{path}: unknown pose file kind {path.suffix!r}; use a .json (nerfstudio/instant-ngp), "
                      "an LLFF poses_bounds.npy, colmap:DIR or strecha:DIR")
