"""Per-vertex part labels (``damcap export --labels``): a ``.npy`` or ``.txt`` file, one integer
label in [0, parts) per mesh vertex (what ``damcap segment-labels`` writes).

Reading is bounded by the mesh: a ``.npy`` header is read and checked (integer dtype, shape
``(V,)``) before any array is allocated, pickles are never loaded, and a ``.txt`` file larger
than V lines of numbers could fill is refused before it is parsed.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from damcap.common.errors import DamcapError

LABEL_SUFFIXES = (".npy", ".txt")
#: most bytes a .txt label line may take (an int64 and its newline, with room for spaces / CRLF)
TXT_BYTES_PER_LABEL = 32


def _npy_header(path: Path) -> tuple[np.dtype, tuple[int, ...]]:
    """dtype and shape a ``.npy`` file's header states (nothing else is read).

    Raises:
        DamcapError: not a .npy file, a damaged header, a Fortran-ordered array.
    """
    fmt = np.lib.format
    try:
        with open(path, "rb") as fp:
            version = fmt.read_magic(fp)
            if version == (1, 0):
                shape, fortran, dtype = fmt.read_array_header_1_0(fp)
            elif version == (2, 0):
                shape, fortran, dtype = fmt.read_array_header_2_0(fp)
            else:
                raise ValueError(f".npy format version {version[0]}.{version[1]} is not read")
    except (ValueError, OSError, EOFError, SyntaxError, TypeError) as e:
        raise DamcapError(f"{path}: not a readable .npy file ({str(e).splitlines()[0][:120] or type(e).__name__})") from None
    if fortran and len(shape) > 1:
        raise DamcapError(f"{path}: a Fortran-ordered array; labels are a 1-D array")
    return dtype, tuple(shape)


def _read_npy(path: Path, n_vertices: int) -> np.ndarray:
    dtype, shape = _npy_header(path)
    if dtype.hasobject or dtype.kind not in "iu":
        raise DamcapError(f"{path}: labels must be integers, the file holds {dtype} values")
    if shape != (n_vertices,):
        raise DamcapError(f"{path}: expected {n_vertices} labels (shape ({n_vertices},), one per mesh vertex), "
                          f"the file holds shape {shape}")
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise DamcapError(f"{path}: damaged or truncated .npy file ({str(e).splitlines()[0][:120]})") from None


def _read_txt(path: Path, n_vertices: int) -> np.ndarray:
    size = path.stat().st_size
    if size > TXT_BYTES_PER_LABEL * n_vertices + 1024:
        raise DamcapError(f"{path}: {size} bytes is more than {n_vertices} labels (one per mesh vertex) take")
    try:
        text = path.read_bytes().decode("ascii")
    except UnicodeDecodeError:
        raise DamcapError(f"{path}: not a text file of integer labels (one per line)") from None
    rows = text.split()
    if len(rows) != n_vertices:
        raise DamcapError(f"{path}: expected {n_vertices} labels (one per mesh vertex, one per line), the file holds {len(rows)}")
    for r in rows:
        if not (r.lstrip("+-").isdigit() and len(r) <= 19 and r.count("-") + r.count("+") <= 1):
            raise DamcapError(f"{path}: label {r[:40]!r} is not an integer label; expected one integer per line")
    return np.array([int(r) for r in rows], np.int64)


def read_vertex_labels(path: str | os.PathLike, n_vertices: int, parts: int) -> np.ndarray:
    """Per-vertex part labels from ``path``.

    Args:
        n_vertices: vertices of the mesh the labels belong to.
        parts: models given (labels must lie in [0, parts)).

    Returns:
        (n_vertices,) int64 labels in [0, parts).

    Raises:
        DamcapError: naming the file: missing, an unknown suffix, not integers, the wrong count or
            shape, a label outside [0, parts) (the value and its vertex are named).
    """
    path = Path(path)
    if path.suffix.lower() not in LABEL_SUFFIXES:
        raise DamcapError(f"{path}: labels are read from .npy or .txt (one integer per line), not {path.suffix or 'a file without suffix'}")
    if not path.is_file():
        raise DamcapError(f"{path}: label file not found")
    labels = _read_npy(path, n_vertices) if path.suffix.lower() == ".npy" else _read_txt(path, n_vertices)
    labels = labels.astype(np.int64)
    bad = np.flatnonzero((labels < 0) | (labels >= parts))
    if bad.size:
        v = int(bad[0])
        raise DamcapError(f"{path}: label {int(labels[v])} at vertex {v} is outside 0..{parts - 1} "
                          f"({parts} model(s) were given, one per part)")
    return labels
