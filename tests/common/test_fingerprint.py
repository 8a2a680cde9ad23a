"""Fingerprints of a job's inputs: stable, order- and type-sensitive, content-exact."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np
import torch

from damcap.common.fingerprint import file_digest, fingerprint


def test_known_value_and_stability():
    # sha256 of the tagged JSON encoding: b"J" + 8-byte length + b'"damcap"'
    import hashlib

    text = b'"damcap"'
    assert fingerprint("damcap") == hashlib.sha256(b"J" + len(text).to_bytes(8, "little") + text).hexdigest()
    assert len(fingerprint()) == 64 and fingerprint() == hashlib.sha256().hexdigest()


def test_json_parts_ignore_key_order_but_not_values():
    from damcap.appearance.fit import FitOptions

    a, b = asdict(FitOptions()), asdict(FitOptions(learning_rate=2e-2))
    assert fingerprint(a) == fingerprint(dict(reversed(list(a.items()))))
    assert fingerprint(a) != fingerprint(b)


def test_arrays_and_tensors_hash_dtype_shape_and_every_bit():
    x = np.arange(12, dtype=np.float32).reshape(3, 4)
    assert fingerprint(x) == fingerprint(torch.from_numpy(x.copy()))  # a tensor hashes as its array
    assert fingerprint(x) == fingerprint(np.asfortranarray(x))  # memory layout does not matter
    assert fingerprint(x) != fingerprint(x.reshape(4, 3))
    assert fingerprint(x) != fingerprint(x.astype(np.float64))
    y = x.copy()
    y.view(np.uint32)[1, 2] ^= 1  # one bit of one value
    assert fingerprint(x) != fingerprint(y)
    assert fingerprint(np.zeros((0, 3), np.float32)) != fingerprint(np.zeros((3, 0), np.float32))


def test_parts_do_not_run_into_each_other():
    assert fingerprint(b"ab", b"c") != fingerprint(b"a", b"bc")
    assert fingerprint("1") != fingerprint(1) != fingerprint(b"1")
    assert fingerprint([1, 2]) != fingerprint(1, 2)


def test_file_digest_streams_the_content(tmp_path):
    import hashlib

    p = tmp_path / "f.bin"
    data = bytes(range(256)) * 5000
    p.write_bytes(data)
    assert file_digest(p, chunk=1000) == file_digest(p) == hashlib.sha256(data).hexdigest()
