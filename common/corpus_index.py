"""The corpus index ``corpus.json`` that ``damcap synth-set`` writes beside its captures: the one
reader of that file (the writer is :mod:`damcap.synth.corpus`).

``{"captures": [{"path": "captures/NAME", "split": "train" | "heldout", ...}, ...], ...}``; a
capture is finished once its folder holds ``transforms.json``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from damcap.common.errors import DamcapError

INDEX_NAME = "corpus.json"


def read_corpus_index(corpus: str | os.PathLike, reader: str = "this command") -> dict[str, Any]:
    """The parsed ``corpus.json`` of a corpus folder.

    Args:
        corpus: the folder given to ``damcap synth-set``.
        reader: what reads it, named in the error (e.g. ``"train-hyper"``).

    Raises:
        DamcapError: no index, or one that is not a corpus index (no ``captures`` list of entries
            with a ``path``).
    """
    corpus = Path(corpus)
    index = corpus / INDEX_NAME
    if not index.is_file():
        raise DamcapError(f"{corpus}: no {INDEX_NAME}; {reader} reads a corpus written by `damcap synth-set`")
    try:
        doc = json.loads(index.read_text())
        captures = doc["captures"]
        if not isinstance(captures, list) or not all(isinstance(e, dict) and isinstance(e.get("path"), str) for e in captures):
            raise TypeError("'captures' is not a list of entries with a 'path'")
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise DamcapError(f"{index}: not a damcap corpus index ({e!r}); pass the folder given to damcap synth-set") from None
    return doc


def finished_captures(corpus: str | os.PathLike, split: str, reader: str = "this command") -> list[tuple[Path, dict[str, Any]]]:
    """The finished captures of one split (``"train"`` or ``"heldout"``), in index order:
    (capture folder, its index entry). Unfinished ones (no ``transforms.json`` yet) are left out."""
    corpus = Path(corpus)
    entries = read_corpus_index(corpus, reader)["captures"]
    return [(corpus / e["path"], e) for e in entries
            if e.get("split") == split and (corpus / e["path"] / "transforms.json").is_file()]
