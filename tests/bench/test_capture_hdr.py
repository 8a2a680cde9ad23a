"""bench.capture_hdr at tiny sizes: Memorial Church cropped to 40x24 and a simulated RAW bracket
of a 128x64 piece of an environment map, every method side by side."""

from __future__ import annotations

import json
import shutil

import numpy as np

from bench import capture_hdr


def tiny_data(shared_data, root):
    """A shared-data folder in miniature: memorial's 16 frames and reference cropped alike, one
    small environment map."""
    import cv2

    from damcap.common.exr import read_exr

    (root / "MANIFEST.md").parent.mkdir(parents=True, exist_ok=True)
    (root / "MANIFEST.md").write_text("tiny copy for the bench smoke test\n")
    src, dst = shared_data / "brackets" / "memorial", root / "brackets" / "memorial"
    dst.mkdir(parents=True)
    shutil.copy(src / "memorial.hdr_image_list.txt", dst)
    crop = (slice(300, 324), slice(200, 240))
    for png in sorted(src.glob("memorial*.png")):
        cv2.imwrite(str(dst / png.name), cv2.imread(str(png), cv2.IMREAD_UNCHANGED)[crop])
    ref = read_exr(src / "memorial_reference.hdr")[0][..., :3][crop]
    cv2.imwrite(str(dst / "memorial_reference.hdr"), np.ascontiguousarray(ref[..., ::-1], np.float32))
    env = read_exr(shared_data / "envmaps" / "sunset.hdr")[0][..., :3][192:256, 384:512]
    (root / "envmaps").mkdir()
    cv2.imwrite(str(root / "envmaps" / "tiny.hdr"), np.ascontiguousarray(env[..., ::-1], np.float32))
    return root


def test_capture_hdr_study_writes_errors(tmp_path, shared_data):
    data = tiny_data(shared_data, tmp_path / "data")
    argv = ["--data", str(data), "--envmaps", "tiny", "--repeats", "1", "--skip-slow", "--skip-knobs",
            "--json", str(tmp_path / "capture_hdr.json"), "--md", str(tmp_path / "capture_hdr.md")]
    assert capture_hdr.main(argv) == 0
    doc = json.loads((tmp_path / "capture_hdr.json").read_text())
    assert doc["command"].endswith(" && .venv/bin/python -m bench.capture_hdr " + " ".join(argv))
    assert doc["memorial"]["frames"] == 16 and doc["memorial"]["size"] == [24, 40]
    rows = doc["memorial"]["rows"]
    assert "colour-hdri own Debevec response" not in rows and "memorial_knobs" not in doc  # --skip-slow, --skip-knobs
    for name in ("damcap (Debevec response recovered)", "damcap (told: sRGB curve)", "OpenCV Debevec calibrate + merge"):
        assert 0.0 <= rows[name]["median"] <= rows[name]["p90"] < 5.0
    raw = doc["raw"]["tiny"]
    assert raw["size"] == [64, 128]
    for method in ("damcap", "colour-hdri"):
        assert 0.0 <= raw[method]["median"] <= raw[method]["p90"] < 5.0 and len(raw[method]["wall_s_all"]) == 1
    assert raw["speedup_wall"] > 0
    md = (tmp_path / "capture_hdr.md").read_text()
    assert "damcap (Debevec response recovered)" in md
