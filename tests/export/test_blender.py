"""DAMs into Blender: the OSL text (pure Python) and, in Blender 5.0.1 itself (the bpy module of
.venv-blender, `make blender`), Cycles renders of the exported materials against damcap's own
evaluation of the models."""

from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, hidden_activation, rotated_world_weights
from damcap.appearance.dam_file import save_dam
from damcap.cli.main import main
from damcap.export.blender import blender_from_world, materials_script, mesh_arrays, osl_source, shader_name
from damcap.export.turntable import shape_and_parts

REPO = Path(__file__).resolve().parents[2]
DRIVER = Path(__file__).with_name("blender_driver.py")
#: the agreement asked of Cycles' render and damcap's evaluation: median relative error per colour value
MEDIAN_REL_TOL = 0.005
#: a wrong axis mapping or a flipped view direction must miss by far more than the tolerance
WRONG_REL_MIN = 0.1
RESOLUTION = 24
TORUS_RESOLUTION = 48
CAMERA = {"location": [0.8, -2.6, 1.2], "target": [0.0, 0.0, 0.0], "lens_mm": 50.0}
UPS = {"yup": [0.0, 1.0, 0.0], "zup": [0.0, 0.0, 1.0]}
#: Blender's frame from each model's, written out (what Blender's OBJ importer does to a +Y-up mesh):
#: the renders are checked against these, not against the code under test
BLENDER_FROM_DAM = {"yup": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]), "zup": np.eye(3)}


def random_model(arch: DamArchitecture, scale: float, seed: int) -> DeepAppearanceMap:
    """A DAM with random weights and (if any) random biases: strongly view-dependent, no symmetry."""
    g = torch.Generator().manual_seed(seed)
    m = DeepAppearanceMap(arch, scale, generator=g)
    if arch.bias:
        m.set_flat_weights(m.get_flat_weights() + 0.2 * torch.randn(arch.num_weights, generator=g))
    return m


MODELS = {  # name: (architecture, radiance scale)
    "yup": (DamArchitecture(width=16, depth=3, encoding="vnr", bias=True, activation="leaky_relu"), 2.5),
    "zup": (DamArchitecture(width=16, depth=2, encoding="nr", separable=True, activation="shifted_softplus"), 0.7),
}


def osl_arrays(src: str) -> dict[str, np.ndarray]:
    """The constant arrays of an OSL shader's text, by name."""
    return {m.group(1): np.array([float(x) for x in m.group(2).split(",")])
            for m in re.finditer(r"float (\w+)\[\d+\] = \{([^}]*)\};", src)}


def osl_forward_numpy(src: str, arch: DamArchitecture, v: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The shader's network read back from its text and evaluated in float64 (the OSL's loops)."""
    arrays = osl_arrays(src)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    r = 2 * np.sum(n * v, -1, keepdims=True) * n - v
    x = np.concatenate({"vn": [v, n], "nr": [n, r], "vnr": [v, n, r]}[arch.encoding], -1)
    for k, (o, i) in enumerate(arch.layer_shapes):
        x = x @ arrays[f"W{k}"].reshape(o, i).T + (arrays[f"B{k}"] if arch.bias else 0)
        if k < len(arch.layer_shapes) - 1:
            x = hidden_activation(torch.from_numpy(x), arch.activation).numpy()
    scale = float(re.search(r"radiance = color\(.*\) \* ([^;]+);", src).group(1))
    return torch.nn.functional.softplus(torch.from_numpy(x)).numpy() * scale


def test_blender_from_world_turns_up_onto_z_like_blenders_importers():
    r = blender_from_world(np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(r @ [1.0, 2.0, 3.0], [1.0, -3.0, 2.0], atol=1e-12)  # (x, y, z) -> (x, -z, y)
    np.testing.assert_allclose(blender_from_world(np.array([0.0, 0.0, 2.0])), np.eye(3), atol=1e-12)
    down = blender_from_world(np.array([0.0, 0.0, -1.0]))
    np.testing.assert_allclose(down @ [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], atol=1e-12)
    assert np.linalg.det(down) == pytest.approx(1.0)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_osl_text_evaluates_the_model_in_blenders_frame(name):
    arch, scale = MODELS[name]
    model = random_model(arch, scale, seed=3)
    rot = blender_from_world(np.array(UPS[name]))
    src = osl_source(model, rot, shader_name(name), note="test")
    assert f"shader damcap_{name}(" in src and "output color radiance" in src
    assert "normalize(I)" in src and ("B0[" in src) == arch.bias
    rng = np.random.default_rng(0)
    v_b, n_b = rng.normal(size=(256, 3)), rng.normal(size=(256, 3))
    got = osl_forward_numpy(src, arch, v_b, n_b)
    with torch.no_grad():  # damcap's own evaluation, in the model's world: v_dam = R^T v_blender
        want = model(torch.from_numpy(v_b @ rot).float(), torch.from_numpy(n_b @ rot).float()).double().numpy()
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-7)
    # the first layer carries the rotation, the others the weights as they are
    arrays = osl_arrays(src)
    turned = rotated_world_weights(model.get_flat_weights().double(), arch, torch.from_numpy(rot.T.copy()))
    n0 = arch.layer_weight_counts[0]
    if not arch.separable:
        np.testing.assert_allclose(arrays["W0"], turned[:n0].numpy(), rtol=1e-7, atol=1e-12)


def test_osl_refuses_a_reflection():
    model = random_model(DamArchitecture(width=4, depth=1), 1.0, seed=0)
    with pytest.raises(ValueError, match="rotation"):
        osl_source(model, np.diag([1.0, 1.0, -1.0]), "m")


def test_materials_script_is_python_carrying_its_configuration():
    mats = [{"name": "gold", "osl": "gold.osl", "exposure": 0.5, "model": "gold.dam"}]
    text = materials_script(mats, {"file": "torus.npz", "name": "torus"})
    code = compile(text, "damcap_materials.py", "exec")
    scope: dict = {"__name__": "not_main"}
    exec(code, scope)  # defines the functions; main() (which needs bpy) only runs as __main__
    assert scope["CONFIG"] == {"materials": mats, "mesh": {"file": "torus.npz", "name": "torus"}}
    assert text.startswith('"""damcap\'s materials for Blender') and "shading_system = True" in text


def test_mesh_arrays_turn_vertices_and_normals():
    rot = blender_from_world(np.array([0.0, 1.0, 0.0]))
    out = mesh_arrays(np.array([[0.0, 1.0, 0.0], [1.0, 2.0, 3.0], [0, 0, 1.0]]), np.array([[0, 1, 2]]),
                      np.array([[0.0, 1.0, 0.0]] * 3), np.array([0]), rot)
    np.testing.assert_allclose(out["vertices"], [[0, 0, 1], [1, -3, 2], [0, -1, 0]], atol=1e-6)
    np.testing.assert_allclose(out["normals"][0], [0, 0, 1], atol=1e-6)
    assert out["triangles"].dtype == np.int32 and out["part"].tolist() == [0]


# ------------------------------------------------------------------------------------------
# The export command, then Blender itself

TWO_PART_OBJ = """# two squares, two materials
v -1 0 0
v 0 0 0
v 0 1 0
v -1 1 0
v 0 0 0.5
v 1 0 0.5
v 1 1 0.5
v 0 1 0.5
vn 0 0 1
usemtl left
f 1//1 2//1 3//1
f 1//1 3//1 4//1
usemtl right
f 5//1 6//1 7//1
f 5//1 7//1 8//1
f 5//1 8//1 6//1
"""


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """Exports: each test model alone, and two models on a two-part mesh (OBJ groups and --labels)."""
    root = tmp_path_factory.mktemp("blender")
    paths = {}
    for k, (name, (arch, scale)) in enumerate(sorted(MODELS.items())):
        paths[name] = root / f"{name}.dam"
        save_dam(paths[name], random_model(arch, scale, seed=10 + k), colorspace="lin_rec709", made_by="fit", up_world=np.array(UPS[name]))
        assert main(["export", str(paths[name]), "--format", "blender", "-o", str(root / f"out_{name}")]) == 0
    obj = root / "two.obj"
    obj.write_text(TWO_PART_OBJ)
    assert main(["export", str(paths["yup"]), str(paths["zup"]), "--format", "blender", "--mesh", str(obj),
                 "-o", str(root / "out_groups")]) == 0
    labels = root / "two_labels.txt"
    labels.write_text("\n".join(["1"] * 4 + ["0"] * 4) + "\n")  # the other way round
    assert main(["export", str(paths["yup"]), str(paths["zup"]), "--format", "blender", "--mesh", str(obj), "--labels", str(labels),
                 "-o", str(root / "out_labels")]) == 0
    torus = root / "torus.obj"
    assert main(["shape", "torus", str(torus)]) == 0
    assert main(["export", str(paths["yup"]), "--format", "blender", "--mesh", str(torus), "-o", str(root / "out_torus")]) == 0
    assert main(["export", str(paths["yup"]), "--mesh", str(torus), "-o", str(root / "frames_torus"), "--views", "1",
                 "--resolution", str(TORUS_RESOLUTION), "--elevation", "35", "--azimuth0-deg", "30"]) == 0
    return root, paths, obj, labels


def blender_camera_of(export_json: dict, rot: np.ndarray) -> dict:
    """The Blender camera (driver spec) that sees the mesh file's vertices, turned by ``rot``, as
    the first frame of damcap export did: its centre moved from the unit-sphere render to the file's frame."""
    m = np.array(export_json["world_from_cam"][0])
    t = export_json["mesh_transform"]
    centre, radius = np.array(t["centre"]), t["radius"]
    intr = export_json["intrinsics"]
    return {"location": (rot @ (centre + radius * m[:3, 3])).tolist(), "target": (rot @ centre).tolist(),
            "lens_mm": intr["fl_x"] / intr["w"] * 36.0}


def test_export_writes_shaders_script_and_mesh(exported, capsys):
    root, paths, obj, labels = exported
    assert sorted(p.name for p in (root / "out_yup").iterdir()) == ["damcap_materials.py", "yup.osl"]
    assert sorted(p.name for p in (root / "out_groups").iterdir()) == ["damcap_materials.py", "two.npz", "yup.osl", "zup.osl"]
    for out, lab in (("out_groups", None), ("out_labels", labels)):
        data = np.load(root / out / "two.npz")
        _, shape, part = shape_and_parts(obj, lab, 2)
        assert data["part"].tolist() == part.tolist() and len(set(part.tolist())) == 2
        rot = blender_from_world(np.array(UPS["yup"]))  # the first model's up
        np.testing.assert_allclose(data["vertices"][4], rot @ [0.0, 0.0, 0.5], atol=1e-6)
    assert main(["export", str(paths["yup"]), "--format", "blender", "-o", str(root / "out_yup")]) == 0  # replaces its own output
    err = capsys.readouterr().err
    assert main(["export", str(paths["yup"]), str(paths["zup"]), "--format", "blender", "-o", str(root / "out_both")]) == 0
    assert "disagree about up" in capsys.readouterr().err and "disagree" not in err


def blender_python() -> Path:
    """The Python that has bpy: DAMCAP_BLENDER_PYTHON, else .venv-blender (`make blender`)."""
    path = Path(os.environ.get("DAMCAP_BLENDER_PYTHON") or REPO / ".venv-blender" / "bin" / "python")
    if not path.exists():
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"{path}: Blender (the bpy module) is required under CI (make test installs it: make blender)")
        pytest.skip(f"{path}: Blender's bpy module not installed (make blender installs it into .venv-blender)")
    return path


@pytest.fixture(scope="module")
def rendered(exported, tmp_path_factory):
    """One Blender process: each model's material on an exact sphere, and the two mesh exports."""
    python = blender_python()
    root, *_ = exported
    work = tmp_path_factory.mktemp("renders")
    jobs = [{"script": str(root / f"out_{n}" / "damcap_materials.py"), "sphere_material": n, "exposure": 1.0,
             "resolution": RESOLUTION, "out": str(work / n), "camera": CAMERA} for n in sorted(MODELS)]
    jobs += [{"script": str(root / out / "damcap_materials.py"), "resolution": 16, "out": str(work / out), "camera": CAMERA}
             for out in ("out_groups", "out_labels")]
    jobs.append({"script": str(root / "out_groups" / "damcap_materials.py"), "resolution": 8, "out": str(work / "rerun"), "camera": CAMERA,
                 "user_material": "yup", "runs": 2})
    frame = json.loads((root / "frames_torus" / "export.json").read_text())
    jobs.append({"script": str(root / "out_torus" / "damcap_materials.py"), "resolution": TORUS_RESOLUTION, "exposure": 1.0,
                 "out": str(work / "out_torus"), "camera": blender_camera_of(frame, BLENDER_FROM_DAM["yup"])})
    (work / "jobs.json").write_text(json.dumps(jobs))
    run = subprocess.run([str(python), str(DRIVER), str(work / "jobs.json")], capture_output=True, text=True, timeout=300,
                         env={k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")})
    if run.returncode != 0:
        pytest.fail(f"Blender driver failed ({run.returncode}):\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}")
    reports = json.loads((work / "jobs.json.out.json").read_text())
    return {j["out"].rsplit("/", 1)[-1]: (r, j) for j, r in zip(jobs, reports)}, run.stdout


def sphere_pixels(world_from_cam: np.ndarray, n: int, lens_mm: float, min_cos: float = 0.05):
    """Per pixel centre of an n x n Blender camera (36 mm sensor width): whether its ray meets the
    unit sphere at the origin (at more than ``min_cos`` from grazing), the world normal and the
    view direction (toward the camera) there. Returns (mask (n, n), normals (M, 3), views (M, 3))."""
    m = np.asarray(world_from_cam, np.float64)
    f = lens_mm / 36.0 * n
    j, i = np.meshgrid(np.arange(n) + 0.5, np.arange(n) + 0.5)
    d = np.stack([(j - n / 2) / f, (n / 2 - i) / f, -np.ones_like(j)], -1) @ m[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = m[:3, 3]
    b = d @ o
    disc = b * b - (o @ o - 1)
    p = o + (-b - np.sqrt(np.maximum(disc, 0)))[..., None] * d
    normal = p / np.linalg.norm(p, axis=-1, keepdims=True)
    mask = (disc > 0) & (np.sum(normal * -d, -1) > min_cos)
    return mask, normal[mask], -d[mask]


def relative_errors(got: np.ndarray, model: DeepAppearanceMap, views_dam: np.ndarray, normals_dam: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        want = model(torch.from_numpy(views_dam).float(), torch.from_numpy(normals_dam).float()).double().numpy()
    return np.abs(got - want) / np.maximum(np.abs(want), 1e-6)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_cycles_renders_the_model_as_damcap_evaluates_it(rendered, exported, name):
    from damcap.appearance.dam_file import load_dam

    reports, _ = rendered
    report, job = reports[name]
    assert (report["engine"], report["device"], report["osl"]) == ("CYCLES", "CPU", True)
    assert report["groups"][f"damcap {name}"]["script_outputs"] == ["radiance"]
    px = np.load(job["out"] + ".npy")
    mask, normals_b, views_b = sphere_pixels(np.array(report["world_from_cam"]), RESOLUTION, CAMERA["lens_mm"])
    covered = (px[..., 3] > 0.999)[mask]  # the render's silhouette agrees with the analytic one
    assert covered.mean() > 0.99, covered.mean()
    normals_b, views_b, got = normals_b[covered], views_b[covered], px[mask][covered][:, :3].astype(np.float64)
    assert len(got) >= 300, len(got)  # most of the frame is sphere
    model, _ = load_dam(exported[1][name])
    rot = BLENDER_FROM_DAM[name]
    rel = relative_errors(got, model, views_b @ rot, normals_b @ rot)
    print(f"{name}: {len(got)} pixels, median relative error {np.median(rel):.2e}, p90 {np.percentile(rel, 90):.2e}")
    assert np.median(rel) <= MEDIAN_REL_TOL, (np.median(rel), np.percentile(rel, 90))
    # the comparison tells the conventions apart: a view direction pointing the other way, or
    # the model's world taken as Blender's (no turn; for the +Z-up model: the +Y-up turn) miss by far
    wrong_rot = BLENDER_FROM_DAM["zup" if name == "yup" else "yup"]
    assert np.median(relative_errors(got, model, -views_b @ rot, normals_b @ rot)) > WRONG_REL_MIN
    assert np.median(relative_errors(got, model, views_b @ wrong_rot, normals_b @ wrong_rot)) > WRONG_REL_MIN


@pytest.mark.parametrize("out, slots", [("out_groups", ["yup", "zup"]), ("out_labels", ["yup", "zup"])])
def test_script_adds_the_mesh_with_one_material_per_part(rendered, exported, out, slots):
    root, paths, obj, labels = exported
    reports, stdout = rendered
    report, job = reports[out]
    part = np.load(root / out / "two.npz")["part"]
    assert report["objects"]["two"]["slots"] == slots
    assert report["objects"]["two"]["material_index"] == np.bincount(part, minlength=2).tolist()
    scope: dict = {"__name__": "not_main"}
    exec(compile((root / out / "damcap_materials.py").read_text(), "damcap_materials.py", "exec"), scope)
    for m in scope["CONFIG"]["materials"]:
        assert report["groups"][f"damcap {m['name']}"]["exposure"] == pytest.approx(m["exposure"], rel=1e-6)
    assert report["view_transform"] == "Standard"
    px = np.load(job["out"] + ".npy")
    assert (px[..., 3] > 0.5).sum() > 10 and np.isfinite(px).all() and px[..., :3].max() > 0  # the mesh renders, lit by its DAMs
    assert "damcap: added two (5 triangles) with material slots yup, zup" in stdout


def test_the_mesh_in_blender_looks_as_damcaps_own_frame(rendered, exported):
    """The exported torus and its material, seen in Blender from damcap export's first camera:
    the same pixels covered, the same radiance (vertex normals interpolated by both renderers)."""
    from damcap.common.exr import read_exr

    root, *_ = exported
    reports, _ = rendered
    _, job = reports["out_torus"]
    px = np.load(job["out"] + ".npy")
    frame = read_exr(root / "frames_torus" / "frames" / "0000.exr")[0]
    ours, theirs = frame[..., 3] > 0.999, px[..., 3] > 0.999
    assert ours.sum() > 300 and (ours & theirs).sum() >= 0.98 * ours.sum(), ((ours & theirs).sum(), ours.sum(), theirs.sum())
    both = ours & theirs
    rel = np.abs(px[..., :3][both] - frame[..., :3][both]) / np.maximum(frame[..., :3][both], 1e-6)
    print(f"torus: {both.sum()} pixels, median relative error {np.median(rel):.2e}, p90 {np.percentile(rel, 90):.2e}")
    assert np.median(rel) <= MEDIAN_REL_TOL, (np.median(rel), np.percentile(rel, 90))


def test_script_reruns_refill_its_own_materials_and_leave_the_users(rendered):
    """Run twice in a scene that has a material of the user's named like a model: that one stays
    as it was, the DAM's gets a suffix, and the second run makes no further copies."""
    reports, _ = rendered
    report, _ = reports["rerun"]
    assert report["user_materials"] == ["yup"]
    assert report["materials"] == {"yup": [], "yup.001": ["damcap yup"], "zup": ["damcap zup"]}
    assert sorted(report["groups"]) == ["damcap yup", "damcap zup"] and report["texts"] == ["yup.osl", "zup.osl"]
    assert [o["slots"] for o in report["objects"].values()] == [["yup.001", "zup"]] * 2  # each run adds the mesh once
