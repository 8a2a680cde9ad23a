"""bench.export at tiny sizes: a 32x32 CPU render of a generated torus (ray cast + DAM)."""

from __future__ import annotations

import json

from bench import export
from damcap.cli.main import main as damcap_main


def test_export_study_writes_render_times(tmp_path, small_capture):
    mesh = tmp_path / "torus.obj"
    assert damcap_main(["shape", "torus", str(mesh)]) == 0
    out = tmp_path / "out"
    argv = ["--mesh", str(mesh), "--capture", str(small_capture), "--resolution", "32", "--frames", "2",
            "--fit-steps", "20", "--fps-sizes", "--out", str(out)]
    assert export.main(argv) == 0
    doc = json.loads((out / "export.json").read_text())
    assert doc["command"] == "make bench  (.venv/bin/python -m bench.export " + " ".join(argv) + ")"
    r = doc["cpu_render_512"]
    assert r["resolution"] == 32 and r["frames"] == 2
    assert 50 < r["covered_pixels_median"] < 32 * 32  # the torus covers part of the frame
    assert 0 < r["raycast_ms_median"] < 10_000 and 0 < r["dam_ms_median"] < 10_000
    assert r["total_ms_median"] >= r["raycast_ms_median"]
    assert doc["mesh"]["triangles"] > 100 and doc["viewer_fps_headless_chromium_swiftshader"] == {}
    md = (out / "export.md").read_text()
    assert "## CPU render of a 32x32 frame" in md and f"Raw results: `{out / 'export.json'}`" in md
