"""The capture folder (``docs/capture-format.md``): read, write and validate.

A capture folder holds ``transforms.json`` (cameras, frames, splits), ``images/*.exr`` (linear
radiance), ``geometry/*.exr`` (world normal ``N.*``, world position ``P.*``, coverage ``A``) and
optionally ``weights/*.exr`` (material weights ``W.0 .. W.{n-1}``). Everything downstream works
on the plain arrays of :class:`FrameData`.
"""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Literal

import numpy as np

from damcap.common.atomic import write_json_atomic
from damcap.common.cameras import up_direction
from damcap.common.errors import DamcapError
from damcap.common.exr import read_exr_channels, write_exr
from damcap.common.validate import MAX_MATERIALS, check_camera_centres, finite_in, load_json_file, require_foreground, require_resolution

FORMAT_VERSION = 1
RADIANCE_CHANNELS = ("R", "G", "B")
NORMAL_CHANNELS = ("N.X", "N.Y", "N.Z")
POSITION_CHANNELS = ("P.X", "P.Y", "P.Z")
COVERAGE_CHANNEL = "A"
GEOMETRY_CHANNELS = NORMAL_CHANNELS + POSITION_CHANNELS + (COVERAGE_CHANNEL,)
#: |norm(N) - 1| allowed on covered pixels (half-float storage rounds at about 1e-3).
NORMAL_UNIT_TOL = 1e-2
#: max |R^T R - I| and |det R - 1| allowed for a camera-to-world rotation.
RIGID_TOL = 1e-3
#: the ``colorspace`` values a capture may state: linear, scene-referred, with these primaries
#: (the names of ``damcap hdr --colorspace``)
COLORSPACES: tuple[str, ...] = ("lin_rec709", "acescg")
#: bytes per pixel a frame needs in memory (radiance, geometry, weights and derived float32
#: buffers, with copies): what bounds the resolution transforms.json may state
FRAME_BYTES_PER_PIXEL = 4 * 64
#: largest transforms.json read, bytes: refused from its size, before parsing (a 182 MB one took
#: 35 s and 1.2 GB to parse and refuse). 32 MiB holds about 60,000 frames of reconstruct's ~520
#: bytes each, far beyond a capture's hundreds
MAX_TRANSFORMS_BYTES = 32 * 2 ** 20

Split = Literal["train", "test", "all"]


def weight_channels(n: int) -> tuple[str, ...]:
    """Channel names of an n-material weight map: ``W.0 .. W.{n-1}``."""
    return tuple(f"W.{i}" for i in range(n))


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels; pixel (i, j) has its centre at (j + 0.5, i + 0.5)."""

    fl_x: float
    fl_y: float
    cx: float
    cy: float
    w: int
    h: int

    def to_json(self) -> dict[str, Any]:
        return {"fl_x": self.fl_x, "fl_y": self.fl_y, "cx": self.cx, "cy": self.cy, "w": self.w, "h": self.h}


@dataclass
class Frame:
    """One photo of a capture: its files, camera and exposure record."""

    file_path: str
    """Radiance image, relative to the capture root (``images/0000.exr``)."""
    geometry_path: str
    """Geometry EXR, relative to the capture root."""
    world_from_cam: np.ndarray
    """(4, 4) float64 camera-to-world, OpenGL camera axes (x right, y up, looking down -z)."""
    intrinsics: Intrinsics
    weights_path: str | None = None
    exposure: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    """Unknown keys, preserved on rewrite."""

    @property
    def name(self) -> str:
        """The frame's base name (``images/IMG_5881.exr`` -> ``IMG_5881``)."""
        return Path(self.file_path).stem

    @property
    def camera_centre_world(self) -> np.ndarray:
        """(3,) camera centre in world space."""
        return self.world_from_cam[:3, 3].copy()


@dataclass
class Capture:
    """A parsed ``transforms.json`` plus the folder it lives in."""

    root: Path
    frames: list[Frame]
    train_filenames: list[str]
    test_filenames: list[str]
    colorspace: str = "lin_rec709"
    materials: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def up_world(self) -> np.ndarray:
        """(3,) unit up direction of the capture, from its cameras (:func:`.cameras.up_direction`)."""
        return up_direction(np.stack([f.world_from_cam for f in self.frames]))

    def split(self, split: Split) -> list[Frame]:
        """Frames of a split, in file order. Raises DamcapError when the split is empty."""
        if split == "all":
            frames = list(self.frames)
        elif split in ("train", "test"):
            wanted = set(self.train_filenames if split == "train" else self.test_filenames)
            frames = [f for f in self.frames if f.file_path in wanted]
        else:
            raise DamcapError(f"unknown split {split!r}: use train, test or all")
        if not frames:
            raise DamcapError(
                f"{self.root / 'transforms.json'}: the {split!r} split is empty; "
                f"list frames in '{split}_filenames'"
            )
        return frames

    def frame(self, name: str) -> Frame:
        """The frame with this base name or file path."""
        for f in self.frames:
            if name in (f.name, f.file_path):
                return f
        raise DamcapError(f"{self.root}: no frame named {name!r}")


@dataclass
class FrameData:
    """The per-pixel arrays of one frame."""

    radiance_lin: np.ndarray
    """(H, W, 3) float32, linear scene-referred radiance, >= 0."""
    normal_world: np.ndarray
    """(H, W, 3) float32, unit world-space normals on covered pixels, 0 on background."""
    position_world: np.ndarray
    """(H, W, 3) float32, world-space surface points (scene units)."""
    coverage: np.ndarray
    """(H, W) float32 in [0, 1]."""
    weights: np.ndarray | None = None
    """(H, W, n) float32 material weights summing to 1 on covered pixels, or None."""


# --------------------------------------------------------------------------------------------
# transforms.json
# --------------------------------------------------------------------------------------------

def _number(where: str, key: str, value: Any) -> float:
    # finite in float32: intrinsics end up in float32 ray and pixel buffers
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DamcapError(f"{where}: '{key}' must be a finite number, got {value!r}")
    return finite_in(value, "float32", f"'{key}'", where)


def _intrinsics(where: str, obj: dict[str, Any], default: Intrinsics | None) -> Intrinsics:
    keys = ("fl_x", "fl_y", "cx", "cy", "w", "h")
    if default is None and not all(k in obj for k in keys):
        missing = [k for k in keys if k not in obj]
        raise DamcapError(f"{where}: missing camera intrinsics {', '.join(missing)}")
    vals = {k: _number(where, k, obj[k]) if k in obj else getattr(default, k) for k in keys}
    if "fl_y" not in obj and "fl_x" in obj and default is None:
        vals["fl_y"] = vals["fl_x"]
    w, h = vals["w"], vals["h"]
    if w != int(w) or h != int(h) or not (w > 0 and h > 0):
        raise DamcapError(f"{where}: image size must be positive integers, got w={w}, h={h}")
    # a frame's pixels: radiance (3) + geometry (7) + derived buffers, float32, a few copies
    require_resolution(w, h, FRAME_BYTES_PER_PIXEL, "a frame", where)
    if not (vals["fl_x"] > 0 and vals["fl_y"] > 0):
        bad = ", ".join(f"{k}={vals[k]!r}" for k in ("fl_x", "fl_y") if not vals[k] > 0)
        raise DamcapError(f"{where}: focal lengths must be positive, got {bad}")
    return Intrinsics(vals["fl_x"], vals["fl_y"], vals["cx"], vals["cy"], int(w), int(h))


def _frame_file(where: str, root: Path, key: str, value: Any, must_exist: bool) -> str:
    """A frame's file path (``file_path``, ``geometry_path``, ``weights_path``), checked: a
    relative path that stays inside the capture folder (and, if ``must_exist``, names a file).

    Raises:
        DamcapError: naming the key and the value.
    """
    if not isinstance(value, str) or not value:
        raise DamcapError(f"{where}: '{key}' must be a file path relative to the capture folder, got {value!r}")
    rel = Path(value)
    if rel.is_absolute() or rel.drive or ".." in rel.parts:
        raise DamcapError(f"{where}: '{key}' {value!r} points outside the capture folder; "
                          "frame files are paths relative to it, without '..'")
    if must_exist and not (root / rel).is_file():
        what = "is not a file" if (root / rel).exists() else "names a file that does not exist"
        raise DamcapError(f"{where}: '{key}' {value!r} {what} (in {root})")
    return value


def _split_list(path: Path, key: str, value: Any, names: list[str]) -> list[str]:
    """A split (``train_filenames`` / ``test_filenames``), checked: distinct frame file paths."""
    if not isinstance(value, list) or not all(isinstance(s, str) for s in value):
        raise DamcapError(f"{path}: '{key}' must be a list of file paths")
    known = set(names)
    unknown = [s for s in value if s not in known]
    if unknown:
        raise DamcapError(f"{path}: '{key}' names {unknown[0]!r}, which is not a frame's file_path")
    if len(set(value)) != len(value):
        dup = next(s for s in value if value.count(s) > 1)
        raise DamcapError(f"{path}: '{key}' lists {dup!r} {value.count(dup)} times (duplicate entry)")
    return value


def rigid_problem(world_from_cam: np.ndarray, tol: float = RIGID_TOL) -> str | None:
    """Why a 4x4 matrix is not a rigid camera-to-world transform, or None when it is.

    Args:
        world_from_cam: (4, 4) float64.
        tol: allowed deviation of R^T R from I and of det(R) from 1.
    """
    m = np.asarray(world_from_cam, dtype=np.float64)
    if m.shape != (4, 4):
        return f"shape {m.shape}, expected 4x4"
    if not np.all(np.isfinite(m)):
        return "contains NaN or inf"
    if np.abs(m[3] - np.array([0, 0, 0, 1])).max() > tol:
        return f"last row is {m[3].tolist()}, expected [0, 0, 0, 1]"
    r = m[:3, :3]
    ortho = np.abs(r.T @ r - np.eye(3)).max()
    if ortho > tol:
        return f"rotation part is not orthonormal (max |R^T R - I| = {ortho:.3g}; scale or shear?)"
    det = np.linalg.det(r)
    if abs(det - 1) > tol:
        return f"rotation part has determinant {det:.3g}, expected +1 (a reflection?)"
    return None


def read_capture(root: str | os.PathLike, *, check_files: bool = True) -> Capture:
    """Parse ``root/transforms.json`` (structure only; pixels are read by :func:`read_frame`).

    Args:
        root: the capture folder.
        check_files: also require every frame's files to exist (``inspect`` leaves that to
            :func:`read_frame`, to list every missing file).

    Raises:
        DamcapError: missing folder or file, invalid JSON, missing keys, non-rigid cameras,
            frame paths outside the folder (or, with ``check_files``, missing), an unknown
            colorspace, split entries that name no frame, name one twice or are in both splits.
    """
    root = Path(root)
    if not root.is_dir():
        raise DamcapError(f"{root}: capture folder not found")
    path = root / "transforms.json"
    if not path.is_file():
        raise DamcapError(f"{path}: not found; a capture folder needs a transforms.json")
    doc = load_json_file(path, "transforms.json", MAX_TRANSFORMS_BYTES)
    if not isinstance(doc, dict):
        raise DamcapError(f"{path}: expected a JSON object at the top level")
    version = doc.get("damcap_version", FORMAT_VERSION)
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise DamcapError(
            f"{path}: damcap_version {version!r} is newer than this damcap reads ({FORMAT_VERSION}); upgrade damcap"
        )
    model = doc.get("camera_model", "PINHOLE")
    distortion = {k: doc[k] for k in ("k1", "k2", "k3", "k4", "p1", "p2") if doc.get(k, 0)}
    if model not in ("PINHOLE", "OPENCV") or distortion:
        raise DamcapError(
            f"{path}: camera_model {model!r} with distortion {distortion or 'none'}; a capture must be "
            "undistorted pinhole images (damcap reconstruct undistorts them)"
        )
    shared = _intrinsics(str(path), doc, None) if "fl_x" in doc else None
    raw_frames = doc.get("frames")
    if not isinstance(raw_frames, list) or not raw_frames:
        raise DamcapError(f"{path}: 'frames' must be a non-empty list")
    frames: list[Frame] = []
    known = {"file_path", "geometry_path", "weights_path", "transform_matrix", "exposure",
             "fl_x", "fl_y", "cx", "cy", "w", "h"}
    for i, fr in enumerate(raw_frames):
        where = f"{path}: frames[{i}]"
        if not isinstance(fr, dict):
            raise DamcapError(f"{where}: expected an object")
        for key in ("file_path", "geometry_path", "transform_matrix"):
            if key not in fr:
                raise DamcapError(f"{where}: missing '{key}'")
        file_path = _frame_file(where, root, "file_path", fr["file_path"], check_files)
        where = f"{where} ({file_path})"
        geometry_path = _frame_file(where, root, "geometry_path", fr["geometry_path"], check_files)
        weights_path = fr.get("weights_path")
        if weights_path is not None:
            _frame_file(where, root, "weights_path", weights_path, check_files)
        try:
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise DamcapError(f"{where}: transform_matrix is not a 4x4 number matrix") from None
        problem = rigid_problem(m)
        if problem:
            raise DamcapError(f"{where}: transform_matrix is not a rigid camera-to-world: {problem}")
        frames.append(Frame(
            file_path=file_path,
            geometry_path=geometry_path,
            world_from_cam=m,
            intrinsics=_intrinsics(where, fr, shared),
            weights_path=weights_path,
            exposure=fr.get("exposure"),
            extra={k: v for k, v in fr.items() if k not in known},
        ))
    names = [f.file_path for f in frames]
    check_camera_centres(np.stack([f.world_from_cam[:3, 3] for f in frames]), names, path)
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise DamcapError(f"{path}: duplicate file_path entries ({dup!r} appears {names.count(dup)} times)")
    splits = {key: _split_list(path, key, doc.get(key, []), names) for key in ("train_filenames", "test_filenames")}
    both = [s for s in splits["train_filenames"] if s in set(splits["test_filenames"])]
    if both:
        raise DamcapError(f"{path}: {both[0]!r} is in both 'train_filenames' and 'test_filenames'; "
                          "a frame is either a train or a test frame")
    colorspace = doc.get("colorspace", "lin_rec709")
    if colorspace not in COLORSPACES:
        raise DamcapError(f"{path}: colorspace {colorspace!r} is not one damcap knows; use one of {', '.join(COLORSPACES)}")
    materials = doc.get("materials")
    if materials is not None:  # bounded: weight_channels(materials) and the weight maps are built from it
        if not isinstance(materials, int) or isinstance(materials, bool) or not 1 <= materials <= MAX_MATERIALS:
            raise DamcapError(f"{path}: 'materials' must be an integer in [1, {MAX_MATERIALS}], got {materials!r}")
    top_known = {"damcap_version", "camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", "colorspace",
                 "frames", "train_filenames", "test_filenames", "materials"}
    return Capture(
        root=root,
        frames=frames,
        train_filenames=splits["train_filenames"],
        test_filenames=splits["test_filenames"],
        colorspace=colorspace,
        materials=materials,
        extra={k: v for k, v in doc.items() if k not in top_known},
    )


def capture_to_json(capture: Capture) -> dict[str, Any]:
    """The ``transforms.json`` document of a capture (unknown keys preserved)."""
    intr = {f.intrinsics for f in capture.frames}
    doc: dict[str, Any] = {"damcap_version": FORMAT_VERSION, "camera_model": "PINHOLE"}
    shared = intr.pop() if len(intr) == 1 else None
    if shared is not None:
        doc.update(shared.to_json())
    doc["colorspace"] = capture.colorspace
    frames = []
    for f in capture.frames:
        fr: dict[str, Any] = {"file_path": f.file_path, "geometry_path": f.geometry_path}
        if f.weights_path:
            fr["weights_path"] = f.weights_path
        fr["transform_matrix"] = np.asarray(f.world_from_cam, dtype=np.float64).tolist()
        if shared is None:
            fr.update(f.intrinsics.to_json())
        if f.exposure is not None:
            fr["exposure"] = f.exposure
        fr.update(copy.deepcopy(f.extra))
        frames.append(fr)
    doc["frames"] = frames
    doc["train_filenames"] = list(capture.train_filenames)
    doc["test_filenames"] = list(capture.test_filenames)
    if capture.materials is not None:
        doc["materials"] = capture.materials
    doc.update(copy.deepcopy(capture.extra))
    return doc


def write_transforms(capture: Capture) -> None:
    """Write ``capture.root/transforms.json`` atomically."""
    write_json_atomic(capture.root / "transforms.json", capture_to_json(capture))


# --------------------------------------------------------------------------------------------
# Pixels
# --------------------------------------------------------------------------------------------

def _check_finite(path: Path, name: str, arr: np.ndarray) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        idx = np.argwhere(bad)[0]
        raise DamcapError(
            f"{path}: {name} has {int(bad.sum())} NaN/inf value(s), first at pixel (row {idx[0]}, col {idx[1]})"
        )


def read_frame(capture: Capture, frame: Frame, *, with_weights: bool = True) -> FrameData:
    """Read and validate one frame's pixels.

    Raises:
        DamcapError: missing files or channels, size mismatch, NaN/inf, negative radiance
            on covered pixels, non-unit normals on covered pixels.
    """
    img_path = capture.root / frame.file_path
    geo_path = capture.root / frame.geometry_path
    rgb = read_exr_channels(img_path, RADIANCE_CHANNELS)
    geo = read_exr_channels(geo_path, GEOMETRY_CHANNELS)
    want = (frame.intrinsics.h, frame.intrinsics.w)
    for p, a in ((img_path, rgb), (geo_path, geo)):
        if a.shape[:2] != want:
            raise DamcapError(
                f"{p}: image is {a.shape[1]}x{a.shape[0]} (WxH) but transforms.json says {want[1]}x{want[0]}"
            )
    _check_finite(img_path, "radiance", rgb)
    _check_finite(geo_path, "geometry", geo)
    normal, position, coverage = geo[..., 0:3], geo[..., 3:6], geo[..., 6]
    if coverage.min() < -1e-3 or coverage.max() > 1 + 1e-3:
        raise DamcapError(f"{geo_path}: coverage A must lie in [0, 1], found [{coverage.min():.3g}, {coverage.max():.3g}]")
    covered = coverage > 0
    if not covered.any():
        raise DamcapError(f"{geo_path}: no covered pixels (A is 0 everywhere)")
    norms = np.linalg.norm(normal[covered], axis=-1)
    dev = np.abs(norms - 1)
    if dev.max() > NORMAL_UNIT_TOL:
        k = int(np.argmax(dev))
        raise DamcapError(
            f"{geo_path}: normals must be unit length on covered pixels; found length {norms[k]:.4g} "
            f"({int((dev > NORMAL_UNIT_TOL).sum())} pixel(s) off)"
        )
    if (rgb[covered] < 0).any():
        raise DamcapError(f"{img_path}: negative radiance {rgb[covered].min():.4g} on covered pixels")
    weights = None
    if with_weights and frame.weights_path and capture.materials:
        w_path = capture.root / frame.weights_path
        weights = read_exr_channels(w_path, weight_channels(capture.materials))
        if weights.shape[:2] != want:
            raise DamcapError(f"{w_path}: size {weights.shape[1]}x{weights.shape[0]} does not match the frame")
        _check_finite(w_path, "weights", weights)
        total = weights[covered].sum(-1)
        if np.abs(total - 1).max() > 1e-2:
            raise DamcapError(f"{w_path}: weights must sum to 1 on covered pixels, found sum {total.min():.3g}..{total.max():.3g}")
    return FrameData(
        radiance_lin=np.where(covered[..., None], rgb, 0).astype(np.float32),
        normal_world=np.where(covered[..., None], normal, 0).astype(np.float32),
        position_world=position.astype(np.float32),
        coverage=np.clip(coverage, 0, 1).astype(np.float32),
        weights=weights,
    )


def write_frame(capture: Capture, frame: Frame, data: FrameData, *, dtype: Literal["half", "float"] = "half") -> None:
    """Write one frame's radiance, geometry and (if present) weights EXRs, atomically each."""
    write_exr(capture.root / frame.file_path, data.radiance_lin, RADIANCE_CHANNELS, dtype=dtype,
              attributes={"damcap:colorspace": capture.colorspace})
    geo = np.concatenate([data.normal_world, data.position_world, data.coverage[..., None]], axis=-1)
    # Geometry needs float32: half would quantise positions and normals visibly.
    write_exr(capture.root / frame.geometry_path, geo, GEOMETRY_CHANNELS, dtype="float")
    if data.weights is not None:
        if not frame.weights_path:
            raise ValueError(f"frame {frame.name} has weights but no weights_path")
        write_exr(capture.root / frame.weights_path, data.weights, weight_channels(data.weights.shape[-1]), dtype="half")


def write_capture(capture: Capture, data: Iterable[FrameData], *, dtype: Literal["half", "float"] = "half") -> None:
    """Write every frame's pixels, then ``transforms.json`` last (a reader sees a complete capture)."""
    capture.root.mkdir(parents=True, exist_ok=True)
    for frame, d in zip(capture.frames, data, strict=True):
        write_frame(capture, frame, d, dtype=dtype)
    write_transforms(capture)


# --------------------------------------------------------------------------------------------
# Validation report (damcap inspect)
# --------------------------------------------------------------------------------------------

@dataclass
class CaptureSummary:
    """What ``damcap inspect`` reports."""

    frames: int
    resolution: tuple[int, int]
    coverage_mean: float
    radiance_min: float
    radiance_max: float
    radiance_p50: float
    train: int
    test: int
    materials: int | None
    colorspace: str
    problems: list[str]


def inspect_capture(root: str | os.PathLike) -> CaptureSummary:
    """Read every frame of a capture and collect all problems instead of stopping at the first.

    Raises:
        DamcapError: when ``transforms.json`` itself cannot be parsed (nothing else can be checked).
    """
    capture = read_capture(root, check_files=False)  # a missing file is one of the problems listed
    problems: list[str] = []
    covs, mins, maxs, meds = [], [], [], []
    peaks: list[np.ndarray] = []
    sizes = set()
    for frame in capture.frames:
        sizes.add((frame.intrinsics.w, frame.intrinsics.h))
        try:
            d = read_frame(capture, frame)
        except DamcapError as e:
            problems.append(str(e))
            continue
        fg = d.coverage > 0.5
        covs.append(float(fg.mean()))
        peaks.append(np.asarray(d.coverage.max()))  # only its peak is kept
        if fg.any():
            vals = d.radiance_lin[fg]
            mins.append(float(vals.min()))
            maxs.append(float(vals.max()))
            meds.append(float(np.median(vals)))
    if peaks:
        try:
            require_foreground(peaks, 0.5, capture.root)
        except DamcapError as e:
            problems.append(str(e))
    for split in ("train", "test"):
        try:
            capture.split(split)  # type: ignore[arg-type]
        except DamcapError as e:
            problems.append(str(e))
    w, h = max(sizes)
    return CaptureSummary(
        frames=len(capture.frames),
        resolution=(w, h),
        coverage_mean=float(np.mean(covs)) if covs else 0.0,
        radiance_min=min(mins) if mins else float("nan"),
        radiance_max=max(maxs) if maxs else float("nan"),
        radiance_p50=float(np.median(meds)) if meds else float("nan"),
        train=len(capture.train_filenames),
        test=len(capture.test_filenames),
        materials=capture.materials,
        colorspace=capture.colorspace,
        problems=problems,
    )
