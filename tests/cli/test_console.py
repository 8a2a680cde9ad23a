"""The console script: an interrupt while the commands load ends in one line, never a traceback."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

import pytest

# the signal is sent from inside the import of damcap.cli.main, so it always lands while the
# commands load, however slow the machine
SCRIPT = textwrap.dedent("""
    import os, signal, sys

    class SignalOnLoad:
        def find_spec(self, name, path=None, target=None):
            if name == "damcap.cli.main":
                os.kill(os.getpid(), {sig})
            return None

    sys.meta_path.insert(0, SignalOnLoad())
    sys.argv = ["damcap", "--version"]
    from damcap.cli.console import run
    run()
""")


@pytest.mark.parametrize(("sig", "code", "line"), [(signal.SIGINT, 130, "interrupted"),
                                                    (signal.SIGTERM, 143, "interrupted (SIGTERM)")])
def test_an_interrupt_while_the_commands_load_is_one_line(sig, code, line):
    p = subprocess.run([sys.executable, "-c", SCRIPT.format(sig=int(sig))], capture_output=True, text=True, timeout=120)
    assert p.returncode == code, p.stderr
    assert p.stderr.strip().splitlines() == [line] and p.stdout == ""


def test_once_loaded_the_command_runs_with_its_own_handling():
    script = "import sys; sys.argv = ['damcap', '--version']\nfrom damcap.cli.console import run\nrun()"
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and p.stdout.startswith("damcap ") and p.stderr == "", p.stderr
