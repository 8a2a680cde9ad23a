"""bench.clipped: the simulated sensor clip, and the study at tiny sizes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench import clipped
from damcap.appearance.views import ViewData
from damcap.common.capture_folder import FrameData


def _view(values: list[float], covered: list[bool]) -> ViewData:
    rad = np.repeat(np.asarray(values, np.float32)[None, :, None], 3, axis=2)
    rad[..., 1] *= 0.5  # the largest channel is R
    n = len(values)
    nrm = np.zeros((1, n, 3), np.float32)
    nrm[..., 2] = 1
    cov = np.asarray(covered, np.float32)[None]
    return ViewData("v", FrameData(rad, nrm, np.zeros((1, n, 3), np.float32), cov), np.eye(4))


def test_clip_level_is_the_object_pixels_largest_channel_quantile():
    v = _view([0.1, 0.2, 0.3, 0.4, 5.0], [True, True, True, True, False])  # the background's 5.0 does not count
    assert clipped.clip_level([v], 0.25) == pytest.approx(np.quantile([0.1, 0.2, 0.3, 0.4], 0.75))


def test_clipped_views_clamp_every_channel_and_drop_or_keep_the_clipped_pixels():
    v = _view([0.1, 0.5, 2.0], [True, True, True])
    (drop,), (keep,) = clipped.clipped_views([v], 0.5, "drop"), clipped.clipped_views([v], 0.5, "keep")
    for out in (drop, keep):
        assert out.data.radiance_lin[0, :, 0].tolist() == pytest.approx([0.1, 0.5, 0.5]) and out.data.radiance_lin[0, 2, 1] == 0.5
    assert drop.data.coverage.tolist() == [[1, 0, 0]] and keep.data.coverage.tolist() == [[1, 1, 1]]
    assert v.data.radiance_lin[0, 2, 0] == 2.0  # the input is not modified


def test_clipped_study_scores_each_treatment(tmp_path, is_dssim):
    out = tmp_path / "out"
    assert clipped.main(["--scenes", "sphere-env", "--clip-fraction", "0.1", "--fit-steps", "20", "--resolution", "24",
                         "--cache", str(tmp_path / "cache"), "--out", str(out)]) == 0
    doc = json.loads((out / "clipped.json").read_text())
    assert [r["treatment"] for r in doc["rows"]] == ["drop", "keep"]
    for r in doc["rows"]:
        assert is_dssim(r["novel_dssim"]) and r["highlight_pixels"] > 0 and r["highlight_error"] > 0
        assert r["true_peak_over_level"] > 1
    assert doc["rows"][0]["novel_dssim"] != doc["rows"][1]["novel_dssim"]
    assert "| sphere-env | 10% |" in (out / "clipped.md").read_text()
