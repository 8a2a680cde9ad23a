"""The one user-error type."""

from __future__ import annotations

from damcap.common.errors import DamcapError


def test_damcap_error_is_an_exception_with_its_message():
    assert issubclass(DamcapError, Exception)
    assert str(DamcapError("x.exr: file not found")) == "x.exr: file not found"
