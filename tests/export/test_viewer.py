"""The WebGL viewer against damcap's CPU render, in a real browser."""

from __future__ import annotations

import numpy as np

from damcap.appearance.metrics import dssim
from damcap.cli.main import main
from damcap.common.colour import display_srgb8
from damcap.common.exr import read_exr, read_image_u8
from damcap.export.browser import screenshot


def _linear(u8: np.ndarray) -> np.ndarray:
    import colour
    return colour.cctf_decoding(u8[..., :3] / 255.0, function="sRGB")


def test_viewer_matches_cpu_render_in_a_real_browser(browser, model_file, bunny, tmp_path):
    assert main(["view", str(model_file), "--mesh", str(bunny), "-o", str(tmp_path / "view.html"), "--azimuth", "45"]) == 0
    html = (tmp_path / "view.html").read_text()
    assert "<script src" not in html and "http" not in html.split("<script>", 1)[1]  # self-contained
    screenshot(tmp_path / "view.html", tmp_path / "shot.png", 256, fragment="az=45&el=20&caption=0")
    shot = read_image_u8(tmp_path / "shot.png")
    # damcap's own CPU render of the same view (the export's second frame of 8 is at azimuth 45)
    assert main(["export", str(model_file), "--mesh", str(bunny), "-o", str(tmp_path / "cpu"), "--views", "8", "--resolution", "256"]) == 0
    cpu = read_exr(tmp_path / "cpu" / "frames" / "0001.exr")[0]
    scale = float(html.split('"exposure_scale": ')[1].split(",")[0])
    ref = display_srgb8(cpu[..., :3], scale)
    d = dssim(_linear(ref), _linear(shot), cpu[..., 3])
    assert d <= 0.02, d
    # background is black where damcap sees no surface
    assert shot[cpu[..., 3] == 0][:, :3].mean() < 1.0
