"""The corpus index reader: finished captures by split, and one-line refusals of what is not an index."""

from __future__ import annotations

import json

import pytest

from damcap.common.corpus_index import finished_captures, read_corpus_index
from damcap.common.errors import DamcapError


def _corpus(root, entries):
    root.mkdir(parents=True, exist_ok=True)
    (root / "corpus.json").write_text(json.dumps({"captures": entries}))
    return root


def test_finished_captures_by_split_in_index_order(tmp_path):
    entries = [{"path": f"captures/c{k}", "split": s} for k, s in enumerate(["train", "heldout", "train", "train"])]
    root = _corpus(tmp_path / "corpus", entries)
    for k in (0, 1, 3):  # c2 is planned but not rendered yet
        (root / f"captures/c{k}").mkdir(parents=True)
        (root / f"captures/c{k}/transforms.json").write_text("{}")
    assert [p.name for p, _ in finished_captures(root, "train")] == ["c0", "c3"]
    assert [(p.name, e["split"]) for p, e in finished_captures(root, "heldout")] == [("c1", "heldout")]


@pytest.mark.parametrize("content, needle", [
    (None, "no corpus.json; train-hyper reads a corpus"),
    ("{not json", "corpus.json: invalid JSON"),
    ("[" * 100_000 + "]" * 100_000, "corpus.json: corpus index is nested too deeply"),
    ('{"frames": []}', "not a damcap corpus index"),
    ('{"captures": [{"split": "train"}]}', "not a damcap corpus index"),
    ('{"captures": [{"path": "/etc", "split": "train"}]}', "'/etc'; capture paths are relative"),
    ('{"captures": [{"path": "../../etc", "split": "train"}]}', "'../../etc'; capture paths are relative"),
    ('{"captures": [{"path": "captures/a", "split": "banana"}]}', "split 'banana'"),
    ('{"captures": [{"path": "captures/a", "split": "train"}, {"path": "captures/a/", "split": "train"}]}', "listed twice"),
])
def test_refuses_what_is_not_an_index(tmp_path, content, needle):
    if content is not None:
        (tmp_path / "corpus.json").write_text(content)
    with pytest.raises(DamcapError, match=needle):
        read_corpus_index(tmp_path, reader="train-hyper")
