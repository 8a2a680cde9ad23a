"""``damcap``: the command-line entry point.

Every user mistake ends in one line on stderr and a non-zero exit, never a traceback:

- 2: a user mistake (``error: ...``) or an operating-system error while reading or writing
  (``error: PATH: Permission denied; ...``, a full disk, a read-only filesystem);
- 2 also when memory runs out (``error: out of memory (...)``, a ``MemoryError`` or an
  allocator's RuntimeError anywhere in the command);
- 130: Ctrl-C, 143: SIGTERM (``interrupted: ...`` says what was kept, e.g. a checkpoint that a
  rerun resumes).

Python and NumPy warnings are printed as one line each, ``warning: ...``, on stderr.
``damcap CMD --help-all`` prints the command's help with its advanced options (exit 0).
Commands live in one module per stage; importing a module registers its commands.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import warnings

import typer

from damcap.common.errors import DamcapError

from damcap.cli import appearance_cmds  # noqa: F401  (registers inspect, fit, render, evaluate)
from damcap.cli import tables_cmds  # noqa: F401  (registers tables)
from damcap.cli import capture_cmds  # noqa: F401
from damcap.cli import synth_cmds  # noqa: F401  (registers closed-form, synth, synth-set, synth-photos, shape)
from damcap.cli import reconstruct_cmds  # noqa: F401
from damcap.cli import export_cmds  # noqa: F401  (registers export, view)
from damcap.cli import segment_cmds  # noqa: F401  (registers segment)
from damcap.cli import hyper_cmds  # noqa: F401  (registers train-hyper, predict)
from damcap.cli.app import build_app
from damcap.cli.paths import Interrupted, Terminated, os_error_line


HELP_ALL = "--help-all"
"""``damcap CMD --help-all``: the command's help with its advanced options too"""


def printable(text: str) -> str:
    r"""``text`` with what UTF-8 cannot encode (lone surrogates: a file's undecodable bytes, as
    Python hands them over) spelled as escapes, so that a message about a damaged file can be
    written to any stderr.

    >>> printable("channels R, G, \udc80")
    'channels R, G, \\udc80'
    """
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


def _say(line: str) -> None:
    """One line to stderr (:func:`printable`)."""
    typer.echo(printable(line), err=True)


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    _say(f"warning: {' '.join(str(message).split())}")


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


@contextlib.contextmanager
def _signals_and_warnings():
    """SIGTERM raises :class:`Terminated` (Ctrl-C's path); warnings print as one line each."""
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _one_line_warning
            yield
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


_OOM_PHRASES = ("can't allocate memory", "out of memory", "cannot allocate memory", "std::bad_alloc")
"""how torch's allocators and C++ extensions say they ran out of memory in a RuntimeError"""


def is_out_of_memory(e: BaseException) -> bool:
    """A RuntimeError that says memory ran out (torch's CPU or CUDA allocator, a C++ bad_alloc)."""
    text = str(e).lower()
    return any(p in text for p in _OOM_PHRASES)


def out_of_memory_line(e: BaseException) -> str:
    """The one line for memory running out anywhere in a command.

    >>> out_of_memory_line(MemoryError())
    'out of memory (MemoryError); close other programs, or make the work smaller (fewer views, a lower resolution or batch size)'
    """
    detail = " ".join(str(e).split())
    detail = f"{type(e).__name__}: {detail[:160]}" if detail else type(e).__name__
    return f"out of memory ({detail}); close other programs, or make the work smaller (fewer views, a lower resolution or batch size)"


def main(argv: list[str] | None = None) -> int:
    """Console-script entry point: runs a command, turning user mistakes into one-line errors."""
    args = sys.argv[1:] if argv is None else [str(a) for a in argv]
    selected = next((a for a in args if not a.startswith("-")), None)  # the top level takes only --help, --version
    show_all = HELP_ALL in args  # the help with every panel, the advanced options included
    if show_all:
        args = ["--help" if a == HELP_ALL else a for a in args]
    try:
        with _signals_and_warnings():
            rv = build_app(selected, show_all=show_all)(args=args, prog_name="damcap", standalone_mode=False)
        if isinstance(rv, int) and not isinstance(rv, bool) and rv != 0:  # typer returns 130 for a bare Ctrl-C
            if rv == 130:
                _say("interrupted")
            return rv
    except Interrupted as e:
        _say(f"interrupted{' (SIGTERM)' if e.terminated else ''}: {e.kept}")
        return e.exit_code
    except DamcapError as e:
        _say(f"error: {e}")
        return 2
    except typer.Abort:
        _say("aborted")
        return 130
    except typer.Exit as e:
        return int(getattr(e, "exit_code", 0) or 0)
    except typer.TyperException as e:  # usage errors: missing argument, unknown option or command
        if type(e).__name__ == "NoArgsIsHelpError":  # bare ``damcap``: the help, as a usage error
            e.show()  # type: ignore[attr-defined]
            return 2
        ctx = getattr(e, "ctx", None)
        hint = f" (see {ctx.command_path} --help)" if ctx is not None else ""
        message = e.format_message() if hasattr(e, "format_message") else str(e)
        _say(f"error: {' '.join(message.split())}{hint}")
        return int(getattr(e, "exit_code", 2) or 2)
    except OSError as e:  # permission denied, disk full, read-only filesystem: one line, never a traceback
        _say(f"error: {os_error_line(e)}")
        return 2
    except MemoryError as e:
        _say(f"error: {out_of_memory_line(e)}")
        return 2
    except RuntimeError as e:
        if not is_out_of_memory(e):
            raise
        _say(f"error: {out_of_memory_line(e)}")
        return 2
    except Terminated:
        _say("interrupted (SIGTERM)")
        return 143
    except KeyboardInterrupt:
        _say("interrupted")
        return 130
    return 0


def run() -> None:
    """The ``damcap`` console script.

    Exits without interpreter teardown once every output is closed: OpenImageIO's nanobind
    bindings print spurious reference-leak reports at shutdown when open3d or torch.onnx were
    imported in the same process.
    """
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    run()
