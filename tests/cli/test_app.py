"""What every command shares: progress that reaches a log when output is not a terminal."""

from __future__ import annotations

from damcap.cli.app import LOG_PROGRESS_EVERY_S, LineProgress, make_bar


def _clock(times):
    it = iter(times)
    return lambda: next(it)


def test_a_short_stage_prints_nothing_and_a_long_one_prints_every_period_and_at_its_end():
    lines: list[str] = []
    short = LineProgress(3, "fit", clock=_clock([0.0, 1.0, 2.0, 3.0]), echo=lines.append)
    for _ in range(3):
        short.update()
    assert lines == []
    p = LOG_PROGRESS_EVERY_S
    long = LineProgress(10, "segment", clock=_clock([0.0] + [k * p / 3 for k in range(1, 11)]), echo=lines.append)
    for _ in range(10):
        long.update()
    assert [ln.split(":")[1].split(",")[0].strip() for ln in lines] == ["3/10 steps (30%)", "6/10 steps (60%)", "9/10 steps (90%)",
                                                                         "10/10 steps (100%)"]
    assert "left" in lines[0] and "left" not in lines[-1]


def test_iterating_counts_and_postfix_is_shown():
    lines: list[str] = []
    bar = LineProgress(2, "export", "frame", iterable=["a", "b"], clock=_clock([0.0, 100.0, 200.0]), echo=lines.append)
    bar.set_postfix_str("IMG_0001", refresh=False)
    assert list(bar) == ["a", "b"] and bar.n == 2
    assert lines[-1] == "export: 2/2 frames (100%), 200 s (IMG_0001)"


def test_a_log_gets_line_progress(monkeypatch):
    import sys

    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)
    assert isinstance(make_bar(5, "x"), LineProgress)
