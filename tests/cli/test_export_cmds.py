"""`damcap view` and `damcap export --format threejs` with several models (one per mesh part), and
`damcap shape pot`: what they parse, what the page and the module hold, and the one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
from damcap.appearance.dam_file import save_dam

from tests.conftest import assert_one_line_error, run_cli, write_tetra_obj_with_materials


@pytest.fixture(scope="module")
def dams(tmp_path_factory):
    """Three small random DAMs (no fit: what is checked here is which model goes where)."""
    import torch

    folder = tmp_path_factory.mktemp("dams")
    paths = []
    for k in range(3):
        model = DeepAppearanceMap(DamArchitecture(width=8, depth=1), generator=torch.Generator().manual_seed(k))
        save_dam(folder / f"m{k}.dam", model, colorspace="lin_rec709", made_by="fit")
        paths.append(folder / f"m{k}.dam")
    return paths


@pytest.fixture(scope="module")
def pot(tmp_path_factory):
    from damcap.export.shapes import pot_mesh, write_parted_obj

    mesh, names = pot_mesh(segments=24, rings=12)
    return write_parted_obj(mesh, names, tmp_path_factory.mktemp("pot") / "pot.obj")[0]


def _page_data(html: str) -> dict:
    return json.loads(html.split("const DATA = ", 1)[1].split(";\nconst params", 1)[0])


def _glsl_weights(glsl: str) -> str:
    """The first layer's constants of a DAM's GLSL (tells the models apart)."""
    return glsl.split("dam_W0", 1)[1].split(";", 1)[0]


def test_view_draws_each_part_with_its_model(dams, pot, tmp_path, capsys):
    from damcap.appearance.dam_file import load_dam
    from damcap.export.glsl import glsl_source

    code, out, err = run_cli(["view", *dams, "--mesh", pot, "-o", tmp_path / "v.html"], capsys)
    assert code == 0, err
    assert "body: m0.dam, lid: m1.dam, handle: m2.dam on pot.obj" in out
    data = _page_data((tmp_path / "v.html").read_text())
    assert [p["name"] for p in data["parts"]] == ["body", "lid", "handle"]
    # the index buffer holds the parts one after the other, in the OBJ's group order
    from damcap.export.turntable import shape_and_parts

    _, shape, part = shape_and_parts(pot, None, 3)
    counts = np.bincount(part, minlength=3)
    assert [(p["first"], p["count"]) for p in data["parts"]] == [(0, counts[0]), (counts[0], counts[1]), (counts[0] + counts[1], counts[2])]
    indices = np.frombuffer(__import__("base64").b64decode(data["mesh"]["indices"]), "<u4").reshape(-1, 3)
    assert np.array_equal(indices, shape.triangles[np.argsort(part, kind="stable")])
    for k, path in enumerate(dams):
        assert _glsl_weights(data["dam_glsl"][k]) == _glsl_weights(glsl_source(load_dam(path)[0]))
    assert len({_glsl_weights(g) for g in data["dam_glsl"]}) == 3


def test_view_of_one_model_is_unchanged_in_use(dams, pot, tmp_path, capsys):
    code, out, err = run_cli(["view", dams[0], "-o", tmp_path / "s.html"], capsys)
    assert code == 0 and out.strip() == f"wrote {tmp_path / 's.html'}", (out, err)
    data = _page_data((tmp_path / "s.html").read_text())
    assert len(data["dam_glsl"]) == 1 and data["parts"][0]["name"] == "part 0" and data["title"] == "m0.dam on a sphere"
    # one model on a mesh in parts: every part takes it
    code, _, err = run_cli(["view", dams[0], "--mesh", pot, "-o", tmp_path / "p.html"], capsys)
    assert code == 0, err
    data = _page_data((tmp_path / "p.html").read_text())
    assert len(data["parts"]) == 1 and data["parts"][0]["count"] * 3 == len(__import__("base64").b64decode(data["mesh"]["indices"])) // 4


def test_view_with_labels(dams, tmp_path, capsys):
    obj = write_tetra_obj_with_materials(tmp_path)  # 4 vertices
    np.save(tmp_path / "l.npy", np.array([0, 1, 1, 0]))
    code, _, err = run_cli(["view", dams[0], dams[1], "--mesh", obj, "--labels", tmp_path / "l.npy", "-o", tmp_path / "v.html"], capsys)
    assert code == 0, err
    data = _page_data((tmp_path / "v.html").read_text())
    assert [p["name"] for p in data["parts"]] == ["part 0", "part 1"] and sum(p["count"] for p in data["parts"]) == 4


@pytest.mark.parametrize("case", ["two-models-no-mesh", "labels-no-mesh", "more-models-than-groups", "fewer-models-than-groups",
                                  "models-no-groups", "labels-fewer-parts", "label-out-of-range"])
@pytest.mark.parametrize("command", ["view", "threejs"])
def test_parts_and_models_must_agree(command, case, dams, pot, tmp_path, capsys):
    obj = write_tetra_obj_with_materials(tmp_path)
    plain = tmp_path / "plain.obj"
    plain.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    np.save(tmp_path / "two.npy", np.array([0, 1, 1, 0]))
    np.save(tmp_path / "three.npy", np.array([0, 1, 2, 0]))
    args, needles = {
        "two-models-no-mesh": ([dams[0], dams[1]], ["2 models were given", "no --mesh"]),
        "labels-no-mesh": ([dams[0], "--labels", tmp_path / "two.npy"], ["two.npy", "--labels needs --mesh"]),
        "more-models-than-groups": ([*dams, dams[0], "--mesh", pot], ["pot.obj", "3 part(s), but 4 models were given"]),
        "fewer-models-than-groups": ([dams[0], dams[1], "--mesh", pot], ["pot.obj", "part 2 has no model", "give 3 .dam files"]),
        "models-no-groups": ([dams[0], dams[1], "--mesh", plain], ["plain.obj", "no OBJ material groups", "2 models were given"]),
        "labels-fewer-parts": ([*dams, "--mesh", obj, "--labels", tmp_path / "two.npy"], ["two.npy", "labels name parts 0..1, but 3 models"]),
        "label-out-of-range": ([dams[0], dams[1], "--mesh", obj, "--labels", tmp_path / "three.npy"], ["three.npy", "label 2 at vertex 2"]),
    }[case]
    out = tmp_path / ("v.html" if command == "view" else "m.js")
    cmd = ["view", *args, "-o", out] if command == "view" else ["export", *args, "--format", "threejs", "-o", out]
    code, _, err = run_cli(cmd, capsys)
    assert_one_line_error(code, err, *needles)
    assert not out.exists()


def test_threejs_module_in_parts(dams, pot, tmp_path, capsys):
    code, out, err = run_cli(["export", *dams, "--mesh", pot, "--format", "threejs", "-o", tmp_path / "m.js"], capsys)
    assert code == 0, err
    js = (tmp_path / "m.js").read_text()
    assert 'export const PARTS = ["body", "lid", "handle"];' in js
    glsl = json.loads(js.split("const DAM_GLSL = ", 1)[1].split(";\nconst VERTEX_SHADER", 1)[0])
    assert len(glsl) == 3 and len({_glsl_weights(g) for g in glsl}) == 3
    geometry = json.loads(js.split("const GEOMETRY = ", 1)[1].split(";\n", 1)[0])
    starts = [g[0] for g in geometry["groups"]]
    assert [g[2] for g in geometry["groups"]] == [0, 1, 2] and starts[0] == 0 and starts[1] == geometry["groups"][0][1]
    # one model, no mesh: the module of one material, as before
    code, out, err = run_cli(["export", dams[0], "--format", "threejs", "-o", tmp_path / "one.js"], capsys)
    assert code == 0 and "import { damcapMaterial } from it" in out, err
    one = (tmp_path / "one.js").read_text()
    assert "export function damcapMaterial(THREE" in one and "damcapGeometry" not in one


def test_shape_pot_writes_an_obj_in_three_named_parts(tmp_path, capsys):
    from damcap.common.mesh import load_mesh
    from damcap.export.shapes import obj_part_names

    code, out, err = run_cli(["shape", "pot", tmp_path / "pot.obj"], capsys)
    assert code == 0, err
    assert "parts body, lid, handle" in out and (tmp_path / "pot.mtl").is_file()
    assert obj_part_names(tmp_path / "pot.obj") == ["body", "lid", "handle"]
    assert set(np.unique(load_mesh(tmp_path / "pot.obj").triangle_groups)) == {0, 1, 2}
    code, _, err = run_cli(["shape", "pot", tmp_path / "pot.ply"], capsys)
    assert_one_line_error(code, err, "pot.ply", "written as .obj")
    assert not (tmp_path / "pot.ply").exists()
