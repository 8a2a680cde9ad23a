"""The predictor network, its input image, and predicting a DAM (also through the predict command)."""

from __future__ import annotations

import json
import math

import torch

from damcap.appearance.dam_file import load_dam
from damcap.appearance.hyper.file import save_predictor
from damcap.appearance.hyper.model import HyperArchitecture, HyperNet, predictor_image, rotation_y
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
