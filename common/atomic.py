"""Atomic file writes: write next to the target, fsync it, rename it over the target, fsync the folder.

One test hook lives here, :func:`pause_point`: with ``DAMCAP_TEST_PAUSE_AT`` unset (always, outside
the kill tests of tests/fuzz/test_kill_matrix.py) it does nothing.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator, Optional

import numpy as np


def fsync_path(path: str | os.PathLike) -> None:
    """Flush a file's or a folder's data and metadata to disk (a folder: the names in it).

    Filesystems that cannot fsync a folder (EINVAL, ENOTSUP) are tolerated.
    """
    is_dir = os.path.isdir(path)
    fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if is_dir else 0))
    try:
        os.fsync(fd)
    except OSError as e:
        if not is_dir or e.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
    finally:
        os.close(fd)


#: the test hook's environment variable (read by :func:`pause_point` only): ``NAME`` or ``NAME#K``
PAUSE_ENV = "DAMCAP_TEST_PAUSE_AT"
_pause_counts: dict[str, int] = {}
_pause_stderr: dict[int, int] = {}  # by process: fd 2 as its first moment found it (a thread may redirect fd 2 later)


def pause_point(path: str | os.PathLike) -> None:
    """Test hook: stop this process for good at a named moment, so that a test can kill it there.

    The moments are: an output locked (``path``: its lock file, ``.m.dam.lock``), a staged file
    about to be renamed onto ``path``, a staged folder about to move into ``path``. With
    ``DAMCAP_TEST_PAUSE_AT=NAME[#K]`` the K-th (default first) moment whose ``path``'s name
    matches the shell pattern ``NAME`` prints one stderr line ``damcap test hook: paused before
    PATH`` and sleeps until the process is killed. Unset, it returns at once and changes nothing.
    """
    spec = os.environ.get(PAUSE_ENV)
    if not spec:
        return
    import fnmatch
    import time

    if os.getpid() not in _pause_stderr:  # the first moment is an output's lock, before any native library redirects fd 2
        _pause_stderr[os.getpid()] = os.dup(2)
    pattern, _, k = spec.partition("#")
    if not fnmatch.fnmatchcase(Path(path).name, pattern):
        return
    key = f"{os.getpid()}:{pattern}"  # a forked child counts its own moments
    _pause_counts[key] = _pause_counts.get(key, 0) + 1
    if _pause_counts[key] == int(k or 1):
        os.write(_pause_stderr[os.getpid()], f"damcap test hook: paused before {path}\n".encode())
        while True:
            time.sleep(60)


def _replace_durably(staged: Path, path: Path) -> None:
    fsync_path(staged)
    pause_point(path)
    os.replace(staged, path)
    fsync_path(path.parent)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, keep_name: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix); on success rename it onto ``path``.

    A reader never sees a half-written file, and a crash leaves the previous file intact: the
    staged file is fsynced before the rename and the folder after it.
    ``keep_name``: the temporary file has ``path``'s own name, inside a temporary folder beside
    it, for formats that record their file's name (an OBJ names its object after it).
    """
    path = Path(path)
    created = _make_parents(path)
    done = False
    try:
        with _naming(path):  # an error about the temporary name names the file the user gave
            if keep_name:
                stage = Path(tempfile.mkdtemp(prefix=f".{path.stem}.", dir=path.parent))
                tmp_path = stage / path.name
            else:
                fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
                os.close(fd)
                stage = tmp_path = Path(tmp)
                umask = os.umask(0)
                os.umask(umask)
                os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; outputs get the usual permissions
        try:
            with _naming(path, stage):
                yield tmp_path
                _replace_durably(tmp_path, path)
            done = True
        finally:
            if stage.is_dir():
                shutil.rmtree(stage, ignore_errors=True)
            elif stage.exists():
                stage.unlink()
    finally:
        if not done:  # folders made for this file go too: a failed write leaves nothing behind
            for folder in created:
                with contextlib.suppress(OSError):
                    folder.rmdir()


def _make_parents(path: Path) -> list[Path]:
    """Create ``path``'s missing parent folders; return them, deepest first."""
    missing = []
    p = path.parent
    while not p.exists() and p != p.parent:
        missing.append(p)
        p = p.parent
    with _naming(path):
        path.parent.mkdir(parents=True, exist_ok=True)
    return missing


@contextlib.contextmanager
def _naming(path: Path, stage: Optional[Path] = None) -> Iterator[None]:
    """Re-raise an OSError as one about ``path``: any (``stage`` None), or one that names no file or
    the temporary ``stage`` (a full disk while writing it); one about another file passes as is."""
    try:
        yield
    except OSError as e:
        name = None if e.filename is None else Path(os.fsdecode(e.filename))
        if stage is None or name is None or name == stage or stage in name.parents:
            raise OSError(e.errno, e.strerror or str(e), str(path)) from None
        raise


def cut_short_error(tmp: str | os.PathLike, path: str | os.PathLike, nbytes: int) -> Optional[OSError]:
    """Why a native writer (OpenImageIO, RPly) failed to write ``tmp``, as an OSError naming
    ``path`` (the file the user asked for), or None when it is neither of these:

    - ENOSPC: the disk holding ``tmp`` has less room left than ``nbytes`` (what was being written);
    - EFBIG: ``tmp`` reached the process's file size limit (``ulimit -f``).

    Such writers say only that the output failed, naming the temporary file.
    """
    import resource

    try:
        st = os.statvfs(Path(tmp).parent)
        if st.f_bavail * st.f_frsize < nbytes:
            return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if limit != resource.RLIM_INFINITY and os.path.getsize(tmp) >= limit:
            return OSError(errno.EFBIG, f"{os.strerror(errno.EFBIG)} (the file size limit, ulimit -f, is {limit} bytes)", str(path))
    except OSError:
        return None
    return None


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_json_atomic(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` as indented JSON to ``path`` atomically."""
    write_text_atomic(path, json.dumps(data, indent=2) + "\n")


def write_npy_atomic(path: str | os.PathLike, array: np.ndarray) -> None:
    """Write ``array`` as a NumPy ``.npy`` file to ``path`` atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array)
