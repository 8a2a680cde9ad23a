"""Initial clustering: k-means, the illumination-aware k-means, darkest observations, initial labels."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from damcap.appearance.segment.cluster import chromaticity_features, darkest_observation, illumination_aware_kmeans, initial_labels, kmeans, pixel_spacing
from damcap.appearance.segment.options import SegmentOptions
from damcap.appearance.segment.score import match_materials
from damcap.appearance.views import radiance_scale_of


def test_darkest_observation_finds_the_same_surface_point_in_other_frames():
    """Three frames see points on a plane (pixel spacing 0.1, each frame shifted by 0.15 of it);
    frame 1 has a highlight on every point. A point across a fold (opposite normal) at the same
    place is another surface and never counts."""
    grid = np.stack(np.meshgrid(np.arange(5) * 0.1, np.arange(5) * 0.1, indexing="ij"), -1).reshape(-1, 2)
    pos = np.concatenate([np.c_[grid + 0.015 * f, np.zeros(len(grid))] for f in range(3)])
    nrm = np.tile([0.0, 0.0, 1.0], (len(pos), 1))
    frame = np.repeat(np.arange(3), len(grid))
    brightness = np.where(frame == 1, 5.0, 1.0) + 0.1 * frame  # frame 0 is the darkest everywhere
    # the fold: one more point of frame 2, at the first point's place, facing away, very dark
    pos, nrm = np.r_[pos, pos[:1]], np.r_[nrm, [[0.0, 0.0, -1.0]]]
    frame, brightness = np.r_[frame, 2], np.r_[brightness, 0.0]
    spacing = pixel_spacing([pos[frame == f] for f in range(3)])
    assert spacing == pytest.approx(0.1)
    best = darkest_observation(pos, nrm, frame, brightness, 0.5 * spacing)
    n = len(grid)
    assert np.array_equal(best[:n], np.arange(n))  # frame 0 is already the darkest
    assert np.array_equal(best[n:2 * n], np.arange(n))  # frame 1's highlights resolve to frame 0
    assert np.array_equal(best[2 * n:3 * n], np.arange(n))
    assert best[-1] == len(pos) - 1  # the fold's point has no other observation
    # a radius below the frames' offset finds nobody else
    assert np.array_equal(darkest_observation(pos, nrm, frame, brightness, 0.01), np.arange(len(pos)))


def test_darkest_view_initialisation_ignores_view_dependent_highlights(two_materials):
    """Give material 0 a strong highlight tinted like material 1 in some frames: clustering each
    pixel's own colour labels the highlights as material 1; the darkest observation does not."""
    _, train, _ = two_materials
    fgs = [v.data.coverage > 0.5 for v in train]
    truth = np.concatenate([v.data.weights[fg].argmax(1) for v, fg in zip(train, fgs)])
    rad = np.concatenate([v.data.radiance_lin[fg] for v, fg in zip(train, fgs)])
    scale = radiance_scale_of(torch.from_numpy(rad))
    chroma, _ = chromaticity_features(rad, scale)
    tint = np.median(chroma[truth == 1], 0)
    views = []
    for i, (v, fg) in enumerate(zip(train, fgs)):
        r = v.data.radiance_lin.copy()
        if i % 2:  # every other frame: a highlight band over half of material 0, as bright as the scene
            band = fg & (v.data.weights.argmax(-1) == 0) & (np.arange(r.shape[1])[None, :] < r.shape[1] // 2)
            r[band] += 3 * scale * tint
        views.append(dataclasses.replace(v, data=dataclasses.replace(v.data, radiance_lin=r)))
    ious = {}
    for init in ("pixel", "darkest-view"):
        labels = np.concatenate(initial_labels(views, scale, SegmentOptions(materials=2, init_colour=init)))
        known = labels >= 0
        assert known.mean() > 0.5
        ious[init] = match_materials(np.eye(2)[labels[known]], np.eye(2)[truth[known]])[1]
    assert ious["darkest-view"] > 0.85 and ious["darkest-view"] > ious["pixel"] + 0.05, ious


def test_dim_pixels_are_assigned_to_the_clusters_of_the_bright_ones(two_materials):
    """Darken the left half of every frame to a mean radiance of 1e-3 (as if lit only by
    interreflection): with ``colour_floor`` 0.02 it starts unlabelled; with the default floor its
    pixels are assigned to the clusters the bright pixels form, and the bright pixels' labels do
    not change."""
    _, train, _ = two_materials
    fgs = [v.data.coverage > 0.5 for v in train]
    views, dim = [], []
    for v, fg in zip(train, fgs):
        band = fg & (np.arange(fg.shape[1])[None, :] < fg.shape[1] // 2)
        r = v.data.radiance_lin.copy()
        r[band] *= 1e-3 / max(float(r[band].sum(-1).mean()) / 3, 1e-30)  # mean radiance 1e-3
        views.append(dataclasses.replace(v, data=dataclasses.replace(v.data, radiance_lin=r)))
        dim.append(band[fg])
    dim = np.concatenate(dim)
    truth = np.concatenate([v.data.weights[fg].argmax(1) for v, fg in zip(train, fgs)])
    scale = radiance_scale_of(torch.from_numpy(np.concatenate([v.data.radiance_lin[fg] for v, fg in zip(views, fgs)])))
    assert 1e-3 < 0.02 * scale and dim.mean() > 0.1
    # each pixel's own colour: the darkening depends on the frame, which no real shading does
    bright_only = np.concatenate(initial_labels(views, scale, SegmentOptions(materials=2, colour_floor=0.02, init_colour="pixel")))
    floor = np.concatenate(initial_labels(views, scale, SegmentOptions(materials=2, init_colour="pixel")))
    assert (bright_only[dim] == -1).all()
    assert np.array_equal(floor[~dim], bright_only[~dim])
    assert (floor[dim] >= 0).all()
    assert match_materials(np.eye(2)[floor[dim]], np.eye(2)[truth[dim]])[1] > 0.9


def test_illumination_aware_kmeans_assigns_unfitted_pixels_after_removing_the_tint():
    """Pixels outside ``fit`` do not move the clusters; each gets the material whose colour, with
    the fitted tint at its normal, is nearest."""
    rng = np.random.default_rng(1)
    n = rng.normal(size=(3000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    truth = rng.integers(0, 2, len(n))
    material_log = np.array([[0.15, 0.0, -0.15], [-0.15, 0.0, 0.15]])
    rgb = np.exp(material_log[truth] + 0.5 * n[:, :1] * np.array([[1.0, 0.0, -1.0]]) + rng.normal(0, 0.02, (len(n), 3)))
    chroma = rgb / rgb.sum(1, keepdims=True)
    fit = np.arange(len(n)) < 2000
    both = illumination_aware_kmeans(chroma, n, 2, seed=0, degree=2, fit=fit)
    assert np.array_equal(both[fit], illumination_aware_kmeans(chroma[fit], n[fit], 2, seed=0, degree=2))
    assert match_materials(np.eye(2)[both[~fit]], np.eye(2)[truth[~fit]])[1] > 0.95
    plain = illumination_aware_kmeans(chroma, n, 2, seed=0, degree=0, fit=fit)  # no tint model: splits by the tint
    assert match_materials(np.eye(2)[plain[~fit]], np.eye(2)[truth[~fit]])[1] < 0.9


def test_kmeans_on_separable_clusters():
    rng = np.random.default_rng(0)
    a = rng.normal(0, 0.1, (200, 6))
    b = rng.normal(3, 0.1, (300, 6))
    lab = kmeans(np.concatenate([a, b]).astype(np.float32), 2, seed=1)
    assert len(set(lab[:200])) == 1 and len(set(lab[200:])) == 1 and lab[0] != lab[-1]


def test_illumination_aware_kmeans_separates_materials_under_a_tinted_light():
    """Two materials under a light that is redder on one side and bluer on the other, by more than
    the materials differ: plain k-means splits by orientation, the tint model by material."""
    rng = np.random.default_rng(0)
    n = rng.normal(size=(4000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    truth = rng.integers(0, 2, len(n))  # materials independent of orientation
    material_log = np.array([[0.15, 0.0, -0.15], [-0.15, 0.0, 0.15]])
    tint_log = 0.8 * n[:, :1] * np.array([[1.0, 0.0, -1.0]]) + 0.3 * (n[:, 1:2] * n[:, 2:3]) * np.array([[0.0, 1.0, -1.0]])
    rgb = np.exp(material_log[truth] + tint_log + rng.normal(0, 0.02, (len(n), 3))) * rng.uniform(0.2, 3.0, (len(n), 1))
    chroma = rgb / rgb.sum(1, keepdims=True)

    def iou(lab):
        return match_materials(np.eye(2)[lab], np.eye(2)[truth])[1]

    plain = kmeans(chroma.astype(np.float32), 2, seed=0)
    aware = illumination_aware_kmeans(chroma, n, 2, seed=0, degree=2)
    assert iou(plain) < 0.7
    assert iou(aware) > 0.95
    log_chroma = np.log(chroma) - np.log(chroma).mean(1, keepdims=True)
    assert np.array_equal(illumination_aware_kmeans(chroma, n, 2, seed=0, degree=0), kmeans(log_chroma.astype(np.float32), 2, seed=0))
