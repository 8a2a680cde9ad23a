"""Which files the damcap distribution holds; every other field lives in pyproject.toml.

The repository's top-level folders are the pipeline's rooms. Installed, room ``R`` becomes ``damcap.R`` and every folder below it that has an ``__init__.py``
becomes a subpackage, found here at build time: a new subpackage cannot silently leave the wheel.
``damcap/`` holds the top-level module (``damcap.__version__`` and the public API).
Package data (the shipped predictor, the viewer's HTML template) is found by pattern at any depth
inside a room and belongs to the nearest package above it, so it survives moves between
subpackages. ``tests/test_packaging.py`` builds the wheel and checks all of this.
"""

from __future__ import annotations

from pathlib import Path

from setuptools import find_packages

ROOT = Path(__file__).resolve().parent

#: the pipeline's rooms, each installed as ``damcap.<room>`` (a new room is a decision: add it here)
ROOMS = ("common", "capture", "reconstruct", "appearance", "export", "synth", "paper", "cli")
#: top-level folders with an ``__init__.py`` that are deliberately not installed
NOT_INSTALLED = ("bench", "tests")
#: package data, as glob patterns relative to a room (any depth)
DATA_PATTERNS = ("**/*.html", "**/predictors/*.safetensors", "**/predictors/*.json")


def discover(root: Path = ROOT) -> tuple[list[str], dict[str, str], dict[str, list[str]]]:
    """The distribution's packages, their source folders and their data files.

    Returns:
        ``packages`` (``damcap``, every ``damcap.<room>`` and all their subpackages, sorted),
        ``package_dir`` (``damcap`` -> ``damcap``, ``damcap.<room>`` -> ``<room>``; subpackages
        follow their room) and ``package_data`` (package -> file paths relative to its folder).
    """
    packages = ["damcap"]
    package_dir = {"damcap": "damcap"}
    package_folder: dict[str, Path] = {}
    for room in ROOMS:
        base = f"damcap.{room}"
        package_dir[base] = room
        package_folder[base] = root / room
        for sub in find_packages(where=str(root / room)):
            package_folder[f"{base}.{sub}"] = root / room / sub.replace(".", "/")
    packages += sorted(package_folder)
    package_data: dict[str, list[str]] = {}
    for room in ROOMS:
        for pattern in DATA_PATTERNS:
            for path in sorted((root / room).glob(pattern)):
                if not path.is_file() or "__pycache__" in path.parts:
                    continue
                # the nearest package above the file owns it
                owner = max((p for p, folder in package_folder.items() if folder in path.parents),
                            key=lambda p: len(package_folder[p].parts))
                package_data.setdefault(owner, []).append(path.relative_to(package_folder[owner]).as_posix())
    return packages, package_dir, package_data


if __name__ == "__main__":  # setuptools' build backend runs this file as __main__
    from setuptools import setup

    _packages, _package_dir, _package_data = discover()
    # package_data alone says which data files ship (no MANIFEST.in, no VCS file finder)
    setup(packages=_packages, package_dir=_package_dir, package_data=_package_data, include_package_data=False)
