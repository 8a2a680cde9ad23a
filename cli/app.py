"""The typer application and what every command shares (progress bars, output guards)."""

from __future__ import annotations

from pathlib import Path

import typer

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


LOG_PROGRESS_EVERY_S = 10.0
"""where output is not a terminal (a log file, CI), a long stage prints one progress line this often"""


class LineProgress:
    """tqdm's stand-in where stderr is not a terminal: a stage that runs longer than
    :data:`LOG_PROGRESS_EVERY_S` prints one line to stdout that often (done / total, elapsed, time
    left) and one when it ends; a shorter stage prints nothing. The subset of tqdm's interface
    damcap's commands use: ``n``, ``total``, ``update``, ``refresh``, ``set_postfix``,
    ``set_postfix_str``, ``close`` and iteration.

    >>> t = iter([0.0, 4.0, 11.0, 15.0, 22.0, 25.0])
    >>> bar = LineProgress(4, "fit", clock=lambda: next(t), echo=print)
    >>> for _ in range(4):
    ...     bar.update()
    fit: 2/4 steps (50%), 11 s, about 11 s left
    fit: 4/4 steps (100%), 22 s
    >>> bar.close()
    """

    def __init__(self, total: int | None, desc: str, unit: str = "step", iterable=None, clock=None, echo=None) -> None:
        import time

        self.total, self.desc, self.unit, self.n, self._iterable = total, desc, unit, 0, iterable
        self._clock = clock or time.monotonic
        self._echo = echo or (lambda line: typer.echo(line))
        self._start = self._last = self._clock()
        self._postfix, self._printed_n = "", None

    def _line(self, now: float) -> str:
        total = f"/{self.total}" if self.total else ""
        pct = f" ({100 * self.n / self.total:.0f}%)" if self.total else ""
        elapsed = now - self._start
        left = (f", about {elapsed * (self.total - self.n) / self.n:.0f} s left"
                if self.total and 0 < self.n < self.total else "")
        return f"{self.desc}: {self.n}{total} {self.unit}s{pct}, {elapsed:.0f} s{left}" + (f" ({self._postfix})" if self._postfix else "")

    def refresh(self) -> None:
        now = self._clock()
        done = self.total is not None and self.n >= self.total
        if now - self._last >= LOG_PROGRESS_EVERY_S or (done and now - self._start >= LOG_PROGRESS_EVERY_S and self._printed_n != self.n):
            self._echo(self._line(now))
            self._last, self._printed_n = now, self.n

    def update(self, k: int = 1) -> None:
        self.n += k
        self.refresh()

    def set_postfix(self, values: dict | None = None, refresh: bool = True, **kw) -> None:
        self._postfix = ", ".join(f"{k} {v}" for k, v in {**(values or {}), **kw}.items())
        if refresh:
            self.refresh()

    def set_postfix_str(self, text: str, refresh: bool = True) -> None:
        self._postfix = text
        if refresh:
            self.refresh()

    def close(self) -> None:
        """Nothing to tear down (tqdm's interface)."""

    def __iter__(self):
        for item in self._iterable:
            yield item
            self.update()


def make_bar(total: int | None, desc: str, unit: str = "step", iterable=None, leave: bool = False):
    """A tqdm bar on a terminal, a :class:`LineProgress` elsewhere (logs get progress lines)."""
    import sys

    if sys.stderr.isatty():
        from tqdm import tqdm

        return tqdm(iterable, total=total, desc=desc, unit=unit, dynamic_ncols=True, leave=leave)
    return LineProgress(total, desc, unit, iterable)


def progress_bar(total: int, desc: str):
    """A ``progress(step, steps, stats)`` callback: a tqdm bar on a terminal, progress lines in a
    log (:func:`make_bar`)."""
    bar = make_bar(total, desc)

    def update(step: int, steps: int, stats: dict) -> None:
        bar.n = step
        if step % 25 == 0 or step == steps:
            bar.set_postfix({k: f"{v:.4f}" for k, v in stats.items()}, refresh=False)
            bar.refresh()
        if step == steps:
            bar.close()

    return update


def stage_progress():
    """A ``(stage, done, total)`` callback: one bar per stage (:func:`make_bar`: progress lines
    in a log)."""
    state: dict = {"stage": None, "bar": None}

    def update(stage: str, done: int, total: int | None) -> None:
        total = total if total and total > 0 else None  # unknown: a count without percentage
        if stage != state["stage"]:
            if state["bar"] is not None:
                state["bar"].close()
            state["stage"] = stage
            state["bar"] = make_bar(total, stage)
        bar = state["bar"]
        bar.total = total
        bar.n = done
        bar.refresh()
        if total is not None and done >= total:
            bar.close()
            state["stage"], state["bar"] = None, None

    return update


def refuse_input_overlap(out: Path, *inputs: Path) -> None:
    """Outputs never land on or inside an input (inputs are never modified): the file-output case
    of :func:`damcap.cli.paths.check_paths`, which every writing command uses.

    Raises:
        DamcapError: ``out`` is an input or lies inside an input folder.
    """
    from damcap.cli.paths import check_paths, file_out

    check_paths(inputs, [file_out(out)])
