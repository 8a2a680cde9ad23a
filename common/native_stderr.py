"""C libraries that print to the process's stderr themselves (libpng under OpenImageIO, RPly under
Open3D): their lines are caught, so a damaged file ends in damcap's one ``error:`` line only."""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
from typing import Iterator

#: most characters of caught text kept (a library looping on a damaged file can print a lot)
MAX_CAUGHT_CHARS = 64 * 1024
#: one block at a time, across threads: file descriptor 2 is the process's, and two blocks that
#: overlapped (reconstruct's frame writer verifying an EXR while the next photo is read) would
#: restore it out of order and leave it on a deleted temporary file, losing every later stderr line
_ONE_AT_A_TIME = threading.RLock()


@contextlib.contextmanager
def native_stderr_caught() -> Iterator[list[str]]:
    """Within the block, what is written to file descriptor 2 is caught instead of printed.

    Wrap only the native call (reading one file), not code that warns through Python: a warning
    printed inside the block is caught too.

    Yields:
        a list that, after the block, holds the caught lines (stripped, empty lines dropped), for
        an error message to quote.
    """
    with _ONE_AT_A_TIME:
        with _caught() as lines:
            yield lines


@contextlib.contextmanager
def _caught() -> Iterator[list[str]]:
    lines: list[str] = []
    try:
        sys.stderr.flush()
    except (AttributeError, OSError, ValueError):
        pass
    try:
        saved = os.dup(2)
    except OSError:  # no stderr at all: nothing to keep quiet
        yield lines
        return
    try:
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield lines
            finally:
                try:
                    sys.stderr.flush()
                except (AttributeError, OSError, ValueError):
                    pass
                os.dup2(saved, 2)
                tmp.seek(0)
                text = tmp.read(MAX_CAUGHT_CHARS).decode("utf-8", "replace")
                lines.extend(ln.strip() for ln in text.splitlines() if ln.strip())
    finally:
        os.close(saved)


#: set (to anything but 0) by ``damcap --verbose``: native libraries' own log lines reach the terminal
VERBOSE_ENV = "DAMCAP_VERBOSE"


def native_logs_wanted() -> bool:
    """Whether the user asked for native libraries' own log lines (``damcap --verbose``)."""
    return os.environ.get(VERBOSE_ENV, "").strip() not in ("", "0")


@contextlib.contextmanager
def signal_handlers_kept() -> Iterator[None]:
    """Load a native library inside the block: the Ctrl-C and SIGTERM handlers in place before it
    are in place after it.

    glog, inside pycolmap, installs its failure handler for SIGTERM when it loads (a SIGTERM then
    printed a 35-line native stack dump instead of damcap's one ``interrupted`` line), while
    Python still reports its own handler; setting Python's handler again puts it back.
    """
    import signal
    import threading

    signals = [signal.SIGINT, signal.SIGTERM]
    main = threading.current_thread() is threading.main_thread()
    saved = {s: signal.getsignal(s) for s in signals} if main else {}
    try:
        yield
    finally:
        for s, handler in saved.items():
            if handler is not None:  # None: installed outside Python, nothing of ours to put back
                signal.signal(s, handler)


def load_pycolmap():
    """pycolmap, loaded as damcap needs it everywhere: after OpenImageIO and OpenCV (its wheel
    bundles its own libpng/zlib; loaded first, their PNG writers crash later in the same process,
    ``free(): invalid pointer``), with damcap's signal handlers kept (:func:`signal_handlers_kept`)
    and COLMAP's own log lines (its errors too: "Failed to create any sparse model") off the
    terminal, where damcap's line says what happened, unless ``damcap --verbose``."""
    import cv2  # noqa: F401
    import OpenImageIO  # noqa: F401

    with signal_handlers_kept():  # glog takes SIGTERM when it loads
        import pycolmap

    pycolmap.logging.minloglevel = 0 if native_logs_wanted() else 3
    return pycolmap
