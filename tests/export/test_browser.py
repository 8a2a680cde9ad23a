"""Driving a headless browser: the viewer's frame rate."""

from __future__ import annotations

from damcap.cli.main import main
from damcap.export.browser import frame_rate


def test_viewer_frame_rate_is_reported(browser, model_file, tmp_path):
    assert main(["view", str(model_file), "-o", str(tmp_path / "v.html")]) == 0
    fps = frame_rate(tmp_path / "v.html", 128, frames=5)
    assert fps > 0
