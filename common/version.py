"""damcap's package version (the installed distribution's), as output records carry it.

Not the capture format's version: that is the integer ``"damcap_version"`` in ``transforms.json``
(:data:`damcap.common.capture_folder.FORMAT_VERSION`). Output records (``.dam`` provenance,
checkpoints, the JSON of ``fit``, ``render``, ``evaluate``, ...) carry this string as
``"damcap_package_version"`` (records written before it had its own key say ``"damcap_version"``).
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version


def package_version() -> str:
    """The installed damcap distribution's version, e.g. ``"0.1.0"``; ``"0+unknown"`` in a source
    tree that was never installed."""
    try:
        return version("damcap")
    except PackageNotFoundError:  # running from a source tree without installing
        return "0+unknown"
