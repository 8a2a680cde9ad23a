"""Dense geometry from calibrated photos on a CPU: plane-sweep stereo in torch, fused by Open3D.

Per reference view (at most ``max_views``, spread over the set):

1. neighbour views whose baseline angle, seen from the object, lies in a window
   (:func:`select_neighbours`);
2. a depth range from the visual hull's coarse carve (masks) or the sparse points (quantiles)
   (:func:`depth_range`);
3. plane-sweep stereo (Collins 1996; Gallup et al. 2007): fronto-parallel planes sampled
   uniformly in inverse depth, every neighbour warped onto each plane by its homography with
   ``grid_sample``, windowed normalised cross-correlation on grayscale, the mean of the best K
   neighbours' NCC per hypothesis (occlusion robustness, Kang et al. 2001), winner-take-all, then
   a finer sweep of +-1.5 plane steps around the median-filtered winner and a parabola through
   the best sample and its two neighbours (:func:`plane_sweep_depth`); hypotheses that land on a
   neighbour's background are rejected (the visual hull, for free);
4. geometric consistency across views: a depth survives when at least ``min_consistent``
   neighbours' depth maps reproject onto it within a pixel and a relative depth tolerance
   (:func:`consistency_mask`; as in COLMAP's fusion and MVSNet's filter);
5. fusion: screened Poisson on the fused oriented points, or Open3D's tensor TSDF
   (``VoxelBlockGrid``); mesh parts outside the silhouettes (up to ``trim_tolerance`` of the
   views may disagree) are discarded, then the mesh is cleaned (largest component, optional
   Taubin smoothing).

Frames: the capture's cameras are OpenGL (x right, y up, looking down -z); all stereo math here
is done in OpenCV camera axes (x right, y down, looking down +z, ``cam_cv = diag(1, -1, -1) cam_gl``),
where depth is the +z coordinate and a pixel (i, j) has its centre at ``(u, v) = (j + 0.5, i + 0.5)``
(damcap's convention; Open3D puts pixel centres at integers, so its K is shifted by half a pixel).
Arrays are numpy at the public functions; torch runs inside on ``DenseOptions.device``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from damcap.common.capture_folder import Intrinsics
from damcap.common.errors import DamcapError
from damcap.common.mesh import Mesh, signed_volume
from damcap.common.validate import FRACTION, MAX_IMAGE_SIDE, check_ranges, in_range
from damcap.reconstruct.geometry import (
    MASK_THRESHOLD,
    GeometryInputs,
    GeometryResult,
    _object_points,
    carve,
    carve_hull_grid,
    clean_surface,
    fuse_poisson,
    project_points,
)

FusionKind = Literal["poisson", "tsdf"]
Progress = Callable[[str, int, int], None]
#: OpenGL camera axes -> OpenCV camera axes (and back: it is its own inverse)
CV_FROM_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class DenseOptions:
    """Dense multi-view stereo and fusion (``--geometry dense``; ``damcap reconstruct``'s "Dense
    stereo" options are the fields with a ``cli_flag``, the others are the library's and the bench's)."""

    image_size: int = field(default=320, metadata=in_range(16, MAX_IMAGE_SIDE, cli_flag="--dense-size"))
    """working image size: longest side of the photos stereo matches, pixels (never upsampled). On
    the rendered bunny (36 photos of 320 px, true cameras; bench/reconstruct.md) 160 px took 16 s
    against 23 s, for a median normal error of 12.3 deg against 11.2 and Chamfer 1.72 % against 1.53"""
    depth_planes: int = field(default=64, metadata=in_range(4, 1024, cli_flag="--dense-planes"))
    """depth hypotheses per reference view (fronto-parallel planes, uniform in inverse depth). On
    the rendered bunny 32 planes took 20 s (11.3 deg, Chamfer 1.61 %) and 128 took 34 s (11.5 deg,
    1.53 %), against 64's 23 s (11.2 deg, 1.53 %)"""
    neighbours: int = field(default=4, metadata=in_range(1, 32, cli_exclude=True))
    """source views matched against each reference view"""
    refine_samples: int = field(default=4, metadata=in_range(0, 64, cli_exclude=True))
    """refinement around the winning plane: hypotheses per plane step, over +-1.5 steps (0: none)"""
    best_k: int = field(default=2, metadata=in_range(1, 32, cli_exclude=True))
    """a hypothesis' cost is the mean NCC of its best K neighbours (occlusion robustness; <= neighbours)"""
    min_baseline_deg: float = field(default=5.0, metadata=in_range(0, 90, cli_exclude=True))
    """neighbours: smallest angle between the two cameras seen from the object, degrees"""
    max_baseline_deg: float = field(default=40.0, metadata=in_range(0, 180, lo_open=True, cli_exclude=True))
    """neighbours: largest angle between the two cameras seen from the object, degrees"""
    ncc_window: int = field(default=7, metadata=in_range(3, 31, cli_exclude=True))
    """NCC window side, pixels (odd)"""
    min_ncc: float = field(default=0.5, metadata=in_range(-1, 1, cli_exclude=True))
    """a depth is kept when its best-K mean NCC reaches this"""
    consistency_px: float = field(default=1.0, metadata=in_range(0, 100, lo_open=True, cli_exclude=True))
    """geometric consistency: largest reprojection distance through a neighbour's depth, working pixels"""
    consistency_depth: float = field(default=0.01, metadata=in_range(0, 1, lo_open=True, cli_exclude=True))
    """geometric consistency: largest relative depth difference"""
    min_consistent: int = field(default=2, metadata=in_range(0, 32, cli_exclude=True))
    """a depth survives when at least this many neighbours agree with it (0: no filter)"""
    voxels: int = field(default=256, metadata=in_range(16, 2048, cli_exclude=True))
    """fusion resolution: voxels along the longest side of the object's box (Poisson: octree depth
    ceil(log2(voxels)))"""
    fusion: FusionKind = field(default="poisson", metadata={"cli_exclude": True})
    """'poisson' (screened Poisson of the fused oriented points) or 'tsdf' (Open3D VoxelBlockGrid)"""
    max_views: int = field(default=40, metadata=in_range(2, 100_000, cli_flag="--dense-views", cli_panel="advanced"))
    """most reference views (chosen spread over the cameras' directions)"""
    trim_tolerance: float = field(default=0.1, metadata=in_range(0, 1, cli_exclude=True))
    """masks: the fused mesh keeps a triangle where at most this fraction of the views see
    background (holes of clipped highlights in a mask, slightly wrong masks)"""
    smooth_iterations: int = field(default=0, metadata=in_range(0, 1000, cli_exclude=True))
    """Taubin smoothing iterations of the fused mesh (0 = none)"""
    min_valid_fraction: float = field(default=0.05, metadata={**FRACTION, "cli_exclude": True})
    """refuse (too little texture to match) when fewer of the object's pixels keep a depth"""
    device: str = field(default="cpu", metadata={"cli_exclude": True})
    """torch device of the stereo ('cpu', 'cuda', 'cuda:1', ...)"""

    def validate(self) -> None:
        """Raise DamcapError naming the first bad value."""
        check_ranges(self)
        if self.ncc_window % 2 == 0:
            raise DamcapError(f"--ncc-window must be odd, got {self.ncc_window}")
        if self.best_k > self.neighbours:
            raise DamcapError(f"--best-k {self.best_k} must not exceed --neighbours {self.neighbours}")
        if not self.min_baseline_deg < self.max_baseline_deg:
            raise DamcapError(f"--min-baseline-deg {self.min_baseline_deg:g} must be below --max-baseline-deg "
                              f"{self.max_baseline_deg:g}")
        if self.fusion not in ("poisson", "tsdf"):
            raise DamcapError(f"--fusion must be one of poisson, tsdf, got {self.fusion!r}")
        try:
            import torch

            torch.empty(0, device=self.device)
        except (RuntimeError, ValueError) as e:
            raise DamcapError(f"--device {self.device!r} is not usable by torch here ({str(e).splitlines()[0]})") from None


# --------------------------------------------------------------------------------------------
# Cameras
# --------------------------------------------------------------------------------------------

def k_matrix(intr: Intrinsics) -> np.ndarray:
    """(3, 3) float64 pinhole matrix mapping OpenCV camera points to pixel coordinates, pixel
    (i, j) centre at (j + 0.5, i + 0.5)."""
    return np.array([[intr.fl_x, 0.0, intr.cx], [0.0, intr.fl_y, intr.cy], [0.0, 0.0, 1.0]])


def cam_cv_from_world(world_from_cam_gl: np.ndarray) -> np.ndarray:
    """(..., 4, 4) OpenCV world-to-camera extrinsics of OpenGL camera-to-world matrices.

    >>> np.round(cam_cv_from_world(np.eye(4)) @ [0.0, 0.0, -2.0, 1.0], 12).tolist()  # 2 in front
    [0.0, 0.0, 2.0, 1.0]
    """
    return CV_FROM_GL @ np.linalg.inv(np.asarray(world_from_cam_gl, np.float64))


def scaled_intrinsics(intr: Intrinsics, scale: float) -> Intrinsics:
    """The intrinsics of the image resampled by ``scale`` (edges kept: pixel edges scale with it)."""
    w, h = max(1, round(intr.w * scale)), max(1, round(intr.h * scale))
    sx, sy = w / intr.w, h / intr.h
    return Intrinsics(intr.fl_x * sx, intr.fl_y * sy, intr.cx * sx, intr.cy * sy, w, h)


def resize_image(image: np.ndarray, w: int, h: int) -> np.ndarray:
    """(h, w[, C]) float32 area-resampled (bilinear when enlarging)."""
    import cv2

    img = np.ascontiguousarray(image, dtype=np.float32)
    if img.shape[1] == w and img.shape[0] == h:
        return img
    interp = cv2.INTER_AREA if w < img.shape[1] else cv2.INTER_LINEAR
    return cv2.resize(img, (w, h), interpolation=interp)


def gray_normalised(image: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """Grayscale (mean of the channels) shifted and scaled to zero mean and unit deviation over
    the mask (the whole image without one), so that thresholds below are scale-free.

    Args:
        image: (h, w) or (h, w, C) float, linear or sRGB, >= 0.
        mask: (h, w) in [0, 1] or None.

    Returns:
        (h, w) float32.
    """
    g = np.asarray(image, np.float32)
    if g.ndim == 3:
        g = g.mean(-1)
    sel = g[mask > MASK_THRESHOLD] if mask is not None and (mask > MASK_THRESHOLD).any() else g.reshape(-1)
    sd = float(sel.std())
    return ((g - float(sel.mean())) / (sd if sd > 0 else 1.0)).astype(np.float32)


def spread_views(directions: np.ndarray, n: int) -> np.ndarray:
    """Indices of ``n`` views spread over their directions (farthest-point sampling from view 0).

    Args:
        directions: (N, 3) unit directions from the object to each camera.
        n: how many to keep.

    Returns:
        (min(n, N),) sorted int64 indices.

    >>> spread_views(np.array([[1.0, 0, 0], [0.99, 0.14, 0], [-1, 0, 0]]), 2).tolist()
    [0, 2]
    """
    d = np.asarray(directions, np.float64)
    if n >= len(d):
        return np.arange(len(d))
    chosen = [0]
    dist = np.arccos(np.clip(d @ d[0], -1, 1))
    for _ in range(n - 1):
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.arccos(np.clip(d @ d[k], -1, 1)))
    return np.sort(np.array(chosen, np.int64))


def select_neighbours(centres_world: np.ndarray, object_centre: np.ndarray, n: int, min_deg: float = 5.0,
                      max_deg: float = 40.0, target_deg: float | None = None) -> list[np.ndarray]:
    """Neighbour views of each view: those whose baseline angle seen from the object lies in
    [min_deg, max_deg], nearest to ``target_deg`` first.

    Args:
        centres_world: (N, 3) camera centres.
        object_centre: (3,) the object's centre.
        n: neighbours per view (fewer when the window holds fewer).
        min_deg, max_deg: the baseline angle window, degrees.
        target_deg: preferred angle (default: the window's geometric middle, sqrt(min * max) or
            max / 2 when min is 0).

    Returns:
        N int64 arrays of view indices.
    """
    d = np.asarray(centres_world, np.float64) - np.asarray(object_centre, np.float64)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    ang = np.degrees(np.arccos(np.clip(d @ d.T, -1.0, 1.0)))
    target = target_deg if target_deg is not None else (math.sqrt(min_deg * max_deg) if min_deg > 0 else max_deg / 2)
    out = []
    for r in range(len(d)):
        ok = np.nonzero((ang[r] >= min_deg) & (ang[r] <= max_deg) & (np.arange(len(d)) != r))[0]
        out.append(ok[np.argsort(np.abs(ang[r, ok] - target), kind="stable")][:n].astype(np.int64))
    return out


def depth_range(points_world: np.ndarray, world_from_cam: np.ndarray, quantiles: tuple[float, float] = (0.0, 1.0),
                margin: float = 0.05) -> tuple[float, float]:
    """The depth range of points seen from a camera: quantiles of their depths, widened by
    ``margin`` of the range on each side.

    Args:
        points_world: (P, 3) points on or in the object (hull voxels, sparse points).
        world_from_cam: (4, 4) OpenGL camera-to-world.
        quantiles: (lo, hi) in [0, 1] (sparse points: e.g. (0.01, 0.99)).
        margin: fraction of the range added on each side.

    Returns:
        (near, far), scene units along the optical axis, near > 0.

    Raises:
        DamcapError: no point in front of the camera.
    """
    z = (cam_cv_from_world(world_from_cam)[:3] @ np.c_[points_world, np.ones(len(points_world))].T)[2]
    z = z[z > 0]
    if not len(z):
        raise DamcapError("no object point lies in front of a reference camera: cannot bound its depths")
    lo, hi = np.quantile(z, quantiles)
    pad = margin * max(hi - lo, 1e-3 * hi)
    return float(max(lo - pad, 1e-3 * hi)), float(hi + pad)


def inverse_depth_planes(near: float, far: float, n: int) -> np.ndarray:
    """(n,) float64 depths from near to far, uniform in inverse depth.

    >>> inverse_depth_planes(1.0, 4.0, 3).tolist()
    [1.0, 1.6, 4.0]
    """
    return 1.0 / np.linspace(1.0 / near, 1.0 / far, n)


# --------------------------------------------------------------------------------------------
# Plane sweep
# --------------------------------------------------------------------------------------------

def box_mean(x, window: int):
    """Mean over a ``window`` x ``window`` box of a (..., H, W) torch tensor, zeros beyond the
    borders (the divisor stays window^2), by running sums (four times faster than ``avg_pool2d``
    on a CPU)."""
    import torch.nn.functional as F

    r = window // 2
    c = F.pad(x, (r + 1, r)).cumsum(-1)
    x = c[..., 2 * r + 1:] - c[..., :-2 * r - 1]
    c = F.pad(x, (0, 0, r + 1, r)).cumsum(-2)
    return (c[..., 2 * r + 1:, :] - c[..., :-2 * r - 1, :]) * (1.0 / (window * window))


def _ncc_costs(ref_t, mu_i, var_i, sources: list, inv_depth, window: int, best_k: int, ncc_eps: float, chunk: int):
    """Best-K mean NCC of every inverse-depth hypothesis (torch, inside :func:`plane_sweep_depth`).

    Args:
        ref_t: (1, 1, hc, wc) reference crop; mu_i, var_i: its window mean and variance.
        sources: per source (image (1, 2, hs, ws) [gray, mask], a (3, P), b (3,)) with the source
            pixel of reference pixel p at depth z ~ z * a[:, p] + b.
        inv_depth: (D, 1) planes or (D, P) per-pixel hypotheses, 1 / scene units.

    Returns:
        (D, hc, wc) float32 cost in [-1, 1] (higher is better).
    """
    import torch
    import torch.nn.functional as F

    _, _, hc, wc = ref_t.shape
    n_hyp = inv_depth.shape[0]
    ncc_all = torch.empty((len(sources), n_hyp, hc, wc), dtype=torch.float32, device=ref_t.device)
    for s, (src_t, a, b) in enumerate(sources):
        hs, ws = src_t.shape[-2:]
        for c0 in range(0, n_hyp, chunk):
            zc = 1.0 / inv_depth[c0:c0 + chunk]  # (Dc, 1 or P)
            dc = zc.shape[0]
            x = zc[:, None, :] * a[None] + b[None, :, None]  # (Dc, 3, P)
            zs = x[:, 2]
            behind = zs <= 1e-6
            zs = torch.where(behind, torch.ones_like(zs), zs)
            grid = torch.stack([2 * x[:, 0] / (zs * ws) - 1, 2 * x[:, 1] / (zs * hs) - 1], -1).reshape(dc, hc, wc, 2)
            grid = torch.where(behind.reshape(dc, hc, wc, 1), torch.full_like(grid, -2.0), grid)
            warped = F.grid_sample(src_t.expand(dc, -1, -1, -1), grid, mode="bilinear", padding_mode="zeros",
                                   align_corners=False)  # (Dc, 2, hc, wc)
            j_img = warped[:, :1]
            moments = box_mean(torch.cat([j_img, j_img * j_img, j_img * ref_t], 1), window)  # (Dc, 3, hc, wc)
            mu_j = moments[:, :1]
            var_j = (moments[:, 1:2] - mu_j * mu_j).clamp_min(0)
            ncc = (moments[:, 2:3] - mu_j * mu_i) / torch.sqrt(var_j * var_i + ncc_eps)
            ncc = torch.where(warped[:, 1:] > MASK_THRESHOLD, ncc, torch.full_like(ncc, -1.0))
            ncc_all[s, c0:c0 + dc] = ncc[:, 0]
    if best_k < len(sources):
        return ncc_all.topk(best_k, dim=0).values.mean(0)
    return ncc_all.mean(0)


def _argmax_parabola(cost):
    """Winner-take-all over the first axis of a (D, ...) torch cost and the sub-sample offset of
    the parabola through the winner and its two neighbours (0 at the ends or without a maximum).

    Returns:
        best (...) int64 index, offset (...) in [-0.5, 0.5] samples, the winner's cost (...).
    """
    import torch

    n = cost.shape[0]
    best = cost.argmax(0)
    c0 = cost.gather(0, best[None])[0]
    lo = cost.gather(0, (best - 1).clamp_min(0)[None])[0]
    hi = cost.gather(0, (best + 1).clamp_max(n - 1)[None])[0]
    denom = lo - 2 * c0 + hi
    inner = (best > 0) & (best < n - 1) & (denom < 0)
    offset = torch.where(inner, 0.5 * (lo - hi) / torch.where(inner, denom, torch.full_like(denom, -1.0)), torch.zeros_like(denom))
    return best, offset.clamp(-0.5, 0.5), c0


def _masked_median(x, valid, size: int):
    """Median of the valid values in a ``size`` x ``size`` window around each pixel of a (H, W)
    torch tensor (the pixel's own value where its window holds no valid value)."""
    import torch
    import torch.nn.functional as F

    r = size // 2
    h, w = x.shape
    vals = F.unfold(x[None, None], size, padding=r)[0]  # (size^2, H*W)
    ok = F.unfold(valid[None, None].float(), size, padding=r)[0] > 0.5
    vals = torch.where(ok, vals, torch.full_like(vals, float("nan")))
    med = vals.nanmedian(0).values.reshape(h, w)
    return torch.where(torch.isnan(med), x, med)


def plane_sweep_depth(ref_gray: np.ndarray, ref_intr: Intrinsics, ref_world_from_cam: np.ndarray,
                      src_grays: list[np.ndarray], src_intrs: list[Intrinsics], src_world_from_cams: np.ndarray,
                      depths: np.ndarray, *, ref_mask: np.ndarray | None = None, src_masks: list[np.ndarray] | None = None,
                      window: int = 7, best_k: int = 2, refine_samples: int = 4, min_texture: float = 0.05,
                      ncc_eps: float = 1e-4, device: str = "cpu", chunk: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Plane-sweep stereo of one reference view against its neighbours.

    For each depth ``z`` of ``depths``, every source image is warped onto the reference by the
    homography of the fronto-parallel plane at depth z, ``H_z = K_s (R + t n^T / z) K_r^-1`` with
    ``n = (0, 0, 1)`` (written here as ``x_s ~ z K_s R K_r^-1 p + K_s t``); NCC over a
    ``window`` box compares it with the reference; a hypothesis' score is the mean of its best
    ``best_k`` sources' NCC; the best plane wins. Then, per pixel, ``2 refine_samples + 1``
    hypotheses spaced by ``1 / refine_samples`` of a plane step around the winner (in inverse
    depth) are scored alike, and a parabola through the best of them and its two neighbours
    gives the depth.

    Args:
        ref_gray: (h, w) float32 reference grayscale (any gain and offset).
        ref_intr: its pinhole intrinsics (of this size).
        ref_world_from_cam: (4, 4) OpenGL camera-to-world.
        src_grays: S (hs, ws) float32 source grayscales.
        src_intrs: S intrinsics.
        src_world_from_cams: (S, 4, 4) OpenGL camera-to-world.
        depths: (D,) increasing depths along the reference's optical axis, uniform in inverse depth
            (:func:`inverse_depth_planes`), scene units.
        ref_mask: (h, w) in [0, 1]: only pixels above 0.5 get a depth (None: all).
        src_masks: S (hs, ws) in [0, 1]: a hypothesis landing on a source's background (or
            outside it) scores NCC -1 there (None: only outside counts).
        window: NCC box side, odd, pixels.
        best_k: sources averaged per hypothesis (1 <= best_k <= S).
        refine_samples: sub-plane hypotheses per plane step in the refinement (0: the parabola
            through the planes only).
        min_texture: pixels whose window's deviation is below this fraction of the reference's
            deviation over the mask get no depth (NCC is undefined on flat patches).
        ncc_eps: added to the product of the window variances of the images, each normalised to
            unit deviation over its mask (:func:`gray_normalised`).
        device: torch device.
        chunk: hypotheses warped at once (memory: about 8 x chunk x h x w floats).

    Returns:
        depth: (h, w) float32 depth along +z (OpenCV axes), 0 where none.
        score: (h, w) float32 best-K mean NCC in [-1, 1] of the depth, -1 where none.
    """
    import torch

    if len(src_grays) < best_k or best_k < 1:
        raise DamcapError(f"plane sweep needs at least best_k={best_k} >= 1 source views, got {len(src_grays)}")
    h, w = ref_gray.shape
    dev = torch.device(device)
    ref_sel = np.ones((h, w), bool) if ref_mask is None else np.asarray(ref_mask) > MASK_THRESHOLD
    depth_out = np.zeros((h, w), np.float32)
    score_out = np.full((h, w), -1.0, np.float32)
    if not ref_sel.any():
        return depth_out, score_out
    # crop to the mask's box plus half a window (the window reads the reference beyond the mask)
    rows, cols = np.nonzero(ref_sel)
    r = window // 2
    i0, i1 = max(0, rows.min() - r), min(h, rows.max() + r + 1)
    j0, j1 = max(0, cols.min() - r), min(w, cols.max() + r + 1)
    hc, wc = i1 - i0, j1 - j0
    g = gray_normalised(ref_gray, ref_mask)  # NCC is affine-invariant; this makes ncc_eps scale-free
    ref_t = torch.from_numpy(np.ascontiguousarray(g[i0:i1, j0:j1])).to(dev)[None, None]
    mu_i = box_mean(ref_t, window)
    var_i = (box_mean(ref_t * ref_t, window) - mu_i * mu_i).clamp_min(0)
    textured = (var_i[0, 0] > min_texture ** 2).cpu().numpy()

    # homogeneous reference pixel coordinates of the crop, (3, hc*wc)
    jj, ii = np.meshgrid(np.arange(j0, j1) + 0.5, np.arange(i0, i1) + 0.5)
    pix = np.stack([jj.ravel(), ii.ravel(), np.ones(jj.size)])
    ref_cam = cam_cv_from_world(ref_world_from_cam)
    k_ref_inv = np.linalg.inv(k_matrix(ref_intr))
    sources = []
    for s, (src, intr_s, m_s) in enumerate(zip(src_grays, src_intrs, src_world_from_cams)):
        src_from_ref = cam_cv_from_world(m_s) @ np.linalg.inv(ref_cam)
        k_s = k_matrix(intr_s)
        a = torch.as_tensor(k_s @ src_from_ref[:3, :3] @ k_ref_inv @ pix, dtype=torch.float32, device=dev)  # (3, P)
        b = torch.as_tensor(k_s @ src_from_ref[:3, 3], dtype=torch.float32, device=dev)  # (3,)
        chans = [gray_normalised(src, None if src_masks is None else src_masks[s]),
                 np.ones_like(src, np.float32) if src_masks is None else np.asarray(src_masks[s], np.float32)]
        sources.append((torch.from_numpy(np.stack(chans)).to(dev)[None], a, b))

    inv_planes = torch.as_tensor(1.0 / np.asarray(depths, np.float64), dtype=torch.float32, device=dev)
    n_planes = len(inv_planes)
    step = (inv_planes[-1] - inv_planes[0]) / max(n_planes - 1, 1)
    cost = _ncc_costs(ref_t, mu_i, var_i, sources, inv_planes[:, None], window, best_k, ncc_eps, chunk)
    best, offset, score = _argmax_parabola(cost)
    del cost
    inv_best = inv_planes[best] + offset * step  # (hc, wc)
    if refine_samples > 0:
        # hypotheses around a smoothed surface, so that a window's pixels stay on one surface
        base = _masked_median(inv_best, score > 0, 5).reshape(-1)
        m = refine_samples
        k = torch.arange(-(3 * m) // 2, (3 * m) // 2 + 1, device=dev, dtype=torch.float32)
        cost = _ncc_costs(ref_t, mu_i, var_i, sources, base[None] + k[:, None] * (step / m), window, best_k, ncc_eps, chunk)
        fbest, foffset, fscore = _argmax_parabola(cost)
        del cost
        inv_fine = base + (k[fbest.reshape(-1)] + foffset.reshape(-1)) * (step / m)
        better = (fscore >= score).reshape(-1)
        inv_best = torch.where(better, inv_fine, inv_best.reshape(-1))
        score = torch.maximum(fscore, score)
    inv_best = inv_best.reshape(-1)
    depth_c = (1.0 / inv_best.double()).reshape(hc, wc).float().cpu().numpy()
    score_c = score.cpu().numpy()
    keep = ref_sel[i0:i1, j0:j1] & textured & (score_c > -1.0) & (depth_c > 0)
    depth_out[i0:i1, j0:j1] = np.where(keep, depth_c, 0.0)
    score_out[i0:i1, j0:j1] = np.where(keep, score_c, -1.0)
    return depth_out, score_out


# --------------------------------------------------------------------------------------------
# Depth maps: points, normals, consistency
# --------------------------------------------------------------------------------------------

def backproject(depth: np.ndarray, intr: Intrinsics, world_from_cam: np.ndarray) -> np.ndarray:
    """(h, w, 3) float64 world points of a depth map (0 depth gives the camera centre).

    Args:
        depth: (h, w) depth along the optical axis (OpenCV +z), scene units.
        intr: its pinhole intrinsics.
        world_from_cam: (4, 4) OpenGL camera-to-world.
    """
    h, w = depth.shape
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    x_cv = np.stack([(jj - intr.cx) / intr.fl_x, (ii - intr.cy) / intr.fl_y, np.ones_like(jj)], -1) * depth[..., None]
    world_from_cv = np.asarray(world_from_cam, np.float64) @ CV_FROM_GL
    return x_cv @ world_from_cv[:3, :3].T + world_from_cv[:3, 3]


def depth_normals(depth: np.ndarray, intr: Intrinsics, world_from_cam: np.ndarray) -> np.ndarray:
    """(h, w, 3) float32 unit world normals of a depth map by central differences, facing the
    camera; 0 where the pixel or a neighbour used has no depth.

    Args:
        depth: (h, w) depth along +z (OpenCV), 0 where none.
        intr, world_from_cam: as :func:`backproject`.
    """
    p = backproject(depth, intr, world_from_cam)
    valid = depth > 0
    n = np.zeros(p.shape, np.float64)
    du = p[1:-1, 2:] - p[1:-1, :-2]
    dv = p[2:, 1:-1] - p[:-2, 1:-1]
    c = np.cross(du, dv)
    ok = valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    length = np.linalg.norm(c, axis=-1)
    ok &= length > 0
    c = c / np.where(ok, length, 1.0)[..., None]
    to_cam = np.asarray(world_from_cam, np.float64)[:3, 3] - p[1:-1, 1:-1]
    c *= np.where(np.einsum("ijk,ijk->ij", c, to_cam) < 0, -1.0, 1.0)[..., None]
    n[1:-1, 1:-1] = np.where(ok[..., None], c, 0.0)
    return n.astype(np.float32)


def consistency_mask(depths: list[np.ndarray], intrinsics: list[Intrinsics], world_from_cams: np.ndarray,
                     neighbours: list[np.ndarray], max_px: float = 1.0, max_rel_depth: float = 0.01,
                     min_agree: int = 2) -> list[np.ndarray]:
    """Geometric consistency of depth maps: a depth is kept when at least ``min_agree`` of its
    view's neighbours agree, a neighbour agreeing when the point, projected into it, lifted by its
    depth (nearest pixel) and projected back, lands within ``max_px`` of the pixel and within
    ``max_rel_depth`` of the depth.

    Args:
        depths: V (h, w) depths along +z (OpenCV), 0 where none.
        intrinsics: V intrinsics.
        world_from_cams: (V, 4, 4) OpenGL camera-to-world.
        neighbours: V arrays of indices into these V views.
        max_px: reprojection tolerance, pixels.
        max_rel_depth: relative depth tolerance.
        min_agree: agreeing neighbours required.

    Returns:
        V (h, w) bool masks (False where there is no depth).
    """
    out = []
    for r, (d_r, intr_r) in enumerate(zip(depths, intrinsics)):
        valid = d_r > 0
        if min_agree <= 0:
            out.append(valid)
            continue
        ii, jj = np.nonzero(valid)
        z_r = d_r[ii, jj].astype(np.float64)
        x_world = backproject(d_r, intr_r, world_from_cams[r])[ii, jj]
        agree = np.zeros(len(ii), np.int32)
        cam_r = cam_cv_from_world(world_from_cams[r])
        for s in neighbours[r]:
            d_s, intr_s = depths[s], intrinsics[s]
            uv, front = project_points(x_world, world_from_cams[s], intr_s)
            js, is_ = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
            inside = front & (js >= 0) & (js < intr_s.w) & (is_ >= 0) & (is_ < intr_s.h)
            js, is_ = np.clip(js, 0, intr_s.w - 1), np.clip(is_, 0, intr_s.h - 1)
            z_s = d_s[is_, js].astype(np.float64)
            inside &= z_s > 0
            # lift the neighbour's depth at the pixel centre it hit, project back into the reference
            back = backproject_points(np.stack([js + 0.5, is_ + 0.5], -1), z_s, intr_s, world_from_cams[s])
            xr = back @ cam_r[:3, :3].T + cam_r[:3, 3]
            zr = np.where(xr[:, 2] > 1e-9, xr[:, 2], 1.0)
            du = intr_r.fl_x * xr[:, 0] / zr + intr_r.cx - (jj + 0.5)
            dv = intr_r.fl_y * xr[:, 1] / zr + intr_r.cy - (ii + 0.5)
            ok = inside & (xr[:, 2] > 1e-9) & (du * du + dv * dv <= max_px ** 2) & (np.abs(zr - z_r) <= max_rel_depth * z_r)
            agree += ok
        keep = np.zeros_like(valid)
        keep[ii, jj] = agree >= min_agree
        out.append(keep)
    return out


def backproject_points(uv: np.ndarray, depth: np.ndarray, intr: Intrinsics, world_from_cam: np.ndarray) -> np.ndarray:
    """(P, 3) float64 world points at pixel coordinates ``uv`` (P, 2) and depths (P,) along +z."""
    x_cv = np.stack([(uv[:, 0] - intr.cx) / intr.fl_x, (uv[:, 1] - intr.cy) / intr.fl_y, np.ones(len(uv))], -1) * depth[:, None]
    world_from_cv = np.asarray(world_from_cam, np.float64) @ CV_FROM_GL
    return x_cv @ world_from_cv[:3, :3].T + world_from_cv[:3, 3]


# --------------------------------------------------------------------------------------------
# Fusion
# --------------------------------------------------------------------------------------------

def fuse_tsdf(depths: list[np.ndarray], intrinsics: list[Intrinsics], world_from_cams: np.ndarray, voxel_size: float,
              trunc_voxels: float = 4.0, min_weight: float = 2.0, device: str = "CPU:0") -> tuple[np.ndarray, np.ndarray]:
    """Truncated signed distance fusion of depth maps (Curless & Levoy 1996) with Open3D's tensor
    ``VoxelBlockGrid``, its zero set meshed by marching cubes.

    Args:
        depths: V (h, w) float32 depths along +z (OpenCV), 0 where none.
        intrinsics: V intrinsics (damcap's pixel centres; Open3D's are half a pixel earlier).
        world_from_cams: (V, 4, 4) OpenGL camera-to-world.
        voxel_size: scene units.
        trunc_voxels: truncation distance, voxels.
        min_weight: a voxel is meshed when at least this many depth maps saw it.
        device: Open3D device.

    Returns:
        vertices (P, 3) float64, triangles (T, 3) int32 (possibly empty).
    """
    import open3d as o3d
    import open3d.core as o3c

    dev = o3c.Device(device)
    n_obs = sum(int((d > 0).sum()) for d in depths)
    est = max(1000, int(4 * n_obs / max(len(depths), 1) / 16))  # blocks of 8^3 voxels near the surface
    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
                                        attr_channels=((1), (1)), voxel_size=float(voxel_size), block_resolution=8,
                                        block_count=est, device=dev)
    for d, intr, m in zip(depths, intrinsics, world_from_cams):
        if not (d > 0).any():
            continue
        k = k_matrix(intr)
        k[0, 2] -= 0.5
        k[1, 2] -= 0.5
        k_t = o3c.Tensor(k, o3c.float64)
        ext = o3c.Tensor(cam_cv_from_world(m), o3c.float64)
        img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(d, np.float32))).to(dev)
        depth_max = float(d.max()) * 1.01
        blocks = vbg.compute_unique_block_coordinates(img, k_t, ext, 1.0, depth_max, trunc_voxels)
        vbg.integrate(blocks, img, k_t, ext, 1.0, depth_max, trunc_voxels)
    tm = vbg.extract_triangle_mesh(weight_threshold=float(min_weight))
    if "positions" not in tm.vertex or tm.triangle.indices.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32)
    return tm.vertex.positions.cpu().numpy().astype(np.float64), tm.triangle.indices.cpu().numpy().astype(np.int32)


def keep_inside_silhouettes(vertices: np.ndarray, triangles: np.ndarray, masks: list[np.ndarray], world_from_cams: np.ndarray,
                            intrinsics: list[Intrinsics], tolerance: int = 1, level: float = 0.25) -> np.ndarray:
    """Triangles whose three vertices lie inside the visual hull (carved occupancy above
    ``level``, ``tolerance`` views may disagree).

    Returns:
        (T,) bool.
    """
    occ = carve(masks, world_from_cams, intrinsics, vertices, tolerance)
    inside = occ > level
    return inside[triangles].all(1)


# --------------------------------------------------------------------------------------------
# The whole
# --------------------------------------------------------------------------------------------

@dataclass
class DepthMaps:
    """Filtered depth maps of the reference views, at the working resolution."""

    views: np.ndarray
    """(V,) int64 indices of the reference views among the inputs' cameras"""
    intrinsics: list[Intrinsics]
    """V working-resolution intrinsics"""
    world_from_cams: np.ndarray
    """(V, 4, 4) float64 OpenGL camera-to-world"""
    depth: list[np.ndarray]
    """V (h, w) float32 depths along the optical axis (OpenCV +z), scene units; 0 where none"""
    score: list[np.ndarray]
    """V (h, w) float32 best-K mean NCC of the raw depth, -1 where none"""
    neighbours: list[np.ndarray]
    """V int64 arrays: each view's neighbours, as indices into these V views"""
    box: tuple[np.ndarray, np.ndarray]
    """the object's box (min (3,), max (3,)) the depths were searched in"""
    stats: dict[str, Any] = field(default_factory=dict)


def _object_bounds(inputs: GeometryInputs) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray], tuple[float, float], float]:
    """Points inside the object (a 48^3 carve of the hull's grid, :func:`~.geometry.carve_hull_grid`,
    or the sparse points), its box, the depth quantiles to use and a depth margin (scene units)."""
    cams = np.asarray(inputs.world_from_cams, np.float64)
    if inputs.masks:
        # the hull's grid within what the photos judge (an object cut by the frame does not fill the search cube)
        obj = _object_points(inputs)
        grid = carve_hull_grid(inputs.masks, cams, inputs.intrinsics, 1, 48, obj if len(obj) else None)
        if grid is None:
            raise DamcapError("dense geometry: no point is inside the silhouettes (check the masks and cameras)")
        pts = grid.centres()
        return pts[grid.occupancy.reshape(-1) > 0.2], (grid.bounds.box_min, grid.bounds.box_max), (0.0, 1.0), 1.5 * grid.size
    pts = np.asarray(inputs.points_world, np.float64)
    if len(pts) < 20:
        raise DamcapError(f"dense geometry without masks needs at least 20 sparse points to bound the depths, got {len(pts)}")
    quant = (0.02, 0.98)
    lo, hi = np.quantile(pts, quant, axis=0)
    return pts, (lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo)), quant, 0.05 * float((hi - lo).max())


def compute_depth_maps(inputs: GeometryInputs, images: list[np.ndarray], opts: DenseOptions = DenseOptions(),
                       progress: Progress | None = None) -> DepthMaps:
    """Plane-sweep depth maps of up to ``opts.max_views`` reference views, filtered by NCC and by
    geometric consistency (see :func:`dense_mesh` for the arguments).

    Raises:
        DamcapError: bad options or inputs, too little texture (fewer than ``min_valid_fraction``
            of the object's pixels keep a depth).
    """
    opts.validate()
    report = progress or (lambda stage, done, total: None)
    n = len(images)
    if n != len(inputs.intrinsics) or n != len(inputs.world_from_cams):
        raise DamcapError(f"dense geometry: {n} images for {len(inputs.intrinsics)} cameras")
    if inputs.masks is not None and len(inputs.masks) != n:
        raise DamcapError(f"dense geometry: {len(inputs.masks)} masks for {n} images")
    for k, (img, intr) in enumerate(zip(images, inputs.intrinsics)):
        if img.shape[:2] != (intr.h, intr.w):
            raise DamcapError(f"dense geometry: image {k} is {img.shape[1]}x{img.shape[0]}, its camera {intr.w}x{intr.h}")
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    cams = np.asarray(inputs.world_from_cams, np.float64)
    object_pts, box, quant, margin = _object_bounds(inputs)
    centre = 0.5 * (box[0] + box[1])

    scale = min(1.0, opts.image_size / max(max(i.w, i.h) for i in inputs.intrinsics))
    intrs = [scaled_intrinsics(i, scale) for i in inputs.intrinsics]
    dirs = cams[:, :3, 3] - centre
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
    refs = spread_views(dirs, opts.max_views)
    masks = {int(k): resize_image(inputs.masks[k], intrs[k].w, intrs[k].h) for k in refs} if inputs.masks else None
    grays = {int(k): gray_normalised(resize_image(images[k], intrs[k].w, intrs[k].h), None if masks is None else masks[int(k)])
             for k in refs}
    nbrs = select_neighbours(cams[refs, :3, 3], centre, opts.neighbours, opts.min_baseline_deg, opts.max_baseline_deg)
    seconds["setup"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    depths: list[np.ndarray] = []
    scores: list[np.ndarray] = []
    skipped = 0
    for q, r in enumerate(refs):
        report("dense depth maps", q, len(refs))
        r = int(r)
        h, w = grays[r].shape
        src = [int(k) for k in refs[nbrs[q]]]
        if len(src) < opts.best_k:
            skipped += 1
            depths.append(np.zeros((h, w), np.float32))
            scores.append(np.full((h, w), -1.0, np.float32))
            continue
        near, far = depth_range(object_pts, cams[r], quant, margin=0.0)
        near, far = max(near - margin, 1e-3 * far), far + margin
        d, s = plane_sweep_depth(grays[r], intrs[r], cams[r], [grays[k] for k in src], [intrs[k] for k in src], cams[src],
                                 inverse_depth_planes(near, far, opts.depth_planes),
                                 ref_mask=None if masks is None else masks[r],
                                 src_masks=None if masks is None else [masks[k] for k in src],
                                 window=opts.ncc_window, best_k=opts.best_k, refine_samples=opts.refine_samples,
                                 device=opts.device)
        d[s < opts.min_ncc] = 0.0
        depths.append(d)
        scores.append(s)
    report("dense depth maps", len(refs), len(refs))
    seconds["depth_maps"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    keep = consistency_mask(depths, [intrs[k] for k in refs], cams[refs], nbrs, opts.consistency_px,
                            opts.consistency_depth, opts.min_consistent)
    filtered = [np.where(kp, d, 0.0).astype(np.float32) for kp, d in zip(keep, depths)]
    seconds["consistency"] = time.perf_counter() - t2
    object_px = sum(int((m > MASK_THRESHOLD).sum()) for m in masks.values()) if masks is not None else sum(d.size for d in depths)
    raw_px = sum(int((d > 0).sum()) for d in depths)
    kept_px = sum(int((d > 0).sum()) for d in filtered)
    valid_fraction = kept_px / max(object_px, 1)
    if valid_fraction < opts.min_valid_fraction:
        raise DamcapError(
            f"dense geometry: only {valid_fraction:.1%} of the object's pixels got a consistent depth (at least "
            f"{opts.min_valid_fraction:.0%} needed; {raw_px / max(object_px, 1):.1%} before the consistency check): the "
            "photos have too little texture to match, or the cameras are wrong; use --geometry visual-hull")
    stats = {"views_used": int(len(refs) - skipped), "views_without_neighbours": int(skipped),
             "working_size": [int(intrs[int(refs[0])].w), int(intrs[int(refs[0])].h)],
             "valid_fraction_raw": raw_px / max(object_px, 1), "valid_fraction": valid_fraction, "seconds": seconds}
    return DepthMaps(refs, [intrs[int(k)] for k in refs], cams[refs], filtered, scores, nbrs, box, stats)


def fuse_depth_maps(maps: DepthMaps, inputs: GeometryInputs, opts: DenseOptions = DenseOptions(),
                    progress: Progress | None = None) -> tuple[Mesh, dict[str, Any]]:
    """The mesh of filtered depth maps: Poisson or TSDF fusion (``opts.fusion``), trimmed by the
    silhouettes (when ``inputs`` has masks), cleaned, wound outward.

    Raises:
        DamcapError: an empty fusion, or nothing inside the silhouettes.
    """
    report = progress or (lambda stage, done, total: None)
    seconds: dict[str, float] = {}
    t3 = time.perf_counter()
    report("dense fusion", 0, 1)
    voxel_size = float((maps.box[1] - maps.box[0]).max()) / opts.voxels
    pts_list, nrm_list = [], []
    for d, intr, m in zip(maps.depth, maps.intrinsics, maps.world_from_cams):
        nrm = depth_normals(d, intr, m)
        ok = (d > 0) & (np.abs(nrm).sum(-1) > 0)
        pts_list.append(backproject(d, intr, m)[ok])
        nrm_list.append(nrm[ok])
    points = np.concatenate(pts_list)
    normals = np.concatenate(nrm_list).astype(np.float64)
    if opts.fusion == "tsdf":
        verts, tris = fuse_tsdf(maps.depth, maps.intrinsics, maps.world_from_cams, voxel_size)
    else:
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pcd.normals = o3d.utility.Vector3dVector(normals)
        pcd = pcd.voxel_down_sample(voxel_size)
        nn = np.asarray(pcd.normals)
        nn /= np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-12)
        verts, tris = fuse_poisson(np.asarray(pcd.points), nn, math.ceil(math.log2(opts.voxels)))
    seconds["fusion"] = time.perf_counter() - t3

    t4 = time.perf_counter()
    if len(tris) == 0:
        raise DamcapError("dense geometry: the fusion gave an empty mesh (no depth survived where views overlap)")
    if inputs.masks:
        tolerance = int(opts.trim_tolerance * len(inputs.masks))
        tris = tris[keep_inside_silhouettes(verts, tris, inputs.masks, inputs.world_from_cams, inputs.intrinsics, tolerance)]
        if len(tris) == 0:
            raise DamcapError("dense geometry: no part of the fused mesh lies inside the silhouettes")
    mesh = clean_surface(verts, tris, opts.smooth_iterations)
    if signed_volume(mesh.vertices, mesh.triangles) < 0:
        mesh = Mesh(mesh.vertices, mesh.triangles[:, ::-1].copy(), -mesh.vertex_normals, mesh.triangle_groups)
    seconds["clean"] = time.perf_counter() - t4
    report("dense fusion", 1, 1)
    return mesh, {"points_fused": len(points), "voxel_size": voxel_size, "triangles": len(mesh.triangles),
                  "seconds": seconds}


def dense_mesh(inputs: GeometryInputs, images: list[np.ndarray], opts: DenseOptions = DenseOptions(),
               progress: Progress | None = None) -> tuple[Mesh, dict[str, Any]]:
    """A mesh from multi-view stereo depth maps of calibrated photos, fused and cleaned
    (:func:`compute_depth_maps`, then :func:`fuse_depth_maps`).

    Args:
        inputs: normalised cameras (OpenGL camera-to-world), intrinsics, masks (optional but
            recommended: they bound the depths and trim the mesh), sparse points (used for the
            depth range without masks).
        images: N (h, w) or (h, w, 3) float32 photos at the intrinsics' resolution, linear or
            sRGB (NCC ignores gain and offset).
        opts: options.
        progress: called as ``progress(stage, done, total)``.

    Returns:
        the mesh (float32, outward normals) and stats: views used, valid-depth fractions, points
        fused, seconds per stage, the backend.

    Raises:
        DamcapError: bad options, no masks and fewer than 20 points, too little texture (fewer
            than ``min_valid_fraction`` of the object's pixels keep a depth), an empty fusion.
    """
    t0, cpu0 = time.perf_counter(), time.process_time()
    maps = compute_depth_maps(inputs, images, opts, progress)
    mesh, fstats = fuse_depth_maps(maps, inputs, opts, progress)
    stats = dict(maps.stats)
    stats["seconds"] = {**maps.stats["seconds"], **fstats.pop("seconds")}
    stats["seconds"]["total"] = time.perf_counter() - t0
    stats["cpu_seconds"] = time.process_time() - cpu0
    stats.update(fstats)
    fusion = "Open3D VoxelBlockGrid TSDF" if opts.fusion == "tsdf" else "screened Poisson (Open3D)"
    stats["backend"] = f"plane sweep (torch, {opts.device}) + {fusion}"
    return mesh, stats


def dense_geometry(inputs: GeometryInputs, opts: DenseOptions = DenseOptions(),
                   progress: Progress | None = None) -> GeometryResult:
    """``--geometry dense``: :func:`dense_mesh` of ``inputs.images``, as the other geometry modes
    report themselves (:func:`damcap.reconstruct.geometry.build_geometry`).

    Raises:
        DamcapError: no photos in ``inputs``, or what :func:`dense_mesh` raises.
    """
    if not inputs.images:
        raise DamcapError("--geometry dense needs the photos (none were given to the geometry step)")
    mesh, stats = dense_mesh(inputs, inputs.images, opts, progress)
    return GeometryResult(mesh, "dense", (f"multi-view stereo of {stats['views_used']} views ({stats['backend']}); "
                                          f"{stats['valid_fraction']:.0%} of the object's pixels kept a depth"), None, stats)
