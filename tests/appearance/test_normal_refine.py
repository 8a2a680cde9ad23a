"""Photometric normal refinement against a closed form: a sphere rendered with bumps it was not given."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from damcap.appearance.fit import FitOptions, fit_dam
from damcap.appearance.normal_field import refined_normals
from damcap.appearance.normal_refine import NormalRefineOptions, refine_normals
from damcap.appearance.pixels import gather_samples
from damcap.appearance.spatial_fit import training_footprint
from damcap.appearance.views import ViewData, positions_of
from damcap.synth.closed_form import ClosedFormOptions, Material, environment_lighting, render_closed_form, shade
from tests.appearance.conftest import bumpy_normals


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))


@pytest.mark.slow
def test_refinement_recovers_bumps_the_geometry_lacks():
    cams, intr, frames, _ = render_closed_form(ClosedFormOptions(shape="sphere", light="env", views=8, train_views=6, resolution=48,
                                                                 env_grid=12, seed=2))
    light, mat = environment_lighting(12), Material((0.5, 0.3, 0.2), 0.3, (0.4, 0.4, 0.4))  # a glossy metal: shading pins normals down
    views, truth = [], []
    for m, d in zip(cams, frames):
        fg = d.coverage > 0
        true_n = bumpy_normals(d.normal_world, d.position_world)
        v = m[:3, 3] - d.position_world
        v /= np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
        rad = np.zeros_like(d.radiance_lin)
        rad[fg] = shade(torch.from_numpy(true_n[fg]).float(), torch.from_numpy(v[fg]).float(), light, mat).numpy()
        views.append(ViewData(f"{len(views)}", dataclasses.replace(d, radiance_lin=rad), m))  # smooth normals, bumpy shading
        truth.append(true_n[d.coverage > 0.5])
    samples = gather_samples([v.data for v in views], [v.centre_world for v in views])
    points, true_n = positions_of(views), np.concatenate(truth).astype(np.float32)
    model = fit_dam(samples, FitOptions(steps=600, checkpoint_every=0)).model
    before = angle_deg(samples.normal_world.numpy(), true_n)
    knobs = NormalRefineOptions(voxel_px=4.0, steps=400, batch=8192, lr_offsets=1e-2)
    # the DAM fitted to the smooth normals has averaged the bumps' shading away; with its weights
    # trained too, the field recovers most of them. Measured: median error 18.6 deg before, 12.0
    # after (the rest lies mostly along the iso-shading direction, which shading alone cannot see)
    refined_model, nf = refine_normals(model, samples, points, training_footprint(views), dataclasses.replace(knobs, lr_dam=1e-3))
    after = angle_deg(refined_normals(nf, samples.normal_world.numpy(), points), true_n)
    assert np.median(after) < 0.75 * np.median(before), (np.median(before), np.median(after))
    assert math.isfinite(float(refined_model.get_flat_weights().sum()))
    # the default keeps the DAM as fitted (it generalises better on a real object): the field
    # still lowers the error, less (measured 18.6 -> 17.4 deg), and the weights do not move
    kept_model, nf = refine_normals(model, samples, points, training_footprint(views), knobs)
    kept = angle_deg(refined_normals(nf, samples.normal_world.numpy(), points), true_n)
    assert np.median(kept) < 0.97 * np.median(before), (np.median(before), np.median(kept))
    assert torch.equal(kept_model.get_flat_weights(), model.get_flat_weights())
