"""The normal field of a DAM: offsets that refine the surface's normals (pure).

:mod:`.normal_refine` fits it; a model carries it (``model.normal_field``) and every renderer
that knows a pixel's surface point shades with :func:`surface_normals`. Storage is the spatial
factor's sparse corner grid (:mod:`.spatial`): tangent offsets at the corners of the voxels that
training pixels touch, interpolated trilinearly, so one surface point gets one normal in every
view. Arrays in, arrays out; no torch module state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from damcap.appearance.spatial import KEY_BITS, corner_lookup, grid_problem, pack_keys, trilinear_corners

OFFSET_MAX = 100.0
"""the longest offset a file may store (a tangent of length 100 tilts a normal by 89.4 deg);
a fitted field stays far below it (the cape's: 28 deg at the 90th percentile)"""


@dataclass(frozen=True)
class NormalField:
    """A sparse voxel field of normal offsets (world units per unit normal, tangent part used)."""

    origin_world: np.ndarray
    """(3,) float64 world position of corner (0, 0, 0)"""
    voxel_size: float
    """voxel edge, world units"""
    keys: np.ndarray
    """(M,) int64 sorted, unique corner keys (:func:`.spatial.pack_keys`)"""
    offset: np.ndarray
    """(M, 3) float32 offset added to the normal at each corner (its normal component is dropped)"""

    def problem(self) -> str | None:
        """Why these arrays cannot be a normal field (None when they can)."""
        off = self.offset
        grid = grid_problem(self.origin_world, self.voxel_size, self.keys, off, "offset")
        if grid:
            return grid
        if off.size and float(np.abs(off).max()) > OFFSET_MAX:
            return f"offsets reach {float(np.abs(off).max()):.3g}, more than {OFFSET_MAX:g}"
        return None


def empty_field(points_world: np.ndarray, voxel_size: float) -> NormalField:
    """A zero field with a corner for every corner the points touch.

    Args:
        points_world: (N, 3) surface points.
        voxel_size: voxel edge, world units.
    """
    origin = np.asarray(points_world, np.float64).min(0) - 2 * voxel_size
    keys, _ = trilinear_corners(points_world, origin, voxel_size)
    keys = np.unique(keys[keys >= 0])
    return NormalField(origin, float(voxel_size), keys, np.zeros((keys.size, 3), np.float32))


def corner_positions(nf: NormalField) -> np.ndarray:
    """(M, 3) float64 world positions of the field's corners.

    >>> nf = NormalField(np.zeros(3), 0.5, pack_keys(np.array([[1, 2, 3]])), np.zeros((1, 3), np.float32))
    >>> corner_positions(nf).tolist()
    [[0.5, 1.0, 1.5]]
    """
    k = np.asarray(nf.keys, np.int64)
    mask = (1 << KEY_BITS) - 1
    ijk = np.stack([(k >> (2 * KEY_BITS)) & mask, (k >> KEY_BITS) & mask, k & mask], -1)
    return nf.origin_world + ijk * nf.voxel_size


def resampled_offsets(initial: NormalField, onto: NormalField) -> np.ndarray:
    """(M, 3) float32: ``initial``'s offsets interpolated at ``onto``'s corners (0 where
    ``initial`` has none): a refinement started from another field on other grid corners."""
    idx, w, _ = corner_lookup(initial, corner_positions(onto))  # type: ignore[arg-type]
    if initial.keys.size == 0:
        return np.zeros((onto.keys.size, 3), np.float32)
    return np.einsum("nk,nkc->nc", w, initial.offset[idx].astype(np.float64)).astype(np.float32)


def apply_offsets(normal_world: torch.Tensor, offset: torch.Tensor, index: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Refined unit normals: n + the interpolated offset's tangent part, normalised.

    Args:
        normal_world: (N, 3) unit normals.
        offset: (M, 3) per-corner offsets.
        index: (N, 8) corner indices into ``offset``.
        weight: (N, 8) trilinear weights (0 for missing corners).

    Returns:
        (N, 3) unit normals.

    >>> n = torch.tensor([[0.0, 0.0, 1.0]])
    >>> apply_offsets(n, torch.tensor([[1.0, 0.0, 5.0]]), torch.zeros(1, 8, dtype=torch.long), torch.full((1, 8), 0.125)).tolist()
    [[0.7071067690849304, 0.0, 0.7071067690849304]]
    """
    off = (weight[..., None] * offset[index]).sum(1)
    off = off - (off * normal_world).sum(-1, keepdim=True) * normal_world
    return torch.nn.functional.normalize(normal_world + off, dim=-1)


def refined_normals(nf: NormalField, normal_world: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """(N, 3) float32 refined normals at surface points (unchanged where the field has no corner)."""
    idx, w, _ = corner_lookup(nf, points_world)  # NormalField has the fields corner_lookup reads
    out = apply_offsets(torch.from_numpy(np.ascontiguousarray(normal_world, np.float32)), torch.from_numpy(nf.offset),
                        torch.from_numpy(idx), torch.from_numpy(w).float())
    return out.numpy()


def field_share(nf: NormalField, points_world: np.ndarray) -> float:
    """Share of the points at which the field has a corner (the points lie on its surface)."""
    if len(points_world) == 0:
        return 0.0
    return float(corner_lookup(nf, np.asarray(points_world, np.float64))[2].mean())


def surface_normals(nf: NormalField | None, normal_world: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """The normals a model shades with: ``normal_world`` refined by its normal field ``nf``
    (``model.normal_field``), unchanged when it has none. (N, 3) in, (N, 3) float32 out."""
    if nf is None or len(normal_world) == 0:
        return np.ascontiguousarray(normal_world, np.float32)
    return refined_normals(nf, normal_world, points_world)
