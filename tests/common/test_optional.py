"""Optional dependencies: the module is returned when installed, a one-line error names the extra."""

from __future__ import annotations

import sys

import pytest

from damcap.common.errors import DamcapError
from damcap.common.optional import EXTRA_OF_MODULE, MissingExtraError, missing_extra_message, require


def test_present_module_is_returned() -> None:
    assert require("onnx", "a test") is sys.modules["onnx"]


@pytest.mark.parametrize("module", sorted(EXTRA_OF_MODULE))
def test_missing_module_names_the_extra(monkeypatch: pytest.MonkeyPatch, module: str) -> None:
    monkeypatch.setitem(sys.modules, module, None)  # import now raises ModuleNotFoundError
    with pytest.raises(MissingExtraError, match=rf"^damcap frob needs {module}, which is not installed: "
                                                  rf"install damcap\[{EXTRA_OF_MODULE[module]}\]") as e:
        require(module, "damcap frob")
    assert isinstance(e.value, DamcapError)  # the CLI prints it as one line, exit code 2
    assert "\n" not in str(e.value)


def test_message() -> None:
    assert missing_extra_message("pidng", "x") == "x needs pidng, which is not installed: install damcap[synth] (pip install 'damcap[synth]')"


def test_unknown_module_is_a_programming_error() -> None:
    with pytest.raises(KeyError, match="'numpy' is not an optional dependency"):
        require("numpy", "a test")
