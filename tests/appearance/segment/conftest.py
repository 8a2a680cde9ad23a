"""Shared fixtures of the segmentation tests: closed-form torus captures with known materials
and one segmentation of the two-material capture (computed once per session)."""

from __future__ import annotations

import pytest

from damcap.appearance.segment.options import SegmentOptions
from damcap.appearance.segment.train import segment_materials
from damcap.appearance.views import load_views
from damcap.common.capture_folder import read_capture
from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture


FAST = dict(steps=300, init_steps=150, batch_pixels=2048, prior="off")
"""short runs of the plain joint fit (the predictor's prior: test_prior.py)"""


def _torus_capture(tmp_path_factory, materials: int):
    """A 40 px closed-form torus under the sky, 12 views (5 train): (folder, train views, test views)."""
    out = tmp_path_factory.mktemp("seg") / f"torus{materials}"
    make_closed_form_capture(out, ClosedFormOptions(shape="torus", light="env", env_grid=12, materials=materials, views=12,
                                                    resolution=40, train_views=5, seed=2, dtype="float"))
    cap = read_capture(out)
    return out, load_views(cap, "train"), load_views(cap, "test")


@pytest.fixture(scope="session")
def two_materials(tmp_path_factory):
    return _torus_capture(tmp_path_factory, 2)


@pytest.fixture(scope="session")
def segmented(two_materials):
    _, train, _ = two_materials
    return segment_materials(train, SegmentOptions(materials=2, **FAST))
