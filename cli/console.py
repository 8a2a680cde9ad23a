"""The ``damcap`` console script: the command line's modules load under interrupt handling.

Loading the commands (typer, every command module) takes about a tenth of a second; a Ctrl-C or
SIGTERM in that time used to end in a ``KeyboardInterrupt`` traceback. Here they end in one line,
``interrupted`` (exit 130) or ``interrupted (SIGTERM)`` (exit 143), as they do once a command runs
(:mod:`damcap.cli.main`). Nothing has been written yet at that point.
"""

from __future__ import annotations

import os
import signal
import sys

EXIT_CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}
"""the exit code of an interrupt while the commands load (the shell's 128 + signal number)"""


def _interrupted_while_loading(signum: int, frame) -> None:
    sys.stderr.write("interrupted (SIGTERM)\n" if signum == signal.SIGTERM else "interrupted\n")
    sys.stderr.flush()
    os._exit(EXIT_CODES[signum])


def run() -> None:
    """Load :mod:`damcap.cli.main` with Ctrl-C and SIGTERM ending in one line, then run it (its
    own handling takes over from there)."""
    previous = {s: signal.signal(s, _interrupted_while_loading) for s in EXIT_CODES}
    from damcap.cli import main

    for s, handler in previous.items():
        signal.signal(s, handler)
    main.run()
