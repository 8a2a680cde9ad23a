"""The distribution: every subpackage and data file reaches the wheel, the metadata (license,
extras) is consistent, ``import damcap`` gives the version and the public API, and commands whose
optional dependency is missing fail with one line naming the extra. Also: the capture-folder
contract in docs/ states the format versions the code writes."""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import textwrap
import zipfile
from email.parser import Parser
from pathlib import Path
from types import ModuleType

import pytest

REPO = Path(__file__).resolve().parents[1]
#: data files that must ship (globs relative to the repository root)
DATA_GLOBS = ("appearance/**/predictors/*.safetensors", "appearance/**/predictors/*.json", "export/*.html")


def _setup_module() -> ModuleType:
    spec = importlib.util.spec_from_file_location("damcap_setup", REPO / "setup.py")  # not __main__: setup() is not run
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


SETUP = _setup_module()


def _package_folders() -> dict[str, Path]:
    """Every folder with an ``__init__.py`` under a room, by its installed name (found independently of setup.py)."""
    found = {}
    for room in SETUP.ROOMS:
        for folder, dirs, files in os.walk(REPO / room):
            dirs[:] = [d for d in dirs if d != "__pycache__" and not d.startswith(".")]
            if "__init__.py" in files:
                rel = Path(folder).relative_to(REPO)
                found[".".join(("damcap", *rel.parts))] = rel
    return found


def _installed_path(source: Path) -> str:
    """Where a repository file lands in the wheel: ``appearance/x.py`` -> ``damcap/appearance/x.py``."""
    return f"damcap/{source.as_posix()}"


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> zipfile.ZipFile:
    """The wheel built from a copy of the working tree (offline, this venv's setuptools)."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    src.mkdir()
    for name in ("pyproject.toml", "setup.py", "README.md", "LICENSE"):
        shutil.copy2(REPO / name, src / name)
    for folder in ("damcap", *SETUP.ROOMS):
        shutil.copytree(REPO / folder, src / folder, ignore=ignore)
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "--no-index",
                           "-w", str(tmp / "dist"), str(src)], capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.fail(f"building the wheel failed (exit {proc.returncode}; setuptools >= 77 needed, make venv installs it):\n"
                    f"{proc.stdout[-3000:]}{proc.stderr[-3000:]}")
    (path,) = (tmp / "dist").glob("damcap-*.whl")
    with zipfile.ZipFile(path) as z:
        yield z


def _metadata(wheel: zipfile.ZipFile):
    (name,) = [n for n in wheel.namelist() if n.endswith(".dist-info/METADATA")]
    return Parser().parsestr(wheel.read(name).decode())


def test_discovery_finds_every_package_folder() -> None:
    packages, package_dir, _ = SETUP.discover()
    missing = sorted(set(_package_folders()) - set(packages))
    assert not missing, (f"folders with an __init__.py that setup.py does not install: {missing} "
                         "(a folder between them and their room lacks an __init__.py?)")
    assert "damcap" in packages and package_dir["damcap"] == "damcap"
    assert all(package_dir[f"damcap.{room}"] == room for room in SETUP.ROOMS)


def test_top_level_packages_are_rooms() -> None:
    """A new top-level package folder is either a room (installed) or declared as not installed."""
    top = {p.parent.name for p in REPO.glob("*/__init__.py")}
    unknown = sorted(top - set(SETUP.ROOMS) - set(SETUP.NOT_INSTALLED) - {"damcap"})
    assert not unknown, f"top-level packages neither in setup.py's ROOMS nor in NOT_INSTALLED: {unknown}"


def test_wheel_holds_every_module(wheel: zipfile.ZipFile) -> None:
    names = set(wheel.namelist())
    assert "damcap/__init__.py" in names
    expected = []
    for rel in _package_folders().values():
        expected += [_installed_path(p.relative_to(REPO)) for p in (REPO / rel).glob("*.py")]
    assert len(expected) > 50
    missing = sorted(set(expected) - names)
    assert not missing, f"modules missing from the wheel: {missing}"
    assert not any(n.startswith(("damcap/tests/", "damcap/bench/", "tests/", "bench/")) for n in names)


def test_wheel_holds_the_data_files(wheel: zipfile.ZipFile) -> None:
    names = set(wheel.namelist())
    for pattern in DATA_GLOBS:
        files = [p for p in REPO.glob(pattern) if p.is_file()]
        assert files, f"no {pattern} in the repository (the shipped predictor and the viewer template must exist)"
        missing = [_installed_path(p.relative_to(REPO)) for p in files if _installed_path(p.relative_to(REPO)) not in names]
        assert not missing, f"{pattern}: missing from the wheel: {missing}"


def test_wheel_metadata(wheel: zipfile.ZipFile) -> None:
    meta = _metadata(wheel)
    assert meta["License-Expression"] == "MIT"
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in wheel.namelist())
    assert "MIT License" in (REPO / "LICENSE").read_text()
    assert set(meta.get_all("Provides-Extra")) >= {"synth", "onnx", "all", "test"}
    required = [r for r in meta.get_all("Requires-Dist") if "extra ==" not in r]
    assert "torch" in {re.split(r"[<>=!~;\[ ]", r)[0] for r in required}


def test_extras_install_the_optional_modules(wheel: zipfile.ZipFile) -> None:
    """Every optional module is installed by the extra the error message names, and by no core requirement."""
    from damcap.common.optional import EXTRA_OF_MODULE

    by_extra: dict[str, set[str]] = {}
    core = set()
    for r in _metadata(wheel).get_all("Requires-Dist"):
        name = re.split(r"[<>=!~;\[ ]", r)[0].lower()
        m = re.search(r'extra == "([^"]+)"', r)
        (by_extra.setdefault(m.group(1), set()) if m else core).add(name)
    for module, extra in EXTRA_OF_MODULE.items():
        if module == "drjit":  # a dependency of mitsuba
            continue
        assert module in by_extra.get(extra, set()), f"damcap[{extra}] does not install {module}"
        assert module not in core, f"{module} is optional (damcap[{extra}]) but also a core requirement"
    requires = _metadata(wheel).get_all("Requires-Dist")
    assert 'damcap[onnx,synth]; extra == "all"' in requires and 'damcap[all]; extra == "test"' in requires


def test_public_api() -> None:
    import damcap

    assert damcap.__version__ == importlib.metadata.version("damcap")
    for name in damcap.__all__:
        assert getattr(damcap, name) is not None, name
    assert damcap.load_dam.__module__ == "damcap.appearance.dam_file"
    assert set(damcap.__all__) <= set(dir(damcap))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        damcap.nope  # noqa: B018


def test_import_damcap_is_cheap() -> None:
    """The API is imported on first use: importing damcap or one stage loads no other stage."""
    code = "import sys, damcap, damcap.common.errors; print(sorted(m for m in sys.modules if m in ('torch', 'damcap.appearance')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO.parent)
    assert out.stdout.strip() == "[]"


def test_commands_without_their_extra_fail_in_one_line(tmp_path: Path) -> None:
    """With the optional modules hidden, the CLI still imports; synth and ONNX export exit 2 naming the extra."""
    code = textwrap.dedent(f"""
        import sys
        sys.modules.update(dict.fromkeys(("mitsuba", "drjit", "onnx", "onnxruntime", "onnxscript", "pidng")))
        from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
        from damcap.appearance.dam_file import save_dam
        from damcap.cli.main import main
        save_dam({str(tmp_path / 'm.dam')!r}, DeepAppearanceMap(DamArchitecture()), colorspace="lin_rec709", made_by="fit")
        print("onnx", main(["export", {str(tmp_path / 'm.dam')!r}, "--format", "onnx", "-o", {str(tmp_path / 'm.onnx')!r}]))
        print("synth", main(["synth", {str(tmp_path / 'synth')!r}, "--views", "4", "--res", "16", "--train-views", "2"]))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split() == ["onnx", "2", "synth", "2"], proc.stdout + proc.stderr[-3000:]
    errors = proc.stderr.strip().splitlines()
    assert len(errors) == 2, proc.stderr
    assert errors[0].startswith("error: damcap export --format onnx needs onnx") and "install damcap[onnx]" in errors[0]
    assert errors[1].startswith("error: damcap synth needs mitsuba") and "install damcap[synth]" in errors[1]
    assert not (tmp_path / "m.onnx").exists() and not (tmp_path / "synth").exists()


def test_contract_doc_states_the_versions_the_code_writes() -> None:
    """docs/capture-format.md (the contract, in the repository) names the format versions in the code."""
    from damcap.appearance.dam_file import DAM_FORMAT_VERSION
    from damcap.common.capture_folder import FORMAT_VERSION

    doc = (REPO / "docs" / "capture-format.md").read_text(encoding="utf-8")
    assert f'capture folder **{FORMAT_VERSION}** (`"damcap_version": {FORMAT_VERSION}`' in doc
    assert f'`.dam` file **{DAM_FORMAT_VERSION}** (`"format_version": {DAM_FORMAT_VERSION}`' in doc
