"""bench.blender at tiny sizes: the sphere agreement at 16x16 and a 32x32 torus render in Blender."""

from __future__ import annotations

import json
import os

import pytest

from bench import blender


def test_blender_study_writes_agreement_and_render_time(tmp_path):
    if not blender.BLENDER_PYTHON.exists():
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"{blender.BLENDER_PYTHON}: Blender (the bpy module) is required under CI (make test installs it)")
        pytest.skip(f"{blender.BLENDER_PYTHON}: Blender's bpy module not installed (make blender installs it)")
    argv = ["--sphere", "16", "--resolution", "32", "--samples", "1", "--no-install", "--out", str(tmp_path)]
    assert blender.main(argv) == 0
    doc = json.loads((tmp_path / "blender.json").read_text())
    assert doc["command"] == ".venv/bin/python -m bench.blender " + " ".join(argv)
    assert [r["model"] for r in doc["agreement"]] == ["yup", "zup", "fit_default_yup"]
    for r in doc["agreement"]:
        assert r["pixels"] > 150 and r["silhouette_agreement"] > 0.99
        assert r["relative_error"]["exported"]["median"] < 0.005 < 0.1 < r["relative_error"]["view flipped"]["median"]
    rows = doc["mesh_render"]["rows"]
    assert [r["samples"] for r in rows] == [1] and 0 < rows[0]["render_s"] < 60 and 50 < rows[0]["covered_pixels"] < 32 * 32
    assert doc["install"] is None
    md = (tmp_path / "blender.md").read_text()
    versus = doc["mesh_render"]["against_damcap_frame"]
    assert versus["pixels"] >= 0.98 * versus["damcap_covered"] and versus["median"] < 0.005
    assert (tmp_path / "blender_mesh.png").exists()
    assert "## Agreement" in md and "## A mesh" in md and "## Install" not in md
