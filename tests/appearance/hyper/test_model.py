"""The predictor network, its input image, and predicting a DAM (also through the predict command)."""

from __future__ import annotations

import json
import math

import pytest
import torch
import torch.nn.functional as F

from damcap.appearance.dam_file import load_dam
from damcap.appearance.hyper.file import save_predictor
from damcap.appearance.dam import DamArchitecture, encode_inputs
from damcap.appearance.hyper.model import (HyperArchitecture, HyperNet, predict_dam, predicted_loss, predictor_image, predictor_images,
                                           rotation_y)
from damcap.cli.main import main

from tests.appearance.conftest import _crop_of


def test_network_shapes_and_default_architecture():
    arch = HyperArchitecture()
    assert arch.input_size == 256 and len(arch.channels) == 8 and arch.dam.num_weights == 3360
    net = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8, 8, 8, 8)))
    out = net(torch.randn(3, 9, 32, 32))
    assert out.shape == (3, 3360) and torch.isfinite(out).all()
    full = HyperNet(arch)
    n_params = sum(p.numel() for p in full.parameters())
    assert n_params * 4 < 30e6  # the shipped file stays under ~30 MB in float32


def test_predictor_image_channels_units_and_augmentations(small_capture):
    crop = _crop_of(small_capture)
    img, scale = predictor_image(crop, 32)
    assert img.shape == (9, 32, 32) and scale > 0
    fg = img[3:6].norm(dim=0) > 0
    assert fg.any() and (~fg).any()
    assert torch.allclose(img[3:6].norm(dim=0)[fg], torch.ones(()), atol=1e-5)  # unit normals on the foreground
    assert (img[:, ~fg] == 0).all()  # covered pixels only
    # rotation about +y rotates every world vector and leaves RGB alone
    r = rotation_y(0.7)
    rot, scale_r = predictor_image(crop, 32, rotation=r)
    assert scale_r == scale and torch.equal(rot[:3], img[:3])
    assert torch.allclose(rot[3:6], torch.einsum("ij,jhw->ihw", r, img[3:6]), atol=1e-5)
    # mirroring twice is the identity; a gain of 2 leaves the normalised image unchanged and doubles the scale
    back = predictor_image(crop, 32, mirror=True)[0].flip(-1)
    assert torch.allclose(back[3], -img[3], atol=1e-5) and torch.allclose(back[6], -img[6], atol=1e-5)  # world x reflected
    assert torch.allclose(back[[0, 1, 2, 4, 5, 7, 8]], img[[0, 1, 2, 4, 5, 7, 8]], atol=1e-5)
    g, scale_g = predictor_image(crop, 32, rgb_gain=torch.full((3,), 2.0))
    assert math.isclose(scale_g, 2 * scale, rel_tol=1e-5) and torch.allclose(g, img, atol=1e-5)


def test_predict_and_evaluate_cli(tmp_path, small_capture):
    net = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8)))
    pred = tmp_path / "p.safetensors"
    save_predictor(pred, net, {"command": "test"})
    out = tmp_path / "pred.dam"
    assert main(["predict", str(small_capture), "-o", str(out), "--predictor", str(pred), "--refine-steps", "30"]) == 0
    prov = load_dam(out)[1]["provenance"]
    assert prov["train_l1_refined"] <= prov["train_l1_predicted"]
    assert main(["predict", str(small_capture), "-o", str(tmp_path / "x.dam"), "--predictor", str(pred), "--view", "nope"]) == 2
    assert main(["predict", str(small_capture), "-o", str(tmp_path / "x.dam"), "--predictor", str(tmp_path / "missing")]) == 2
    fitted = tmp_path / "fit.dam"
    assert main(["fit", str(small_capture), "-o", str(fitted), "--steps", "50"]) == 0
    js = tmp_path / "e.json"
    assert main(["evaluate", str(small_capture), "--model", str(out), "--model", str(fitted), "--json", str(js)]) == 0
    res = json.loads(js.read_text())
    assert set(res["models"]) == {"predict: pred", "fit: fit"}
    r = res["ratios"]["predict: pred / fit: fit"]["test"]
    assert math.isclose(r, res["results"]["test"]["predict: pred"]["mean"] / res["results"]["test"]["fit: fit"]["mean"], rel_tol=1e-9)


def test_a_set_of_views_is_pooled_in_any_order_and_masked_views_do_not_count():
    torch.manual_seed(0)
    net = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8, 8, 8, 8), input_views=3))
    x = torch.randn(2, 3, 9, 32, 32)
    out = net(x)
    assert torch.allclose(net(x[:, [2, 0, 1]]), out, atol=1e-5)  # a set: the order of the views does not matter
    mask = torch.tensor([[True, True, False], [True, False, False]])
    masked = net(x, mask)
    assert torch.allclose(masked[0], net(x[:1, :2])[0], atol=1e-5) and torch.allclose(masked[1], net(x[1:, 0])[0], atol=1e-5)
    assert torch.equal(net(x[:, 0]), net(x[:, :1]))  # one view = the paper's single-image predictor
    assert HyperArchitecture.from_json(net.arch.to_json()).input_views == 3
    old = net.arch.to_json()
    del old["input_views"]  # a version-1 predictor file: one view
    assert HyperArchitecture.from_json(old).input_views == 1


def test_batched_predictor_images_crop_to_the_foreground():
    s = 16
    stack = torch.zeros(1, 10, s, s)
    stack[0, 0:3] = torch.linspace(1, 2, s)[None, None, :]  # radiance ramps left to right
    stack[0, 3:6] = torch.tensor([0.0, 0.0, 1.0])[:, None, None]
    stack[0, 6:9] = torch.tensor([0.0, 1.0, 0.0])[:, None, None]
    stack[0, 9] = 1.0
    full = predictor_images(stack, s, torch.tensor([2.0]), margin=0.0)
    assert torch.allclose(full[0, 0], torch.log1p(stack[0, 0] / 2), atol=1e-5)  # the whole view: an identity resampling
    assert torch.allclose(full[0, 5], torch.ones(()), atol=1e-6) and torch.allclose(full[0, 7], torch.ones(()), atol=1e-6)
    quarter = torch.zeros_like(stack)
    quarter[..., :8, 8:] = stack[..., :8, 8:]  # the foreground is the top-right quadrant
    out = predictor_images(quarter, s, torch.tensor([2.0]), margin=0.0)
    ref = torch.log1p(F.interpolate(quarter[:, 0:1, :8, 8:], size=(s, s), mode="bilinear", align_corners=False) / 2)
    assert torch.allclose(out[0, 0, 2:-2, 2:-2], ref[0, 0, 2:-2, 2:-2], atol=1e-5)  # cropped and magnified x2
    assert (predictor_images(torch.zeros(1, 10, s, s), s, torch.ones(1)) == 0).all()  # no foreground: zeros


def test_prediction_does_not_depend_on_exposure(small_capture):
    torch.manual_seed(1)
    net = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8, 8, 8, 8), input_views=2))
    crops = [_crop_of(small_capture, 0), _crop_of(small_capture, 1)]
    brighter = [c.clone() for c in crops]
    for c in brighter:
        c[:3] *= 1000.0
    a, b = predict_dam(net, crops, 0.5), predict_dam(net, brighter, 500.0)
    assert torch.allclose(a.get_flat_weights(), b.get_flat_weights(), atol=1e-5)
    assert math.isclose(b.radiance_scale, 1000 * a.radiance_scale, rel_tol=1e-9)


def test_predicted_loss_with_a_readout_solves_on_even_samples_and_scores_odd_ones():
    from damcap.appearance.readout import solved_weights

    arch = DamArchitecture()
    g = torch.Generator().manual_seed(4)
    w = torch.randn(2, arch.num_weights, generator=g) * 0.3
    w.requires_grad_(True)
    v = torch.nn.functional.normalize(torch.randn(2, 64, 3, generator=g), dim=-1)
    n = torch.nn.functional.normalize(torch.randn(2, 64, 3, generator=g), dim=-1)
    y = torch.rand(2, 64, 3, generator=g)
    mask = torch.rand(2, 64, generator=g) > 0.2
    loss = predicted_loss(w, v, n, y, arch, mask, readout_iterations=2)
    x = encode_inputs(v, n, arch.encoding)
    solved = solved_weights(w, arch, x[:, 0::2], y[:, 0::2], mask[:, 0::2].float(), 2)
    assert torch.allclose(loss, predicted_loss(solved, v[:, 1::2], n[:, 1::2], y[:, 1::2], arch, mask[:, 1::2]))
    assert not torch.equal(solved[:, -96:], w[:, -96:]) and torch.equal(solved[:, :-96], w[:, :-96])
    loss.backward()
    assert torch.isfinite(w.grad).all() and w.grad[:, :-96].abs().sum() > 0  # the hidden layers learn through the solve


def test_a_light_orientation_network_predicts_in_it_and_returns_world_weights(small_capture):
    """orientation 'light': the convolutions read the images turned into the light orientation,
    and the DAM comes back turned to the world (same parameters as a world-orientation network)."""
    from damcap.appearance.dam import rotated_world_weights
    from damcap.appearance.hyper.orientation import light_rotation, rotate_images
    from damcap.common.errors import DamcapError

    world = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8), input_views=2), torch.Generator().manual_seed(0))
    light = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8), input_views=2, orientation="light"))
    light.load_state_dict(world.state_dict())
    img = predictor_image(_crop_of(small_capture), 32)[0]
    images = torch.stack([img, predictor_image(_crop_of(small_capture), 32, rotation=rotation_y(1.0))[0]])[None]
    r = light_rotation(images)
    assert not torch.allclose(r, torch.eye(3))
    expect = rotated_world_weights(world(rotate_images(images, r)), light.arch.dam, r)
    assert torch.allclose(light(images), expect, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(light(images), world(images), atol=1e-3)
    # the orientation is part of the file's architecture, written as "orientation"; files written
    # before it had that name say "frame"; files without either are world-orientation predictors
    assert HyperArchitecture.from_json(light.arch.to_json()) == light.arch
    assert light.arch.to_json()["orientation"] == "light" and "frame" not in light.arch.to_json()
    old = {k: v for k, v in light.arch.to_json().items() if k != "orientation"}
    assert HyperArchitecture.from_json({**old, "frame": "light"}) == light.arch
    assert HyperArchitecture.from_json(old).orientation == "world"
    with pytest.raises(DamcapError, match="unknown predictor orientation 'sky'"):
        HyperArchitecture(orientation="sky")
    with pytest.raises(DamcapError, match="unknown predictor orientation 'sky'"):
        HyperArchitecture.from_json({**old, "frame": "sky"})


def test_predict_records_where_a_light_orientation_predictor_put_the_light(tmp_path, small_capture):
    for orientation in ("world", "light"):
        pred = tmp_path / f"{orientation}.safetensors"
        save_predictor(pred, HyperNet(HyperArchitecture(input_size=32, channels=(4, 8), orientation=orientation)), {"command": "test"})
        out = tmp_path / f"{orientation}.dam"
        assert main(["predict", str(small_capture), "-o", str(out), "--predictor", str(pred)]) == 0
        prov = load_dam(out)[1]["provenance"]
        if orientation == "world":
            assert "light_up_world" not in prov
        else:
            assert math.isclose(math.hypot(*prov["light_up_world"]), 1.0, rel_tol=1e-5)


def test_a_light_rotation_found_by_the_caller_gives_the_same_weights(small_capture):
    """HyperNet(images, rotation=light_rotation(images)) is the plain call (damcap predict finds the
    rotation once for the network and its record); a world-orientation network ignores a rotation."""
    from damcap.appearance.hyper.orientation import light_rotation, light_up_world, rotation_to_up, terminator_fit, unit_direction

    light = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8), input_views=2, orientation="light"), torch.Generator().manual_seed(1))
    world = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8), input_views=2), torch.Generator().manual_seed(1))
    img = predictor_image(_crop_of(small_capture), 32)[0]
    images = torch.stack([img, predictor_image(_crop_of(small_capture), 32, rotation=rotation_y(1.0))[0]])[None]
    r = light_rotation(images)
    assert torch.equal(light(images, rotation=r), light(images))
    assert torch.equal(rotation_to_up(terminator_fit(images)), r) and torch.equal(unit_direction(terminator_fit(images)), light_up_world(images))
    assert torch.equal(world(images, rotation=r), world(images))
