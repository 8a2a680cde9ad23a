"""damcap's version string (from the installed distribution)."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version


def damcap_version() -> str:
    try:
        return version("damcap")
    except PackageNotFoundError:  # running from a source tree without installing
        return "0+unknown"
