"""A command's options derived from its stage's options dataclass: one source for every option.

style.md: "One source per option: the stage's dataclass, with a docstring under each field; the
CLI is derived from it". Each field of the dataclass becomes one typer option:

- the flag is ``--kebab-name`` (``batch_size`` -> ``--batch-size``); a nested options dataclass
  (``TableOptions.fit``) contributes its fields as ``--fit-steps``, ...;
- the help is the first sentence of the field's attribute docstring (the string literal under
  it, read from the class source with :mod:`ast`; cached), in plain text (Sphinx roles and
  double backticks removed): what the option does; the rest of the docstring (why, evidence)
  stays in the source. The default is the dataclass's own (never restated here);
- ``Literal[...]`` -> those choices; any other value ends in one line,
  ``--init-colour must be one of pixel, darkest-view, got 'brightest'`` (exit 2);
- ``bool`` -> ``--x/--no-x``; ``X | None`` -> optional, default None;
- ``int`` / ``float`` are parsed here so that a bad value is one line naming the flag; a float
  must be finite (NaN passes every ``x <= 1`` check, so it is refused before any check runs);
- ``tuple[int, ...]`` / ``list[float]`` -> comma-separated values (``--channels 16,32,64``).

Per-field metadata (plain keys, so the library never imports ``cli``):

- ``cli_flag``: the flag where an existing spelling differs from the field name
  (``{"cli_flag": "--res"}``; for a bool ``"--single-camera/--camera-per-photo"``);
- ``cli_old_flags``: a field's earlier spelling(s), comma-separated (``"--frame"``): they still
  parse, for users' scripts, and stay out of ``--help``; giving both spellings is an error;
- ``cli_exclude``: True for a field that is not a user option;
- ``cli_parse``: ``str -> value`` for a value with its own syntax (raises DamcapError);
- ``cli_what``: what a rejected choice is called (``"DAM input encoding"`` -> ``unknown DAM
  input encoding 'polar'; ...``) where a library message already names it so;
- on a nested options dataclass field, ``cli_prefix``: the flag prefix of its fields instead of
  the field's name (``""``: ``ReconstructOptions.geometry.voxels`` is ``--voxels``; ``"dense"``:
  ``--dense-...``), and ``cli_panel``: the help panel of its fields (``"Geometry"``);
- ``cli_panel`` on any other field: its help panel, which wins over its group's. Fields without
  one sit in their group's panel, or in "Quality and speed"; ``"advanced"`` puts a rarely
  needed research knob in the "Advanced" panel, which ``--help`` leaves out (the option still
  parses) and ``damcap CMD --help-all`` shows.

A command's own parameters (positional paths, ``-o``, ``--model``) sit in "Inputs and outputs".

"Given by the user": a command that must know whether an option was typed (``fit
--target-dssim`` chooses width and depth itself and refuses ``--width``) declares a keyword
parameter ``given``; it receives the names of the dataclass fields set on the command line
(click's parameter source), so defaults are never ``None`` stand-ins for "not given".

Commands are built lazily: a command's dataclass (and the torch it may import) is imported only
when that command runs or shows its help (``damcap --help`` and ``damcap --version`` stay fast).
"""

from __future__ import annotations

import ast
import copy
import dataclasses
import functools
import importlib
import inspect
import re
import textwrap
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal, Union, get_args, get_origin

import typer

from damcap.common.errors import DamcapError
from damcap.common.validate import RANGE, Range, check_value

CLI_FLAG = "cli_flag"
CLI_EXCLUDE = "cli_exclude"
CLI_OLD_FLAGS = "cli_old_flags"
CLI_PARSE = "cli_parse"
CLI_WHAT = "cli_what"
CLI_PREFIX = "cli_prefix"
CLI_PANEL = "cli_panel"
ADVANCED = "advanced"
"""the ``cli_panel`` of a rarely needed option: hidden from ``--help``, shown by ``--help-all``"""
ADVANCED_PANEL = "Advanced"
DEFAULT_PANEL = "Quality and speed"
"""the panel of a derived option whose field and group name none"""
OWN_PANEL = "Inputs and outputs"
"""the panel of a command's own parameters"""
GIVEN = "given"
"""name of the keyword parameter that receives the fields given on the command line"""


# --------------------------------------------------------------------------------------------
# Reading a dataclass
# --------------------------------------------------------------------------------------------


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings of a dataclass and its dataclass bases: ``{field: one-line text}``.

    The docstring of a field is the string literal right under its annotated assignment.
    """
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for a, b in zip(body, body[1:]):
            if (isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name) and isinstance(b, ast.Expr)
                    and isinstance(b.value, ast.Constant) and isinstance(b.value.value, str)):
                docs[a.target.id] = " ".join(inspect.cleandoc(b.value.value).split())
    return docs


_ABBREVIATIONS = ("e.g.", "i.e.", "vs.", "etc.", "cf.", "approx.", "resp.", "Eq.", "Eqs.", "Fig.", "al.", "no.", "Sec.")
_OPENING, _CLOSING = "([{", ")]}"


def first_sentence(text: str) -> str:
    """The first sentence of ``text``: up to the first ``.``, ``!`` or ``?`` that is followed by
    a space (or ends the text) outside parentheses, brackets and quotes, and that does not end an
    abbreviation (``e.g.``, ``vs.``); decimals (``0.5``) never end a sentence.

    >>> first_sentence("Steps of Adam (e.g. 2000. More is slower). Figures follow.")
    'Steps of Adam (e.g. 2000. More is slower).'
    >>> first_sentence("Weight 0.5 vs. 1.0 of ``a. b``; kept")
    'Weight 0.5 vs. 1.0 of ``a. b``; kept'
    """
    depth, quote, i = 0, None, 0
    while i < len(text):
        c = text[i]
        if quote:
            if text.startswith(quote, i):
                i += len(quote) - 1
                quote = None
        elif text.startswith("``", i):
            quote = "``"
            i += 1
        elif c in '"`':
            quote = c
        elif c in _OPENING:
            depth += 1
        elif c in _CLOSING:
            depth = max(0, depth - 1)
        elif c in ".!?" and depth == 0 and (i + 1 == len(text) or text[i + 1].isspace()):
            word = text[:i + 1].split()[-1] if text[:i + 1].split() else ""
            if not any(word.endswith(a) and (len(word) == len(a) or not word[-len(a) - 1].isalnum())
                       for a in _ABBREVIATIONS):
                return text[:i + 1]
        i += 1
    return text


_ROLE = re.compile(r":(?:[a-z]+:)?[a-z]+:`~?([^`<]*?)(?:\s*<[^>]*>)?`")


def plain(text: str) -> str:
    """Sphinx markup as plain text: ``:func:`~a.b.f``` -> ``f``, double backticks dropped.

    >>> plain(":attr:`~damcap.x.FitOptions.steps` of ``up`` and `a`")
    'steps of up and a'
    """
    text = _ROLE.sub(lambda m: m.group(1).rsplit(".", 1)[-1], text)
    return text.replace("``", "").replace("`", "")


MAX_HELP_CHARS = 90
"""a first sentence longer than this is shown up to its first clause (two lines of help at 80 columns)"""


def first_clause(text: str, shortest: int = 24) -> str:
    """``text`` up to its first ``" ("``, ``"; "`` or ``": "`` outside parentheses and quotes
    that leaves at least ``shortest`` characters (``text`` itself where there is none).

    >>> first_clause("path-tracing samples per pixel (noise floor: 512 under maps)")
    'path-tracing samples per pixel'
    """
    depth, quote = 0, None
    for i, c in enumerate(text):
        if quote:
            quote = None if c == quote else quote
        elif c in "'\"" and (i == 0 or not text[i - 1].isalnum()):
            quote = c
        elif c in _OPENING:
            if c == "(" and depth == 0 and i >= shortest and text[i - 1] == " ":
                return text[:i - 1]
            depth += 1
        elif c in _CLOSING:
            depth = max(0, depth - 1)
        elif c in ";:" and depth == 0 and i >= shortest and text[i + 1:i + 2] == " ":
            return text[:i]
    return text


def help_line(doc: str) -> str:
    """A field's help line: its docstring's first sentence in plain text, without its full stop
    (help lines are phrases: ``optimiser steps (Adam) (>= 1)``); a sentence longer than
    :data:`MAX_HELP_CHARS` up to its first clause (the rest stays in the docstring)."""
    line = plain(first_sentence(doc)).strip()
    line = line[:-1] if line.endswith(".") and not line.endswith("..") else line
    return first_clause(line) if len(line) > MAX_HELP_CHARS else line


def kebab(name: str) -> str:
    return name.replace("_", "-")


def _strip_optional(tp: Any) -> tuple[Any, bool]:
    """(X, True) for ``X | None`` / ``Optional[X]``, else (tp, False)."""
    if get_origin(tp) in (Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) < len(get_args(tp)) and len(args) == 1:
            return args[0], True
    return tp, False


def _default_of(f: dataclasses.Field, instance: Any) -> Any:
    if instance is not None:
        return getattr(instance, f.name)
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    return ...  # required


# --------------------------------------------------------------------------------------------
# Parsers: every bad value is one line naming the flag (DamcapError -> "error: ...", exit 2)
# --------------------------------------------------------------------------------------------


def parse_int(flag: str, rng: "Range | tuple[int, int] | None" = None) -> Callable[[Any], Any]:
    """A parser of an integer option, refusing values outside ``rng`` (a :class:`Range` or an
    inclusive ``(lo, hi)``) with the text as typed."""
    if isinstance(rng, tuple):
        rng = Range(*rng)

    def parse(text: Any) -> Any:
        if not isinstance(text, str):
            return text
        try:
            value: Any = int(text.strip())
        except ValueError:
            value = text  # check_value names it as not an integer, with the allowed values
        return check_value(value, rng, integer=True, what=flag, shown=text)
    return parse


def parse_float(flag: str, rng: "Range | None" = None) -> Callable[[Any], Any]:
    """A parser of a number option: finite in float32 (NaN passes every ``x <= 1`` check, so it
    is refused before any check runs) and inside ``rng``."""
    def parse(text: Any) -> Any:
        if not isinstance(text, str):
            return text
        try:
            value: Any = float(text)
        except ValueError:
            value = text
        return float(check_value(value, rng, integer=False, what=flag, shown=text))
    return parse


def parse_choice(flag: str, choices: tuple, what: str | None = None) -> Callable[[Any], Any]:
    by_text = {str(c): c for c in choices}

    def parse(text: Any) -> Any:
        if not isinstance(text, str) or text in by_text:
            return by_text.get(text, text) if isinstance(text, str) else text
        listed = ", ".join(by_text)
        if what:
            raise DamcapError(f"unknown {what} {text!r}; use one of {listed} ({flag})")
        raise DamcapError(f"{flag} must be one of {listed}, got {text!r}")
    return parse


def parse_list(flag: str, item: type, container: type, rng: "Range | None" = None) -> Callable[[Any], Any]:
    one = parse_float(flag, rng) if item is float else parse_int(flag, rng) if item is int else (lambda s: s)
    kind = {int: "integers", float: "numbers"}.get(item, "values")
    each = f" each{rng.phrase()}" if rng is not None else ""

    def parse(text: Any) -> Any:
        if not isinstance(text, str):
            return text
        try:
            return container(one(s.strip()) for s in text.split(","))
        except DamcapError:
            raise DamcapError(f"{flag} must be comma-separated {kind}{each}, got {text!r}") from None
    return parse


# --------------------------------------------------------------------------------------------
# Fields -> options
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class OptionSpec:
    """One command-line option derived from one dataclass field."""

    param: str
    """the Python parameter name (nested fields: ``fit__steps``)"""
    path: tuple[str, ...]
    """the field's path from the top dataclass (``("fit", "steps")``)"""
    flags: tuple[str, ...]
    """the flag spelling(s), e.g. ``("--batch-size",)`` or ``("--video/--no-video",)``"""
    default: Any
    annotation: Any
    """the annotation typer sees"""
    info: Any
    """the ``typer.Option(...)`` default"""
    old: bool = False
    """an earlier spelling of the field's option (``cli_old_flags``): parsed, hidden from the help"""


def option_specs(cls: type, *, exclude: frozenset[str] = frozenset(), prefix: tuple[str, ...] = (),
                 instance: Any = None, panel: str | None = None, flag_prefix: tuple[str, ...] | None = None,
                 hidden: bool = False, show_all: bool = False) -> list[OptionSpec]:
    """One :class:`OptionSpec` per field of the options dataclass ``cls`` (nested dataclasses
    flattened with their field name, or their ``cli_prefix``, as flag prefix); ``exclude`` lists
    field names to leave out; ``hidden`` keeps every option out of ``--help`` (still parsed);
    ``show_all`` shows the advanced ones (``--help-all``), which are otherwise hidden."""
    flag_prefix = prefix if flag_prefix is None else flag_prefix
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    specs: list[OptionSpec] = []
    for f in dataclasses.fields(cls):
        if f.name in exclude or f.metadata.get(CLI_EXCLUDE) or not f.init:
            continue
        path = prefix + (f.name,)
        default = _default_of(f, instance)
        tp, optional = _strip_optional(hints[f.name])
        if dataclasses.is_dataclass(tp):
            sub_prefix = f.metadata.get(CLI_PREFIX)
            sub_flags = flag_prefix + ((f.name,) if sub_prefix is None else (sub_prefix,) if sub_prefix else ())
            specs += option_specs(tp, prefix=path, instance=default, flag_prefix=sub_flags, hidden=hidden,
                                  show_all=show_all, panel=f.metadata.get(CLI_PANEL) or panel or f"{kebab(f.name)} options")
            continue
        flag = f.metadata.get(CLI_FLAG) or "--" + "-".join(kebab(p) for p in flag_prefix + (f.name,))
        first = flag.split(",")[0].split("/")[0]
        help_text = help_line(docs.get(f.name, ""))
        if f.metadata.get(RANGE) is not None:
            help_text += _range_note(f.metadata[RANGE])
        field_panel = f.metadata.get(CLI_PANEL) or panel or DEFAULT_PANEL
        advanced = field_panel.lower() == ADVANCED
        kw: dict[str, Any] = {"help": help_text, "rich_help_panel": ADVANCED_PANEL if advanced and not hidden else field_panel,
                              "hidden": hidden or (advanced and not show_all)}
        parse = f.metadata.get(CLI_PARSE)
        origin = get_origin(tp)
        if parse is not None:
            annotation: Any = str
            kw.update(parser=_passthrough(parse), metavar="TEXT")
        elif origin is Literal:
            choices = get_args(tp)
            annotation = str
            metavar = "[" + "|".join(map(str, choices)) + "]"
            if len(metavar) > MAX_CHOICE_METAVAR:  # a long list goes into the help, the flag column stays narrow
                metavar = "CHOICE"
                kw["help"] += f" (one of: {', '.join(map(str, choices))})"
            kw.update(parser=parse_choice(first, choices, f.metadata.get(CLI_WHAT)), metavar=metavar)
        elif tp is bool:
            annotation = bool
            if "/" not in flag and not f.metadata.get(CLI_FLAG):
                flag = f"{first}/--no-{first[2:]}"
        elif tp is int:
            annotation = int
            kw.update(parser=parse_int(first, f.metadata.get(RANGE)), metavar="INTEGER")
        elif tp is float:
            annotation = float
            kw.update(parser=parse_float(first, f.metadata.get(RANGE)), metavar="FLOAT")
        elif origin in (tuple, list) and get_args(tp):
            item = get_args(tp)[0]
            annotation = str
            kw.update(parser=parse_list(first, item, origin, f.metadata.get(RANGE)), metavar=f"{item.__name__.upper()},...")
            if default not in (None, ...):
                kw["show_default"] = ",".join(map(str, default))
        elif tp is str or tp is Path:
            annotation = tp
            kw["metavar"] = "PATH" if tp is Path else "TEXT"
        else:
            raise TypeError(f"{cls.__name__}.{f.name}: no command-line form for {tp!r}; "
                            f"give it metadata {{{CLI_PARSE!r}: ...}} or {{{CLI_EXCLUDE!r}: True}}")
        if optional:
            annotation = typing.Optional[annotation]
        flags = tuple(flag.split(",")) if "," in flag else (flag,)
        info = typer.Option(default, *flags, **kw)
        specs.append(OptionSpec("__".join(path), path, flags, default, annotation, info))
        if f.metadata.get(CLI_OLD_FLAGS):
            old_flags = tuple(f.metadata[CLI_OLD_FLAGS].split(","))
            old_kw = {**kw, "hidden": True, "rich_help_panel": None}
            if "parser" in old_kw and origin is Literal:  # a rejected value names the spelling typed
                old_kw["parser"] = parse_choice(old_flags[0], get_args(tp), f.metadata.get(CLI_WHAT))
            specs.append(OptionSpec("__".join(path) + "__old", path, old_flags, default, annotation,
                                    typer.Option(default, *old_flags, **old_kw), old=True))
    return specs


MAX_CHOICE_METAVAR = 18
"""longest ``[a|b|c]`` shown beside a flag; longer choice lists are listed in the help text"""


def _range_note(rng: Range) -> str:
    """`` (>= 1)``, `` (in [1, 64])``: a range for the help line. An upper bound of a million
    or more is a limit of what a machine can hold (:data:`~damcap.common.validate.MAX_COUNT`), not
    a choice, and is left out (the parser still names it)."""
    if rng.hi is not None and rng.hi >= 1e6:
        rng = dataclasses.replace(rng, hi=None, hi_open=False)
    phrase = rng.phrase().strip()
    return f" ({phrase})" if phrase else ""


def _passthrough(parse: Callable[[str], Any]) -> Callable[[Any], Any]:
    return lambda value: parse(value) if isinstance(value, str) else value


def build_options(cls: type, values: dict[tuple[str, ...], Any], prefix: tuple[str, ...] = (), instance: Any = None) -> Any:
    """The dataclass ``cls`` from parsed values keyed by field path (nested ones rebuilt)."""
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        path = prefix + (f.name,)
        tp, _ = _strip_optional(hints[f.name])
        if dataclasses.is_dataclass(tp) and any(k[:len(path)] == path for k in values):
            kwargs[f.name] = build_options(tp, values, path, _default_of(f, instance))
        elif path in values:
            kwargs[f.name] = values[path]
    if instance is not None:
        return dataclasses.replace(instance, **kwargs)
    return cls(**kwargs)


def import_object(path: str | type) -> Any:
    """``"damcap.appearance.fit:FitOptions"`` -> the class (a class is returned as it is)."""
    if not isinstance(path, str):
        return path
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


# --------------------------------------------------------------------------------------------
# Commands
# --------------------------------------------------------------------------------------------


class DerivedCommand:
    """A command function whose keyword parameters named in ``sources`` are options dataclasses
    filled from the command line (one option per field); the other parameters are the command's
    own (positional paths, ``-o``). Calling it calls the function; ``__signature__`` is what
    typer sees (the command's own parameters, then one per field)."""

    def __init__(self, fn: Callable[..., Any], name: str, sources: dict[str, str | type], exclude: dict[str, frozenset[str]],
                 hidden: frozenset[str] = frozenset()):
        self.fn = fn
        self.hidden = hidden
        self.name = name
        self.sources = sources
        self.exclude = exclude
        self.wants_given = GIVEN in inspect.signature(fn).parameters
        functools.update_wrapper(self, fn)  # type: ignore[arg-type]
        del self.__wrapped__  # inspect must use __signature__, not the function's own

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.fn(*args, **kwargs)

    def classes(self) -> dict[str, type]:
        return {p: import_object(path) for p, path in self.sources.items()}

    def specs(self, show_all: bool = False) -> dict[str, list[OptionSpec]]:
        """Per dataclass parameter, its fields' options (imports the dataclasses); ``show_all``:
        the advanced ones shown in the help too (``--help-all``)."""
        return {p: option_specs(cls, exclude=self.exclude.get(p, frozenset()), hidden=p in self.hidden, show_all=show_all)
                for p, cls in self.classes().items()}

    def _own_parameters(self) -> tuple[list[inspect.Parameter], dict[str, Any]]:
        sig = inspect.signature(self.fn)
        glob = getattr(self.fn, "__globals__", {})
        params, ann = [], {}
        for p in sig.parameters.values():
            if p.name in self.sources or p.name == GIVEN:
                continue
            a = eval(p.annotation, glob) if isinstance(p.annotation, str) else p.annotation  # noqa: S307 (our own source)
            default = p.default
            if isinstance(default, typer.models.ParameterInfo) and default.rich_help_panel is None:
                default = copy.copy(default)
                default.rich_help_panel = OWN_PANEL
            params.append(p.replace(annotation=a, default=default, kind=inspect.Parameter.KEYWORD_ONLY))
            ann[p.name] = a
        return params, ann

    @property
    def __signature__(self) -> inspect.Signature:  # type: ignore[override]
        """The command's parameters as the user sees them: its own, then one per field."""
        sig = inspect.signature(self.typer_function(full=True))
        return sig.replace(parameters=[p for p in sig.parameters.values() if p.name != "_ctx"])

    def typer_function(self, full: bool, show_all: bool = False) -> Callable[..., Any]:
        """The function typer registers: with every derived option (``full``), or, for a command
        that is not run this time, only its own parameters (nothing imported); ``show_all``: the
        advanced options shown in its help (``--help-all``)."""
        params, ann = self._own_parameters()
        specs = self.specs(show_all) if full else {}
        classes = self.classes() if full else {}
        names = {p.name for p in params}
        for pname, group in specs.items():
            for s in group:
                if s.param in names:
                    raise TypeError(f"damcap {self.name}: option {s.param!r} of {pname} clashes with another option")
                names.add(s.param)
                params.append(inspect.Parameter(s.param, inspect.Parameter.KEYWORD_ONLY, default=s.info, annotation=s.annotation))
                ann[s.param] = s.annotation
        params.append(inspect.Parameter("_ctx", inspect.Parameter.KEYWORD_ONLY, annotation=typer.Context))
        ann["_ctx"] = typer.Context

        def run(**kwargs: Any) -> Any:
            ctx = kwargs.pop("_ctx")
            if self.sources and not full:
                raise RuntimeError(f"damcap {self.name} was built without its options")
            given: set[str] = set()
            for pname, group in specs.items():
                values = {}
                for s in group:  # an old spelling comes right after its field's own option
                    value = kwargs.pop(s.param)
                    source = ctx.get_parameter_source(s.param)
                    typed = source is not None and source.name in ("COMMANDLINE", "ENVIRONMENT")
                    if s.old and typed and ".".join(s.path) in given:
                        new = next(t.flags[0] for t in group if t.path == s.path and not t.old)
                        raise typer.BadParameter(f"{s.flags[0]} is the old spelling of {new}: give one of them")
                    if typed or not s.old:
                        values[s.path] = value
                    if typed:
                        given.add(".".join(s.path))
                kwargs[pname] = build_options(classes[pname], values)
            if self.wants_given:
                kwargs[GIVEN] = frozenset(given)
            from damcap.cli.paths import NOTHING_KEPT, command_locks, on_interrupt

            # the outputs that check_paths locks stay locked for the command's life, released however it ends;
            # Ctrl-C / SIGTERM reach cli.main as Interrupted (typer would exit 0)
            with command_locks(), on_interrupt(lambda: NOTHING_KEPT):
                return self.fn(**kwargs)

        run.__name__ = self.fn.__name__
        run.__doc__ = self.fn.__doc__
        run.__signature__ = inspect.Signature(params)  # type: ignore[attr-defined]
        run.__annotations__ = ann
        return run

    def flags(self) -> dict[str, tuple[str, ...]]:
        """Every derived option's flags by field path (``"fit.steps"``), for help and tests."""
        return {".".join(s.path): s.flags for group in self.specs().values() for s in group if not s.old}


COMMANDS: list[DerivedCommand] = []
"""every ``damcap`` command, in the order ``damcap --help`` lists them"""


def command(name: str | None = None, exclude: dict[str, tuple[str, ...]] | None = None, hidden: tuple[str, ...] = (),
            **sources: str | type) -> Callable[[Callable[..., Any]], DerivedCommand]:
    """Register a ``damcap`` command.

    Args:
        name: the command's name (default: the function's, dashes for underscores).
        exclude: per dataclass parameter, fields that the command replaces by options of its own
            (``segment``'s ``--materials`` takes 'auto' or a number).
        hidden: dataclass parameters whose options are parsed but left out of ``--help`` (the
            paper's table options that ``evaluate`` still accepts for old scripts).
        sources: keyword parameter -> ``"module:OptionsClass"`` (imported when the command is
            built: a class given as a string costs nothing until its command runs) or the class;
            the parameter receives the options dataclass built from the command line.
    """
    def register(fn: Callable[..., Any]) -> DerivedCommand:
        cmd = DerivedCommand(fn, name or fn.__name__.replace("_", "-"), dict(sources),
                             {k: frozenset(v) for k, v in (exclude or {}).items()}, frozenset(hidden))
        COMMANDS.append(cmd)
        return cmd
    return register
