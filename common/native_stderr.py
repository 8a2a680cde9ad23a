"""C libraries that print to the process's stderr themselves (libpng under OpenImageIO, RPly under
Open3D): their lines are caught, so a damaged file ends in damcap's one ``error:`` line only."""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from typing import Iterator

#: most characters of caught text kept (a library looping on a damaged file can print a lot)
MAX_CAUGHT_CHARS = 64 * 1024


@contextlib.contextmanager
def native_stderr_caught() -> Iterator[list[str]]:
    """Within the block, what is written to file descriptor 2 is caught instead of printed.

    Wrap only the native call (reading one file), not code that warns through Python: a warning
    printed inside the block is caught too.

    Yields:
        a list that, after the block, holds the caught lines (stripped, empty lines dropped), for
        an error message to quote.
    """
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
