"""cli/options.py: a command's options derived from its options dataclass (one source per option)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from dataclasses import dataclass, field
from typing import Literal

import pytest

import damcap.cli.main  # noqa: F401  (registers every command)
from damcap.cli import app as app_module
from damcap.cli.options import COMMANDS, DerivedCommand, field_docs
from damcap.common.validate import RANGE, number_kind, in_range
from damcap.common.version import package_version

from tests.conftest import assert_one_line_error
from tests.conftest import run_cli as run


@dataclass(frozen=True)
class Toy:
    """A stage's options."""

    steps: int = 5
    """optimiser steps"""
    mode: Literal["fast", "exact"] = "fast"
    """how to compute it:
    'fast' or 'exact'"""
    flag: bool = False
    """turn the extra on"""
    scale: float = 1.5
    """a scale factor"""
    limit: float | None = None
    """an optional limit (None: no limit)"""
    resolution: int = field(default=16, metadata={"cli_flag": "--res"})
    """frame size, pixels"""
    sizes: tuple[int, ...] = (1, 2)
    """channel sizes"""
    secret: int = field(default=7, metadata={"cli_exclude": True})
    """not a user option"""
    rate: float = field(default=0.5, metadata=in_range(0, 1, lo_open=True))
    """a fraction in (0, 1]"""
    count: int = field(default=3, metadata=in_range(1, 10))
    """a count in [1, 10]"""


@dataclass(frozen=True)
class Outer:
    """Options with a nested options dataclass."""

    inner: Toy = Toy(steps=3)
    """the nested stage"""
    rounds: int = 2
    """rounds of the outer loop"""


@dataclass(frozen=True)
class Renamed:
    """Options one of whose flags was renamed."""

    shade: Literal["light", "dark"] = field(default="light", metadata={"cli_old_flags": "--tone,--hue"})
    """the shade"""


@pytest.fixture()
def toy(monkeypatch):
    """``damcap toy`` and ``damcap outer``, registered for one test; the calls they received."""
    calls: list[tuple] = []

    def toy_fn(*, opts: Toy, given: frozenset[str]) -> None:
        """A toy command."""
        calls.append((opts, given))

    def outer_fn(*, opts: Outer) -> None:
        """A command with nested options."""
        calls.append((opts,))

    def renamed_fn(*, opts: Renamed, given: frozenset[str]) -> None:
        """A command with a renamed flag."""
        calls.append((opts, given))

    cmds = [DerivedCommand(toy_fn, "toy", {"opts": Toy}, {}), DerivedCommand(outer_fn, "outer", {"opts": Outer}, {}),
            DerivedCommand(renamed_fn, "renamed", {"opts": Renamed}, {})]
    monkeypatch.setattr(app_module, "COMMANDS", COMMANDS + cmds)
    return calls


def help_text(args, capsys, monkeypatch, flag="--help") -> str:
    monkeypatch.setenv("COLUMNS", "400")
    monkeypatch.setenv("TERMINAL_WIDTH", "400")
    code, out, err = run([*args, flag], capsys)
    assert code == 0, err
    return out


def test_field_docstrings_are_read_from_the_source():
    docs = field_docs(Toy)
    assert docs["steps"] == "optimiser steps"
    assert docs["mode"] == "how to compute it: 'fast' or 'exact'"  # one line
    assert docs["secret"] == "not a user option"
    assert field_docs(Toy) is docs  # cached


def test_help_has_docstrings_choices_bool_pairs_and_overridden_flags(toy, capsys, monkeypatch):
    out = help_text(["toy"], capsys, monkeypatch)
    for text in ("optimiser steps", "how to compute it: 'fast' or 'exact'", "[fast|exact]", "--[no-]flag", "--res",
                 "frame size, pixels", "[default: 5]", "[default: fast]"):
        assert text in out, text
    assert "--resolution" not in out and "--secret" not in out


def test_defaults_are_the_dataclass_defaults_and_nothing_is_given(toy, capsys):
    code, _, err = run(["toy"], capsys)
    assert code == 0, err
    assert toy == [(Toy(), frozenset())]


def test_values_parse_and_given_names_what_was_typed(toy, capsys):
    code, _, err = run(["toy", "--steps", "9", "--mode", "exact", "--flag", "--scale", "2", "--limit", "0.25", "--res", "32",
                        "--sizes", "3,4,5"], capsys)
    assert code == 0, err
    opts, given = toy[-1]
    assert opts == Toy(steps=9, mode="exact", flag=True, scale=2.0, limit=0.25, resolution=32, sizes=(3, 4, 5))
    assert given == {"steps", "mode", "flag", "scale", "limit", "resolution", "sizes"}
    code, _, err = run(["toy", "--no-flag", "--steps", "5"], capsys)
    assert code == 0, err
    assert toy[-1] == (Toy(), frozenset({"flag", "steps"}))  # typed, though equal to the default


@pytest.mark.parametrize("args, needles", [
    (["--mode", "slow"], ["--mode must be one of fast, exact, got 'slow'"]),
    (["--steps", "2.5"], ["--steps must be an integer, got 2.5"]),
    (["--scale", "nan"], ["--scale must be a finite number, got nan"]),
    (["--scale", "inf"], ["--scale must be a finite number"]),
    (["--scale", "1e300"], ["--scale must be a finite number, got 1e300"]),  # finite in float64, not in float32
    (["--limit", "-inf"], ["--limit must be a finite number"]),
    (["--scale", "big"], ["--scale must be a finite number, got big"]),
    (["--sizes", "3,x"], ["--sizes must be comma-separated integers, got '3,x'"]),
    (["--rate", "0"], ["--rate must be a finite number in (0, 1], got 0"]),
    (["--rate", "1.5"], ["--rate must be a finite number in (0, 1], got 1.5"]),
    (["--rate", "nan"], ["--rate must be a finite number in (0, 1], got nan"]),
    (["--count", "0"], ["--count must be an integer in [1, 10], got 0"]),
    (["--count", "100000000000000000000"], ["--count must be an integer in [1, 10], got 100000000000000000000"]),
    (["--resolution", "32"], ["No such option", "--resolution"]),
    (["--secret", "1"], ["No such option", "--secret"]),
])
def test_bad_values_are_one_line_errors_with_exit_2(toy, capsys, args, needles):
    code, _, err = run(["toy", *args], capsys)
    assert_one_line_error(code, err, *needles)
    assert len(err.strip().splitlines()) == 1 and not toy


def test_nested_options_dataclass_is_flattened_with_its_instance_defaults(toy, capsys, monkeypatch):
    out = help_text(["outer"], capsys, monkeypatch)
    assert "--inner-steps" in out and "--inner-no-flag" not in out and "--[no-]inner-flag" in out and "--rounds" in out
    code, _, err = run(["outer"], capsys)
    assert code == 0, err
    assert toy[-1] == (Outer(),) and toy[-1][0].inner.steps == 3
    code, _, err = run(["outer", "--inner-mode", "exact", "--rounds", "4"], capsys)
    assert code == 0, err
    assert toy[-1] == (Outer(inner=Toy(steps=3, mode="exact"), rounds=4),)


def test_an_old_flag_spelling_parses_and_stays_out_of_the_help(toy, capsys, monkeypatch):
    for flag in ("--help", "--help-all"):
        out = help_text(["renamed"], capsys, monkeypatch, flag=flag)
        assert "--shade" in out and "--tone" not in out and "--hue" not in out
    for args in (["--tone", "dark"], ["--hue", "dark"], ["--shade", "dark"]):
        code, _, err = run(["renamed", *args], capsys)
        assert code == 0, err
        assert toy[-1] == (Renamed(shade="dark"), frozenset({"shade"}))
    code, _, err = run(["renamed"], capsys)
    assert code == 0 and toy[-1] == (Renamed(), frozenset())  # the old spelling's default does not count as given
    n = len(toy)
    code, _, err = run(["renamed", "--tone", "grey"], capsys)
    assert_one_line_error(code, err, "--tone must be one of light, dark, got 'grey'")
    code, _, err = run(["renamed", "--shade", "dark", "--tone", "dark"], capsys)
    assert_one_line_error(code, err, "--tone", "--shade")
    assert len(toy) == n
    assert DerivedCommand(lambda *, opts: None, "x", {"opts": Renamed}, {}).flags() == {"shade": ("--shade",)}


def _fields(cls, prefix=""):
    """Every user-option field of an options dataclass, nested ones as 'outer.inner'."""
    out = []
    for f in dataclasses.fields(cls):
        if f.metadata.get("cli_exclude"):
            continue
        default = f.default if f.default is not dataclasses.MISSING else None
        if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]  (ReconstructOptions.geometry)
            default = f.default_factory()  # type: ignore[misc]
        if dataclasses.is_dataclass(default):
            out += _fields(type(default), f"{prefix}{f.name}.")
        else:
            out.append(f"{prefix}{f.name}")
    return out


@pytest.mark.parametrize("cmd", [c for c in COMMANDS if c.sources], ids=lambda c: c.name)
def test_every_field_of_every_command_is_reachable_from_its_help(cmd, capsys, monkeypatch):
    """Every field's flag is in ``--help-all`` (advanced ones included), a bool as ``--[no-]x``
    where its off spelling is ``--no-x``; options a command hides (old aliases) are skipped."""
    out = help_text([cmd.name], capsys, monkeypatch, flag="--help-all")
    flags = cmd.flags()
    for param, cls in cmd.classes().items():
        excluded = cmd.exclude.get(param, frozenset())
        for name in _fields(cls):
            if name in excluded:  # replaced by an option of the command's own (segment's --materials)
                assert f"--{name.replace('_', '-')}" in out, (cmd.name, name)
                continue
            assert name in flags, (cmd.name, name)
            if param in cmd.hidden:
                continue
            for spelling in flags[name]:
                on, _, off = spelling.partition("/")
                shown = [f"--[no-]{on[2:]}"] if off == f"--no-{on[2:]}" else [on, off] if off else [on]
                for flag in shown:
                    assert f"{flag} " in out or f"{flag}\n" in out or f"{flag}," in out, (cmd.name, name, flag)


def test_version_prints_damcap_and_its_version(capsys):
    code, out, _ = run(["--version"], capsys)
    assert code == 0 and out.strip() == f"damcap {package_version()}"


def test_listing_commands_imports_no_options_dataclass():
    """``damcap --help`` / ``--version`` build no command's options: torch is not imported."""
    code = ("import sys; from damcap.cli.main import main; main(['--version']); main(['--help']); "
            "print(sorted(m for m in ('torch', 'damcap.appearance.fit', 'damcap.reconstruct.pipeline') if m in sys.modules))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines()[-1] == "[]"


def test_usage_mistakes_are_one_line(capsys):
    code, _, err = run(["fit"], capsys)
    assert_one_line_error(code, err, "Missing argument", "damcap fit --help")
    code, _, err = run(["no-such-command"], capsys)
    assert_one_line_error(code, err, "No such command")


def test_shape_command_writes_a_mesh_and_refuses_bad_requests(tmp_path, capsys):
    code, out, err = run(["shape", "torus", tmp_path / "t.obj"], capsys)
    assert code == 0 and (tmp_path / "t.obj").stat().st_size > 1000, err
    code, _, err = run(["shape", "torus", tmp_path / "bad.txt"], capsys)
    assert code == 2
    assert "error:" in err and not (tmp_path / "bad.txt").exists()
    code, _, err = run(["shape", "cube", tmp_path / "c.obj"], capsys)
    assert_one_line_error(code, err, "'cube'", "torus, sphere")


def test_range_bounds_are_inclusive_where_declared_and_in_the_help(toy, capsys, monkeypatch):
    for args in (["--rate", "1"], ["--count", "1"], ["--count", "10"]):
        code, _, err = run(["toy", *args], capsys)
        assert code == 0, err
    assert "(in (0, 1])" in help_text(["toy"], capsys, monkeypatch)


@pytest.mark.parametrize("cmd", [c for c in COMMANDS if c.sources], ids=lambda c: c.name)
def test_every_numeric_option_of_every_command_declares_its_range(cmd):
    """One source for an option's allowed values: its field's metadata (the CLI checks it while
    parsing, the library's validate() with check_ranges)."""
    import typing

    def walk(cls, prefix=""):
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            default = f.default if f.default is not dataclasses.MISSING else None
            if dataclasses.is_dataclass(default):
                yield from walk(type(default), f"{prefix}{f.name}.")
            elif number_kind(hints[f.name]) is not None and not f.metadata.get("cli_exclude"):
                yield f"{prefix}{f.name}", f.metadata.get(RANGE)

    for param, cls in cmd.classes().items():
        for name, rng in walk(cls):
            if name in cmd.exclude.get(param, frozenset()):
                continue
            assert rng is not None, f"damcap {cmd.name}: {cls.__name__}.{name} declares no range (metadata=in_range(...))"
