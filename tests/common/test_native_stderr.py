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


def test_signal_handlers_are_kept_across_a_library_that_takes_them():
    import signal

    from damcap.common.native_stderr import signal_handlers_kept

    def ours(signum, frame):
        pass

    previous = signal.signal(signal.SIGTERM, ours)
    try:
        with signal_handlers_kept():
            signal.signal(signal.SIGTERM, signal.SIG_IGN)  # as a library loading would
        assert signal.getsignal(signal.SIGTERM) is ours
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_verbose_lets_native_log_lines_through(tmp_path, monkeypatch, capsys):
    from damcap.cli.main import main
    from damcap.common.native_stderr import VERBOSE_ENV, native_logs_wanted

    monkeypatch.delenv(VERBOSE_ENV, raising=False)
    assert not native_logs_wanted()
    monkeypatch.setenv(VERBOSE_ENV, "0")
    assert not native_logs_wanted()
    monkeypatch.delenv(VERBOSE_ENV)
    assert main(["--verbose", "shape", "sphere", str(tmp_path / "s.obj")]) == 0
    assert native_logs_wanted()
