"""Blender benchmark: does Cycles render ``damcap export --format blender``'s materials as damcap
evaluates the models, how long does a 512x512 frame of a mesh with them take, and what does the
Blender install (PyPI's bpy 5.0.1) cost?

Run (from the repository root, after ``make blender``): .venv/bin/python -m bench.blender
(writes bench/results/blender.json and bench/blender.md; ``--out DIR`` writes both into DIR instead;
``--demo DIR`` takes the materials and mesh of a ``make demo`` output, default: one DAM of the
fit's default architecture with random weights on a generated torus;
``--sphere 16 --resolution 32 --samples 1 --no-install`` makes a smoke run).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bench.common import BENCH, REPO, RESULTS, command_line, log, machine_info
from tests.export.test_blender import sphere_pixels  # the test's closed-form sphere: the same reference pixels

DRIVER = REPO / "tests" / "export" / "blender_driver.py"
BLENDER_PYTHON = REPO / ".venv-blender" / "bin" / "python"
REQUIREMENTS = REPO / "tests" / "blender.txt"
SPHERE_CAMERA = {"location": [0.8, -2.6, 1.2], "target": [0.0, 0.0, 0.0], "lens_mm": 50.0}


def run_blender(jobs: list[dict], work: Path) -> list[dict]:
    (work / "jobs.json").write_text(json.dumps(jobs))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    run = subprocess.run([str(BLENDER_PYTHON), str(DRIVER), str(work / "jobs.json")], capture_output=True, text=True, env=env)
    if run.returncode != 0:
        raise SystemExit(f"Blender driver failed ({run.returncode}):\n{run.stdout[-2000:]}\n{run.stderr[-2000:]}")
    return json.loads((work / "jobs.json.out.json").read_text())


def agreement(work: Path, n: int) -> list[dict]:
    """The test's models (+Y up, +Z up, and fit's default DAM +Y up) on an exact sphere, n x n pixels, against damcap."""
    from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
    from damcap.appearance.dam_file import save_dam
    from damcap.appearance.fit import FitOptions
    from damcap.export.blender import blender_from_world, export_blender
    from damcap.export.turntable import OrbitOptions

    cases = {"yup": (DamArchitecture(width=16, depth=3, encoding="vnr", bias=True, activation="leaky_relu"), 2.5, [0.0, 1.0, 0.0]),
             "zup": (DamArchitecture(width=16, depth=2, encoding="nr", separable=True, activation="shifted_softplus"), 0.7, [0.0, 0.0, 1.0]),
             "fit_default_yup": (FitOptions().architecture, 1.0, [0.0, 1.0, 0.0])}
    jobs, models = [], {}
    for k, (name, (arch, scale, up)) in enumerate(cases.items()):
        g = torch.Generator().manual_seed(10 + k)
        model = DeepAppearanceMap(arch, scale, generator=g)
        if arch.bias:
            model.set_flat_weights(model.get_flat_weights() + 0.2 * torch.randn(arch.num_weights, generator=g))
        save_dam(work / f"{name}.dam", model, colorspace="lin_rec709", made_by="fit", up_world=np.array(up))
        (work / f"out_{name}").mkdir()
        export_blender([model], [work / f"{name}.dam"], np.array(up), work / f"out_{name}", OrbitOptions())  # what damcap export --format blender writes
        models[name] = (model, arch, up)
        jobs.append({"script": str(work / f"out_{name}" / "damcap_materials.py"), "sphere_material": name, "exposure": 1.0,
                     "resolution": n, "out": str(work / name), "camera": SPHERE_CAMERA})
    rows = []
    for job, rep in zip(jobs, run_blender(jobs, work)):
        name = Path(job["out"]).name
        model, arch, up = models[name]
        px = np.load(job["out"] + ".npy")
        mask, normals, views = sphere_pixels(np.array(rep["world_from_cam"]), n, SPHERE_CAMERA["lens_mm"])
        covered = (px[..., 3] > 0.999)[mask]
        got = px[mask][covered][:, :3].astype(np.float64)
        rot = blender_from_world(np.array(up))
        errs = {}
        for label, sign, r in (("exported", 1, rot), ("view flipped", -1, rot), ("no turn" if up[2] == 0 else "+Y turn", 1,
                                                                                    np.eye(3) if up[2] == 0 else blender_from_world(np.array([0.0, 1, 0])))):
            with torch.no_grad():
                want = model(torch.from_numpy(sign * views[covered] @ r).float(), torch.from_numpy(normals[covered] @ r).float()).double().numpy()
            rel = np.abs(got - want) / np.maximum(np.abs(want), 1e-6)
            errs[label] = {"median": float(np.median(rel)), "p90": float(np.percentile(rel, 90))}
        rows.append({"model": name, "architecture": arch.to_json(), "radiance_scale": model.radiance_scale, "up": up,
                     "pixels": int(covered.sum()), "silhouette_agreement": float(covered.mean()), "relative_error": errs,
                     "render_s": rep["render_s"]})
        log(f"{name}: {rows[-1]['pixels']} px, median {errs['exported']['median']:.2e}, p90 {errs['exported']['p90']:.2e}")
    return rows


def mesh_render(work: Path, demo: Path | None, resolution: int, samples: list[int], picture: Path | None) -> dict:
    """A mesh with the exported materials, resolution^2, seen from damcap export's first camera
    (orbit defaults): once as damcap's frame is made (pixel-centre rays) and compared with it, then timed per sample
    count with Blender's default pixel filter (Blackman-Harris 1.5 px). ``picture``: where the
    side-by-side PNG (damcap | Blender) goes, or None."""
    from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
    from damcap.appearance.dam_file import load_dam, recorded_up, save_dam
    from damcap.common.cameras import focal_px_from_fov
    from damcap.common.colour import display_srgb8, exposure_scale_for
    from damcap.common.exr import write_png
    from damcap.common.mesh import unit_sphere_transform
    from damcap.export.blender import blender_from_world, export_blender
    from damcap.export.turntable import OrbitOptions, orbit_up, render_orbit, shape_and_parts

    if demo is not None and (demo / "pot.obj").is_file():  # make demo's pot: body, lid, handle take material_2, _0, _1 (the Makefile's POT_MATERIALS)
        model_paths = [demo / "segmentation" / f"material_{k}.dam" for k in (2, 0, 1)]
        mesh, labels = demo / "pot.obj", None
        what = f"the demo's three segmentation materials on its pot ({demo.name}/pot.obj, its OBJ material groups)"
    elif demo is not None:
        model_paths = [demo / "segmentation" / f"material_{k}.dam" for k in range(3)]
        mesh, labels = demo / "torus.obj", demo / "torus_labels.npy"
        what = f"the demo's three segmentation materials on its torus ({demo.name}/torus.obj, labels torus_labels.npy)"
    else:
        from damcap.common.shapes import write_shape

        mesh, labels = write_shape("torus", work / "torus.obj"), None
        model = DeepAppearanceMap(DamArchitecture(activation="shifted_softplus"), 1.0, generator=torch.Generator().manual_seed(0))
        save_dam(work / "random.dam", model, colorspace="lin_rec709", made_by="fit")
        model_paths = [work / "random.dam"]
        what = "one DAM of the fit's default architecture (random weights) on damcap's generated torus"
    loaded = [load_dam(p) for p in model_paths]
    dams = [d.dam_alone() for d, _ in loaded]
    up, _, _ = orbit_up("model", [recorded_up(meta) for _, meta in loaded])  # as damcap export takes it
    orbit = OrbitOptions(views=1, resolution=resolution)
    (work / "out_mesh").mkdir()
    export_blender(dams, model_paths, up, work / "out_mesh", orbit, mesh, labels)  # what damcap export --format blender writes
    # damcap export's first frame (pixel-centre rays), and the Blender camera that sees the file's mesh as it does
    raw, shape, part = shape_and_parts(mesh, labels, len(dams))
    world_from_cam, buf, rad = next(render_orbit(dams, shape, part, orbit, up_world=up))
    centre, radius = unit_sphere_transform(raw.vertices)
    rot = blender_from_world(up)
    cam = {"location": (rot @ (centre + radius * world_from_cam[:3, 3])).tolist(), "target": (rot @ centre).tolist(),
           "lens_mm": focal_px_from_fov(orbit.fov_deg, resolution) / resolution * 36.0}
    frame = np.concatenate([rad, buf.coverage[..., None]], -1)
    scale = exposure_scale_for(rad, buf.coverage > 0.5)
    script = str(work / "out_mesh" / "damcap_materials.py")
    jobs = [{"script": script, "resolution": resolution, "samples": 1, "exposure": 1.0, "out": str(work / "mesh_exact"), "camera": cam}]
    jobs += [{"script": script, "resolution": resolution, "samples": s, "filter_width": 1.5, "out": str(work / f"mesh_{s}spp"), "camera": cam}
             for s in samples]
    reps = run_blender(jobs, work)
    obj = next(iter(reps[0]["objects"].values()))
    # damcap's own frame (pixel-centre rays) against Blender's 1-sample, 0.01 px box-filter render, linear radiance
    exact = np.load(jobs[0]["out"] + ".npy")
    both = (frame[..., 3] > 0.999) & (exact[..., 3] > 0.999)
    rel = np.abs(exact[..., :3][both] - frame[..., :3][both]) / np.maximum(frame[..., :3][both], 1e-6)
    versus = {"pixels": int(both.sum()), "damcap_covered": int((frame[..., 3] > 0.999).sum()),
              "blender_covered": int((exact[..., 3] > 0.999).sum()), "median": float(np.median(rel)), "p90": float(np.percentile(rel, 90))}
    log(f"mesh against damcap's frame: {versus}")
    if picture is not None:
        write_png(picture, np.concatenate([display_srgb8(frame[..., :3], scale), display_srgb8(exact[..., :3], scale)], 1))
    rows = []
    for s, job, rep in zip(samples, jobs[1:], reps[1:]):
        px = np.load(job["out"] + ".npy")
        rows.append({"samples": s, "render_s": rep["render_s"], "covered_pixels": int((px[..., 3] > 0.5).sum())})
        log(f"mesh {resolution}px {s} spp: {rep['render_s']:.2f} s")
    return {"what": what, "triangles": int(sum(obj["material_index"])), "materials": obj["slots"], "resolution": resolution,
            "threads": os.cpu_count(), "camera": "damcap export's first orbit view (elevation 20 deg, azimuth 0, 45 deg field of view)",
            "against_damcap_frame": versus, "picture": None if picture is None else picture.name, "rows": rows}


def install_cost(work: Path) -> dict:
    """The bpy wheel's size and a fresh install of tests/blender.txt into a scratch venv (pip's cache as it is)."""
    wheels = work / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "-d", str(wheels), "bpy==5.0.1"], check=True)
    wheel = next(wheels.glob("bpy-*.whl"))
    venv = work / "venv"
    subprocess.run(["python3.11", "-m", "venv", str(venv)], check=True)
    t0 = time.perf_counter()
    subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", "-r", str(REQUIREMENTS)], check=True)
    install_s = time.perf_counter() - t0
    size = sum(f.stat().st_size for f in venv.rglob("*") if f.is_file() and not f.is_symlink())
    t0 = time.perf_counter()
    subprocess.run([str(venv / "bin" / "python"), "-c", "import bpy"], check=True)
    return {"wheel": wheel.name, "wheel_bytes": wheel.stat().st_size, "install_s": install_s, "venv_bytes": size,
            "import_bpy_s": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sphere", type=int, default=64, help="agreement: sphere render size, px")
    ap.add_argument("--resolution", type=int, default=512, help="mesh render: frame size, px")
    ap.add_argument("--samples", type=int, nargs="+", default=[1, 16], help="mesh render: samples per pixel, one render each")
    ap.add_argument("--demo", type=Path, default=None,
                    help="a make demo output whose materials and torus are rendered (default: a random DAM on a generated torus)")
    ap.add_argument("--no-install", dest="install", action="store_false", help="skip the install measurement")
    ap.add_argument("--out", type=Path, default=None, help="write blender.json and blender.md here instead of bench/results/ and bench/")
    args = ap.parse_args(argv)
    if not BLENDER_PYTHON.exists():
        raise SystemExit(f"{BLENDER_PYTHON}: run make blender first")
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        rows = agreement(work, args.sphere)
        md_path = BENCH / "blender.md" if args.out is None else args.out / "blender.md"
        mesh = mesh_render(work, args.demo, args.resolution, args.samples, md_path.with_name("blender_mesh.png"))
        install = install_cost(work) if args.install else None
    result = {"command": command_line("blender", sys.argv[1:] if argv is None else argv),
              "machine": {**machine_info(), "load_average_1min": [load_before, os.getloadavg()[0]]},
              "blender": "bpy 5.0.1 (Cycles, CPU, Open Shading Language)", "agreement": rows, "mesh_render": mesh, "install": install}
    out = RESULTS / "blender.json" if args.out is None else args.out / "blender.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    md_path.write_text(report(result, out))
    print(md_path.read_text())
    return 0


def report(r: dict, out: Path) -> str:
    m = r["machine"]
    lines = [
        "# Blender benchmark",
        "",
        "Does Cycles render the materials of `damcap export --format blender` as damcap evaluates the",
        "models, how long does a frame take, and what does the Blender install cost?",
        "",
        f"Command: `{r['command']}` (after `make blender`). Machine: {m['cpu_model']}, {m['nproc']} cores, {r['blender']}.",
        f"Date: {m['date_utc']}. Raw results: `{out.relative_to(REPO) if out.is_relative_to(REPO) else out}`. Load average (1 min) at",
        f"start and end: {m['load_average_1min'][0]:.1f}, {m['load_average_1min'][1]:.1f} (above ~2 on 2 cores, other work shared the CPUs).",
        "",
        "## Agreement: Cycles against damcap, per colour value of each pixel",
        "",
        "An exact sphere (a one-point point cloud, radius 1) with the exported material, exposure 1,",
        "1 sample per pixel through a 0.01 px box filter (each pixel is its centre ray), against",
        "damcap's own evaluation of the model for the pixel's analytic normal and view direction.",
        "The last two columns are what a wrong convention would give: the view direction reversed,",
        "or the model's world taken without its turn onto Blender's +Z (for the +Z-up model: with",
        "the +Y-up turn).",
        "",
        "| model | architecture | up | pixels | median rel. error | p90 | view flipped (median) | wrong turn (median) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in r["agreement"]:
        a, e = row["architecture"], row["relative_error"]
        wrong = next(v for k, v in e.items() if k not in ("exported", "view flipped"))
        arch = f"{a['depth']}x{a['width']} {a['activation']}, '{a['encoding']}'" + (", separable" if a["separable"] else "") + (", biases" if a["bias"] else "")
        lines.append(f"| {row['model']} | {arch} | {row['up']} | {row['pixels']} | {e['exported']['median']:.1e} | {e['exported']['p90']:.1e} "
                     f"| {e['view flipped']['median']:.2f} | {wrong['median']:.2f} |")
    mr = r["mesh_render"]
    v = mr["against_damcap_frame"]
    lines += ["", f"## A mesh: {mr['what']}", "",
              f"{mr['triangles']} triangles, materials {', '.join(mr['materials'])} (the script's mesh, slot k = model k), seen from",
              f"{mr['camera']}, {mr['resolution']}x{mr['resolution']}.", "",
              "Against damcap's own frame of the same view (`damcap export --views 1`, pixel-centre rays; Blender",
              f"with 1 sample through a 0.01 px box filter): {v['pixels']} pixels covered in both (damcap {v['damcap_covered']},",
              f"Blender {v['blender_covered']}), median relative error {v['median']:.1e}, p90 {v['p90']:.1e}"
              + (f"; [{mr['picture']}]({mr['picture']}) shows both (damcap left, Blender right, damcap's display exposure)." if mr["picture"] else "."),
              "", "Render time: Cycles on the CPU "
              f"({mr['threads']} threads), OSL, Blender's default pixel filter (Blackman-Harris, 1.5 px), no denoiser;",
              "the time of `bpy.ops.render.render` (scene sync, OSL compile and JIT, render).", "",
              "| samples per pixel | render s | covered pixels |", "|---|---|---|"]
    lines += [f"| {row['samples']} | {row['render_s']:.2f} | {row['covered_pixels']} |" for row in mr["rows"]]
    if r["install"]:
        i = r["install"]
        lines += ["", "## Install", "",
                  f"`{i['wheel']}`: {i['wheel_bytes'] / 1e6:.0f} MB. `pip install -r tests/blender.txt` into a fresh venv: {i['install_s']:.0f} s",
                  f"(with this machine's pip cache as it was), {i['venv_bytes'] / 1e9:.2f} GB installed; `import bpy`: {i['import_bpy_s']:.1f} s."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
