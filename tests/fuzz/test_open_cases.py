"""The list of open fuzz cases names only cases that exist (a renamed or fixed case leaves it)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.fuzz.conftest import OPEN_CASES_FILE, open_cases

REPO = Path(__file__).resolve().parents[2]


def test_open_cases_are_real_test_ids():
    listed = open_cases()
    if not listed:
        return
    out = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:randomly", "tests/fuzz"],
                         cwd=REPO, capture_output=True, text=True, env={**__import__("os").environ, "DAMCAP_FUZZ_OPEN": "1"},
                         timeout=300)
    collected = {ln.strip() for ln in out.stdout.splitlines() if ln.startswith("tests/fuzz/")}
    assert collected, out.stdout[-2000:] + out.stderr[-2000:]
    missing = sorted(listed - collected)
    assert not missing, f"{OPEN_CASES_FILE.name} lists cases that do not exist: {missing[:10]}"
