"""What C libraries print to file descriptor 2 is caught inside the block and restored after."""

from __future__ import annotations

import os

from damcap.common.native_stderr import native_stderr_caught


def test_fd2_writes_are_caught_and_stderr_is_restored(capfd):
    with native_stderr_caught() as lines:
        os.write(2, b"libpng error: gAMA: Read error\n\n  RPly: Error reading 'x'  \n")
    os.write(2, b"after\n")
    assert lines == ["libpng error: gAMA: Read error", "RPly: Error reading 'x'"]
    assert capfd.readouterr().err == "after\n"


def test_caught_even_when_the_block_raises(capfd):
    try:
        with native_stderr_caught() as lines:
            os.write(2, b"native\n")
            raise ValueError("x")
    except ValueError:
        pass
    assert lines == ["native"]
    os.write(2, b"back\n")
    assert capfd.readouterr().err == "back\n"
