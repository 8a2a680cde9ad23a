"""Does a registration agree with its photos? A self-check that needs no ground truth.

Every ``damcap reconstruct`` runs it on its cameras (registered or known) and stores it in the
capture. Per photo:

- **Silhouette agreement** (with masks): the visual hull carved by all *other* photos (a few of
  them may disagree, ``tolerance_fraction``) must project onto this photo's mask
  (``precision``: the hull's voxels that land on the mask) and explain it (``recall``: rays
  through the mask's pixels that meet the hull). With right cameras both are near 1; a wrong
  camera, a mirrored photo, a photo of another object or a wrong mask leave one of them low.
- **Reprojection error** of the photo's sparse points (COLMAP's observations), and how many of
  them lie on the object (inside its mask): a camera placed by the background alone has none.

For the set: the angle the cameras span around the point they look at (a turntable registered
on its static background collapses to one viewpoint).

Photos below ``min_silhouette_recall`` / ``min_silhouette_precision`` or above ``max_reprojection_px`` are flagged; when more
than half are flagged the registration as a whole is inconsistent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Literal

import numpy as np

from damcap.common.cameras import pixel_rays_world
from damcap.common.capture_folder import Intrinsics
from damcap.common.validate import FRACTION, POSITIVE, in_range

from damcap.reconstruct.geometry import (
    MASK_THRESHOLD,
    GeometryInputs,
    _object_points,
    grid_box,
    hull_bounds,
    mask_values_and_judged,
    project_points,
    reaches_limits,
    sample_bilinear,
    voxel_centres,
)


Verdict = Literal["consistent", "photos flagged", "inconsistent", "not checked"]


@dataclass(frozen=True)
class SelfCheckOptions:
    """Thresholds and resolution of the self-check (``damcap reconstruct``'s "Self-check" options;
    the grid's fields are the library's and the bench's)."""

    min_silhouette_recall: float = field(default=0.95, metadata={**FRACTION, "cli_panel": "advanced"})
    """a photo is flagged when fewer of its mask's pixels see the others' visual hull. Right
    cameras: >= 0.985 on every cape photo; one camera turned by 3 deg: 0.85."""
    min_silhouette_precision: float = field(default=0.5, metadata={**FRACTION, "cli_panel": "advanced"})
    """a photo is flagged when less of the others' visual hull lands on its mask. It is low where a
    photo alone carves the hull: >= 0.67 on every cape photo with right cameras."""
    max_reprojection_px: float = field(default=2.0, metadata={**POSITIVE, "cli_panel": "advanced"})
    """a photo whose sparse points reproject worse than this (mean, photo pixels) is flagged"""
    tolerance_fraction: float = field(default=0.1, metadata=in_range(0, 0.5, cli_exclude=True))
    """the consensus hull keeps a voxel that up to this fraction of the other photos see as background"""
    voxels: int = field(default=64, metadata=in_range(8, 512, cli_exclude=True))
    """consensus hull grid: voxels along the object's longest side"""
    ray_samples: int = field(default=1500, metadata=in_range(10, 1_000_000, cli_exclude=True))
    """mask pixels sampled per photo for the recall"""


@dataclass
class PhotoCheck:
    """The self-check of one photo."""

    name: str
    silhouette_precision: float | None = None
    """fraction of the others' hull (voxels) that projects onto this photo's mask; None without masks"""
    silhouette_recall: float | None = None
    """fraction of this mask's pixels whose rays meet the others' hull; None without masks"""
    reprojection_px: float | None = None
    """mean reprojection error of its sparse points, photo pixels; None without points"""
    points: int = 0
    """its sparse points (observations with a 3D point)"""
    object_points: int | None = None
    """those inside its mask; None without masks"""
    problem: str | None = None
    """why it is flagged, or None"""


@dataclass
class SelfCheck:
    """The self-check of a registration."""

    photos: list[PhotoCheck]
    view_span_deg: float
    """largest angle between two cameras' directions seen from the point they look at"""
    verdict: Verdict
    consensus_voxels: int = 0
    """occupied voxels of the consensus hull (0 without masks)"""
    options: dict[str, Any] = field(default_factory=dict)
    precision_skipped: str | None = None
    """why no photo is flagged on silhouette precision (the consensus hull reaches the limits of
    what the photos judge, so it is not the object there), or None when it is tested"""

    @property
    def flagged(self) -> dict[str, str]:
        """photo name -> problem, for the flagged photos."""
        return {p.name: p.problem for p in self.photos if p.problem}

    def median(self, what: str) -> float | None:
        vals = [getattr(p, what) for p in self.photos if getattr(p, what) is not None]
        return float(np.median(vals)) if vals else None

    def summary(self) -> str:
        """One line for the user."""
        parts = [f"{self.verdict}: {len(self.photos) - len(self.flagged)} of {len(self.photos)} photos agree"]
        if self.median("silhouette_recall") is not None:
            parts.append(f"silhouette recall min {min(p.silhouette_recall for p in self.photos):.3f}, "  # type: ignore[type-var]
                         f"precision min {min(p.silhouette_precision for p in self.photos):.3f}")  # type: ignore[type-var]
        rep = self.median("reprojection_px")
        if rep is not None:
            parts.append(f"reprojection median {rep:.2f} px")
        parts.append(f"cameras span {self.view_span_deg:.0f} deg around the object")
        if self.precision_skipped:
            parts.append(f"silhouette precision not tested: {self.precision_skipped}")
        return "; ".join(parts)

    def to_json(self) -> dict[str, Any]:
        return {"verdict": self.verdict, "summary": self.summary(), "view_span_deg": round(self.view_span_deg, 3),
                "consensus_voxels": self.consensus_voxels, "flagged": self.flagged, "options": self.options,
                "precision_skipped": self.precision_skipped,
                "photos": {p.name: {k: (round(v, 4) if isinstance(v, float) else v) for k, v in
                                    (("silhouette_precision", p.silhouette_precision), ("silhouette_recall", p.silhouette_recall),
                                     ("reprojection_px", p.reprojection_px), ("points", p.points),
                                     ("object_points", p.object_points), ("problem", p.problem))}
                           for p in self.photos}}


# --------------------------------------------------------------------------------------------
# Pure pieces
# --------------------------------------------------------------------------------------------

def consensus_tolerance(n_others: int, fraction: float) -> int:
    """Photos of the others allowed to see background where the consensus hull keeps a voxel.

    >>> consensus_tolerance(9, 0.1), consensus_tolerance(118, 0.1), consensus_tolerance(3, 0.1)
    (0, 11, 0)
    """
    return int(math.floor(fraction * n_others))


def view_span_deg(centres_world: np.ndarray, focus_world: np.ndarray) -> float:
    """Largest angle between two cameras' directions from ``focus_world`` (degrees, [0, 180]).

    Args:
        centres_world: (N, 3) camera centres.
        focus_world: (3,) the point they look at.

    >>> round(view_span_deg(np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]), np.zeros(3)), 6)
    90.0
    """
    d = np.asarray(centres_world, np.float64) - np.asarray(focus_world, np.float64)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    if len(d) < 2:
        return 0.0
    return float(np.degrees(np.arccos(np.clip((d @ d.T).min(), -1.0, 1.0))))


def smallest_views(values: list[np.ndarray], keep: int) -> tuple[np.ndarray, np.ndarray]:
    """Per voxel, the ``keep`` smallest values over the photos and which photo gave each.

    Args:
        values: N (V,) float32 arrays (one per photo: its mask value at each voxel).
        keep: how many to keep (at most N).

    Returns:
        vals: (keep, V) float32, ascending along axis 0.
        ids: (keep, V) int32, the photo index of each value.
    """
    stack = np.stack(values)  # (N, V)
    keep = min(keep, len(values))
    idx = np.argpartition(stack, keep - 1, axis=0)[:keep] if keep < len(values) else np.tile(
        np.arange(len(values))[:, None], (1, stack.shape[1]))
    vals = np.take_along_axis(stack, idx, axis=0)
    order = np.argsort(vals, axis=0, kind="stable")
    return np.take_along_axis(vals, order, axis=0), np.take_along_axis(idx, order, axis=0).astype(np.int32)


def leave_one_out_occupancy(vals: np.ndarray, ids: np.ndarray, photo: int, tolerance: int) -> np.ndarray:
    """Occupancy of each voxel carved by every photo but ``photo``, ``tolerance`` of them may disagree.

    The (tolerance+1)-th smallest mask value among the other photos: ``vals[tolerance + 1]`` where
    ``photo`` is among the first ``tolerance + 1`` entries, else ``vals[tolerance]``.

    Args:
        vals, ids: from :func:`smallest_views` with ``keep >= tolerance + 2``.
        photo: the photo left out.
        tolerance: photos allowed to see background inside the hull.

    Returns:
        (V,) float32 in [0, 1].
    """
    among = (ids[:tolerance + 1] == photo).any(axis=0)
    if tolerance + 1 >= len(vals):  # only tolerance + 1 photos at all: nothing left to carve
        return np.where(among, np.float32(1.0), vals[tolerance])
    return np.where(among, vals[tolerance + 1], vals[tolerance])


def silhouette_precision(hull_points_world: np.ndarray, mask: np.ndarray, world_from_cam: np.ndarray,
                         intr: Intrinsics) -> float:
    """Fraction of hull points (voxel centres) that project onto the mask; points behind the
    camera or outside a photo that the object's silhouette leaves (it touches the border) do not count.

    Returns:
        in [0, 1]; 0 for an empty hull.
    """
    if len(hull_points_world) == 0:
        return 0.0
    uv, front = project_points(hull_points_world, world_from_cam, intr)
    h, w = mask.shape
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    border = max(mask[0].max(), mask[-1].max(), mask[:, 0].max(), mask[:, -1].max()) > MASK_THRESHOLD
    counted = front & (inside | ~border)
    if not counted.any():
        return 0.0
    vals = sample_bilinear(mask, uv[counted], outside=0.0)
    return float((vals > MASK_THRESHOLD).mean())


def rays_hit_volume(origin: np.ndarray, dirs: np.ndarray, occupied_zyx: np.ndarray, grid_origin: np.ndarray,
                    voxel_size: float) -> np.ndarray:
    """Whether each ray passes through an occupied voxel (marched at half-voxel steps through the grid's box).

    Args:
        origin: (3,) ray origin, world.
        dirs: (R, 3) unit directions, world.
        occupied_zyx: (Z, Y, X) bool.
        grid_origin: (3,) world position of voxel [0, 0, 0]'s corner (x, y, z).
        voxel_size: world units.

    Returns:
        (R,) bool.
    """
    dims = np.array(occupied_zyx.shape[::-1], np.float64)  # (X, Y, Z)
    lo, hi = grid_origin, grid_origin + dims * voxel_size
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        t0, t1 = (lo - origin) * inv, (hi - origin) * inv
    t_near = np.nanmax(np.minimum(t0, t1), axis=1).clip(min=0.0)
    t_far = np.nanmin(np.maximum(t0, t1), axis=1)
    hit = np.zeros(len(dirs), bool)
    live = t_far > t_near
    if not live.any():
        return hit
    steps = int(2 * dims.max() * math.sqrt(3)) + 1
    frac = (np.arange(steps) + 0.5) / steps
    tn, tf, d = t_near[live], t_far[live], dirs[live]
    ts = tn[:, None] + (tf - tn)[:, None] * frac[None, :]  # (R', S)
    pts = origin + ts[..., None] * d[:, None, :]
    ijk = np.floor((pts - lo) / voxel_size).astype(np.int64)
    ok = ((ijk >= 0) & (ijk < dims.astype(np.int64))).all(-1)
    ijk = np.where(ok[..., None], ijk, 0)
    occ = occupied_zyx[ijk[..., 2], ijk[..., 1], ijk[..., 0]] & ok
    hit[live] = occ.any(axis=1)
    return hit


def silhouette_recall(mask: np.ndarray, world_from_cam: np.ndarray, intr: Intrinsics, occupied_zyx: np.ndarray,
                      grid_origin: np.ndarray, voxel_size: float, samples: int, rng: np.random.Generator) -> float:
    """Fraction of the mask's pixels (``samples`` of them at random) whose rays meet the hull.

    Returns:
        in [0, 1]; 1 for an empty mask (nothing to explain).
    """
    ij = np.argwhere(mask > MASK_THRESHOLD)
    if len(ij) == 0:
        return 1.0
    if len(ij) > samples:
        ij = ij[rng.choice(len(ij), samples, replace=False)]
    origin, dirs = pixel_rays_world(np.asarray(world_from_cam, np.float64), intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h)
    d = dirs[ij[:, 0], ij[:, 1]].astype(np.float64)
    return float(rays_hit_volume(origin, d / np.linalg.norm(d, axis=1, keepdims=True), occupied_zyx, grid_origin, voxel_size).mean())


def observation_stats(observations_px: np.ndarray | None, mask_photo: np.ndarray | None) -> tuple[float | None, int, int | None]:
    """(mean reprojection error px or None, points, points inside the mask or None) of one photo.

    Args:
        observations_px: (M, 3) rows (x, y, reprojection error), photo pixels; None: no points.
        mask_photo: (H, W) mask at the photo's resolution, or None.
    """
    if observations_px is None or len(observations_px) == 0:
        return None, 0, (0 if mask_photo is not None else None)
    obs = np.asarray(observations_px, np.float64)
    inside = None
    if mask_photo is not None:
        h, w = mask_photo.shape
        x = np.clip(obs[:, 0].astype(np.int64), 0, w - 1)
        y = np.clip(obs[:, 1].astype(np.int64), 0, h - 1)
        inside = int((mask_photo[y, x] > MASK_THRESHOLD).sum())
    return float(obs[:, 2].mean()), len(obs), inside


def photo_problem(check: PhotoCheck, opts: SelfCheckOptions, precision: bool = True) -> str | None:
    """Why a photo disagrees with the others, or None; ``precision=False`` leaves the silhouette
    precision untested (a consensus hull that reaches its bounds).

    >>> photo_problem(PhotoCheck("a.jpg", 0.95, 0.42, 0.5, 100, 80), SelfCheckOptions())
    "silhouette recall 0.420 < 0.95: rays through its mask miss the others' visual hull (camera or mask wrong)"
    """
    if check.silhouette_recall is not None and check.silhouette_recall < opts.min_silhouette_recall:
        return (f"silhouette recall {check.silhouette_recall:.3f} < {opts.min_silhouette_recall:g}: rays through its mask miss "
                "the others' visual hull (camera or mask wrong)")
    if precision and check.silhouette_precision is not None and check.silhouette_precision < opts.min_silhouette_precision:
        return (f"silhouette precision {check.silhouette_precision:.3f} < {opts.min_silhouette_precision:g}: the others' visual "
                "hull falls outside its mask (camera or mask wrong)")
    if check.reprojection_px is not None and check.reprojection_px > opts.max_reprojection_px:
        return f"reprojection error {check.reprojection_px:.2f} px > {opts.max_reprojection_px:g} px"
    return None


def verdict_of(flagged: int, photos: int) -> Verdict:
    """'consistent' (none flagged), 'photos flagged' (up to half), 'inconsistent' (more than half).

    >>> verdict_of(0, 10), verdict_of(5, 10), verdict_of(6, 10)
    ('consistent', 'photos flagged', 'inconsistent')
    """
    if flagged == 0:
        return "consistent"
    return "inconsistent" if 2 * flagged > photos else "photos flagged"


# --------------------------------------------------------------------------------------------
# The check
# --------------------------------------------------------------------------------------------

def self_check(names: list[str], world_from_cams: np.ndarray, intrinsics: list[Intrinsics],
               masks: list[np.ndarray] | None, observations: list[tuple[float | None, int, int | None]],
               opts: SelfCheckOptions = SelfCheckOptions(), seed: int = 0,
               progress: Callable[[str, int, int], None] | None = None, points_world: np.ndarray | None = None) -> SelfCheck:
    """Check cameras against the photos' masks and sparse points (see the module docstring).

    Args:
        names: N photo names.
        world_from_cams: (N, 4, 4) OpenGL camera-to-world in the normalised frame (the point the
            cameras look at on the origin, object radius about 1: :func:`~damcap.reconstruct.normalize.normalization_transform`).
        intrinsics: N pinhole cameras of ``masks``.
        masks: N (h, w) float32 masks in [0, 1] in those pinhole cameras, or None.
        observations: N :func:`observation_stats` of each photo's sparse points.
        opts: thresholds.
        seed: which mask pixels are sampled.
        progress: called as ("self-check", done, total).
        points_world: (P, 3) sparse points in the same frame, or None: those on the object bound
            the consensus hull's grid (:func:`~damcap.reconstruct.geometry.hull_bounds`).

    Silhouette precision is not tested when the consensus hull reaches the limits of what the
    photos judge (:func:`~damcap.reconstruct.geometry.reaches_limits`: an object that leaves the
    frame in many photos): there the hull is not the object, and right cameras would fall below
    the threshold; :attr:`SelfCheck.precision_skipped` says so.

    Returns:
        the check (the verdict counts flagged photos).
    """
    cams = np.asarray(world_from_cams, np.float64)
    n = len(names)
    checks = []
    progress = progress or (lambda stage, done, total: None)
    for k in range(n):
        rep, pts, obj = observations[k]
        checks.append(PhotoCheck(names[k], reprojection_px=rep, points=pts, object_points=obj))
    focus = np.zeros(3)  # the normalised frame's origin: the point the cameras look at
    voxels_on = 0
    precision_skipped: str | None = None
    if masks is not None and n >= 2:
        tol = consensus_tolerance(n - 1, opts.tolerance_fraction)
        pts = None
        if points_world is not None and len(points_world):
            pts = _object_points(GeometryInputs(cams, list(intrinsics), masks, np.asarray(points_world, np.float64)))
        bounds = hull_bounds(masks, cams, intrinsics, tol, points_world=pts if pts is not None and len(pts) else None)
        if bounds is None:
            for c in checks:
                c.silhouette_precision, c.silhouette_recall = 0.0, 0.0
        else:
            origin, size, dims = grid_box(bounds.box_min, bounds.box_max, opts.voxels)
            centres = voxel_centres(origin, size, dims).astype(np.float32)
            per_photo, seen = [], np.zeros(len(centres), np.int32)
            for m, w, i in zip(masks, cams, intrinsics):
                v, s = mask_values_and_judged(centres, m, w, i)
                per_photo.append(v)
                seen += s
            vals, ids = smallest_views(per_photo, tol + 2)
            del per_photo
            judged = seen >= bounds.min_views
            if bounds.points_box is not None:
                judged &= np.all((centres >= bounds.points_box[0]) & (centres <= bounds.points_box[1]), axis=1)
            rng = np.random.default_rng(seed)
            hull_all = (leave_one_out_occupancy(vals, ids, -1, tol) > 0.5) & judged
            unjudged = (leave_one_out_occupancy(vals, ids, -1, tol) > 0) & ~judged
            if reaches_limits(hull_all.reshape(dims[::-1]), unjudged.reshape(dims[::-1])):
                precision_skipped = ("the others' visual hull reaches the limits of what the photos judge (the object "
                                     "leaves the frame in many photos), so it is not the object there")
            voxels_on = int(hull_all.sum())
            if voxels_on:
                focus = centres[hull_all].mean(0).astype(np.float64)
            for k in range(n):
                progress("self-check", k, n)
                occ = (leave_one_out_occupancy(vals, ids, k, tol) > 0.5) & judged
                checks[k].silhouette_precision = silhouette_precision(centres[occ], masks[k], cams[k], intrinsics[k])
                checks[k].silhouette_recall = silhouette_recall(masks[k], cams[k], intrinsics[k], occ.reshape(dims[::-1]),
                                                                origin, size, opts.ray_samples, rng)
    progress("self-check", n, n)
    for c in checks:
        c.problem = photo_problem(c, opts, precision=precision_skipped is None)
    flagged = sum(1 for c in checks if c.problem)
    return SelfCheck(photos=checks, view_span_deg=view_span_deg(cams[:, :3, 3], focus), verdict=verdict_of(flagged, n),
                     consensus_voxels=voxels_on, options={k: getattr(opts, k) for k in opts.__dataclass_fields__},
                     precision_skipped=precision_skipped)
