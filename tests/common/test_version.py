"""damcap's version string: the installed distribution's, or a marker in an uninstalled tree."""

from __future__ import annotations

import importlib.metadata

from damcap.common import version as version_module
from damcap.common.version import package_version


def test_version_is_the_installed_distributions():
    assert package_version() == importlib.metadata.version("damcap")
    assert package_version()[0].isdigit()


def test_uninstalled_tree_gives_the_marker(monkeypatch):
    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(version_module, "version", missing)
    assert package_version() == "0+unknown"
