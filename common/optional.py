"""Optional dependencies: which extra installs each one, and a one-line error when it is missing.

damcap's core (capture, reconstruct, appearance, export to frames / GLSL / the viewer) needs only
the required dependencies. A few commands need more, installed as extras (pyproject.toml):
``damcap[synth]`` (Mitsuba 3 renders, simulated RAW brackets), ``damcap[onnx]`` (ONNX export),
``damcap[all]`` (both). A command that needs a missing one stops with a :class:`MissingExtraError`,
which the CLI prints as one line naming the extra.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from damcap.common.errors import DamcapError

#: importable module -> the extra that installs it (tests/test_packaging.py checks pyproject.toml)
EXTRA_OF_MODULE = {
    "mitsuba": "synth",
    "drjit": "synth",  # installed with mitsuba
    "pidng": "synth",
    "onnx": "onnx",
    "onnxruntime": "onnx",
    "onnxscript": "onnx",
}


class MissingExtraError(DamcapError):
    """An optional dependency a command needs is not installed."""


def missing_extra_message(module: str, needed_for: str) -> str:
    """The one-line message for a missing optional module.

    >>> missing_extra_message("onnxruntime", "damcap export --format onnx")
    "damcap export --format onnx needs onnxruntime, which is not installed: install damcap[onnx] (pip install 'damcap[onnx]')"
    """
    extra = EXTRA_OF_MODULE[module]
    return f"{needed_for} needs {module}, which is not installed: install damcap[{extra}] (pip install 'damcap[{extra}]')"


def require(module: str, needed_for: str) -> ModuleType:
    """Import an optional module, or raise a one-line error naming the extra that installs it.

    Args:
        module: the module's import name; a key of :data:`EXTRA_OF_MODULE`.
        needed_for: what needs it, as the user sees it (e.g. ``"damcap synth"``).

    Returns:
        the imported module.

    Raises:
        MissingExtraError: the module (or a module it imports) is not installed.
        KeyError: ``module`` is not a known optional dependency (a programming error).
    """
    if module not in EXTRA_OF_MODULE:
        raise KeyError(f"{module!r} is not an optional dependency of damcap (known: {', '.join(EXTRA_OF_MODULE)})")
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        raise MissingExtraError(missing_extra_message(module, needed_for)) from e
