"""The typer application and what every command shares (progress bars, output guards)."""

from __future__ import annotations

from pathlib import Path

import typer

from damcap.common.errors import DamcapError

from damcap.cli.options import COMMANDS, command  # noqa: F401  (command: the decorator every command module uses)


def _print_version(value: bool) -> None:
    if value:
        from damcap.common.version import damcap_version

        typer.echo(f"damcap {damcap_version()}")
        raise typer.Exit()


def _root(version: bool = typer.Option(False, "--version", is_eager=True, callback=_print_version,
                                       help="print damcap's version and exit")) -> None:
    """damcap: from photos to deep appearance maps."""


def build_app(selected: str | None = None) -> typer.Typer:
    """The ``damcap`` application. Only the ``selected`` command (the one being run, or whose help
    is shown) imports its options dataclasses; the others are listed by name and summary."""
    app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                      help="damcap: from photos to deep appearance maps.")
    app.callback()(_root)
    for cmd in COMMANDS:
        app.command(cmd.name)(cmd.typer_function(full=cmd.name == selected))
    return app


def progress_bar(total: int, desc: str):
    """A tqdm bar as a ``progress(step, steps, stats)`` callback (silent when not a terminal)."""
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit="step", dynamic_ncols=True, leave=False, disable=None)

    def update(step: int, steps: int, stats: dict) -> None:
        bar.n = step
        if step % 25 == 0 or step == steps:
            bar.set_postfix({k: f"{v:.4f}" for k, v in stats.items()}, refresh=False)
            bar.refresh()
        if step == steps:
            bar.close()

    return update


def refuse_input_overlap(out: Path, *inputs: Path) -> None:
    """Outputs never land on or inside an input (inputs are never modified): the file-output case
    of :func:`damcap.cli.paths.check_paths`, which every writing command uses.

    Raises:
        DamcapError: ``out`` is an input or lies inside an input folder.
    """
    from damcap.cli.paths import check_paths, file_out

    check_paths(inputs, [file_out(out)])
