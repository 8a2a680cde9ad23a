"""Per-vertex label files: read when they fit the mesh and the models, refused in one line naming
the file otherwise, and a .npy header's shape bounded before anything is allocated."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.errors import DamcapError
from damcap.export.labels import read_vertex_labels


def test_reads_npy_and_txt(tmp_path):
    np.save(tmp_path / "l.npy", np.array([0, 1, 1, 0], np.int32))
    (tmp_path / "l.txt").write_text("0\n1\n1\n0\n")
    for name in ("l.npy", "l.txt"):
        got = read_vertex_labels(tmp_path / name, 4, 2)
        assert got.dtype == np.int64 and got.tolist() == [0, 1, 1, 0]


def _bomb(p):
    hdr = "{'descr': '<i8', 'fortran_order': False, 'shape': (1000000000000,), }"
    hdr += " " * (-(len(hdr) + 11) % 64) + "\n"
    p.write_bytes(b"\x93NUMPY\x01\x00" + len(hdr).to_bytes(2, "little") + hdr.encode() + b"\0" * 64)


@pytest.mark.parametrize("name, make, needle", [
    ("short.npy", lambda p: np.save(p, np.zeros(3, np.int64)), r"expected 4 labels .* shape \(3,\)"),
    ("two-d.npy", lambda p: np.save(p, np.zeros((4, 2), np.int64)), r"shape \(4, 2\)"),
    ("float.npy", lambda p: np.save(p, np.array([0, 1, np.nan, 0])), "must be integers.*float64"),
    ("pickle.npy", lambda p: np.save(p, np.array([{}] * 4, dtype=object), allow_pickle=True), "must be integers.*object"),
    ("empty.npy", lambda p: p.write_bytes(b""), "not a readable .npy file"),
    ("random.npy", lambda p: p.write_bytes(b"\x00" * 300), "not a readable .npy file"),
    ("bomb.npy", _bomb, r"shape \(1000000000000,\)"),
    ("negative.npy", lambda p: np.save(p, np.array([0, -1, 0, 1])), "label -1 at vertex 1 is outside 0..1"),
    ("high.npy", lambda p: np.save(p, np.array([0, 1, 2, 1])), "label 2 at vertex 2 is outside 0..1"),
    ("words.txt", lambda p: p.write_text("0\n1\nbanana\n0\n"), "'banana' is not an integer"),
    ("count.txt", lambda p: p.write_text("0\n1\n"), "expected 4 labels"),
    ("labels.csv", lambda p: p.write_text("0,1,0,1"), "from .npy or .txt"),
])
def test_refuses_naming_the_file(tmp_path, name, make, needle):
    make(tmp_path / name)
    with pytest.raises(DamcapError, match=needle) as e:
        read_vertex_labels(tmp_path / name, 4, 2)
    assert name in str(e.value) and "\n" not in str(e.value)
