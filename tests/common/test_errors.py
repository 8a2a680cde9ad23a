"""The one user-error type and the option checks whose messages name the CLI flag and the value."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from damcap.common.errors import DamcapError
from damcap.common.validate import require_options


def test_damcap_error_is_an_exception_with_its_message():
    assert issubclass(DamcapError, Exception)
    assert str(DamcapError("x.exr: file not found")) == "x.exr: file not found"


def test_valid_options_pass():
    opts = SimpleNamespace(steps=1, batch_size=64, holdout_views=0, learning_rate=1e-3)
    assert require_options(opts, at_least_1=("steps", "batch_size"), at_least_0=("holdout_views",),
                           positive_finite=("learning_rate",)) is None


@pytest.mark.parametrize("value, message", [
    (0, "--batch-size must be >= 1, got 0"),
    (-3, "--batch-size must be >= 1, got -3"),
    (0.5, "--batch-size must be >= 1, got 0.5"),
    (math.nan, "--batch-size must be >= 1, got nan"),
])
def test_at_least_1(value, message):
    with pytest.raises(DamcapError) as e:
        require_options(SimpleNamespace(batch_size=value), at_least_1=("batch_size",))
    assert str(e.value) == message


def test_at_least_0():
    require_options(SimpleNamespace(holdout_views=0), at_least_0=("holdout_views",))
    with pytest.raises(DamcapError) as e:
        require_options(SimpleNamespace(holdout_views=-1), at_least_0=("holdout_views",))
    assert str(e.value) == "--holdout-views must be >= 0, got -1"


@pytest.mark.parametrize("value", [0.0, -1e-3, math.inf, -math.inf, math.nan])
def test_positive_finite(value):
    with pytest.raises(DamcapError) as e:
        require_options(SimpleNamespace(learning_rate=value), positive_finite=("learning_rate",))
    assert str(e.value) == f"--learning-rate must be a positive number, got {value}"


def test_the_first_failing_field_is_reported():
    opts = SimpleNamespace(steps=0, batch_size=0)
    with pytest.raises(DamcapError, match="^--steps must be >= 1, got 0$"):
        require_options(opts, at_least_1=("steps", "batch_size"))
