"""Shared fixtures of the export tests: a DAM fitted to the bundled sample, the bunny, a browser."""

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
