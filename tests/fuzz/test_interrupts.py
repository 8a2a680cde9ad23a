"""Ctrl-C and SIGTERM in the middle of ``damcap fit``: non-zero, one line saying what was kept,
no traceback, no half-written model, and the next run resumes (a checkpoint of another capture is
never resumed)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.fuzz.conftest import damcap_fork, digest, problems_of

FIT = ["--steps", "400000", "--batch-size", "32", "--holdout-views", "0", "--checkpoint-every", "20", "--eval-every", "1000000"]


#: seconds after the fork before an early Ctrl-C: a signal that reaches the child before CPython's
#: after-fork reset (``PyOS_AfterFork_Child`` clears pending signals) is lost to the harness, not
#: to damcap (a console start-up is not a fork)
STARTED_S = 0.3

#: what a fit says once it has decided not to resume a checkpoint (the second runs below are
#: stopped as soon as they have said whether they resume: the fits themselves never end)
AFRESH = "starting afresh"


def _interrupted(work, sigs, *, wait_ckpt=True, capture=None):
    out = work / "o.dam"
    ckpt = Path(str(out) + ".ckpt")
    cap = capture or work / "cap"
    before = digest(cap)
    t0 = time.monotonic()
    pred = (lambda: ckpt.is_file()) if wait_ckpt else (lambda: time.monotonic() - t0 > STARTED_S)
    run = damcap_fork(["fit", cap, "-o", out, *FIT], signal_when=(pred, *sigs), timeout=30)
    return run, out, ckpt, before, cap


@pytest.mark.parametrize("name,sigs,code", [("ctrl-c", [signal.SIGINT], 130), ("sigterm", [signal.SIGTERM], 143),
                                             ("double-ctrl-c", [signal.SIGINT, signal.SIGINT], 130)])
def test_fit_interrupted_keeps_checkpoint_and_resumes(name, sigs, code, work):
    run, out, ckpt, before, cap = _interrupted(work, sigs)
    bad = problems_of(run, (), exit_code=code, before_in={cap: before}, before_out={}, timeout=30)
    bad = [b for b in bad if not b.startswith("error line") and not b.startswith("last stderr")]
    last = run.lines[-1] if run.lines else ""
    if ckpt.name not in last:
        bad.append(f"last line does not say what was kept ({ckpt.name}): {last[:160]!r}")
    if out.exists():
        bad.append("a model was written although the fit was interrupted")
    if not ckpt.is_file():
        bad.append("no checkpoint kept")
    assert not bad, "; ".join(bad)
    # resumable: the same command again, stopped as soon as it has said it resumes
    again = damcap_fork(["fit", cap, "-o", out, *FIT], timeout=30, signal_when=("resuming", signal.SIGKILL))
    assert "resum" in (again.err + again.out).lower(), f"second run did not resume: {(again.err + again.out)[-200:]!r}"


def test_fit_ctrl_c_before_first_checkpoint(work):
    run, out, ckpt, before, cap = _interrupted(work, [signal.SIGINT], wait_ckpt=False)
    bad = problems_of(run, (), exit_code=130, before_in={cap: before}, before_out={}, timeout=30)
    bad = [b for b in bad if not b.startswith("error line") and not b.startswith("last stderr")]
    if out.exists():
        bad.append("model written")
    if not run.lines or "interrupt" not in run.lines[-1].lower():
        bad.append(f"last line does not say it was interrupted: {run.lines[-1:]!r}")
    assert not bad, "; ".join(bad)


def test_fit_ctrl_c_console_script(work):
    """The real console script in its own interpreter: Ctrl-C exits 130 with one line."""
    out = work / "o.dam"
    ckpt = Path(str(out) + ".ckpt")
    exe = Path(sys.executable).parent / "damcap"
    # as from a terminal: SIGINT at its default, even when this test run was started in the
    # background by a shell without job control (which starts it, and so every child, with SIGINT
    # ignored: Python then installs no KeyboardInterrupt handler and Ctrl-C does nothing)
    p = subprocess.Popen([str(exe), "fit", str(work / "cap"), "-o", str(out), *FIT], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.monotonic()
    while not ckpt.is_file() and time.monotonic() - t0 < 40 and p.poll() is None:
        time.sleep(0.05)
    p.send_signal(signal.SIGINT)
    try:
        _, err = p.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        p.kill()
        pytest.fail("still running 20 s after Ctrl-C")
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert p.returncode == 130 and "Traceback" not in err and not out.exists(), (p.returncode, err[-300:])
    assert lines and ckpt.name in lines[-1], lines[-1:]


def test_checkpoint_of_another_capture_is_not_resumed(work):
    """A checkpoint left by a fit of capture A must not seed the fit of capture B."""
    run, out, ckpt, _, _ = _interrupted(work, [signal.SIGINT])
    assert ckpt.is_file(), "setup: no checkpoint"
    other = work / "corpus" / "captures" / "b"
    from tests.fuzz.conftest import transforms, set_transforms
    doc = transforms(other)
    doc["train_filenames"], doc["test_filenames"] = doc["test_filenames"], doc["train_filenames"]
    set_transforms(other, doc)
    again = damcap_fork(["fit", other, "-o", out, *FIT], timeout=30, signal_when=(AFRESH, signal.SIGKILL))
    said = (again.err + again.out).lower()
    assert "resuming" not in said and AFRESH in said, f"resumed another capture's checkpoint: {said[-200:]!r}"


def test_checkpoint_with_other_options_is_not_resumed(work):
    run, out, ckpt, _, cap = _interrupted(work, [signal.SIGINT])
    assert ckpt.is_file(), "setup: no checkpoint"
    again = damcap_fork(["fit", cap, "-o", out, *FIT[:-6], "--width", "16", *FIT[-6:]], timeout=30, signal_when=(AFRESH, signal.SIGKILL))
    said = (again.err + again.out).lower()
    assert "resuming" not in said and AFRESH in said, f"resumed a checkpoint of other options: {said[-200:]!r}"


def test_checkpoint_corrupt_is_refused_or_set_aside(work):
    out = work / "o.dam"
    ckpt = Path(str(out) + ".ckpt")
    ckpt.write_bytes(os.urandom(500))
    run = damcap_fork(["fit", work / "cap", "-o", out, "--steps", "2", "--batch-size", "32", "--holdout-views", "0"], timeout=20)
    assert "Traceback" not in run.err and not run.timed_out, run.err[-300:]
    if run.code != 0:
        assert run.lines and run.lines[-1].startswith("error:") and ckpt.name in run.lines[-1], run.lines[-1:]
