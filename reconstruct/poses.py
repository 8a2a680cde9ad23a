"""Registered cameras, from SfM or from known poses, and the one place where camera axes change.

Every camera that enters damcap ends up as :class:`RegisteredPhoto`: a ``world_from_cam`` with the
contract's OpenGL camera axes (x right, y up, looking down -z) plus the photo's (possibly
distorted) :class:`~damcap.reconstruct.undistort.PhotoCamera`. The axis conventions met at the edge:

- COLMAP: ``cam_from_world``, camera axes x right, y down, looking down +z.
- LLFF ``poses_bounds.npy``: rows of 17 = a 3x5 matrix ``[R | t | (h, w, f)]`` (camera-to-world,
  columns of R = the camera's (down, right, backwards) axes in world space) + near/far bounds;
  h, w, f at the resolution the poses were computed at; rows follow the sorted image names.
- nerfstudio / instant-ngp ``transforms.json``: camera-to-world with OpenGL axes already.

Known poses: ``--poses transforms.json``, ``--poses poses_bounds.npy`` or ``--poses colmap:DIR``
(:func:`load_known_poses`).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from damcap.common.capture_folder import rigid_problem
from damcap.common.errors import DamcapError

from damcap.reconstruct.undistort import PhotoCamera, camera_from_colmap

#: OpenGL camera axes from COLMAP's (and back): flip y and z. Its own inverse.
GL_FROM_CV_CAM = np.diag([1.0, -1.0, -1.0, 1.0])
#: camera centres whose spread is at most this fraction of their largest distance from the world
#: origin count as one position (relative, so that any unit works; float64 resolves about 1e-16)
COINCIDENT_CENTRES_REL = 1e-9


@dataclass
class RegisteredPhoto:
    """One photo with a camera."""

    name: str
    """file name in the photo folder"""
    world_from_cam: np.ndarray
    """(4, 4) float64 camera-to-world, OpenGL camera axes"""
    camera: PhotoCamera


@dataclass
class Registration:
    """Cameras for a photo set plus the sparse points that came with them (if any)."""

    photos: list[RegisteredPhoto]
    """registered photos, sorted by name"""
    unregistered: dict[str, str] = field(default_factory=dict)
    """photo name -> why it has no camera"""
    points_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """(P, 3) float64 sparse 3D points, same world frame as the cameras"""
    points_seen_from: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.int64))
    """(P,) int64 index into ``photos`` of one photo that observes each point"""
    source: str = ""
    """'sfm', 'transforms.json', 'llff' or 'colmap'"""
    stats: dict[str, Any] = field(default_factory=dict)
    """numbers worth reporting (registered count, mean reprojection error px, timings s)"""

    @property
    def world_from_cams(self) -> np.ndarray:
        """(N, 4, 4) float64 camera-to-world of every registered photo."""
        return np.stack([p.world_from_cam for p in self.photos]) if self.photos else np.zeros((0, 4, 4))


# --------------------------------------------------------------------------------------------
# Axis conversions (pure)
# --------------------------------------------------------------------------------------------

def world_from_cam_of_colmap(cam_from_world_cv: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world from COLMAP's world-to-camera.

    Args:
        cam_from_world_cv: (3, 4) or (4, 4) float64 ``[R | t]``, COLMAP camera axes
            (x right, y down, looking down +z).

    Returns:
        (4, 4) float64 world_from_cam, OpenGL camera axes.

    >>> world_from_cam_of_colmap(np.eye(4)).diagonal().tolist()
    [1.0, -1.0, -1.0, 1.0]
    """
    m = np.eye(4)
    m[:3, :4] = np.asarray(cam_from_world_cv, dtype=np.float64)[:3, :4]
    return np.linalg.inv(m) @ GL_FROM_CV_CAM


def colmap_of_world_from_cam(world_from_cam: np.ndarray) -> np.ndarray:
    """COLMAP's (3, 4) cam_from_world (camera axes x right, y down, +z forward) of an OpenGL
    camera-to-world; inverse of :func:`world_from_cam_of_colmap`."""
    m = np.asarray(world_from_cam, dtype=np.float64) @ GL_FROM_CV_CAM
    return np.linalg.inv(m)[:3, :4]


def world_from_cam_of_llff(llff_3x4: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world from an LLFF camera-to-world ``[R | t]``.

    Args:
        llff_3x4: (3, 4) float64; columns of R are the camera's (down, right, backwards) axes.

    Returns:
        (4, 4) float64 world_from_cam with columns (right, up, backwards, centre).
    """
    a = np.asarray(llff_3x4, dtype=np.float64)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = a[:, 1], -a[:, 0], a[:, 2], a[:, 3]
    return m


def llff_of_world_from_cam(world_from_cam: np.ndarray) -> np.ndarray:
    """(3, 4) LLFF ``[R | t]`` (down, right, backwards) of an OpenGL camera-to-world."""
    m = np.asarray(world_from_cam, dtype=np.float64)
    return np.stack([-m[:3, 1], m[:3, 0], m[:3, 2], m[:3, 3]], axis=1)


def orthonormalize_rotation(world_from_cam: np.ndarray) -> np.ndarray:
    """Nearest rigid transform (SVD projection of the rotation part): files store 6-8 digits,
    and a rotation read back is orthonormal only to that precision.

    Raises:
        ValueError: the rotation part is far from a rotation (scale, shear or reflection).
    """
    m = np.array(world_from_cam, dtype=np.float64)
    u, s, vt = np.linalg.svd(m[:3, :3])
    if np.abs(s - 1).max() > 1e-2 or np.linalg.det(u @ vt) < 0:
        raise ValueError(f"not a rotation: singular values {np.round(s, 4).tolist()}")
    m[:3, :3] = u @ vt
    m[3] = (0, 0, 0, 1)
    return m


def coincident_centres(world_from_cams: np.ndarray, rel: float = COINCIDENT_CENTRES_REL) -> str | None:
    """Why cameras cannot see an object from different sides, or None: all their centres at one
    point (translations scaled by 0, one matrix repeated, a panorama turned about its centre).

    Args:
        world_from_cams: (N, 4, 4) camera-to-world.
        rel: spread (largest distance from the centres' mean) at or below ``rel`` times the
            largest centre's distance from the origin counts as one position.

    >>> coincident_centres(np.stack([np.eye(4)] * 3))
    'all 3 cameras are at the same position [0.0, 0.0, 0.0] (spread 0)'
    """
    c = np.asarray(world_from_cams, dtype=np.float64)[:, :3, 3]
    if len(c) < 2:
        return None
    spread = float(np.linalg.norm(c - c.mean(0), axis=1).max())
    if spread > rel * float(np.linalg.norm(c, axis=1).max()):
        return None
    where = [float(f"{x:.6g}") + 0.0 for x in c[0]]  # + 0.0: no '-0.0'
    return f"all {len(c)} cameras are at the same position {where} (spread {spread:.3g})"


# --------------------------------------------------------------------------------------------
# Matching pose entries to photos
# --------------------------------------------------------------------------------------------

def _by_stem(photo_names: list[str]) -> dict[str, str]:
    return {Path(n).stem: n for n in photo_names}


def _finish(source: str, path: Path, found: dict[str, RegisteredPhoto], photo_names: list[str],
            missing_reason: str, extra: dict[str, Any]) -> Registration:
    if not found:
        raise DamcapError(
            f"{path}: none of its entries matches a photo by base name (photos: {photo_names[:3]}...); "
            "the pose file must describe these photos"
        )
    unregistered = {n: missing_reason for n in photo_names if n not in found}
    photos = [found[n] for n in sorted(found)]
    same = coincident_centres(np.stack([p.world_from_cam for p in photos]))
    if same:
        raise DamcapError(f"{path}: {same}; the photos must be taken from different positions around the object "
                          "(translations scaled by 0, or one matrix repeated?)")
    return Registration(photos=photos, unregistered=unregistered, source=source,
                        stats={"registered": len(photos), "photos": len(photo_names), **extra})


def _checked(path: Path, what: str, m: np.ndarray) -> np.ndarray:
    try:
        m = orthonormalize_rotation(m)
    except ValueError as e:
        raise DamcapError(f"{path}: {what} is not a rigid camera-to-world ({e})") from None
    problem = rigid_problem(m)
    if problem:
        raise DamcapError(f"{path}: {what} is not a rigid camera-to-world: {problem}")
    return m


# --------------------------------------------------------------------------------------------
# transforms.json (nerfstudio / instant-ngp)
# --------------------------------------------------------------------------------------------

def _ngp_camera(path: Path, where: str, obj: dict[str, Any], base: dict[str, Any], size: tuple[int, int]) -> PhotoCamera:
    """Intrinsics of one frame: the frame's keys over the file's shared keys, scaled to the photo."""
    v = {**base, **{k: obj[k] for k in obj if k != "transform_matrix"}}
    model = str(v.get("camera_model", "OPENCV"))
    if "FISHEYE" in model.upper() or model.upper() == "EQUIRECTANGULAR":
        raise DamcapError(f"{path}: {where}: camera_model {model} is not supported (pinhole/OpenCV cameras only)")
    w_file = float(v.get("w", size[0]))
    h_file = float(v.get("h", size[1]))
    if "fl_x" in v:
        fx = float(v["fl_x"])
        fy = float(v.get("fl_y", fx))
    elif "camera_angle_x" in v:
        fx = 0.5 * w_file / math.tan(0.5 * float(v["camera_angle_x"]))
        fy = 0.5 * h_file / math.tan(0.5 * float(v["camera_angle_y"])) if "camera_angle_y" in v else fx
    else:
        raise DamcapError(f"{path}: {where}: no focal length (need fl_x or camera_angle_x)")
    cx = float(v.get("cx", w_file / 2))
    cy = float(v.get("cy", h_file / 2))
    if float(v.get("k4", 0.0) or 0.0) != 0.0:
        raise DamcapError(f"{path}: {where}: k4 is a fisheye coefficient; only OpenCV pinhole distortion is supported")
    dist = (float(v.get("k1", 0) or 0), float(v.get("k2", 0) or 0), float(v.get("p1", 0) or 0), float(v.get("p2", 0) or 0),
            float(v.get("k3", 0) or 0), 0.0, 0.0, 0.0)
    vals = (w_file, h_file, fx, fy, cx, cy) + dist
    if not all(math.isfinite(x) for x in vals) or fx <= 0 or fy <= 0 or w_file <= 0 or h_file <= 0:
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
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DamcapError(f"{path}: cannot read transforms.json ({e})") from None
    frames = doc.get("frames") if isinstance(doc, dict) else None
    if not isinstance(frames, list) or not frames:
        raise DamcapError(f"{path}: expected a JSON object with a non-empty 'frames' list")
    stems = _by_stem(list(photo_sizes))
    base = {k: v for k, v in doc.items() if k != "frames"}
    found: dict[str, RegisteredPhoto] = {}
    ignored = 0
    for i, fr in enumerate(frames):
        where = f"frames[{i}]"
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise DamcapError(f"{path}: {where} needs 'file_path' and 'transform_matrix'")
        name = stems.get(Path(str(fr["file_path"])).stem)
        if name is None:
            ignored += 1
            continue
        try:
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise DamcapError(f"{path}: {where}: transform_matrix is not a number matrix") from None
        if m.shape == (3, 4):
            m = np.vstack([m, [0, 0, 0, 1]])
        if m.shape != (4, 4):
            raise DamcapError(f"{path}: {where}: transform_matrix has shape {m.shape}, expected 4x4")
        found[name] = RegisteredPhoto(name, _checked(path, where, m), _ngp_camera(path, where, fr, base, photo_sizes[name]))
    return _finish("transforms.json", path, found, list(photo_sizes), f"no frame in {path.name}",
                   {"pose_entries_without_photo": ignored})


# --------------------------------------------------------------------------------------------
# LLFF poses_bounds.npy
# --------------------------------------------------------------------------------------------

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
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise DamcapError(f"{path}: cannot read LLFF poses_bounds.npy ({e})") from None
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise DamcapError(f"{path}: expected an (N, 17) array (3x5 pose + 2 bounds per row), got shape {arr.shape}")
    names = sorted(photo_sizes)
    if len(arr) != len(names):
        raise DamcapError(f"{path}: {len(arr)} rows but {len(names)} photos; LLFF rows follow the sorted photo "
                          "names one to one, so the photo folder must hold exactly the posed photos")
    if not np.isfinite(arr).all():
        raise DamcapError(f"{path}: contains NaN or inf")
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
    return _finish("llff", path, found, names, "", {"bounds_near_far": [float(arr[:, 15].min()), float(arr[:, 16].max())]})


# --------------------------------------------------------------------------------------------
# COLMAP sparse model
# --------------------------------------------------------------------------------------------

def registration_of_reconstruction(rec: Any, photo_names: list[str], source: str, where: str) -> Registration:
    """Cameras and points of a ``pycolmap.Reconstruction``, in OpenGL camera axes.

    Images are matched to photos by name, then by base name; points keep one observing photo.
    """
    stems = _by_stem(photo_names)
    found: dict[str, RegisteredPhoto] = {}
    id_to_name: dict[int, str] = {}
    for image_id in rec.reg_image_ids():
        img = rec.image(image_id)
        name = img.name if img.name in photo_names else stems.get(Path(img.name).stem)
        if name is None:
            continue
        cam = rec.camera(img.camera_id)
        pc = camera_from_colmap(cam.model.name, cam.width, cam.height, np.asarray(cam.params))
        m = world_from_cam_of_colmap(img.cam_from_world().matrix())
        found[name] = RegisteredPhoto(name, m, pc)
        id_to_name[image_id] = name
    reg = _finish(source, Path(where), found, photo_names, "", {})
    index = {p.name: k for k, p in enumerate(reg.photos)}
    pts, seen = [], []
    for _, p3d in rec.points3D.items():
        for el in p3d.track.elements:
            n = id_to_name.get(el.image_id)
            if n is not None:
                pts.append(p3d.xyz)
                seen.append(index[n])
                break
    if pts:
        reg.points_world = np.asarray(pts, dtype=np.float64)
        reg.points_seen_from = np.asarray(seen, dtype=np.int64)
    return reg


def read_colmap_model(folder: str | os.PathLike, photo_names: list[str]) -> Registration:
    """Cameras and sparse points from a COLMAP model folder (``cameras/images/points3D`` .bin or .txt).

    Raises:
        DamcapError: the folder is missing or holds no readable model.
    """
    from damcap.reconstruct.sfm import import_pycolmap

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


# --------------------------------------------------------------------------------------------
# Dispatch
# --------------------------------------------------------------------------------------------

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
