"""Which geometry the photos agree with: a self-check that needs no ground truth.

With the right surface (and cameras), a photo warped through the surface onto a neighbouring
view reproduces that view's texture where both see the same point; a surface that is off moves
the texture. :func:`photo_consistency` measures it as the mean zero-mean normalised
cross-correlation (NCC, over ``window`` x ``window`` pixels, on grey values) between each of a
few spread reference views and its nearest neighbour warped onto it, over the reference's object
pixels that the neighbour also sees, and the share of the object's pixels so compared; their
product (:attr:`Consistency.score`) is the criterion. NCC ignores exposure and a local gain, so
view-dependent brightness matters little; texture placement matters.

``--geometry auto`` builds the dense geometry besides the silhouette / sparse-point one and keeps
whichever scores higher (:func:`prefer_dense`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from damcap.common.capture_folder import Intrinsics
from damcap.common.mesh import Mesh
from damcap.common.raycast import MeshRaycaster

from damcap.reconstruct.dense import box_mean, gray_normalised, resize_image, scaled_intrinsics, spread_views
from damcap.reconstruct.geometry import MASK_THRESHOLD, project_points, sample_bilinear


@dataclass(frozen=True)
class Consistency:
    """How well the photos agree through one surface."""

    ncc: float
    """mean windowed NCC over the compared pixels (1 = the warped neighbour matches exactly)"""
    compared_fraction: float
    """share of the reference views' object pixels that were compared (hit by the surface and
    seen by the neighbour)"""
    pairs: int

    @property
    def score(self) -> float:
        """Mean NCC over *all* the reference views' object pixels, 0 where nothing was compared:
        ``ncc * compared_fraction``. A surface is not rewarded for comparing only the pixels it
        gets right (a noisy surface fails the visibility test where it is wrong)."""
        return self.ncc * self.compared_fraction


def windowed_ncc(a: np.ndarray, b: np.ndarray, valid: np.ndarray, window: int, eps: float = 1e-4) -> np.ndarray:
    """Zero-mean normalised cross-correlation of two grey images in a box window, per pixel,
    over the valid pixels only.

    Args:
        a, b: (H, W) float images.
        valid: (H, W) bool; invalid pixels take no part in any window.
        window: odd box size, pixels.
        eps: variance floor (a flat window scores 0, not NaN).

    Returns:
        (H, W) float32 NCC in [-1, 1]; 0 where a window holds fewer than half valid pixels.

    >>> x = np.random.default_rng(0).random((9, 9)); v = np.ones((9, 9), bool)
    >>> float(windowed_ncc(x, 3 * x + 1, v, 3)[4, 4].round(6)), float(windowed_ncc(x, -x, v, 3)[4, 4].round(6))
    (1.0, -1.0)
    """
    import torch

    t = lambda x: torch.from_numpy(np.ascontiguousarray(x, np.float32))[None, None]  # noqa: E731
    w = t(valid.astype(np.float32))
    n = box_mean(w, window)
    nz = n.clamp_min(1e-6)
    ta, tb = t(a) * w, t(b) * w
    ma, mb = box_mean(ta, window) / nz, box_mean(tb, window) / nz
    va = box_mean(ta * ta, window) / nz - ma * ma
    vb = box_mean(tb * tb, window) / nz - mb * mb
    cov = box_mean(ta * tb, window) / nz - ma * mb
    ncc = cov / torch.sqrt(va.clamp_min(eps) * vb.clamp_min(eps))
    ncc = torch.where(n >= 0.5, ncc.clamp(-1, 1), torch.zeros_like(ncc))
    return ncc[0, 0].numpy()


def nearest_view(centres_world: np.ndarray, object_centre: np.ndarray, ref: int, min_deg: float = 2.0) -> int | None:
    """The view whose direction from the object is nearest to view ``ref``'s, at least
    ``min_deg`` away (None when there is none)."""
    d = np.asarray(centres_world, np.float64) - object_centre
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    ang = np.degrees(np.arccos(np.clip(d @ d[ref], -1.0, 1.0)))
    ang[ref] = np.inf
    ang[ang < min_deg] = np.inf
    k = int(np.argmin(ang))
    return None if not np.isfinite(ang[k]) else k


def photo_consistency(mesh: Mesh, world_from_cams: np.ndarray, intrinsics: list[Intrinsics], images: list[np.ndarray],
                      masks: list[np.ndarray] | None, views: int = 8, image_size: int = 256, window: int = 7,
                      tolerance: float = 0.01) -> Consistency:
    """The photos' agreement through ``mesh`` (module docstring).

    Args:
        mesh: the surface, in the cameras' (normalised) world.
        world_from_cams: (N, 4, 4) OpenGL camera-to-world.
        intrinsics: per view, of ``images``.
        images: (h, w[, 3]) per view, any linear or display scale.
        masks: per view (h, w) object masks in [0, 1], or None (then every pixel the surface hits).
        views: reference views, spread over the cameras' directions.
        image_size: longest side the photos are compared at, pixels.
        window: NCC window, pixels.
        tolerance: a neighbour sees a point when its own surface point there lies within this
            fraction of the mesh's extent.

    Returns:
        the :class:`Consistency` (ncc 0 and fraction 0 when nothing could be compared).
    """
    centres = world_from_cams[:, :3, 3]
    centre = mesh.vertices.mean(0)
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    caster = MeshRaycaster(mesh)
    refs = spread_views(centres - centre, views)

    def view_at(k: int):
        intr = intrinsics[k]
        s = min(1.0, image_size / max(intr.w, intr.h))
        small = scaled_intrinsics(intr, s)
        img = resize_image(images[k], small.w, small.h)
        m = resize_image(masks[k], small.w, small.h) > MASK_THRESHOLD if masks is not None else None
        buf = caster.buffers(world_from_cams[k], small.fl_x, small.fl_y, small.cx, small.cy, small.w, small.h, supersample=1)
        return small, img, m, buf

    total, count, object_px, pairs = 0.0, 0, 0, 0
    for r in refs:
        j = nearest_view(centres, centre, int(r))
        if j is None:
            continue
        ri, rimg, rmask, rbuf = view_at(int(r))
        ji, jimg, _, jbuf = view_at(j)
        hit = rbuf.triangle_id >= 0
        obj = rmask if rmask is not None else hit
        object_px += int(obj.sum())
        sel = hit & obj
        if not sel.any():
            continue
        p = rbuf.position_world[sel].astype(np.float64)
        uv, z = project_points(p, world_from_cams[j], ji)
        there = np.stack([sample_bilinear(jbuf.position_world[..., c], uv, np.nan) for c in range(3)], -1)
        seen = (z > 0) & (np.linalg.norm(there - p, axis=1) < tolerance * extent)
        jgray = gray_normalised(jimg, None)
        warped = np.zeros(hit.shape, np.float32)
        valid = np.zeros(hit.shape, bool)
        idx = np.nonzero(sel)
        warped[idx[0][seen], idx[1][seen]] = sample_bilinear(jgray, uv[seen], 0.0)
        valid[idx[0][seen], idx[1][seen]] = True
        if not valid.any():
            continue
        ncc = windowed_ncc(gray_normalised(rimg, None), warped, valid, window)
        total += float(ncc[valid].sum())
        count += int(valid.sum())
        pairs += 1
    if count == 0:
        return Consistency(0.0, 0.0, pairs)
    return Consistency(total / count, count / max(object_px, 1), pairs)


def prefer_dense(base: Consistency, dense: Consistency, margin: float) -> bool:
    """Keep the dense surface when its :attr:`Consistency.score` beats the base surface's by at
    least ``margin``. On the rendered blob the dense surface's NCC alone was higher (0.855 vs the
    visual hull's 0.809) while its normals were worse (7.1 vs 1.8 deg median): it was compared on
    72 % of the object's pixels against the hull's 90 %. The score (0.62 vs 0.73) keeps the hull.

    >>> prefer_dense(Consistency(0.80, 0.9, 8), Consistency(0.85, 0.95, 8), 0.02)
    True
    >>> prefer_dense(Consistency(0.81, 0.9, 8), Consistency(0.855, 0.72, 8), 0.02)
    False
    """
    return dense.score >= base.score + margin
