"""``damcap reconstruct``: a folder of photos -> a capture folder (docs/capture-format.md).

Steps (each reports progress):

1. list the photos (8-bit, linear EXR or RAW, one kind; match the masks by base name), and read
   every input (photos, masks, the pose file, a user mesh, EXIF) before the output folder is touched;
2. cameras: COLMAP registration (:mod:`colmap`; resumable; linear and RAW photos through 8-bit
   proxies in the work folder; with masks, features inside them when the whole photos do not
   register well) or known poses (:mod:`known_poses`), then their self-check (:mod:`selfcheck`:
   photos that disagree with the others are named and left out, an inconsistent registration is
   refused);
3. normalise the scene (:mod:`normalize`): object at the origin, radius about 1, up = +y;
4. per photo, one pinhole target camera at ``capture_size`` (:mod:`undistort`); masks resampled;
5. geometry (:mod:`geometry`), then the final centring on its bounding sphere;
6. per frame: the photo linearised (:mod:`photos`: 8-bit photos' tone curve undone, sRGB or a
   ``damcap hdr`` response; linear EXRs and RAW files read linearly; exposure divided out) and
   resampled once into the pinhole image; ray-cast normals, positions and coverage (:mod:`frames`;
   with masks, coverage is also limited to the mask; pixels flagged clipped leave it); frames
   the geometry misses are dropped;
7. train/test split; ``transforms.json`` written last with ``damcap_source`` (resolved options,
   version, registration and geometry reports).

Outputs are atomic per file; the frames and ``transforms.json`` (what makes the folder a capture)
are written into the work folder and replace an earlier run's capture only at the end, so an
interrupted or failed rerun leaves the earlier capture as it was; a run that fails removes the folder it made,
unless it holds a COLMAP registration a rerun resumes from. Work files (COLMAP database and model, the
mesh, the report) live in ``CAPTURE/reconstruction/``.
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Literal, get_args

import numpy as np

from damcap.common.atomic import atomic_path, cut_short_error, fsync_path, pause_point, write_json_atomic
from damcap.common.capture_folder import FRAME_BYTES_PER_PIXEL, Capture, Frame, Intrinsics, write_transforms
from damcap.common.errors import DamcapError
from damcap.common.cameras import up_direction
from damcap.common.validate import COUNT, COUNT_OR_ZERO, FRACTION, MAX_IMAGE_SIDE, check_ranges, in_range, require_memory, require_resolution
from damcap.common.version import package_version

from damcap.reconstruct.geometry import UNBOUNDED_HULL, GeometryInputs, GeometryOptions, GeometryResult, build_geometry, parse_mode
from damcap.reconstruct.normalize import normalization_transform, recentre_transform, similarity_scale, transform_points, transform_world_from_cam
from damcap.reconstruct.dense import DenseOptions, dense_geometry
from damcap.reconstruct.photo_consistency import photo_consistency, prefer_dense
from damcap.reconstruct.split import camera_split
from damcap.reconstruct.frames import FramePhoto, write_frames
from damcap.reconstruct.normalize import transform_mesh_similarity
from damcap.reconstruct.photos import exposure_factors, list_photos, match_masks, read_mask, read_photo_radiance, verify_photos
from damcap.reconstruct.poses import Registration, registration_without
from damcap.reconstruct.known_poses import load_known_poses
from damcap.common.mesh import Mesh, load_mesh
from damcap.reconstruct.colmap.database import WHOLE_PHOTOS_HINT
from damcap.reconstruct.colmap.register import SfmOptions, StageProgress, masked_options, register_photos, triangulate_known
from damcap.reconstruct.selfcheck import SelfCheck, SelfCheckOptions, observation_stats, self_check
from damcap.reconstruct.undistort import pinhole_for, resample_to_pinhole

SplitKind = Literal["consecutive", "spread", "rings"]
ClippedPolicy = Literal["auto", "drop", "keep"]
WORK_FOLDER = "reconstruction"


@dataclass(frozen=True)
class ReconstructOptions:
    """Every option of ``damcap reconstruct``. The registration, geometry, dense-stereo and
    self-check options are those stages' own dataclasses, held here (their defaults are theirs;
    their flags keep short names: ``--voxels``, ``--dense-size``, ``--max-image-size``)."""

    geometry: GeometryOptions = field(default_factory=GeometryOptions, metadata={"cli_prefix": "", "cli_panel": "Geometry"})
    """how the geometry is built (``--geometry``, ``--voxels``, ...)"""
    dense: DenseOptions = field(default_factory=DenseOptions, metadata={"cli_prefix": "", "cli_panel": "Dense stereo"})
    """dense multi-view stereo (``--dense-size``, ``--dense-planes``, ``--dense-views``)"""
    auto_dense: bool = True
    """auto: also build the dense geometry when the object is not a sphere, and keep it when the
    photos agree better through it (reconstruct/photo_consistency.py). --no-auto-dense saves its
    time (about 70 s on the 119-photo cape at 256 px)."""
    auto_judge: Literal["held-out", "photo-consistency"] = field(default="held-out", metadata={"cli_panel": "advanced"})
    """auto, with both geometries built: what chooses between them. 'held-out' fits the DAM (fit's
    defaults without the prior, half the steps) to each geometry's train views, the same views held out, and
    keeps photo consistency's choice unless the other lowers the held-out DSSIM by 2 %
    (bench/geometry_judge.md); 'photo-consistency' alone saves those two fits"""
    auto_dense_margin: float = field(default=0.02, metadata=in_range(0, 2, cli_panel="advanced"))
    """auto: the dense geometry is kept when its photo consistency (mean NCC of neighbouring
    photos warped through the surface, over the object's pixels) beats the other geometry's by at
    least this. Measured on the cape: dense 0.81 vs visual hull 0.70, dense kept; rendered blob:
    0.62 vs 0.73, hull kept (bench/reconstruct.md)."""
    sfm: SfmOptions = field(default_factory=SfmOptions, metadata={"cli_prefix": "", "cli_panel": "Registration"})
    """camera registration (COLMAP; ``--max-image-size``, ``--pairing``, ``--threads``, ``--seed``, ...)"""
    mask_features: Literal["auto", "always", "never"] = "auto"
    """with --masks, where registration matches features. 'never' matches features on the whole
    photo (the static background of a camera moved around a fixed object helps; a background that
    stands still in the image is filtered anyway); 'always' keeps only features on the object (a
    turntable whose background does not turn with it); 'auto' registers the whole photos first and,
    when the self-check flags photos or no more than 95% register, again with features on the object,
    and keeps the registration with more photos that pass the self-check"""
    self_check: Literal["drop", "warn", "off"] = "drop"
    """what the self-check of the cameras does (reconstruct/selfcheck.py): 'drop' leaves out the
    photos it flags (named) and refuses a registration where more than half are flagged; 'warn'
    only reports; 'off' does not run it"""
    selfcheck: SelfCheckOptions = field(default_factory=SelfCheckOptions, metadata={"cli_prefix": "", "cli_panel": "Self-check"})
    """the self-check's thresholds (``--min-silhouette-recall``, ``--min-silhouette-precision``, ``--max-reprojection-px``)"""
    capture_size: int = field(default=512, metadata=in_range(1, MAX_IMAGE_SIDE))
    """longest side of the capture's images, pixels (photos are undistorted and resized once)"""
    train_views: int = field(default=10, metadata=COUNT)
    """frames in the train split (the rest are test)"""
    split: SplitKind = "consecutive"
    """how the train frames are chosen: 'consecutive' (in file order from ``split_start``, as the
    paper), 'spread' (evenly spaced) or 'rings' (one ring of cameras trains, spread in azimuth;
    the cameras more than 15 deg above or below it are the test split, or with one ring the arc
    opposite the first camera; the training ring's other cameras are in neither split:
    reconstruct/split.py)"""
    split_start: int = field(default=0, metadata=COUNT_OR_ZERO)
    """first train frame of a consecutive split"""
    min_registered: int = field(default=3, metadata={**COUNT, "cli_panel": "advanced"})
    """fewest registered photos that make a capture"""
    min_registered_fraction: float = field(default=0.5, metadata={**FRACTION, "cli_panel": "advanced"})
    """fewest registered photos, as a fraction of the photos"""
    ignore_exposure: bool = False
    """only linearise; do not divide by the EXIF exposure (photos at one fixed exposure) nor rescale
    linear EXRs by their recorded reference exposure"""
    response: str | None = None
    """a response curve file written by ``damcap hdr`` (the ``NAME.exr.json`` record beside its
    output, or that ``NAME.exr``) to undo instead of the sRGB curve for 8-bit photos; None: sRGB"""
    clipped: ClippedPolicy = "auto"
    """what becomes of pixels a photo flags clipped (saturated: a display photo's top codes, a RAW
    file's white level, an EXR's ``clipped`` channel; their radiance is only a lower bound): 'drop'
    gives them coverage A = 0, 'keep' keeps them, 'auto' keeps a display photo's and drops the
    others'. Either way reconstruct says how many of the object's pixels were clipped. Why 'auto'
    keeps the 8-bit ones: the photos' white is about where DSSIM's normalisation clips anyway (the
    reference's 95th percentile), and on the bundled studio photos (5 % of the object clipped)
    dropping them made every DAM worse: novel-view DSSIM of the segmentation 0.262 -> 0.274 and of
    one fitted DAM 0.340 -> 0.371, and the export against the truth on the torus x0.71 -> x0.80
    (aluminium) and x0.29 -> x0.37 (gold) (docs/capture-format.md). Neither wins everywhere: on
    closed-form captures clipped at 3 or 10 % of the object (``bench/clipped.md``, against the
    unclipped truth) dropping them gave the lower novel-view DSSIM under a distant light in 3 of 4
    cases (blob at 3 %: 0.051 against 0.061) and the higher under the environment in all 4 (sphere
    at 10 %: 0.067 against 0.064), and recovered the highlight better in all 8 (the DAM extrapolates
    there instead of flattening at the clip). Kept pixels taken as lower bounds (a censored cost: a
    prediction above them costs nothing) were tried on the same rows and not kept: the DAM overshot
    the highlight (error the largest of the three in all 8 rows, up to 2.92 of the clip level
    against keep's 0.37), novel-view DSSIM the largest in 7 of 8, and the bundled photos' aluminium
    export went from x0.57 to x0.61"""
    mask_coverage: bool = field(default=True, metadata={"cli_panel": "advanced"})
    """with masks: coverage A is also limited to the mask (keeps background out of silhouettes)"""
    supersample: int = field(default=3, metadata=in_range(1, 16, cli_panel="advanced"))
    """sub-pixel grid per axis for coverage at silhouettes"""
    dtype: Literal["half", "float"] = "half"
    """radiance storage in images/*.exr"""

    def validate(self) -> None:
        """Raises DamcapError for out-of-range values (NaN, inf, counts beyond what a machine holds)."""
        check_ranges(self)
        if self.sfm.num_threads == 0:
            raise DamcapError("--threads must be -1 (all) or an integer in [1, 4096], got 0")
        if self.clipped not in get_args(ClippedPolicy):
            raise DamcapError(f"--clipped must be one of {', '.join(get_args(ClippedPolicy))}, got {self.clipped!r}")
        # a voxel grid of voxels^3 (float32 and a label per voxel) and the capture's frame buffers
        voxels = self.geometry.voxels
        require_memory(float(voxels) ** 3 * 8, f"--voxels {voxels} (a {voxels}^3 grid)")
        require_resolution(self.capture_size, self.capture_size, FRAME_BYTES_PER_PIXEL * self.supersample ** 2,
                           f"--capture-size {self.capture_size} with --supersample {self.supersample}: a frame")
        if self.split not in ("consecutive", "spread", "rings"):
            raise DamcapError(f"--split must be consecutive, spread or rings, got {self.split!r}")
        if self.auto_judge not in ("held-out", "photo-consistency"):
            raise DamcapError(f"--auto-judge must be held-out or photo-consistency, got {self.auto_judge!r}")
        if self.dtype not in ("half", "float"):
            raise DamcapError(f"--dtype must be half or float, got {self.dtype!r}")
        for owner, name, allowed in ((self, "mask_features", ("auto", "always", "never")), (self, "self_check", ("drop", "warn", "off")),
                                     (self.sfm, "principal_point", ("auto", "refine", "centre"))):
            if getattr(owner, name) not in allowed:
                raise DamcapError(f"--{name.replace('_', '-')} must be one of {', '.join(allowed)}, got {getattr(owner, name)!r}")


@dataclass
class ReconstructReport:
    """What ``damcap reconstruct`` did."""

    photos: int
    registered: int
    unregistered: dict[str, str]
    frames: int
    dropped: dict[str, str]
    geometry_mode: str
    geometry_reason: str
    train: list[str]
    test: list[str]
    registration: dict[str, Any]
    seconds: dict[str, float] = field(default_factory=dict)
    linearisation: str = ""
    self_check: dict[str, Any] | None = None
    """:meth:`SelfCheck.to_json` of the cameras kept (before flagged photos were left out); None when off"""
    geometry_check: dict[str, Any] | None = None
    """``--geometry auto`` past the sphere test: the dense build and each surface's photo
    consistency (:func:`.photo_consistency.photo_consistency`); None otherwise"""


# --------------------------------------------------------------------------------------------
# Pure helpers
# --------------------------------------------------------------------------------------------

def check_split_options(opts: ReconstructOptions, photos: int, explicit: frozenset[str] = frozenset()) -> None:
    """Refuse a split the photos cannot give, before any work: ``--train-views`` must leave a
    test frame and ``--split-start`` must name a photo. Only options in ``explicit`` (set by the
    user) are refused; a default is clamped by :func:`split_indices`, as are the splits of photos
    that then fail to register.

    Raises:
        DamcapError: naming the option, its value and the number of photos.
    """
    if "train_views" in explicit and photos > 1 and not opts.train_views < photos:
        raise DamcapError(f"--train-views must be below the number of photos ({photos}) so that the test split is not empty, "
                          f"got {opts.train_views}")
    if "split_start" in explicit and not opts.split_start < photos:
        raise DamcapError(f"--split-start must be below the number of photos ({photos}), got {opts.split_start}")


def split_indices(n: int, train_views: int, kind: SplitKind = "consecutive", start: int = 0) -> tuple[list[int], list[int]]:
    """Train and test frame indices.

    Args:
        n: frames.
        train_views: train frames (clamped to n - 1 so that test is not empty when n > 1).
        kind: 'consecutive' (k frames in a row from ``start``, wrapping) or 'spread' (evenly spaced).
        start: first train frame of a consecutive split.

    >>> split_indices(6, 2, "consecutive", 5)
    ([0, 5], [1, 2, 3, 4])
    >>> split_indices(6, 3, "spread")
    ([0, 2, 4], [1, 3, 5])
    """
    k = max(1, min(train_views, n - 1 if n > 1 else 1))
    if kind == "consecutive":
        train = sorted((start + i) % n for i in range(k))
    else:
        train = sorted(set(int(i) for i in np.floor(np.arange(k) * n / k)))
    test = [i for i in range(n) if i not in set(train)]
    return train, test


# --------------------------------------------------------------------------------------------
# I/O steps
# --------------------------------------------------------------------------------------------

def _prepare_output(out: Path, inputs: list[Path]) -> None:
    for i in inputs:
        r = i.resolve()
        if out.resolve() == r or r in out.resolve().parents:
            raise DamcapError(f"{out}: output would overwrite or write into the input {i}; choose another output folder")
    if out.exists() and not out.is_dir():
        raise DamcapError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / WORK_FOLDER).is_dir():
        raise DamcapError(f"{out}: folder exists, is not empty and was not made by damcap reconstruct; choose a new folder")
    out.mkdir(parents=True, exist_ok=True)  # an earlier capture here stays whole until this run's frames replace it (_commit_frames)


def _save_mesh(path: Path, mesh: Mesh) -> None:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices.astype(np.float64)),
                                  o3d.utility.Vector3iVector(mesh.triangles))
    m.vertex_normals = o3d.utility.Vector3dVector(mesh.vertex_normals.astype(np.float64))
    from damcap.common.native_stderr import native_stderr_caught

    with atomic_path(path) as tmp:
        with native_stderr_caught() as printed:  # RPly reports a write the disk cut short only there, and open3d returns True
            ok = o3d.io.write_triangle_mesh(str(tmp), m)
        if not ok or any("Failed writing" in line or "Error" in line for line in printed):
            error = cut_short_error(tmp, path, 32 * (len(mesh.vertices) + len(mesh.triangles)))
            if error is not None:
                raise error
            raise DamcapError(f"{path}: cannot write the mesh ({printed[-1] if printed else 'open3d failed'})")


@dataclass
class RegistrationImages:
    """The images COLMAP reads for a photo set: the photos themselves (8-bit, stored upright), or
    8-bit upright proxies in the work folder of linear and RAW photos and of 8-bit photos stored
    turned (EXIF Orientation; the others linked), same base names, same pixel grid as damcap reads."""

    folder: Path
    """where the images are"""
    by_photo: dict[str, str]
    """photo name -> image name in ``folder``"""
    content: dict[str, str] | None
    """image name -> digest of its bytes (proxies), what the resumable stages fingerprint; None: file sizes"""

    def names(self, photo_names: list[str]) -> list[str]:
        return [self.by_photo[n] for n in photo_names]

    def masks(self, masks: dict[str, Path] | None) -> dict[str, Path] | None:
        return {self.by_photo[n]: m for n, m in masks.items() if n in self.by_photo} if masks else None

    def to_images(self, reg: Registration) -> Registration:
        return renamed_registration(reg, self.by_photo)

    def to_photos(self, reg: Registration) -> Registration:
        return renamed_registration(reg, {v: k for k, v in self.by_photo.items()})


def renamed_registration(reg: Registration, names: dict[str, str]) -> Registration:
    """The registration with its photos renamed (``names``: old -> new; others kept), sorted by the
    new names, with ``points_seen_from`` following the new order."""
    if all(names.get(n, n) == n for n in [p.name for p in reg.photos] + list(reg.unregistered)):
        return reg
    order = sorted(range(len(reg.photos)), key=lambda k: names.get(reg.photos[k].name, reg.photos[k].name))
    new_index = np.empty(len(order), np.int64)
    new_index[order] = np.arange(len(order))
    seen = np.asarray(reg.points_seen_from, np.int64)
    stats = dict(reg.stats)
    if isinstance(stats.get("unregistered"), dict):
        stats["unregistered"] = {names.get(k, k): v for k, v in stats["unregistered"].items()}
    return replace(reg, photos=[replace(reg.photos[k], name=names.get(reg.photos[k].name, reg.photos[k].name)) for k in order],
                   unregistered={names.get(k, k): v for k, v in reg.unregistered.items()},
                   points_seen_from=new_index[seen] if len(seen) else seen, stats=stats)


def _registration_images(photos_dir: Path, names: list[str], work: Path, progress: StageProgress) -> RegistrationImages:
    from damcap.reconstruct.photos import file_digests, needs_registration_proxies, write_registration_proxies

    if not needs_registration_proxies(photos_dir, names):  # 8-bit photos, all stored upright
        return RegistrationImages(photos_dir, {n: n for n in names}, None)
    proxy_dir = work / "proxies"
    by_photo = write_registration_proxies(photos_dir, names, proxy_dir, progress)
    return RegistrationImages(proxy_dir, by_photo, file_digests(proxy_dir, [by_photo[n] for n in names]))


def _registration(photos_dir: Path, names: list[str], work: Path, opts: ReconstructOptions,
                  masks: dict[str, Path] | None, known: Registration | None, progress: StageProgress,
                  object_fraction: float | None) -> Registration:
    """Known poses, or COLMAP on the whole photos (``work/sfm``) or, given the masks' mean
    ``object_fraction``, on features inside the masks (``work/sfm-masked``,
    :func:`~damcap.reconstruct.colmap.register.masked_options`)."""
    if known is not None:
        return known
    images = _registration_images(photos_dir, names, work, progress)
    if object_fraction is not None and masks:
        sfm = masked_options(opts.sfm, object_fraction)
        reg, _ = register_photos(images.folder, images.names(names), work / "sfm-masked", sfm, images.masks(masks), progress,
                                 images.content)
    else:
        reg, _ = register_photos(images.folder, images.names(names), work / "sfm", opts.sfm, None, progress, images.content,
                                 masks_given=bool(masks))
    return images.to_photos(reg)


def _needs_points(opts: ReconstructOptions, has_masks: bool) -> bool:
    """Whether the geometry mode needs sparse points (Poisson; auto/sphere without masks;
    aligning a user mesh without masks; dense without masks: its depth range)."""
    mode, _ = parse_mode(opts.geometry.mode)
    if mode == "poisson":
        return True
    if has_masks:
        return False
    return mode in ("auto", "sphere", "dense") or (mode == "mesh" and opts.geometry.mesh_align == "icp")


class TooFewCameras(DamcapError):
    """A registration with fewer cameras than reconstruct needs (its counts kept for the caller)."""

    def __init__(self, message: str, registered: int, photos: int) -> None:
        super().__init__(message)
        self.registered, self.photos = registered, photos


def features_hint(masks_given: bool, features_masked: bool) -> str:
    """The advice on features for too few registered photos: give masks, use the masks given, or
    nothing more (features are already on the object).

    >>> features_hint(False, False), features_hint(True, False), features_hint(True, True)
    ('; --masks keeps features on the object', '; --mask-features always keeps features on the object', '')
    """
    if features_masked:
        return ""
    return "; --mask-features always keeps features on the object" if masks_given else "; --masks keeps features on the object"


def _check_enough(reg: Registration, n_photos: int, opts: ReconstructOptions, photos_dir: Path, masks_given: bool = False,
                  features_masked: bool = False) -> None:
    need = max(opts.min_registered, int(np.ceil(opts.min_registered_fraction * n_photos)), 2)
    if len(reg.photos) < need:
        why = "; ".join(f"{k}: {v}" for k, v in list(sorted(reg.unregistered.items()))[:4])
        raise TooFewCameras(
            f"{photos_dir}: only {len(reg.photos)} of {n_photos} photos have cameras, at least {need} are needed "
            f"(--min-registered {opts.min_registered}, --min-registered-fraction {opts.min_registered_fraction}). "
            f"Unregistered, e.g. {why}. Photos need overlap (about 60% between neighbours) and texture"
            + features_hint(masks_given, features_masked), len(reg.photos), n_photos)


@dataclass
class NormalisedScene:
    """The scene after normalisation and geometry: what the frames are ray cast against."""

    norm_from_world: np.ndarray
    """(4, 4) similarity from the registration's world to the capture's (object at the origin, radius ~1)"""
    world_from_cams: np.ndarray
    """(N, 4, 4) cameras in the capture's world"""
    mesh: Mesh
    """the geometry in the capture's world"""
    sphere: tuple[np.ndarray, float] | None
    """(centre, radius) when the geometry is an analytic sphere (its normals are used exactly)"""
    geometry: GeometryResult
    """what the geometry step returned (mode, reason, statistics)"""


def _check_inputs(photos_dir: Path, masks_dir: str | os.PathLike | None, poses: str | None,
                  opts: ReconstructOptions) -> tuple[list[str], dict[str, Path] | None]:
    """Step 1: the photos, their masks, and the options that name files (checked before any work)."""
    names = list_photos(photos_dir)
    verify_photos(photos_dir, names)  # a truncated JPEG is refused here, not dropped as unregistered
    masks = match_masks(names, masks_dir) if masks_dir is not None else None
    if poses and not poses.startswith(("colmap:", "strecha:")) and Path(poses).suffix.lower() not in (".json", ".npy"):
        raise DamcapError(f"--poses {poses!r}: use a transforms.json, a poses_bounds.npy, colmap:DIR or strecha:DIR")
    _mode, mesh_path = parse_mode(opts.geometry.mode)
    if mesh_path is not None and not mesh_path.is_file():
        raise DamcapError(f"{mesh_path}: mesh file not found (--geometry mesh:FILE)")
    if mesh_path is not None:
        load_mesh(mesh_path)  # an empty, damaged or degenerate mesh is refused before any work
    return names, masks


def _photo_sizes(photos_dir: Path, names: list[str]) -> dict[str, tuple[int, int]]:
    """Step 1: (width, height) of every photo, from its header."""
    from damcap.reconstruct.photos import image_size

    return {n: image_size(photos_dir / n) for n in names}


def _known_poses(poses: str | None, sizes: dict[str, tuple[int, int]], opts: ReconstructOptions, photos_dir: Path,
                 progress: StageProgress) -> Registration | None:
    """Step 1: the cameras of ``--poses`` (None without it), read before any work.

    Photos the file has no pose for are unregistered; too few posed photos are refused here.

    Raises:
        DamcapError: what the pose file's reader raises; too few posed photos (names some that
            lack a pose, :func:`_check_enough`).
    """
    if not poses:
        return None
    progress("poses", 0, 1)
    reg = load_known_poses(poses, sizes)
    progress("poses", 1, 1)
    _check_enough(reg, len(sizes), opts, photos_dir)
    return reg


def check_masks(masks: dict[str, Path] | None, sizes: dict[str, tuple[int, int]]) -> float | None:
    """Step 1: every mask decodes, has its photo's size and marks some object (read before any work).

    Returns:
        the mean fraction of a photo's pixels inside its mask (None without masks).

    Raises:
        DamcapError: an unreadable or truncated mask, a size other than the photo's, or a mask
            with no object pixel (all black: the photo would see no object), naming the mask.
    """
    from damcap.reconstruct.photos import MASK_THRESHOLD

    fractions = []
    for name, path in (masks or {}).items():
        inside = read_mask(path, sizes[name], name) > MASK_THRESHOLD
        if not inside.any():
            raise DamcapError(f"{path}: the mask of {name} has no object pixel (white = object, none above "
                              f"{MASK_THRESHOLD}); fix the mask or move the photo out of the folder")
        fractions.append(float(inside.mean()))
    return float(np.mean(fractions)) if fractions else None


def _response_curve(photos_dir: Path, names: list[str], opts: ReconstructOptions) -> tuple[np.ndarray | None, str]:
    """Step 1: the response curve of ``--response`` (checked before any work) and its label for the
    linearisation note; (None, 'sRGB') without one."""
    from damcap.capture.hdr import read_response
    from damcap.reconstruct.photos import photo_set_kind

    if not opts.response:
        return None, "sRGB"
    kind = photo_set_kind(names, photos_dir)
    if kind != "display":
        raise DamcapError(f"--response {opts.response}: a response curve undoes the tone curve of 8-bit photos, but "
                          f"{photos_dir} holds {'linear EXR/HDR' if kind == 'linear' else 'RAW'} files")
    curve = read_response(opts.response)
    return curve.log_response, f"response curve of {Path(opts.response).name} ({curve.method}, {curve.levels} levels, from damcap hdr)"


def _cameras(photos_dir: Path, names: list[str], work: Path, opts: ReconstructOptions, masks: dict[str, Path] | None,
             known: Registration | None, progress: StageProgress, log: Callable[[str], None],
             seconds: dict[str, float], object_fraction: float | None = None) -> Registration:
    """Step 2: registration (or known poses; with ``object_fraction``, on features inside the
    masks: :func:`_registration`), and sparse points triangulated at known poses when the
    geometry needs them."""
    t0 = time.perf_counter()
    reg = _registration(photos_dir, names, work, opts, masks, known, progress, object_fraction)
    seconds["registration"] = seconds.get("registration", 0.0) + time.perf_counter() - t0
    _check_enough(reg, len(names), opts, photos_dir, masks is not None, object_fraction is not None and bool(masks))
    if reg.stats.get("points_from") or reg.stats.get("points_without_track"):
        log(f"{len(reg.points_world)} points of the dataset's point cloud ({reg.stats.get('points_from', 'COLMAP points without a track')}) "
            "are the sparse points: no feature matching")
    if len(reg.points_world) == 0 and _needs_points(opts, masks is not None):
        t0 = time.perf_counter()
        log("known poses without sparse points: matching features and triangulating them with the poses held fixed")
        images = _registration_images(photos_dir, [p.name for p in reg.photos], work, progress)
        reg = images.to_photos(triangulate_known(images.folder, images.to_images(reg), work / "sfm", opts.sfm,
                                                 images.masks(masks) if opts.mask_features == "always" else None, progress,
                                                 images.content))
        seconds["triangulation"] = time.perf_counter() - t0
    return reg


def _target_masks(reg: Registration, targets: list[Intrinsics], masks: dict[str, Path] | None,
                  progress: StageProgress) -> tuple[list[np.ndarray] | None, list[tuple[float | None, int, int | None]]]:
    """Step 4: each photo's mask resampled into its pinhole target, in [0, 1] (None without masks),
    and each photo's sparse-point statistics for the self-check (reprojection error, points, points
    on the object)."""
    if masks is None:
        return None, [observation_stats(p.observations_px, None) for p in reg.photos]
    mask_px, stats = [], []
    for k, (p, tgt) in enumerate(zip(reg.photos, targets)):
        progress("masks", k, len(reg.photos))
        m = read_mask(masks[p.name], (p.camera.width, p.camera.height), p.name)
        stats.append(observation_stats(p.observations_px, m))
        mask_px.append(np.clip(resample_to_pinhole(m, p.camera, tgt), 0, 1))
    progress("masks", len(reg.photos), len(reg.photos))
    return mask_px, stats


@dataclass
class CheckedCameras:
    """One candidate registration with its pinhole targets, target masks and self-check."""

    reg: Registration
    targets: list[Intrinsics]
    mask_px: list[np.ndarray] | None
    check: SelfCheck | None
    features: str
    """'whole photos', 'inside the masks' or 'known poses'"""

    def agreeing(self) -> int:
        """Photos that have cameras and pass the self-check (0 for an inconsistent registration)."""
        if self.check is None:
            return len(self.reg.photos)
        return 0 if self.check.verdict == "inconsistent" else len(self.reg.photos) - len(self.check.flagged)

    def brief(self) -> dict[str, Any]:
        out: dict[str, Any] = {"features": self.features, "registered": len(self.reg.photos), "agreeing": self.agreeing()}
        if self.check is not None:
            out["self_check"] = self.check.verdict
        return out


def _candidate(photos_dir: Path, names: list[str], work: Path, opts: ReconstructOptions, masks: dict[str, Path] | None,
               object_fraction: float | None, known: Registration | None, progress: StageProgress,
               log: Callable[[str], None], seconds: dict[str, float], masked: bool) -> CheckedCameras:
    """Cameras of one kind (whole photos or features inside the masks), their targets and masks, and their self-check."""
    reg = _cameras(photos_dir, names, work, opts, masks, known, progress, log, seconds, object_fraction if masked else None)
    targets = [pinhole_for(p.camera, opts.capture_size) for p in reg.photos]
    mask_px, stats = _target_masks(reg, targets, masks, progress)
    check = None
    if opts.self_check != "off":
        t0 = time.perf_counter()
        # in the normalised frame (object radius ~1), as the geometry: the check does not depend on the scene's unit
        norm_from_world = normalization_transform(reg.world_from_cams, reg.points_world if len(reg.points_world) else None)
        check = self_check([p.name for p in reg.photos], transform_world_from_cam(norm_from_world, reg.world_from_cams), targets,
                           mask_px, stats, opts.selfcheck, seed=opts.sfm.seed, progress=progress,
                           points_world=transform_points(norm_from_world, reg.points_world) if len(reg.points_world) else None)
        seconds["self_check"] = seconds.get("self_check", 0.0) + time.perf_counter() - t0
    features = "known poses" if known is not None else ("inside the masks" if masked and masks else "whole photos")
    return CheckedCameras(reg, targets, mask_px, check, features)


def wants_masked_features(registered: int, photos: int, check: SelfCheck | None) -> bool:
    """Whether 'auto' registers again with features inside the masks: no more than 95% of the photos
    registered (38 of 40 is 95 %), or the self-check flagged any.

    >>> wants_masked_features(119, 119, None), wants_masked_features(4, 30, None), wants_masked_features(38, 40, None)
    (False, True, True)
    """
    return registered <= 0.95 * photos + 1e-9 or (check is not None and bool(check.flagged))


def both_failed(whole: DamcapError, masked: DamcapError) -> DamcapError:
    """One error for a registration whose two candidates (whole photos, features inside the
    masks) both failed: the one that registered more photos, then how the other ended.

    >>> w = TooFewCameras("P: only 12 of 36 photos have cameras, at least 18 are needed (...). Unregistered, e.g. ...", 12, 36)
    >>> m = TooFewCameras("P: only 2 of 36 photos have cameras, at least 18 are needed (...). Unregistered, e.g. ...", 2, 36)
    >>> str(both_failed(w, m)).endswith("With features inside the masks instead: only 2 of 36 photos have cameras.")
    True
    """
    def registered(e: DamcapError) -> int:
        return e.registered if isinstance(e, TooFewCameras) else -1

    def short(e: DamcapError) -> str:
        if isinstance(e, TooFewCameras):
            return f"only {e.registered} of {e.photos} photos have cameras"
        return str(e).split(": ", 1)[-1].split(" (")[0].rstrip(".")

    best, other, how = (whole, masked, "features inside the masks") if registered(whole) >= registered(masked) else \
        (masked, whole, "the whole photos")
    return DamcapError(f"{str(best).rstrip('.')}. With {how} instead: {short(other)}.")


def _choose_cameras(photos_dir: Path, names: list[str], work: Path, opts: ReconstructOptions, masks: dict[str, Path] | None,
                    object_fraction: float | None, known: Registration | None, progress: StageProgress, log: Callable[[str], None],
                    seconds: dict[str, float]) -> tuple[CheckedCameras, list[dict[str, Any]]]:
    """Step 2 with the self-check: the registration to keep and every candidate tried.

    With masks and ``--mask-features auto``, the whole photos are registered first; when
    :func:`wants_masked_features`, features inside the masks are registered too and the candidate
    with more photos that pass the self-check is kept (the first on a tie).
    """
    args = (photos_dir, names, work, opts, masks, object_fraction, known, progress, log, seconds)
    first_masked = opts.mask_features == "always" and masks is not None
    first: CheckedCameras | None = None
    error: DamcapError | None = None
    try:
        first = _candidate(*args, masked=first_masked)
    except DamcapError as e:
        error = e
    tried = [first.brief()] if first is not None else [{"features": "whole photos", "error": str(error)}]
    auto = masks is not None and known is None and opts.mask_features == "auto"
    if not auto or (first is not None and not wants_masked_features(len(first.reg.photos), len(names), first.check)):
        if first is None:
            raise error  # type: ignore[misc]
        return first, tried
    why = (f"{len(first.reg.photos)} of {len(names)} photos registered" + (f", the self-check flagged {len(first.check.flagged)}"
           if first.check is not None and first.check.flagged else "")) if first is not None else str(error).split(" (")[0]
    log(f"registration on the whole photos: {why}; registering again with features inside the masks")
    try:
        second = _candidate(*args, masked=True)
    except DamcapError as e:
        tried.append({"features": "inside the masks", "error": str(e)})
        if first is None:
            raise both_failed(error, e) from None  # type: ignore[arg-type]
        return _masked_tried(first, "features inside the masks registered too few photos"), tried
    tried.append(second.brief())
    if first is None or second.agreeing() > first.agreeing():
        return second, tried
    return _masked_tried(first, "features inside the masks gave no more photos that agree"), tried


def _masked_tried(c: CheckedCameras, outcome: str) -> CheckedCameras:
    """The whole-photos candidate kept after features inside the masks were tried: its unregistered
    photos' advice to try them says how that went instead."""
    tail = f"if the object turned in front of the background, {WHOLE_PHOTOS_HINT}"
    c.reg.unregistered = {k: v.replace(tail, outcome) for k, v in c.reg.unregistered.items()}
    return c


def _apply_self_check(c: CheckedCameras, opts: ReconstructOptions, n_photos: int, photos_dir: Path,
                      log: Callable[[str], None]) -> tuple[CheckedCameras, dict[str, str]]:
    """Report the self-check; with ``--self-check drop``, leave out the photos it flags or refuse
    an inconsistent registration.

    Returns:
        the cameras kept, and photo name -> why it was left out.

    Raises:
        DamcapError: more than half of the photos disagree, or too few are left.
    """
    if c.check is None:
        return c, {}
    log(f"self-check ({c.features}): {c.check.summary()}")  # it says when precision was not tested
    flagged = c.check.flagged
    for name, why in sorted(flagged.items()):
        log(f"self-check flags {name}: {why}")
    if opts.self_check != "drop" or not flagged:
        return c, {}
    if c.check.verdict == "inconsistent":
        worst = "; ".join(f"{k}: {v}" for k, v in sorted(flagged.items())[:2])
        raise DamcapError(
            f"{photos_dir}: the cameras disagree with the photos ({c.check.summary()}; e.g. {worst}). "
            "Check that the masks are white on the object and belong to these photos; --self-check warn writes the capture anyway")
    keep = [k for k, p in enumerate(c.reg.photos) if p.name not in flagged]
    reg = registration_without(c.reg, set(flagged))
    dropped = {n: f"self-check: {why}" for n, why in flagged.items()}
    _check_enough(reg, n_photos, opts, photos_dir, c.mask_px is not None, c.features == "inside the masks")
    return CheckedCameras(reg, [c.targets[k] for k in keep], [c.mask_px[k] for k in keep] if c.mask_px is not None else None,
                          c.check, c.features), dropped


def _stereo_photos(reg: Registration, targets: list[Intrinsics], photos_dir: Path, log_response: np.ndarray | None,
                   progress: StageProgress) -> list[np.ndarray]:
    """The registered photos as linear radiance on their pinhole targets (what dense stereo
    matches; exposure does not matter to its normalised cross-correlation)."""
    out = []
    for k, (p, tgt) in enumerate(zip(reg.photos, targets)):
        progress("geometry (photos)", k, len(targets))
        out.append(resample_to_pinhole(read_photo_radiance(photos_dir / p.name, 1.0, 1.0, log_response).radiance_lin,
                                       p.camera, tgt))
    return out


def _scene(reg: Registration, targets: list[Intrinsics], mask_px: list[np.ndarray] | None, opts: ReconstructOptions,
           progress: StageProgress, log: Callable[[str], None], seconds: dict[str, float], photos_dir: Path,
           log_response: np.ndarray | None) -> list[NormalisedScene]:
    """Steps 3 and 5: normalise the scene, build the geometry, centre it on its bounding sphere.
    Under ``--geometry auto`` with both built, the geometry photo consistency did not keep comes
    second (a judge on held-out views may still take it: :func:`_judged`)."""
    norm_from_world = normalization_transform(reg.world_from_cams, reg.points_world if len(reg.points_world) else None)
    cams = transform_world_from_cam(norm_from_world, reg.world_from_cams)
    points = transform_points(norm_from_world, reg.points_world) if len(reg.points_world) else np.zeros((0, 3))
    t0 = time.perf_counter()
    progress("geometry", 0, 1)
    geos: list[GeometryResult]  # their reasons are in the report
    mode = parse_mode(opts.geometry.mode)[0]
    if mode == "dense":
        inputs = GeometryInputs(cams, targets, mask_px, points, reg.points_seen_from,
                                _stereo_photos(reg, targets, photos_dir, log_response, progress))
        geos = [dense_geometry(inputs, opts.dense, progress)]
    else:
        geos = [build_geometry(GeometryInputs(cams, targets, mask_px, points, reg.points_seen_from), opts.geometry,
                               norm_from_world)]
        if mode == "auto" and opts.auto_dense and geos[0].mode != "sphere":
            geos = _auto_dense(geos[0], GeometryInputs(cams, targets, mask_px, points, reg.points_seen_from,
                                                       _stereo_photos(reg, targets, photos_dir, log_response, progress)),
                               opts, progress, log)
    progress("geometry", 1, 1)
    seconds["geometry"] = time.perf_counter() - t0
    return [_placed(geo, norm_from_world, cams) for geo in geos]


def _placed(geo: GeometryResult, norm_from_world: np.ndarray, cams: np.ndarray) -> NormalisedScene:
    """The scene with ``geo`` centred on its bounding sphere (``norm_from_world`` and the cameras
    moved with it)."""
    recentre = recentre_transform(geo.mesh.vertices)
    sphere = None
    if geo.sphere is not None:
        sphere = (transform_points(recentre, geo.sphere[0][None])[0], geo.sphere[1] * similarity_scale(recentre))
    return NormalisedScene(recentre @ norm_from_world, transform_world_from_cam(recentre, cams),
                           transform_mesh_similarity(geo.mesh, recentre), sphere, geo)


def dense_margin(base: GeometryResult, margin: float) -> float:
    """How much better than ``base`` the dense geometry's photo consistency must be to be kept:
    ``margin``, or ``-margin`` for a visual hull that reaches the limits of what the photos judge
    (``touches_box``: it is not the object there, so dense is kept unless it is worse by more
    than ``margin``)."""
    return -margin if base.mode == "visual-hull" and base.stats.get("touches_box") else margin


def _auto_dense(base: GeometryResult, inputs: GeometryInputs, opts: ReconstructOptions, progress: StageProgress,
                log: Callable[[str], None]) -> list[GeometryResult]:
    """``--geometry auto`` past the sphere test: build the dense geometry too and put first
    whichever the photos agree with better (:func:`.photo_consistency.prefer_dense`), with why;
    the other comes second. A dense build that fails (too little texture) leaves the base
    geometry alone, with the reason."""
    t0 = time.perf_counter()
    try:
        dense = dense_geometry(inputs, opts.dense, progress)
    except DamcapError as e:
        log(f"geometry: kept the {base.mode}; the dense geometry could not be built ({e})")
        base.stats["auto_dense"] = {"built": False, "why": str(e)}
        return [base]
    scores = {g.mode: photo_consistency(g.mesh, inputs.world_from_cams, inputs.intrinsics, inputs.images or [], inputs.masks)
              for g in (base, dense)}
    b, d = scores[base.mode], scores["dense"]
    unbounded = base.mode == "visual-hull" and bool(base.stats.get("touches_box"))
    keep_dense = prefer_dense(b, d, dense_margin(base, opts.auto_dense_margin))
    chosen = dense if keep_dense else base
    record = {"built": True, "seconds": time.perf_counter() - t0, "margin": opts.auto_dense_margin,
              "photo_consistency": {k: {"ncc": v.ncc, "compared_fraction": v.compared_fraction, "pairs": v.pairs}
                                    for k, v in scores.items()}, "chosen": chosen.mode, "hull_touches_box": unbounded}
    why = (f"photo consistency, the NCC of neighbouring photos warped through the surface over the object's pixels: "
           f"dense {d.score:.3f} (NCC {d.ncc:.3f} on {d.compared_fraction:.0%}), {base.mode} {b.score:.3f} "
           f"(NCC {b.ncc:.3f} on {b.compared_fraction:.0%})")
    if unbounded:
        why += f"; the visual hull reaches the edge of what the photos judge, so dense is kept unless it is worse by {opts.auto_dense_margin:g}"
    reason = (f"auto: dense multi-view stereo, since the photos agree with it {'about as well as or better' if unbounded else 'better'} "
              f"than with the {base.mode} ({why})" if keep_dense else f"{base.reason}; the dense geometry was not kept ({why})")
    chosen.stats["auto_dense"] = record
    other = base if keep_dense else dense
    other.stats["auto_dense"] = record
    other_reason = (f"auto: dense multi-view stereo ({why})" if not keep_dense
                    else f"{base.reason} ({why})")
    return [GeometryResult(chosen.mesh, chosen.mode, reason, chosen.sphere, chosen.stats),
            GeometryResult(other.mesh, other.mode, other_reason, other.sphere, other.stats)]


@dataclass
class GeometryJudgement:
    """What a :data:`GeometryJudge` decided."""

    chosen: str
    """the geometry mode kept (one of the candidates')"""
    why: str
    """one line: the scores it went by"""
    record: dict[str, Any] = field(default_factory=dict)
    """kept in the capture's geometry statistics (``auto_dense.held_out``)"""


GeometryJudge = Callable[[dict[str, Path]], GeometryJudgement]
"""geometry mode -> a complete capture folder with that geometry (the first: photo consistency's
choice) -> the judgement. Reconstruct cannot fit appearance itself (it comes before appearance),
so the command passes one in."""

CANDIDATE_FRAMES = "frames.candidate"
"""the work folder's subfolder where ``--geometry auto`` writes the second geometry's capture for the judge"""


def _judged(scenes: list[NormalisedScene], first: tuple[list[Frame], dict[str, str], list[str]], staged: Path, work: Path,
            frames_in: Callable[[Path, NormalisedScene, Callable[[str], None]], tuple[list[Frame], dict[str, str]]],
            capture_of: Callable[[Path, NormalisedScene, list[Frame], dict[str, str]], tuple[Capture, ReconstructReport]],
            judge: GeometryJudge, log: Callable[[str], None]) -> tuple[NormalisedScene, list[Frame], dict[str, str], list[str]]:
    """``--geometry auto`` with two geometries: write the second's capture beside the first's
    (already in ``staged``: its frames, dropped photos and what writing them said), let ``judge``
    choose, and leave the chosen one's frames in ``staged``.

    Returns:
        the chosen scene (its geometry's reason and statistics say why), its frames, dropped
        photos and what writing its frames said.
    """
    scene, other = scenes[0], scenes[1]
    candidate = work / CANDIDATE_FRAMES
    if candidate.exists():
        shutil.rmtree(candidate)
    candidate.mkdir()
    try:
        said: list[str] = []
        try:
            second = (*frames_in(candidate, other, said.append), said)
        except DamcapError as e:
            log(f"geometry: the {other.geometry.mode} was not judged ({e})")
            return scene, *first
        write_transforms(capture_of(staged, scene, *first[:2])[0])
        write_transforms(capture_of(candidate, other, *second[:2])[0])
        log(f"geometry: judging the {scene.geometry.mode} and the {other.geometry.mode} by fits on held-out views")
        try:
            verdict = judge({scene.geometry.mode: staged, other.geometry.mode: candidate})
        except DamcapError as e:
            log(f"geometry: kept the {scene.geometry.mode}, not judged on held-out views ({e})")
            return scene, *first
        finally:
            os.remove(staged / "transforms.json")
        keep_other = verdict.chosen == other.geometry.mode
        if keep_other:
            shutil.rmtree(staged)
            os.replace(candidate, staged)
            scene, frames = other, second
        else:
            frames = first
        geo = scene.geometry
        geo.stats["auto_dense"] = {**geo.stats.get("auto_dense", {}), "chosen": geo.mode, "held_out": verdict.record}
        reason = (f"auto: {'dense multi-view stereo' if geo.mode == 'dense' else geo.mode}, kept on held-out views: {verdict.why}"
                  if keep_other else f"{geo.reason}; held-out views agree: {verdict.why}")
        return replace(scene, geometry=replace(geo, reason=reason)), *frames
    finally:
        if candidate.exists():
            shutil.rmtree(candidate)


FRAMES_STAGED = "frames.next"
"""the work folder's subfolder where a run writes its frames and transforms.json (a rerun's too)"""
FRAMES_REPLACED = "frames.previous"
"""the work folder's subfolder where an earlier capture's frames wait, for an instant, while the new ones move in"""
CAPTURE_PARTS = ("images", "geometry")
"""the capture's folders that a run replaces whole (with transforms.json)"""
WORK_PARTS = ("mesh.ply", "report.json")
"""the work folder's files that describe the capture in place (its mesh, its report): staged with
the frames and replaced with them, so a killed rerun never leaves the earlier capture a new mesh"""


def _staged_frames(work: Path, out: Path, log: Callable[[str], None]) -> Path:
    """An empty folder for this run's frames; what a killed run left there goes (an earlier capture
    that a run killed mid-replacement had set aside is put back first)."""
    previous = work / FRAMES_REPLACED
    if previous.is_dir():
        if not (out / "transforms.json").exists() and (previous / "transforms.json").exists():
            for part in (*CAPTURE_PARTS, "transforms.json"):
                if (previous / part).exists():  # set aside, so what stands in its place is the new run's
                    if (out / part).is_dir():
                        shutil.rmtree(out / part)
                    os.replace(previous / part, out / part)
            for part in WORK_PARTS:
                if (previous / part).exists():
                    os.replace(previous / part, work / part)
            log(f"restored: the earlier capture in {out}, which an interrupted run was replacing")
        shutil.rmtree(previous)
    for left in (work / FRAMES_STAGED, work / CANDIDATE_FRAMES):
        if left.exists():
            shutil.rmtree(left)
            log(f"removed: the frames an interrupted run left in {left}")
    staged = work / FRAMES_STAGED
    staged.mkdir()
    return staged


def _commit_frames(out: Path, staged: Path, capture: Capture) -> None:
    """Replace the capture in ``out`` (if any) by the complete one in ``staged`` (frames, and the
    :data:`WORK_PARTS` for the work folder): the earlier capture stays usable until this moment;
    its transforms.json goes first, the new one comes last."""
    write_transforms(replace(capture, root=staged))
    pause_point(out)  # test hook (common/atomic.py): a no-op unless a kill test asks
    previous = staged.parent / FRAMES_REPLACED
    previous.mkdir()
    if (out / "transforms.json").exists():
        os.rename(out / "transforms.json", previous / "transforms.json")
    for part in CAPTURE_PARTS:
        if (out / part).exists():
            os.rename(out / part, previous / part)
        if (staged / part).exists():
            os.rename(staged / part, out / part)
    work = staged.parent
    for part in WORK_PARTS:
        if (work / part).exists():
            os.rename(work / part, previous / part)
        if (staged / part).exists():
            os.rename(staged / part, work / part)
    fsync_path(work)
    os.rename(staged / "transforms.json", out / "transforms.json")
    fsync_path(out)
    shutil.rmtree(previous)
    shutil.rmtree(staged)


def reconstruct_capture(photos_dir: str | os.PathLike, out: str | os.PathLike, opts: ReconstructOptions = ReconstructOptions(),
                        masks_dir: str | os.PathLike | None = None, poses: str | None = None,
                        progress: StageProgress | None = None, log: Callable[[str], None] | None = None,
                        explicit: frozenset[str] = frozenset(), judge: GeometryJudge | None = None) -> tuple[Capture, ReconstructReport]:
    """Run the whole reconstruction (see the module docstring).

    Args:
        photos_dir: folder of photos of one kind: 8-bit JPEG/PNG/TIFF, linear EXR/HDR (``damcap hdr`` /
            ``damcap linearize`` output) or camera RAW (read only; :mod:`damcap.reconstruct.photos`).
        out: capture folder to write (new, or one this function wrote before: its registration is reused).
        opts: options.
        masks_dir: folder of object masks with the photos' base names, or None.
        poses: known cameras (``transforms.json``, ``poses_bounds.npy``, ``colmap:DIR``, ``strecha:DIR``) or None (SfM).
        progress: called as (stage, done, total).
        log: one-line messages (what auto picked and why, dropped photos).
        explicit: names of the options the user set (``train_views``, ``split_start``): a split
            the photos cannot give is refused for these, clamped for defaults.
        judge: under ``--geometry auto`` with two geometries built, what chooses between their
            capture folders (:data:`GeometryJudge`; ``damcap reconstruct`` passes a fit judged on
            held-out views); None: photo consistency alone.

    Returns:
        the capture (as written) and a report.

    Raises:
        DamcapError: a folder without photos, masks that do not match, too few registered photos,
            geometry that no camera sees, bad options.
    """
    opts.validate()
    photos_dir, out = Path(photos_dir), Path(out)
    progress = progress or (lambda stage, done, total: None)
    log = log or (lambda msg: None)
    seconds: dict[str, float] = {}
    t_all = time.perf_counter()

    names, masks = _check_inputs(photos_dir, masks_dir, poses, opts)
    check_split_options(opts, len(names), explicit)
    log_response, tone_curve = _response_curve(photos_dir, names, opts)
    # every input is read and checked before the output folder is touched
    sizes = _photo_sizes(photos_dir, names)
    known = _known_poses(poses, sizes, opts, photos_dir, progress)
    object_fraction = check_masks(masks, sizes)
    exposure_factors([photos_dir / n for n in names], opts.ignore_exposure, tone_curve)  # refuses missing EXIF now
    created = not out.exists()
    _prepare_output(out, [photos_dir] + ([Path(masks_dir)] if masks_dir is not None else []))
    try:
        return _reconstruct_into(photos_dir, out, opts, names, masks, object_fraction, masks_dir, poses, known, log_response,
                                 tone_curve, progress, log, seconds, t_all, judge)
    except DamcapError:
        # a folder this run made is removed, unless it holds a registration a rerun resumes from
        if created and not any((out / WORK_FOLDER / sub).exists() for sub in ("sfm", "sfm-masked")):
            shutil.rmtree(out, ignore_errors=True)
        raise


def _reconstruct_into(photos_dir: Path, out: Path, opts: ReconstructOptions, names: list[str], masks: dict[str, Path] | None,
                      object_fraction: float | None, masks_dir: str | os.PathLike | None, poses: str | None, known: Registration | None,
                      log_response: np.ndarray | None, tone_curve: str, progress: StageProgress, log: Callable[[str], None],
                      seconds: dict[str, float], t_all: float, judge: GeometryJudge | None) -> tuple[Capture, ReconstructReport]:
    """Steps 2 to 7 into the prepared output folder (:func:`reconstruct_capture`)."""
    work = out / WORK_FOLDER
    work.mkdir(exist_ok=True)
    staged = _staged_frames(work, out, log)
    try:
        return _reconstruct_staged(photos_dir, out, staged, opts, names, masks, object_fraction, masks_dir, poses, known, log_response,
                                   tone_curve, progress, log, seconds, t_all, judge)
    finally:
        if staged.exists():  # a failed or interrupted run: the earlier capture, if any, is as it was
            shutil.rmtree(staged, ignore_errors=True)


def _reconstruct_staged(photos_dir: Path, out: Path, staged: Path, opts: ReconstructOptions, names: list[str],
                        masks: dict[str, Path] | None, object_fraction: float | None, masks_dir: str | os.PathLike | None,
                        poses: str | None, known: Registration | None, log_response: np.ndarray | None, tone_curve: str,
                        progress: StageProgress, log: Callable[[str], None], seconds: dict[str, float],
                        t_all: float, judge: GeometryJudge | None) -> tuple[Capture, ReconstructReport]:
    """:func:`_reconstruct_into` with the frames written into ``staged`` and moved into ``out`` at the end."""
    work = out / WORK_FOLDER
    chosen, candidates = _choose_cameras(photos_dir, names, work, opts, masks, object_fraction, known, progress, log, seconds)
    chosen, left_out = _apply_self_check(chosen, opts, len(names), photos_dir, log)
    reg, targets, mask_px = chosen.reg, chosen.targets, chosen.mask_px
    for name, why in sorted(reg.unregistered.items()):
        log(f"unregistered: {name}: {why}")
    # exposure is checked before the long steps
    factors, exposures, reference, lin_note = exposure_factors([photos_dir / p.name for p in reg.photos], opts.ignore_exposure,
                                                               tone_curve)
    log(f"linearisation: {lin_note}")
    scenes = _scene(reg, targets, mask_px, opts, progress, log, seconds, photos_dir, log_response)

    t0 = time.perf_counter()
    photos = [FramePhoto(p.name, photos_dir / p.name, p.camera, tgt, float(factors[k]), exposures[k].to_json() or None,
                         mask_px[k] if (mask_px is not None and opts.mask_coverage) else None)
              for k, (p, tgt) in enumerate(zip(reg.photos, targets))]

    def frames_in(folder: Path, scene: NormalisedScene, say: Callable[[str], None] = log) -> tuple[list[Frame], dict[str, str]]:
        frames, dropped = write_frames(folder, photos, scene.world_from_cams, scene.mesh, scene.sphere, reference,
                                       opts.supersample, opts.dtype, progress, say, log_response, opts.clipped)
        if not frames:
            raise DamcapError(f"{out}: no camera sees the geometry ({scene.geometry.reason}); check --geometry / the mesh's frame")
        if len(frames) < 2:
            raise DamcapError(f"{out}: only {len(frames)} frame sees the geometry; a capture needs at least 2")
        return frames, {**left_out, **dropped}

    def capture_of(root: Path, scene: NormalisedScene, frames: list[Frame], dropped: dict[str, str]) -> tuple[Capture, ReconstructReport]:
        """The capture of ``frames`` in ``root`` (its split, report and provenance; nothing written)."""
        geo = scene.geometry
        if opts.split == "rings":  # the object's centre is the origin here (recentred on the geometry)
            world_from_cams = np.stack([f.world_from_cam for f in frames])
            centres = world_from_cams[:, :3, 3]
            directions = centres / np.maximum(np.linalg.norm(centres, axis=1, keepdims=True), 1e-12)
            train_idx, test_idx = camera_split(directions, up_direction(world_from_cams), min(opts.train_views, len(frames) - 1))
            train_idx = sorted(train_idx)
        else:
            train_idx, test_idx = split_indices(len(frames), opts.train_views, opts.split, opts.split_start % len(frames))
        seconds["total"] = time.perf_counter() - t_all
        report = ReconstructReport(
            photos=len(names), registered=len(reg.photos) + len(left_out), unregistered=dict(reg.unregistered), frames=len(frames),
            dropped=dropped, geometry_mode=geo.mode, geometry_reason=geo.reason,
            train=[frames[i].file_path for i in train_idx], test=[frames[i].file_path for i in test_idx],
            registration={"source": reg.source, **{k: v for k, v in reg.stats.items() if k != "unregistered"},
                          "features_used": chosen.features, "candidates": candidates},
            seconds={k: round(v, 2) for k, v in seconds.items()}, linearisation=lin_note,
            self_check=chosen.check.to_json() if chosen.check is not None else None, geometry_check=geo.stats.get("auto_dense"))
        sphere = scene.sphere
        source = {
            "tool": "damcap reconstruct", "damcap_package_version": package_version(), "photos": str(photos_dir.resolve()),
            "masks": str(Path(masks_dir).resolve()) if masks_dir is not None else None, "poses": poses,
            "options": asdict(opts), "norm_from_input_world": scene.norm_from_world.tolist(),
            "geometry": {"mode": geo.mode, "reason": geo.reason, "mesh": f"{WORK_FOLDER}/mesh.ply",
                         **({"sphere_centre": sphere[0].tolist(), "sphere_radius": sphere[1]} if sphere else {}),
                         "stats": _jsonable(geo.stats)},
            "registration": _jsonable(report.registration), "self_check": _jsonable(report.self_check),
            "unregistered": report.unregistered, "dropped": dropped,
            "linearisation": lin_note, "reference_exposure": reference,
        }
        return Capture(root=root, frames=frames, train_filenames=report.train, test_filenames=report.test,
                       colorspace="lin_rec709", extra={"damcap_source": source}), report

    scene = scenes[0]
    judge = judge if len(scenes) > 1 else None
    said: list[str] = []  # judged: what writing the frames says is said for the geometry kept
    frames, dropped = frames_in(staged, scene, log if judge is None else said.append)
    if judge is not None:
        scene, frames, dropped, said = _judged(scenes, (frames, dropped, said), staged, work, frames_in, capture_of, judge, log)
        for line in said:
            log(line)
    seconds["frames"] = time.perf_counter() - t0
    geo = scene.geometry
    if geo.mode == "visual-hull" and geo.stats.get("touches_box"):
        log(f"warning: {UNBOUNDED_HULL}; photos that hold the whole object close it, or use --geometry dense or mesh:FILE")
    _save_mesh(staged / "mesh.ply", scene.mesh)  # staged: moves into the work folder with the frames (_commit_frames)
    capture, report = capture_of(out, scene, frames, dropped)
    write_json_atomic(staged / "report.json", _jsonable(asdict(report)))
    _commit_frames(out, staged, capture)
    return capture, report


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return obj

