"""The typer application and what every command shares (help layout, progress bars, output guards).

Help is for choosing: ``damcap --help`` lists the commands in workflow order, one line each
(:data:`WORKFLOW`); ``damcap CMD --help`` shows one line or two per option, in panels by what the
user decides (:mod:`damcap.cli.options`), with the advanced ones left to ``damcap CMD --help-all``.
"""

from __future__ import annotations

import inspect
import os
from pathlib import Path

import typer
from typer.core import TyperCommand

from damcap.cli.options import ADVANCED_PANEL, COMMANDS, DEFAULT_PANEL, OWN_PANEL, command, first_sentence, plain  # noqa: F401  (command: the decorator every command module uses)

WORKFLOW: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("Capture", ("hdr", "linearize", "frames")),
    ("Reconstruct", ("reconstruct", "inspect")),
    ("Appearance", ("fit", "predict", "segment", "segment-labels", "render", "evaluate")),
    ("Export", ("export", "view", "export-capture", "shape")),
    ("Synthetic data", ("closed-form", "synth", "synth-set", "synth-photos", "synth-studio")),
    ("Research", ("train-hyper", "tables")),
)
"""the root help's panels, in workflow order, and their commands in the order listed"""
OTHER_PANEL = "Other"
"""the panel of a command :data:`WORKFLOW` does not name (listed last)"""
ROOT_EPILOG = "damcap CMD --help: its options; damcap CMD --help-all: its advanced ones too."
NAME_COLUMN_MAX = 30
"""widest flag column of a command's help (a longer flag widens it; its metavar moves to a second line)"""


def _print_version(value: bool) -> None:
    if value:
        from damcap.common.version import package_version

        typer.echo(f"damcap {package_version()}")
        raise typer.Exit()


def _root(version: bool = typer.Option(False, "--version", is_eager=True, callback=_print_version,
                                       help="print damcap's version and exit"),
          verbose: bool = typer.Option(False, "--verbose", help="also show native libraries' own log lines (COLMAP's), "
                                       "before the command: damcap --verbose CMD ...")) -> None:
    """damcap: from photos to deep appearance maps."""
    if verbose:
        from damcap.common.native_stderr import VERBOSE_ENV

        os.environ[VERBOSE_ENV] = "1"


def summary(doc: str | None) -> str:
    """A command's one line in ``damcap --help``: its docstring's first sentence, plain."""
    first = inspect.cleandoc(doc or "").split("\n\n")[0]
    return plain(first_sentence(" ".join(first.split())))


def workflow_order() -> list[tuple[str, object]]:
    """``(panel, command)`` for every registered command, in :data:`WORKFLOW` order (commands it
    does not name last, under :data:`OTHER_PANEL`)."""
    rank = {name: (i, j) for i, (_, names) in enumerate(WORKFLOW) for j, name in enumerate(names)}
    panel_of = {name: panel for panel, names in WORKFLOW for name in names}
    ordered = sorted(COMMANDS, key=lambda c: rank.get(c.name, (len(WORKFLOW), 0)))
    return [(panel_of.get(c.name, OTHER_PANEL), c) for c in ordered]


def build_app(selected: str | None = None, show_all: bool = False) -> typer.Typer:
    """The ``damcap`` application. Only the ``selected`` command (the one being run, or whose help
    is shown) imports its options dataclasses; the others are listed by name and summary.
    ``show_all``: the selected command's help shows its advanced options too (``--help-all``)."""
    from rich.markup import escape

    app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                      help="damcap: from photos to deep appearance maps.", epilog=escape(ROOT_EPILOG))
    app.callback()(_root)
    for panel, cmd in workflow_order():
        app.command(cmd.name, cls=HelpCommand, rich_help_panel=panel, short_help=escape(summary(cmd.fn.__doc__)))(
            cmd.typer_function(full=cmd.name == selected, show_all=show_all))
    return app


# --------------------------------------------------------------------------------------------
# A command's help: one line or two per option, in panels
# --------------------------------------------------------------------------------------------


class HelpCommand(TyperCommand):
    """A damcap command: its ``--help`` is :func:`print_command_help`'s layout."""

    def format_help(self, ctx, formatter) -> None:  # noqa: ANN001 (click's signature)
        print_command_help(self, ctx)


def _metavar(param, ctx) -> str:
    """``PATH``, ``INTEGER``, ``[train|all]``: what follows a flag (nothing for a switch)."""
    if getattr(param, "is_flag", False):
        return ""
    if param.metavar:
        return param.metavar
    shown = param.display_type_rich(ctx) if hasattr(param, "display_type_rich") else param.type.name
    shown = str(shown or "")
    shown = shown[1:-1].upper() if shown.startswith("<") and shown.endswith(">") else shown.upper()
    return {"STR": "TEXT", "INT": "INTEGER"}.get(shown, shown)


def _names(param, ctx) -> tuple[list[str], str]:
    """The option's spellings (one entry per line it may take) and its metavar."""
    if param.param_type_name == "argument":
        return [param.metavar or param.name.upper()], ""
    longs = [o for o in param.opts if o.startswith("--")]
    shorts = [o for o in param.opts if not o.startswith("--")]
    names = [", ".join(longs + shorts)]
    off = list(param.secondary_opts)
    if off:
        if len(longs) == 1 and off == ["--no-" + longs[0][2:]]:
            names = ["--[no-]" + longs[0][2:] + "".join(", " + o for o in shorts)]
        else:
            names = [names[0] + " /", ", ".join(off)]
    return names, _metavar(param, ctx)


def _default_text(param, ctx) -> str:
    if param.required or param.param_type_name == "argument" or getattr(param, "show_default", True) is False:
        return ""
    if isinstance(param.show_default, str):
        return param.show_default
    default = param.get_default(ctx, call=False) if hasattr(param, "get_default") else param.default
    if default is None or callable(default):
        return ""
    if getattr(param, "is_flag", False) and param.secondary_opts:
        return (param.opts if default else param.secondary_opts)[0]
    if getattr(param, "is_flag", False):
        return ""
    if isinstance(default, (list, tuple)):
        return ",".join(map(str, default))
    return str(default)


def _usage(cmd, ctx) -> str:
    """``Usage: damcap fit [OPTIONS] CAPTURE``."""
    words = [f"Usage: {ctx.command_path}", "[OPTIONS]"]
    for param in cmd.get_params(ctx):
        if param.param_type_name == "argument":
            word = (param.metavar or param.name.upper()) + ("..." if param.nargs != 1 else "")
            words.append(word if param.required else f"[{word}]")
    return " ".join(words)


def print_command_help(cmd, ctx) -> None:
    """``damcap CMD --help``: usage, the command's docstring, then its visible options in panels
    (:data:`~damcap.cli.options.OWN_PANEL`, then :data:`~damcap.cli.options.DEFAULT_PANEL`, the
    nested groups' panels, :data:`~damcap.cli.options.ADVANCED_PANEL` last), each one flag column and one help column, and how many advanced options
    ``--help-all`` adds. Nothing is cut: the flag column is as wide as the longest flag."""
    from rich import box
    from rich.console import Console
    from rich.padding import Padding
    from rich.panel import Panel
    from rich.table import Table
    from rich.text import Text

    width = os.environ.get("TERMINAL_WIDTH")
    console = Console(highlight=False, width=int(width) if width and width.isdigit() else None)
    console.print(Padding(Text(_usage(cmd, ctx), style="bold"), 1))
    doc = inspect.cleandoc(cmd.help or "").partition("\f")[0]
    paragraphs = [" ".join(p.split()) for p in doc.split("\n\n") if p.strip()]
    if paragraphs:
        text = Text(paragraphs[0])
        for p in paragraphs[1:]:
            text.append("\n\n" + p, style="dim")
        console.print(Padding(text, (0, 1, 1, 1)))

    panels: dict[str, list] = {}
    advanced = 0
    for param in cmd.get_params(ctx):
        panel = OWN_PANEL if param.param_type_name == "argument" or param.name == "help" else (
            getattr(param, "rich_help_panel", None) or OWN_PANEL)
        if getattr(param, "hidden", False):
            advanced += panel == ADVANCED_PANEL
            continue
        panels.setdefault(panel, []).append(param)
    order = [OWN_PANEL, DEFAULT_PANEL] + [p for p in panels if p not in (OWN_PANEL, DEFAULT_PANEL, ADVANCED_PANEL)] + [ADVANCED_PANEL]
    rows = {p: [(param, *_names(param, ctx)) for param in panels[p]] for p in order if p in panels}
    cells = [(names, mv) for group in rows.values() for _, names, mv in group]
    longest_token = max((len(n) for names, mv in cells for n in names + [mv]), default=0)
    widest = max((len(names[-1] + " " + mv) if mv else max(map(len, names)) for names, mv in cells), default=0)
    name_width = max(min(widest, NAME_COLUMN_MAX), longest_token)
    for title, group in rows.items():
        table = Table(show_header=False, box=None, padding=(0, 1), pad_edge=False, expand=True)
        table.add_column(width=1, no_wrap=True, style="red")
        table.add_column(width=name_width, no_wrap=True, style="bold cyan")
        table.add_column(ratio=1)
        for param, names, mv in group:
            lines = list(names)
            if mv:
                lines[-1] = lines[-1] + " " + mv if len(lines[-1]) + 1 + len(mv) <= name_width else lines[-1]
                if not lines[-1].endswith(mv):
                    lines.append("  " + mv if len(mv) + 2 <= name_width else mv)
            name = Text()
            for i, line in enumerate(lines):
                if i:
                    name.append("\n")
                flag, _, rest = line.partition(" ") if mv and line.endswith(mv) and line != mv else (line, "", "")
                name.append(flag)
                if rest:
                    name.append(" " + rest, style="yellow")
            help_text = Text(" ".join((getattr(param, "help", None) or "").split()))
            default = _default_text(param, ctx)
            if default:
                help_text.append(f" [default: {default}]", style="dim")
            table.add_row("*" if param.required else "", name, help_text)
        console.print(Panel(table, title=title[:1].upper() + title[1:], title_align="left", border_style="dim", box=box.ROUNDED))
    epilog = []
    if advanced:
        epilog.append(f"{advanced} advanced option{'s' if advanced != 1 else ''}: {ctx.command_path} --help-all")
    if cmd.epilog:
        epilog.append(" ".join(cmd.epilog.split()))
    if epilog:
        console.print(Padding(Text("\n".join(epilog)), (0, 1)))


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


def _stderr_columns() -> int:
    """The width stderr's terminal reports, 0 where it reports none (``script -qc``, some CI and
    IDE consoles report 0 columns; tqdm's bar then draws nothing)."""
    import sys

    try:
        return os.get_terminal_size(sys.stderr.fileno()).columns
    except (AttributeError, OSError, ValueError):  # no fileno, not a terminal, closed
        return 0


def make_bar(total: int | None, desc: str, unit: str = "step", iterable=None, leave: bool = False):
    """A tqdm bar on a terminal that reports its width, a :class:`LineProgress` elsewhere (logs,
    and terminals of zero or unknown width, get progress lines)."""
    import sys

    if sys.stderr.isatty() and _stderr_columns() > 0:
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
