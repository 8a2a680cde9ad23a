"""The corpus index ``corpus.json`` that ``damcap synth-set`` writes beside its captures: the one
reader of that file (the writer is :mod:`damcap.synth.corpus`).

``{"captures": [{"path": "captures/NAME", "split": "train" | "heldout", ...}, ...], ...}``; a
capture is finished once its folder holds ``transforms.json``.
"""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath
from typing import Any

from damcap.common.errors import DamcapError
from damcap.common.validate import load_json_file

INDEX_NAME = "corpus.json"
#: the splits ``damcap synth-set`` writes
SPLITS = ("train", "heldout")


def read_corpus_index(corpus: str | os.PathLike, reader: str = "this command") -> dict[str, Any]:
    """The parsed ``corpus.json`` of a corpus folder.

    Args:
        corpus: the folder given to ``damcap synth-set``.
        reader: what reads it, named in the error (e.g. ``"train-hyper"``).

    Raises:
        DamcapError: no index, or one that is not a corpus index (no ``captures`` list of entries
            with a ``path``), invalid or too deeply nested JSON, a capture path that is absolute or
            leaves the corpus folder, an unknown split, a capture listed twice.
    """
    corpus = Path(corpus)
    index = corpus / INDEX_NAME
    if not index.is_file():
        raise DamcapError(f"{corpus}: no {INDEX_NAME}; {reader} reads a corpus written by `damcap synth-set`")
    doc = load_json_file(index, "corpus index")  # size-limited; bad or too deeply nested JSON is one line
    try:
        captures = doc["captures"]
        if not isinstance(captures, list) or not all(isinstance(e, dict) and isinstance(e.get("path"), str) for e in captures):
            raise TypeError("'captures' is not a list of entries with a 'path'")
    except (KeyError, TypeError) as e:
        raise DamcapError(f"{index}: not a damcap corpus index ({e!r}); pass the folder given to damcap synth-set") from None
    seen: set[PurePosixPath] = set()
    for k, e in enumerate(captures):
        _check_entry(index, k, e, seen)
    return doc


def _check_entry(index: Path, k: int, entry: dict[str, Any], seen: set[PurePosixPath]) -> None:
    """Entry ``k`` names a capture folder inside the corpus (relative, no ``..``), once, with a known split."""
    rel = PurePosixPath(entry["path"].replace("\\", "/"))
    if not entry["path"].strip() or rel.is_absolute() or ".." in rel.parts or rel == PurePosixPath("."):
        raise DamcapError(f"{index}: capture {k} has path {entry['path']!r}; capture paths are relative to the corpus "
                          "folder and stay inside it")
    if entry.get("split") not in SPLITS:
        raise DamcapError(f"{index}: capture {k} ({entry['path']}) has split {str(entry.get('split'))[:40]!r}; "
                          f"expected one of {', '.join(SPLITS)}")
    if rel in seen:
        raise DamcapError(f"{index}: capture {entry['path']!r} is listed twice; each capture once")
    seen.add(rel)


def finished_captures(corpus: str | os.PathLike, split: str, reader: str = "this command") -> list[tuple[Path, dict[str, Any]]]:
    """The finished captures of one split (``"train"`` or ``"heldout"``), in index order:
    (capture folder, its index entry). Unfinished ones (no ``transforms.json`` yet) are left out."""
    corpus = Path(corpus)
    entries = read_corpus_index(corpus, reader)["captures"]
    return [(corpus / e["path"], e) for e in entries
            if e.get("split") == split and (corpus / e["path"] / "transforms.json").is_file()]
