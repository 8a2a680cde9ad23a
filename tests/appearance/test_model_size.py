"""fit --target-dssim: the smallest DAM that reaches the accuracy asked for."""

from __future__ import annotations

import pytest

from damcap.appearance.dam_file import load_dam
from damcap.appearance.fit import FitOptions
from damcap.appearance.model_size import fit_to_target, sizes_by_weight_count
from damcap.appearance.views import load_views
from damcap.cli.main import main
from damcap.common.capture_folder import read_capture
from damcap.common.errors import DamcapError


@pytest.fixture(scope="module")
def train_views(small_capture):
    return load_views(read_capture(small_capture), "train")


def test_a_loose_target_keeps_the_smallest_dam(train_views):
    choice = fit_to_target(train_views, 0.99, FitOptions(steps=60, holdout_views=1, checkpoint_every=0))
    smallest = sizes_by_weight_count("nr")[0]
    assert choice.reached and (choice.width, choice.depth) == smallest[:2] and len(choice.tried) == 1
    assert choice.model.arch.num_weights == smallest[2]


def test_an_unreachable_target_tries_every_size_and_keeps_the_most_accurate(train_views):
    choice = fit_to_target(train_views, 1e-9, FitOptions(steps=40, holdout_views=1, checkpoint_every=0))
    assert not choice.reached and len(choice.tried) == len(sizes_by_weight_count("nr"))
    best = min(choice.tried, key=lambda t: t["heldout_dssim"])
    assert (choice.width, choice.depth) == (best["width"], best["depth"])
    weights = [t["weights"] for t in choice.tried]
    assert weights == sorted(weights)


def test_bad_targets_and_no_holdout_are_refused(train_views):
    with pytest.raises(DamcapError, match="target-dssim"):
        fit_to_target(train_views, 1.5, FitOptions(steps=10))
    with pytest.raises(DamcapError, match="holdout-views"):
        fit_to_target(train_views, 0.5, FitOptions(steps=10, holdout_views=0))


def test_cli(small_capture, tmp_path):
    out = tmp_path / "m.dam"
    assert main(["fit", str(small_capture), "-o", str(out), "--target-dssim", "0.99", "--steps", "40", "--holdout-views", "1"]) == 0
    meta = load_dam(out)[1]
    assert meta["provenance"]["target_reached"] and meta["provenance"]["sizes_tried"][0]["weights"] == 136
    assert main(["fit", str(small_capture), "-o", str(out), "--target-dssim", "0.5", "--width", "8"]) == 2
    assert main(["fit", str(small_capture), "-o", str(out), "--target-dssim", "0"]) == 2
