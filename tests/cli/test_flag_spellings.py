"""Every flag spelling every command accepted before the options were regrouped (panels, advanced
options out of --help, nested options dataclasses, the paper's tables moved to ``damcap tables``,
``--frame`` renamed ``--orientation``) still parses: users' scripts and the Makefile use them.
The lists (flag_spellings.json) are frozen from the commands as they were; a flag may move to a
help panel or be hidden, never disappear."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer

import damcap.cli.main  # noqa: F401  (registers every command)
from damcap.cli.app import build_app

OLD_FLAGS: dict[str, list[str]] = json.loads((Path(__file__).with_name("flag_spellings.json")).read_text())
"""every command's flag spellings as they were before the help was regrouped, frozen from the
commands themselves (tables, new since, has none to keep)"""


def _flags(name: str) -> set[str]:
    click_cmd = typer.main.get_command(build_app(name)).commands[name]  # type: ignore[attr-defined]
    return {f for p in click_cmd.params for f in (*p.opts, *p.secondary_opts) if f.startswith("-")}


@pytest.mark.parametrize("name", sorted(OLD_FLAGS))
def test_every_old_flag_spelling_still_parses(name):
    old = OLD_FLAGS[name]
    missing = sorted(set(old) - _flags(name))
    assert not missing, f"damcap {name} lost flag(s): {missing}"


def test_train_hyper_still_parses_frame_the_old_spelling_of_orientation(tmp_path, capsys, monkeypatch):
    """``--frame world|light`` named the predictor's orientation before it had its own word;
    bench/train_predictor.sh's recipes and the shipped v10's recorded command use it."""
    from damcap.appearance.hyper import train as train_module
    from damcap.cli.main import main
    from damcap.common.errors import DamcapError

    assert {"--orientation", "--frame"} <= _flags("train-hyper")
    seen = []

    def stop(paths, opts, **kw):
        seen.append(opts.orientation)
        raise DamcapError("stopped by the test")

    monkeypatch.setattr(train_module, "train_hyper", stop)
    monkeypatch.chdir(tmp_path)
    for flag in ("--frame", "--orientation"):
        assert main(["train-hyper", "-o", "p.safetensors", "--procedural", "1", flag, "light"]) != 0
    assert seen == ["light", "light"]
    assert "stopped by the test" in capsys.readouterr().err
    monkeypatch.setenv("COLUMNS", "200")
    assert main(["train-hyper", "--help-all"]) == 0
    out = capsys.readouterr().out
    assert "--orientation" in out and "--frame" not in out
