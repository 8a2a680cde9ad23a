"""The template of damcap_materials.py: what runs without Blender (finding its folder). The parts
that need Blender (materials, mesh, OSL compile) run in Blender in tests/export/test_blender.py."""

from __future__ import annotations

import pytest

from damcap.export import blender, blender_script


def test_template_has_one_configuration_line():
    text = open(blender_script.__file__, encoding="utf-8").read()
    assert text.count(blender.CONFIG_LINE) == 1 and blender_script.SCRIPT_NAME == blender.SCRIPT_NAME


def test_script_folder_is_where_the_shaders_are(tmp_path, monkeypatch):
    monkeypatch.setattr(blender_script, "CONFIG", {"materials": [{"osl": "gold.osl"}, {"osl": "red.osl"}]})
    script = tmp_path / "damcap_materials.py"
    script.write_text("")
    (tmp_path / "gold.osl").write_text("")
    with pytest.raises(RuntimeError, match=r"cannot find the \.osl files beside damcap_materials\.py"):
        blender_script.script_folder(str(script))  # red.osl is missing
    (tmp_path / "red.osl").write_text("")
    assert blender_script.script_folder(str(script)) == str(tmp_path)
    with pytest.raises(RuntimeError, match="run it from the folder damcap export wrote"):
        blender_script.script_folder(None)  # no __file__ and no text block of that name
