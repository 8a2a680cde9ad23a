"""The README's Python example runs as written (on the bundled sample capture, with fewer steps)."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_readme_python_example_runs(sample_capture, tmp_path, monkeypatch, capsys):
    text = (REPO / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) == 1, "the README has one Python example"
    code = blocks[0]
    assert '"demo_out/capture"' in code and "steps=2000" in code
    code = code.replace('"demo_out/capture"', repr(str(sample_capture))).replace("steps=2000", "steps=30")
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README.md", "exec"), {})
    dam, rm_pp = (float(x) for x in capsys.readouterr().out.split()[:2])
    assert 0 <= dam <= 1 and 0 <= rm_pp <= 1
    assert (tmp_path / "model.dam").is_file()
