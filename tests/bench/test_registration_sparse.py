"""The sparse-registration study's pure parts: its rotation errors and its report table."""

from __future__ import annotations

import numpy as np

from bench.registration_sparse import _rotation_errors, write_report


def _rot_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    m = np.eye(4)
    m[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    return m


def test_rotation_errors_ignore_one_common_rotation_and_need_two_cameras():
    ref = {f"p{k}": _rot_y(30 * k) for k in range(4)}
    turned = {n: _rot_y(17) @ m for n, m in ref.items()}  # the same cameras in a turned world frame
    out = _rotation_errors(turned, ref)
    assert out["compared"] == 4 and out["median_rot_aligned_deg"] < 1e-6 and out["max_rot_aligned_deg"] < 1e-6
    one_off = dict(turned, p3=_rot_y(17) @ _rot_y(90 + 5))  # one camera 5 deg off
    assert 1.0 < _rotation_errors(one_off, ref)["max_rot_aligned_deg"] < 5.0 + 1e-6
    assert _rotation_errors({"p0": ref["p0"]}, ref) == {"compared": 1}


def test_report_lists_every_row_with_its_command(tmp_path):
    res = {"command": ".venv/bin/python -m bench.registration_sparse", "machine": {"date_utc": "d", "nproc": 2, "cpu_model": "c"},
           "rows": [{"subset": "s", "photos": 30, "method": "damcap", "registered": 15, "median_rot_aligned_deg": 0.1,
                     "max_rot_aligned_deg": 0.2, "wall_s": 74.0},
                    {"subset": "s", "photos": 30, "method": "damcap (no retry)", "registered": 0, "wall_s": 20.0}]}
    write_report(res, tmp_path / "r.md")
    text = (tmp_path / "r.md").read_text()
    assert ".venv/bin/python -m bench.registration_sparse" in text
    assert "| s | 30 | damcap | 15 | 0.100 / 0.200 | 74.0 |" in text and "| s | 30 | damcap (no retry) | 0 | - | 20.0 |" in text
