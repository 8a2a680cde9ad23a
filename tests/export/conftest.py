"""Shared fixtures of the export tests: a DAM fitted to the bundled sample (and two recoloured
copies, one per part of the pot), the bunny, the pot, a browser."""

from __future__ import annotations

import os

import pytest

from damcap.appearance.dam_file import save_dam
from damcap.appearance.fit import FitOptions, fit_dam
from damcap.appearance.views import load_views, samples_of
from damcap.common.capture_folder import read_capture
from damcap.export.browser import chromium_path


@pytest.fixture(scope="session")
def model_file(sample_capture, tmp_path_factory):
    views = load_views(read_capture(sample_capture), "train")
    model = fit_dam(samples_of(views), FitOptions(steps=300, holdout_views=0)).model
    path = tmp_path_factory.mktemp("model") / "torus.dam"
    save_dam(path, model, colorspace="lin_rec709", made_by="fit")
    return path


def _channels_permuted(model, order):
    """The DAM with its output channels reordered (its last layer's rows): the same shading in other colours."""
    from damcap.appearance.dam import DeepAppearanceMap

    arch = model.arch
    flat = model.get_flat_weights().detach().clone()
    k = sum(n + (o if arch.bias else 0) for n, (o, _) in zip(arch.layer_weight_counts[:-1], arch.layer_shapes[:-1]))
    o, i = arch.layer_shapes[-1]
    flat[k:k + o * i] = flat[k:k + o * i].reshape(o, i)[list(order)].reshape(-1)
    if arch.bias:
        flat[k + o * i:k + o * i + o] = flat[k + o * i:k + o * i + o][list(order)]
    return DeepAppearanceMap(arch, model.radiance_scale, flat)


@pytest.fixture(scope="session")
def part_models(model_file, tmp_path_factory):
    """Three .dam files, one per part of a mesh: ``model_file`` and its DAM with the output channels
    turned (G, B, R) and (B, R, G), so each part shades alike but in its own colours."""
    from damcap.appearance.dam_file import load_dam

    model, _ = load_dam(model_file)
    folder = tmp_path_factory.mktemp("parts")
    paths = [model_file]
    for name, order in (("gbr.dam", (1, 2, 0)), ("brg.dam", (2, 0, 1))):
        save_dam(folder / name, _channels_permuted(model, order), colorspace="lin_rec709", made_by="fit")
        paths.append(folder / name)
    return paths


@pytest.fixture(scope="session")
def pot(tmp_path_factory):
    """The pot of ``damcap shape pot``, coarser (64 segments, 24 rings): an OBJ in three parts
    (body, lid, handle) with its material library."""
    from damcap.export.shapes import POT_MTL_KD, pot_mesh, write_parted_obj

    mesh, names = pot_mesh(segments=64, rings=24)
    return write_parted_obj(mesh, names, tmp_path_factory.mktemp("pot") / "pot.obj", POT_MTL_KD)[0]


@pytest.fixture(scope="session")
def bunny(shared_data):
    return shared_data / "meshes" / "stanford-bunny.obj"


@pytest.fixture(scope="session")
def browser():
    if chromium_path() is None:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail("chromium is required under CI (make test installs it)")
        pytest.skip("chromium not installed")


@pytest.fixture(scope="session")
def three_js(browser):
    """Debian's three.js r111 (three.min.js, examples/js/loaders/GLTFLoader.js)."""
    from damcap.export.browser import three_js_dir

    found = three_js_dir()
    if found is None:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail("three.js is required under CI (make test installs Debian's libjs-three)")
        pytest.skip("three.js (libjs-three) not installed")
    return found
