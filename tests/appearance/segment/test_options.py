"""Options of the segmentation: every check names the flag and the value; the saved form round-trips."""

from __future__ import annotations

import pytest

from damcap.appearance.dam import DamArchitecture
from damcap.appearance.segment.options import BRIGHT_FRACTION, SegmentOptions, options_json
from damcap.common.errors import DamcapError


def test_defaults_are_valid_and_give_the_dam_architecture():
    opts = SegmentOptions()
    assert opts.validate() is None
    assert opts.architecture == DamArchitecture(width=32, depth=4, encoding="nr")
    assert SegmentOptions(width=8, depth=2, encoding="vnr").architecture == DamArchitecture(width=8, depth=2, encoding="vnr")


def test_options_json_round_trip():
    opts = SegmentOptions(materials=3, steps=10, init_colour="pixel", colour_floor=0.01, seed=7)
    d = options_json(opts)
    assert d["materials"] == 3 and d["init_colour"] == "pixel" and d["seed"] == 7
    assert SegmentOptions(**d) == opts


@pytest.mark.parametrize("change, message", [
    (dict(materials=0), "--materials must be an integer in [1, 16], got 0"),
    (dict(materials=17), "--materials must be an integer in [1, 16], got 17"),
    (dict(steps=0), "--steps must be an integer in [1, 1000000000], got 0"),
    (dict(batch_pixels=0), "--batch-pixels must be an integer in [1, 16777216], got 0"),
    (dict(frames_per_step=-1), "--frames-per-step must be an integer in [1, 1024], got -1"),
    (dict(init_steps=-1), "--init-steps must be an integer in [0, 1000000000], got -1"),
    (dict(sparsity_beta=-0.1), "--sparsity-beta must be a finite number in [0, 1000000], got -0.1"),
    (dict(prior_weight=-1.0), "--prior-weight must be a finite number in [0, 1000000], got -1.0"),
    (dict(init_colour="brightest"), "--init-colour must be one of pixel, darkest-view, got 'brightest'"),
    (dict(colour_floor=0.0), "--colour-floor must be a finite number in (0, 0.02], got 0.0"),
    (dict(colour_floor=0.5), "--colour-floor must be a finite number in (0, 0.02], got 0.5"),
    (dict(illumination_degree=3), "--illumination-degree must be an integer in [0, 2], got 3"),
    (dict(prior="always"), "--prior must be one of off, predictor, auto, got 'always'"),
    (dict(prior_sigma=0.0), "--prior-sigma must be a finite number in (0, 10], got 0.0"),
    (dict(prior_dam_weight=-1.0), "--prior-dam-weight must be a finite number in [0, 1000000], got -1.0"),
])
def test_each_bad_value_is_named(change, message):
    with pytest.raises(DamcapError) as e:
        SegmentOptions(**change).validate()
    assert str(e.value) == message


def test_the_edges_of_the_allowed_ranges_pass():
    for change in (dict(materials=1), dict(materials=16), dict(init_steps=0), dict(colour_floor=BRIGHT_FRACTION),
                   dict(illumination_degree=0), dict(init_colour="pixel")):
        SegmentOptions(**change).validate()
    assert BRIGHT_FRACTION == 0.02
