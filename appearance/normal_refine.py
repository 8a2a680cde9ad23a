"""Photometric normal refinement: shape-from-shading with the DAM as the reflectance map.

A DAM maps (view, normal) to radiance: it is a reflectance map, the thing shape-from-shading
inverts. Reconstructed surfaces lack the relief that shades a real object (embossing, dents), so
the fitted DAM cannot reproduce even its training photos. This module refines the normals:
a sparse voxel field of tangent offsets on the surface (:mod:`.normal_field`, on the same sparse
corner grid as the spatial factor, :mod:`.spatial`), interpolated trilinearly at each pixel's surface point, so one
surface point gets one normal in every view (the multi-view consistency single-image
shape-from-shading lacks). The field is optimised on the fit's cost (L1 of radiance over the
radiance scale, the pixels' weights), with an L2 prior on the offsets (their smoothness comes from
the voxel size: one offset per corner, interpolated). The DAM's weights stay as fitted by default
(``lr_dam`` 0): trained together with the field they fit the training views better and recover
more of a synthetic relief, but on the real cape they generalised worse to views they had not seen.

Measured on the real cape: bench/normal_refine.md and docs/model.md. Pure: tensors and
arrays in, tensors and arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from damcap.common.validate import COUNT, SEED, check_ranges, in_range

from damcap.appearance.dam import DeepAppearanceMap, encode_inputs
from damcap.appearance.pixels import PixelSamples
from damcap.appearance.normal_field import NormalField, apply_offsets, empty_field, resampled_offsets
from damcap.appearance.spatial import corner_lookup


@dataclass(frozen=True)
class NormalRefineOptions:
    """Knobs of the refinement (each trades speed for accuracy; bench/normal_refine.md)."""

    voxel_px: float = field(default=1.0, metadata=in_range(0.1, 1000))
    """voxel edge of the offset field, in training pixel footprints on the surface: finer
    resolves finer relief and costs more corners"""
    prior: float = field(default=0.01, metadata=in_range(0, 1e6))
    """weight of the L2 prior on the offsets (tangent length; 0.01 ~ a 6 deg offset costs what
    an L1 error of 1e-4 does). On the real cape (voxel 1 px, with the albedo;
    bench/normal_refine.md) 0.001 and 0.1 gave novel-view DSSIM 0.243 and 0.244, as 0.01 does"""
    steps: int = field(default=400, metadata=COUNT)
    """Adam steps of the joint optimisation; time grows linearly. On the real cape (voxel 1 px, with
    the albedo; bench/normal_refine.md) 200 / 400 / 800 steps: novel-view DSSIM 0.249 / 0.244 /
    0.242 in 11 / 19 / 38 s, held-out training views 0.373 / 0.373 / 0.375"""
    batch: int = field(default=16384, metadata=in_range(1, 1 << 24))
    """pixels per step"""
    lr_offsets: float = field(default=3e-3, metadata=in_range(0, 10))
    """Adam learning rate of the offsets (0 = the normals stay: the DAM alone trains on, a control)"""
    lr_dam: float = field(default=0.0, metadata=in_range(0, 10))
    """Adam learning rate of the DAM's weights (0 = the DAM stays as fitted and only the normals
    move). On the real cape (8 train views, voxel 1 px, with the albedo; bench/normal_refine.md)
    1e-3 fitted the training views better (same view 0.099 against 0.134) but generalised worse:
    held-out training views 0.401 against 0.373, novel views 0.251 against 0.244"""
    seed: int = field(default=0, metadata=SEED)
    """seeds the pixel draws"""

    def validate(self) -> None:
        check_ranges(self)


def refine_normals(model: DeepAppearanceMap, samples: PixelSamples, points_world: np.ndarray, footprint_world: float,
                   opts: NormalRefineOptions, progress: Callable[[int, float], None] | None = None,
                   initial: NormalField | None = None) -> tuple[DeepAppearanceMap, NormalField]:
    """Optimise a normal field (and, with ``opts.lr_dam`` > 0, the DAM's weights) on the training pixels.

    Args:
        model: the fitted DAM (not modified).
        samples: the training pixels.
        points_world: (N, 3) their surface points (:func:`.views.positions_of`).
        footprint_world: a training pixel's size on the surface, world units
            (:func:`.spatial_fit.training_footprint`).
        opts: the knobs.
        progress: progress(step, loss) after each step.
        initial: a field to start from (its offsets interpolated at this field's corners,
            :func:`.normal_field.resampled_offsets`); None: zero offsets.

    Returns:
        (the DAM with refined weights, the normal field).
    """
    opts.validate()
    nf = empty_field(points_world, opts.voxel_px * footprint_world)
    idx, w, _ = corner_lookup(nf, points_world)
    idx, w = torch.from_numpy(idx), torch.from_numpy(w).float()
    start = np.zeros((nf.keys.size, 3), np.float32) if initial is None else resampled_offsets(initial, nf)
    offset = torch.from_numpy(start).requires_grad_(True)
    out = DeepAppearanceMap(model.arch, model.radiance_scale, model.get_flat_weights())
    groups = [{"params": [offset], "lr": opts.lr_offsets}] if opts.lr_offsets > 0 else []
    if opts.lr_dam > 0:
        groups.append({"params": [out.weights_flat], "lr": opts.lr_dam})
    else:
        out.weights_flat.requires_grad_(False)
    optim = torch.optim.Adam(groups) if groups else None
    gen = torch.Generator().manual_seed(opts.seed)
    target = samples.radiance_lin / model.radiance_scale
    for step in range(opts.steps):
        b = torch.randint(len(samples), (min(opts.batch, len(samples)),), generator=gen)
        n = apply_offsets(samples.normal_world[b], offset, idx[b], w[b])
        pred = out.forward_normalised(encode_inputs(samples.view_dir_world[b], n, out.arch.encoding))
        wb = samples.weight[b]
        loss = ((pred - target[b]).abs().sum(-1) * wb).sum() / wb.sum().clamp_min(1e-12) + opts.prior * (offset**2).sum(-1).mean()
        if optim is not None:
            optim.zero_grad()
            loss.backward()
            optim.step()
        if progress:
            progress(step + 1, float(loss.detach()))
    out.weights_flat.requires_grad_(True)
    return out, NormalField(nf.origin_world, nf.voxel_size, nf.keys, offset.detach().numpy().astype(np.float32))
