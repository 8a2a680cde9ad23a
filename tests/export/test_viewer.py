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


PARTS_SIZE = 192
#: most a part's mean display colour may differ between the page and damcap's CPU render, 8-bit levels
#: per channel (measured in Chromium's SwiftShader: 0.00, 0.01, 0.04 for body, lid, handle)
PARTS_MEAN_TOL = 0.5
#: the 99th percentile of the per-pixel difference inside a part, 8-bit levels (measured: 1 in each part)
PARTS_P99_TOL = 2.0


def _page_data(html: str) -> dict:
    import json
    return json.loads(html.split("const DATA = ", 1)[1].split(";\nconst params", 1)[0])


def test_page_in_parts_matches_cpu_render_per_part(browser, part_models, pot, tmp_path):
    """Three models on the pot's three OBJ groups: each part of the page shows its own DAM, with
    the colours damcap's CPU render of the same view gives that part."""
    from scipy.ndimage import binary_erosion

    from damcap.appearance.dam_file import load_dam
    from damcap.export.turntable import OrbitOptions, render_orbit, shape_and_parts

    page = tmp_path / "parts.html"
    assert main(["view", *map(str, part_models), "--mesh", str(pot), "-o", str(page), "--azimuth", "30"]) == 0
    data = _page_data(page.read_text())
    assert [p["name"] for p in data["parts"]] == ["body", "lid", "handle"] and len(data["dam_glsl"]) == 3
    screenshot(page, tmp_path / "shot.png", PARTS_SIZE, fragment="az=30&el=20&caption=0")
    shot = read_image_u8(tmp_path / "shot.png")[..., :3].astype(np.float64)
    _, shape, part = shape_and_parts(pot, None, 3)
    dams = [load_dam(m)[0] for m in part_models]
    _, buf, rad = next(render_orbit(dams, shape, part, OrbitOptions(views=1, azimuth0_deg=30.0, resolution=PARTS_SIZE)))
    ref = display_srgb8(rad, data["exposure_scale"]).astype(np.float64)
    part_px = np.where((buf.coverage > 0.999) & (buf.triangle_id >= 0), part[np.maximum(buf.triangle_id, 0)], -1)
    means = []
    for k in range(3):
        inside = binary_erosion(part_px == k, iterations=2)  # away from silhouettes and part borders
        assert inside.sum() > 100, (k, inside.sum())
        diff = np.abs(shot[inside] - ref[inside])
        mean_gap = np.abs(shot[inside].mean(0) - ref[inside].mean(0)).max()
        print(f"part {k}: {inside.sum()} px, mean colour page {shot[inside].mean(0).round(1)} cpu {ref[inside].mean(0).round(1)}, "
              f"largest mean gap {mean_gap:.2f}, p99 {np.percentile(diff, 99):.1f} levels")
        assert mean_gap <= PARTS_MEAN_TOL, (k, mean_gap)
        assert np.percentile(diff, 99) <= PARTS_P99_TOL, (k, np.percentile(diff, 99))
        means.append(ref[inside].mean(0))
    # the parts' own colours differ by far more than the tolerance: a page drawing one DAM everywhere fails
    assert min(np.abs(means[a] - means[b]).max() for a, b in ((0, 1), (0, 2), (1, 2))) > 10 * PARTS_MEAN_TOL
    assert shot[buf.coverage == 0].mean() < 1.0  # background where damcap sees no surface
