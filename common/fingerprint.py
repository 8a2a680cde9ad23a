"""Fingerprints of a job's inputs: what a checkpoint or a partial output was made from.

A resumable job (``fit``, ``train-hyper``, ``synth``) stores :func:`fingerprint` of everything
that determines its result (the data it trains on, its resolved options, the damcap version)
next to its state, and resumes only a state whose fingerprint equals the one of the current
inputs; anything else (another capture written to the same output path, changed options, an
old file without a fingerprint) starts afresh.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

FINGERPRINT_KEY = "fingerprint"
"""the key under which a checkpoint or marker stores its fingerprint"""


def _update(h: "hashlib._Hash", part: Any) -> None:
    """Feed one part, tagged with its kind and length so that different parts never collide."""
    if hasattr(part, "detach") and hasattr(part, "numpy"):  # a torch tensor (without importing torch)
        part = part.detach().cpu().contiguous().numpy()
    if isinstance(part, np.ndarray):
        a = np.ascontiguousarray(part)
        head = json.dumps({"dtype": a.dtype.str, "shape": list(a.shape)}).encode()
        data = a.view(np.uint8).reshape(-1).data if a.size else b""
        h.update(b"A" + len(head).to_bytes(8, "little") + head + a.nbytes.to_bytes(8, "little"))
        h.update(data)
        return
    if isinstance(part, (bytes, bytearray, memoryview)):
        data = bytes(part)
        h.update(b"B" + len(data).to_bytes(8, "little") + data)
        return
    text = json.dumps(part, sort_keys=True, default=str).encode()
    h.update(b"J" + len(text).to_bytes(8, "little") + text)


def fingerprint(*parts: Any) -> str:
    """SHA-256 (hex) of a job's inputs.

    Args:
        parts: bytes, NumPy arrays or torch tensors (hashed by dtype, shape and content) and
            JSON-able objects (dataclass ``asdict`` results, strings, numbers; dict keys sorted).

    Returns:
        64 hexadecimal digits; equal for equal parts in the same order, different (with
        overwhelming probability) otherwise.

    >>> fingerprint({"b": 1, "a": 2}) == fingerprint({"a": 2, "b": 1})
    True
    >>> fingerprint(np.zeros(2, np.float32)) == fingerprint(np.zeros(2, np.float64))
    False
    >>> fingerprint(b"ab", b"c") == fingerprint(b"a", b"bc")
    False
    >>> fingerprint("damcap")[:16]
    '403e6a11d18b582d'
    """
    h = hashlib.sha256()
    for part in parts:
        _update(h, part)
    return h.hexdigest()


def file_digest(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """SHA-256 (hex) of a file's content, read in ``chunk``-byte pieces (streaming).

    Raises:
        OSError: the file cannot be read.
    """
    h = hashlib.sha256()
    with open(Path(path), "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()
