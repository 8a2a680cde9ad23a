"""Joint material estimation and segmentation on closed-form captures with known materials."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from damcap.appearance.views import radiance_scale_of
from damcap.appearance.segment import (
    SegmentOptions, choose_materials, chromaticity_features, darkest_observation, illumination_aware_kmeans, initial_labels, kmeans,
    kmeans_baseline, match_materials, pixel_spacing, segment_materials, segmentation_scores,
)
from damcap.appearance.views import load_views
from damcap.cli.main import main
from damcap.common.capture_folder import read_capture
from damcap.common.exr import read_exr
from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

from ..conftest import assert_one_line_error, run_cli

FAST = dict(steps=300, init_steps=150, batch_pixels=2048)


def _torus_capture(tmp_path_factory, materials: int):
    """A 40 px closed-form torus under the sky, 12 views (5 train): (folder, train views, test views)."""
    out = tmp_path_factory.mktemp("seg") / f"torus{materials}"
    make_closed_form_capture(out, ClosedFormOptions(shape="torus", light="env", env_grid=12, materials=materials, views=12,
                                                    resolution=40, train_views=5, seed=2, dtype="float"))
    cap = read_capture(out)
    return out, load_views(cap, "train"), load_views(cap, "test")


@pytest.fixture(scope="module")
def two_materials(tmp_path_factory):
    return _torus_capture(tmp_path_factory, 2)


@pytest.fixture(scope="module")
def segmented(two_materials):
    _, train, _ = two_materials
    return segment_materials(train, SegmentOptions(materials=2, **FAST))


def _iou(model, views):
    fgs = [v.data.coverage > 0.5 for v in views]
    pw = np.concatenate([model.weights_of(v)[fg] for v, fg in zip(views, fgs)])
    tw = np.concatenate([v.data.weights[fg] for v, fg in zip(views, fgs)])
    return match_materials(pw, tw)[1]


def test_recovers_the_true_partition(two_materials, segmented):
    _, train, test = two_materials
    assert _iou(segmented, train) > 0.85
    # carried onto the geometry, the segmentation also holds in views it never saw, on the part
    # of the surface the training views saw (within 2 % of the scene radius of a training pixel)
    from scipy.spatial import cKDTree
    tree = cKDTree(segmented.points_world)
    pos = np.concatenate([v.data.position_world[v.data.coverage > 0.5] for v in test])
    seen = tree.query(pos)[0] < 0.02 * segmented.scene_radius
    tw = np.concatenate([v.data.weights[v.data.coverage > 0.5] for v in test])
    assert seen.mean() > 0.3
    assert match_materials(segmented.weights_at(pos[seen]), tw[seen])[1] > 0.85


def test_each_dam_reproduces_its_material(two_materials, segmented):
    _, train, test = two_materials
    same = segmentation_scores(segmented, train, train, same_view=True)
    novel = segmentation_scores(segmented, train, test, same_view=False)
    assert np.mean(list(same["estimated weights"].values())) < 0.03
    assert np.mean(list(novel["true weights"].values())) < 0.12
    # and better than the paper's k-means baseline on novel views
    km = kmeans_baseline(train, 2, steps=300)
    km_novel = segmentation_scores(km, train, test, same_view=False)
    assert np.mean(list(novel["true weights"].values())) < 0.9 * np.mean(list(km_novel["true weights"].values()))


def test_prior_weight_keeps_the_initial_labels(two_materials):
    """The joint phase's prior term pulls Psi toward the chromaticity k-means labels it started from."""
    _, train, _ = two_materials
    fgs = [v.data.coverage > 0.5 for v in train]
    rad = np.concatenate([v.data.radiance_lin[fg] for v, fg in zip(train, fgs)])
    chroma, bright = chromaticity_features(rad, radiance_scale_of(torch.from_numpy(rad)))
    init = kmeans(chroma[bright], 2, seed=0)
    agreement = {}
    for prior in (0.0, 50.0):  # a short initialisation: without the prior, the joint phase drifts away
        model = segment_materials(train, SegmentOptions(materials=2, steps=150, init_steps=20, batch_pixels=2048, prior_weight=prior,
                                                        illumination_degree=0, init_colour="pixel"))  # starts from exactly `init`
        assert "prior_ce" in model.history[-1]
        pw = np.concatenate([model.weights_of(v)[fg] for v, fg in zip(train, fgs)])[bright]
        agreement[prior] = match_materials(pw, np.eye(2)[init])[1]
    assert agreement[50.0] > 0.85 and agreement[50.0] > agreement[0.0] + 0.1, agreement
    with pytest.raises(Exception, match="prior-weight"):
        segment_materials(train, SegmentOptions(materials=2, prior_weight=-1.0))


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


def test_match_materials_hungarian():
    t = np.eye(3)[[0, 0, 1, 1, 2, 2]]
    p = np.eye(3)[[2, 2, 0, 0, 1, 1]]
    perm, iou = match_materials(p, t)
    assert perm.tolist() == [2, 0, 1] and iou == 1.0


def test_segment_command_writes_everything(two_materials, tmp_path, capsys):
    path, train, _ = two_materials
    out = tmp_path / "seg"
    assert main(["segment", str(path), "-o", str(out), "--materials", "2", "--steps", "50", "--init-steps", "50"]) == 0
    for k in range(2):
        assert (out / f"material_{k}.dam").is_file()
    w, names = read_exr(out / "weights" / f"{train[0].name}.exr")
    assert names == ("W.0", "W.1")
    fg = train[0].data.coverage > 0.5
    np.testing.assert_allclose(w[fg].sum(-1), 1.0, atol=2e-3)
    assert (out / "preview" / f"{train[0].name}.png").is_file()
    meta = json.loads((out / "segment.json").read_text())
    assert meta["materials"] == 2 and meta["options"]["seed"] == 0
    capsys.readouterr()
    assert main(["evaluate", str(path), "--segmentation", str(out), "--json", str(tmp_path / "e.json")]) == 0
    res = json.loads((tmp_path / "e.json").read_text())["results"]["test"]
    assert {"segment (estimated weights)", "segment (true weights)"} <= set(res)
    assert main(["segment", str(path), "-o", str(tmp_path / "x"), "--materials", "two"]) == 2
    capsys.readouterr()
    assert main(["segment", str(path), "-o", str(tmp_path / "x"), "--materials", "2", "--prior-weight", "-1"]) == 2
    assert "--prior-weight" in capsys.readouterr().err
    assert main(["segment", str(path), "-o", str(tmp_path / "x"), "--materials", "2", "--illumination-degree", "3"]) == 2
    assert "--illumination-degree must be 0, 1 or 2, got 3" in capsys.readouterr().err
    assert main(["segment", str(path), "-o", str(tmp_path / "x"), "--materials", "2", "--init-colour", "brightest"]) == 2
    assert "--init-colour must be one of pixel, darkest-view, got 'brightest'" in capsys.readouterr().err
    assert main(["segment", str(path), "-o", str(tmp_path / "x"), "--materials", "2", "--colour-floor", "0.5"]) == 2
    assert "--colour-floor must be in (0, 0.02], got 0.5" in capsys.readouterr().err
    assert main(["evaluate", str(path), "--segmentation", str(tmp_path / "nothing")]) == 2


@pytest.fixture(scope="module")
def one_material(tmp_path_factory):
    return _torus_capture(tmp_path_factory, 1)[1:]


def test_auto_picks_one_material_for_a_single_material_capture(one_material):
    train, test = one_material
    choice = choose_materials(train, test, SegmentOptions(**FAST), max_materials=2)
    assert choice.materials == 1, choice.curve
    assert [c["materials"] for c in choice.curve] == [1, 2] and len(choice.curve[0]["restarts"]) == 2


def test_auto_picks_two_materials_for_a_two_material_capture(two_materials):
    _, train, test = two_materials
    choice = choose_materials(train, test, SegmentOptions(**FAST), max_materials=3)
    assert choice.materials == 2, choice.curve
    assert choice.model.materials == 2 and "n = 3" in choice.reason
    # the fewest materials that reach an accuracy asked for: 1 material cannot reach what 2 do
    two = choice.curve[1]["heldout_dssim"]
    target = choose_materials(train, test, SegmentOptions(**FAST), max_materials=3, target_dssim=1.001 * two)
    assert target.materials == 2 and "fewest" in target.reason


def _torus_obj(path, scale=1.0, shift=(0.0, 0.0, 0.0)):
    """The closed-form torus (axis y, radii 0.9 and 0.4) as an OBJ, optionally scaled and moved."""
    import open3d as o3d

    from damcap.common.shapes import torus_mesh

    m = torus_mesh(0.9, 0.4)
    v = np.asarray(m.vertices).copy()
    m.vertices = o3d.utility.Vector3dVector(v * scale + np.asarray(shift))
    o3d.io.write_triangle_mesh(str(path), m)
    return v


def test_segmentation_carries_onto_meshes(two_materials, segmented, tmp_path, capsys):
    from scipy.spatial import cKDTree

    from damcap.appearance.segment_file import save_segmentation
    from damcap.synth.closed_form import two_material_weights
    from damcap.common.mesh import load_mesh

    seg = tmp_path / "seg"
    save_segmentation(seg, segmented, colorspace="lin_rec709", provenance={})
    same = tmp_path / "torus.obj"
    _torus_obj(same)
    verts = load_mesh(same).vertices  # the vertices as damcap reads them (labels follow this order)
    code, out, err = run_cli(["segment-labels", seg, "--mesh", same, "-o", tmp_path / "l.npy", "--align", "none"], capsys)
    assert code == 0, err
    labels = np.load(tmp_path / "l.npy")
    assert labels.shape == (len(verts),) and "damcap export" in out
    # on the surface the training views saw, the labels are the true materials (labels matched)
    seen = cKDTree(segmented.points_world).query(verts)[0] < 0.02 * segmented.scene_radius
    assert seen.mean() > 0.3
    iou = match_materials(np.eye(2)[labels[seen]], two_material_weights(verts[seen]))[1]
    assert iou > 0.85, iou
    # a new shape elsewhere and 100x larger: 'sphere' alignment puts the materials back in place
    moved = tmp_path / "moved.ply"
    _torus_obj(moved, scale=100.0, shift=(5.0, -3.0, 40.0))
    code, _, err = run_cli(["segment-labels", seg, "--mesh", moved, "-o", tmp_path / "m.txt", "--weights", tmp_path / "w.npy"], capsys)
    assert code == 0, err
    moved_labels = np.loadtxt(tmp_path / "m.txt", dtype=np.int64)
    assert len(moved_labels) == len(verts) and np.load(tmp_path / "w.npy").shape == (len(verts), 2)
    assert (moved_labels[seen] == labels[seen]).mean() > 0.9
    code, _, err = run_cli(["segment-labels", seg, "--mesh", same, "-o", tmp_path / "l.csv"], capsys)
    assert_one_line_error(code, err, "l.csv", ".npy")
    code, _, err = run_cli(["segment-labels", seg, "--mesh", same, "-o", tmp_path / "l2.npy", "--align", "box"], capsys)
    assert_one_line_error(code, err, "'box'")
