"""Where the shared third-party data lives (meshes/, envmaps/, brackets/, raw/, real/): one rule
for the command line, the benchmarks and the tests."""

from __future__ import annotations

import os
from pathlib import Path

DATA_ENV = "DAMCAP_SHARED_DATA"
"""environment variable naming the shared data folder"""


def shared_data_dir(given: str | os.PathLike | None = None, fallback: str | os.PathLike = Path("..") / "shared" / "data") -> Path:
    """``given``, else ``$DAMCAP_SHARED_DATA``, else ``fallback`` (by default ``../shared/data``
    from the current folder: a checkout's sibling ``shared/``; an installed damcap has no
    repository to look next to).

    >>> str(shared_data_dir("/data/x"))
    '/data/x'
    """
    if given is not None:
        return Path(given)
    env = os.environ.get(DATA_ENV)
    return Path(env) if env else Path(fallback)
