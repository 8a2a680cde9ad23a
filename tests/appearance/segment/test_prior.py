"""The predictor as each material's start and prior (appearance/segment/prior.py) and its use in
segment_materials (--prior predictor, the fallback)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, dam_forward, encode_inputs
from damcap.appearance.fit import PriorSamples
from damcap.appearance.segment.options import SegmentOptions
from damcap.appearance.segment.prior import label_shares, material_views, prior_cost, stack_samples
from damcap.appearance.segment.train import segment_materials
from damcap.common.errors import DamcapError

TINY = SegmentOptions(materials=2, steps=40, init_steps=10, batch_pixels=1024, psi_resolution=16, psi_channels=4, prior_samples=4096,
                      prior="off")


def test_material_views_cover_only_the_material(two_materials):
    _, train, _ = two_materials
    labels = [np.arange(int((v.data.coverage > 0.5).sum())) % 3 - 1 for v in train]  # -1, 0, 1, -1, ...
    for k in (0, 1):
        mine = material_views(train, labels, k)
        for v, m, lab in zip(train, mine, labels):
            assert m.data.radiance_lin is v.data.radiance_lin and m.name == v.name
            assert int((m.data.coverage > 0.5).sum()) == int((lab == k).sum())
            assert np.array_equal(m.data.coverage[m.data.coverage > 0], v.data.coverage[m.data.coverage > 0])
    assert label_shares(labels, 2).tolist() == pytest.approx([0.5, 0.5], abs=0.01)


def test_prior_cost_is_the_share_weighted_l1():
    arch = DamArchitecture(width=8, depth=2, encoding="nr")
    gen = torch.Generator().manual_seed(0)
    w = torch.randn(2, arch.num_weights, generator=gen) * 0.3
    v = torch.nn.functional.normalize(torch.randn(2, 50, 3, generator=gen), dim=-1)
    n = torch.nn.functional.normalize(torch.randn(2, 50, 3, generator=gen), dim=-1)
    x = torch.stack([encode_inputs(v[k], n[k], "nr") for k in range(2)])
    gain = torch.tensor([1.0, 2.0])
    exact = dam_forward(w, x, arch) * gain[:, None, None]
    share = torch.tensor([0.25, 0.75])
    samples = [PriorSamples(x[k], exact[k] + 0.5 * k, torch.ones(50)) for k in range(2)]
    pri = stack_samples(samples, share, [])
    idx = torch.arange(50).expand(2, 50)
    # material 0 sits on its target, material 1 is 0.5 off everywhere: 0.75 x 0.5
    assert float(prior_cost(w, gain, pri, idx, arch)) == pytest.approx(0.375, rel=1e-5)
    pri.weight[1] = 0.0  # where a material's pixels decide, the prior costs nothing
    assert float(prior_cost(w, gain, pri, idx, arch)) == pytest.approx(0.0, abs=1e-6)


def test_start_is_the_prediction_at_the_capture_scale():
    from damcap.appearance.segment.prior import MaterialPriors

    arch = DamArchitecture(width=8, depth=2, encoding="nr")
    pred = DeepAppearanceMap(arch, 3.0, generator=torch.Generator().manual_seed(1))
    other = DeepAppearanceMap(DamArchitecture(width=4, depth=2, encoding="nr"), 5.0)
    pri = MaterialPriors([pred, other], torch.zeros(2, 1, 9), torch.zeros(2, 1, 3), torch.zeros(2, 1), torch.ones(2) / 2)
    weights, gain = pri.start(arch, 1.5)
    assert weights[1] is None and gain.tolist() == [2.0, 1.0]  # another architecture: a random start, no gain
    v = torch.nn.functional.normalize(torch.randn(20, 3), dim=-1)
    n = torch.nn.functional.normalize(v + torch.randn(20, 3) * 0.3, dim=-1)
    started = DeepAppearanceMap(arch, 1.5 * float(gain[0]), weights[0])
    assert torch.allclose(started(v, n), pred(v, n), rtol=1e-6)


def _fake_predictor(monkeypatch) -> list[DeepAppearanceMap]:
    """Replace the shipped predictor by seeded random DAMs of its architecture (radiance scale
    0.5, 1.0, ...), returned in the order they are made."""
    made: list[DeepAppearanceMap] = []

    def predict(views, *args, **kwargs):
        k = len(made) % TINY.materials
        made.append(DeepAppearanceMap(TINY.architecture, 0.5 * (k + 1), generator=torch.Generator().manual_seed(k)))
        return made[-1]

    monkeypatch.setattr("damcap.appearance.hyper.predict.predict_views", predict)
    return made


def test_a_heavy_prior_keeps_each_material_at_its_prediction(two_materials, monkeypatch):
    """Where a material's pixels say least (prior weight > 0.9), a heavy prior keeps its DAM at the
    prediction it started from; without the prior's cost the data pull it away."""
    from damcap.appearance.segment.cluster import initial_labels
    from damcap.appearance.segment.prior import predict_material_priors

    _, train, _ = two_materials
    made = _fake_predictor(monkeypatch)
    opts = replace(TINY, prior="predictor", steps=30)
    drift = {}
    for weight in (0.0, 1000.0):
        model = segment_materials(train, replace(opts, prior_dam_weight=weight))
        assert model.prior_choice["used"] and model.prior_choice["started_from_prediction"] == [True, True]
        assert [d.radiance_scale / model.radiance_scale for d in model.dams] == pytest.approx(
            [m.radiance_scale / model.radiance_scale for m in made[:2]], rel=1e-6)
        pri = predict_material_priors(train, initial_labels(train, model.radiance_scale, opts), 2, model.radiance_scale,
                                      opts.architecture, opts.prior_samples, opts.prior_sigma, opts.seed)
        with torch.no_grad():
            rel = []
            for k, dam in enumerate(model.dams):
                far = pri.weight[k] > 0.9
                got = dam.forward_normalised(pri.inputs[k][far]) * dam.radiance_scale / model.radiance_scale
                rel.append(float((got - pri.target[k][far]).abs().mean() / pri.target[k][far].mean()))
        drift[weight] = float(np.mean(rel))
    # measured: 0.017 against 0.82
    assert drift[1000.0] < 0.05 and drift[1000.0] < 0.1 * drift[0.0], drift


def test_the_plain_path_when_the_predictor_cannot_predict(two_materials, monkeypatch):
    _, train, _ = two_materials
    plain = segment_materials(train, TINY)
    assert plain.prior_choice == {"mode": "off"}

    def cannot(*args, **kwargs):
        raise DamcapError("no lit view with foreground to predict from")

    monkeypatch.setattr("damcap.appearance.hyper.predict.predict_views", cannot)
    lines: list[str] = []
    fallback = segment_materials(train, replace(TINY, prior="predictor"), log=lines.append)
    assert lines == ["prior: none (the predictor could not predict each material from these views: "
                     "no lit view with foreground to predict from)"]
    assert fallback.prior_choice == {"mode": "predictor", "used": False}
    for a, b in zip(plain.dams, fallback.dams):  # the plain path, bit for bit
        assert torch.equal(a.weights_flat, b.weights_flat) and a.radiance_scale == b.radiance_scale
    assert np.array_equal(plain.point_weights, fallback.point_weights)
    with pytest.raises(DamcapError, match="--prior"):
        segment_materials(train, replace(TINY, prior="always"))
