"""The help is for choosing: ``damcap --help`` and every ``damcap CMD --help`` fit an 80-column
terminal, say what each option does in a line or two, and leave the advanced options to
``--help-all`` (where every field's flag is still shown; they still parse)."""

from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass, field

import pytest
import typer

import damcap.cli.main  # noqa: F401  (registers every command)
from damcap.cli import app as app_module
from damcap.cli.app import WORKFLOW, LineProgress, build_app, make_bar, summary
from damcap.cli.options import ADVANCED_PANEL, COMMANDS, DEFAULT_PANEL, first_clause, first_sentence, help_line, option_specs, plain
from damcap.common.validate import in_range

from tests.conftest import run_cli as run

ROOT_MAX_LINES = 60
COMMAND_MAX_LINES = 120
COLUMNS = 80


def help_at_80(args, capsys, monkeypatch) -> str:
    monkeypatch.setenv("COLUMNS", str(COLUMNS))
    monkeypatch.setenv("TERMINAL_WIDTH", str(COLUMNS))
    code, out, err = run(args, capsys)
    assert code == 0, err
    return out


def test_root_help_fits_and_lists_the_commands_in_workflow_order(capsys, monkeypatch):
    out = help_at_80(["--help"], capsys, monkeypatch)
    lines = out.rstrip("\n").splitlines()
    assert len(lines) <= ROOT_MAX_LINES, len(lines)
    assert max(map(len, lines)) <= COLUMNS
    named = [name for _, names in WORKFLOW for name in names]
    assert {c.name for c in COMMANDS} <= set(named), "a command missing from WORKFLOW is listed under 'Other'"
    starts = {}
    for i, line in enumerate(lines):
        m = re.match(r"│ (\S+) ", line)
        if m and m.group(1) in named:
            starts[m.group(1)] = i
    order = [name for name in named if name in {c.name for c in COMMANDS}]
    assert [starts[n] for n in order] == sorted(starts[n] for n in order), starts
    panels = [i for i, line in enumerate(lines) for p, _ in WORKFLOW if line.startswith(f"╭─ {p} ")]
    assert len(panels) == len(WORKFLOW) and panels == sorted(panels)
    for cmd in COMMANDS:  # one line each: the summary sits whole on the command's own line
        assert summary(cmd.fn.__doc__) in lines[starts[cmd.name]], cmd.name
    assert "--help-all" in out


@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: c.name)
def test_every_command_help_fits_80_columns_and_cuts_no_flag(cmd, capsys, monkeypatch):
    out = help_at_80([cmd.name, "--help"], capsys, monkeypatch)
    lines = out.rstrip("\n").splitlines()
    assert len(lines) <= COMMAND_MAX_LINES, len(lines)
    assert max(map(len, lines)) <= COLUMNS
    assert "…" not in out
    for group in cmd.specs().values():
        for s in group:
            if s.info.hidden:
                continue
            assert re.search(re.escape(_shown(s)) + r"(\s|,|$)", out, re.M), (cmd.name, _shown(s))


def _shown(s) -> str:
    """How the help spells an option's flag: ``--steps``, ``--[no-]resume``, ``--single-camera``."""
    on = s.flags[0].split("/")[0]
    return f"--[no-]{on[2:]}" if s.flags[0].endswith(f"/--no-{on[2:]}") else on


EVIDENCE = [
    re.compile(r"\b(19|20)\d\d-\d\d(-\d\d)?\b"),  # 2026-11-28
    re.compile(r"\b(Jan|Feb|Mar|Apr|May|Jun|Jul|Aug|Sep|Oct|Nov|Dec)[a-z]* (19|20)\d\d\b"),
    re.compile(r"bench/"),
    re.compile(r"\bissue \d+", re.I),
    re.compile(r":(func|attr|class|meth|mod|data):"),
    re.compile(r"``"),
]


@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: c.name)
def test_help_carries_no_dates_bench_paths_issues_or_sphinx_markup(cmd, capsys, monkeypatch):
    out = help_at_80([cmd.name, "--help-all"], capsys, monkeypatch)
    texts = [out] + [s.info.help for group in cmd.specs().values() for s in group]
    for text in texts:
        for pattern in EVIDENCE:
            assert not pattern.search(text), (cmd.name, pattern.pattern, text[:200])


def _advanced(cmd):
    """The command's advanced options (not those of a dataclass it hides whole: old aliases)."""
    return [s for p, group in cmd.specs().items() if p not in cmd.hidden
            for s in group if s.info.rich_help_panel == ADVANCED_PANEL]


@pytest.mark.parametrize("cmd", [c for c in COMMANDS if c.sources], ids=lambda c: c.name)
def test_advanced_options_are_left_to_help_all(cmd, capsys, monkeypatch):
    advanced = _advanced(cmd)
    short = help_at_80([cmd.name, "--help"], capsys, monkeypatch)
    full = help_at_80([cmd.name, "--help-all"], capsys, monkeypatch)
    for s in advanced:
        flag = re.escape(_shown(s)) + r"(\s|,|$)"
        assert not re.search(flag, short, re.M) and re.search(flag, full, re.M), s.flags
    if advanced:
        assert f"{len(advanced)} advanced option{'s' if len(advanced) > 1 else ''}: damcap {cmd.name} --help-all" in short
        assert f"╭─ {ADVANCED_PANEL} " in full and f"╭─ {ADVANCED_PANEL} " not in short
    else:
        assert "--help-all" not in short


def test_the_advanced_tags_move_the_options_that_crowded_the_help():
    """The commands with most options keep their default help short by leaving research knobs out."""
    by_name = {c.name: c for c in COMMANDS}
    for name in ("fit", "reconstruct", "train-hyper", "segment", "predict", "hdr"):
        assert len(_advanced(by_name[name])) >= 5, name


def _value_args(s):
    """Command-line words that set option ``s`` to its default (a switch: to its opposite)."""
    default = s.default
    if isinstance(default, bool):
        on, _, off = s.flags[0].partition("/")
        return [off if default else on], (not default)
    if default is None or default is ...:
        return None, None
    text = ",".join(map(str, default)) if isinstance(default, (tuple, list)) else str(default)
    return [s.flags[0].split("/")[0], text], default


@pytest.mark.parametrize("cmd", [c for c in COMMANDS if _advanced(c)], ids=lambda c: c.name)
def test_every_advanced_option_still_parses(cmd):
    click_cmd = typer.main.get_command(build_app(cmd.name)).commands[cmd.name]
    parsed = 0
    for s in _advanced(cmd):
        args, expected = _value_args(s)
        if args is None:
            continue
        ctx = click_cmd.make_context(f"damcap {cmd.name}", list(args), resilient_parsing=True)
        assert ctx.get_parameter_source(s.param).name == "COMMANDLINE", (cmd.name, args)
        value = ctx.params[s.param]
        assert value == expected or (isinstance(expected, tuple) and tuple(value) == expected), (cmd.name, args, value)
        parsed += 1
    assert parsed >= len(_advanced(cmd)) // 2


def test_first_sentence_keeps_abbreviations_decimals_and_brackets():
    assert first_sentence("Steps (e.g. 2000. More is slower). Then more.") == "Steps (e.g. 2000. More is slower)."
    assert first_sentence("Weight 0.5 vs. 1.0 i.e. half. Next.") == "Weight 0.5 vs. 1.0 i.e. half."
    assert first_sentence('the "a. b" rule. Next') == 'the "a. b" rule.'
    assert first_sentence("``x. y`` kept. Next") == "``x. y`` kept."
    assert first_sentence("no full stop at all") == "no full stop at all"


def test_help_line_is_plain_and_short():
    assert plain(":func:`~damcap.a.fit_dam` and :attr:`FitOptions.steps` of ``up``") == "fit_dam and steps of up"
    assert help_line("Exposure of the output. Measured in bench/x.md on 2026-01-01.") == "Exposure of the output"
    long = "path-tracing samples per pixel (" + "x " * 60 + ")"
    assert help_line(long) == "path-tracing samples per pixel"
    assert first_clause("short: then a long tail") == "short: then a long tail"  # no cut under 24 characters


@pytest.fixture()
def fake_terminal(monkeypatch):
    """stderr is a terminal of the width the test sets (``None``: its size cannot be read)."""
    size = {"columns": 0}

    def get_terminal_size(fd=None):
        if size["columns"] is None:
            raise OSError("Inappropriate ioctl for device")
        return os.terminal_size((size["columns"], 24))

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    monkeypatch.setattr(sys.stderr, "fileno", lambda: 2, raising=False)
    monkeypatch.setattr(app_module.os, "get_terminal_size", get_terminal_size)
    return size


def test_a_zero_width_terminal_gets_line_progress(fake_terminal):
    """``script -qc`` and some CI/IDE consoles report 0 columns; tqdm would draw nothing there."""
    fake_terminal["columns"] = 0
    assert isinstance(make_bar(5, "fit"), LineProgress)
    fake_terminal["columns"] = None
    assert isinstance(make_bar(5, "fit"), LineProgress)


def test_a_terminal_with_a_width_gets_a_tqdm_bar(fake_terminal):
    from tqdm import tqdm

    fake_terminal["columns"] = 100
    bar = make_bar(5, "fit")
    try:
        assert isinstance(bar, tqdm)
    finally:
        bar.close()


@dataclass(frozen=True)
class Inner:
    a: int = 1
    """in the group's panel"""
    b: int = field(default=2, metadata=in_range(0, 9, cli_panel="advanced"))
    """a research knob"""
    c: int = field(default=3, metadata={"cli_panel": "Elsewhere"})
    """its own panel"""


@dataclass(frozen=True)
class Outer:
    inner: Inner = field(default_factory=Inner, metadata={"cli_prefix": "", "cli_panel": "Group"})
    top: int = 4
    """a top-level field"""


def test_a_field_panel_wins_over_its_group_and_advanced_is_hidden_until_help_all():
    panels = {s.flags[0]: (s.info.rich_help_panel, s.info.hidden) for s in option_specs(Outer)}
    assert panels == {"--a": ("Group", False), "--b": (ADVANCED_PANEL, True), "--c": ("Elsewhere", False),
                      "--top": (DEFAULT_PANEL, False)}
    shown = {s.flags[0]: s.info.hidden for s in option_specs(Outer, show_all=True)}
    assert shown["--b"] is False
    hidden_group = {s.flags[0]: (s.info.rich_help_panel, s.info.hidden) for s in option_specs(Outer, hidden=True, show_all=True)}
    assert all(h for _, h in hidden_group.values()) and hidden_group["--b"][0] != ADVANCED_PANEL  # aliases stay hidden
