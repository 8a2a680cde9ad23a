"""Synthetic captures rendered with Mitsuba 3: contract, validation, weights, units, resume, errors."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest

from damcap.common.capture_folder import GEOMETRY_CHANNELS, Intrinsics, inspect_capture, read_capture, read_frame, weight_channels
from damcap.common.errors import DamcapError
from damcap.common.exr import read_exr, write_exr
from damcap.common.cameras import orbit_world_from_cam, pixel_rays_world
from damcap.synth.mitsuba_capture import (
    input_digests,
    PARTIAL_MARKER, RENDER_ALPHA_CHANNEL, SynthOptions, camera_setup, compose_frame, coverage_agreement,
    env_mean_luminance, fd_normal_cosines, make_synthetic_capture, parse_light_spec, point_light, resolve_scene,
    train_split, validate_synthetic_capture,
)
from damcap.synth.geometry import RayCaster, SceneGeometry, frame_geometry, subpixel_offsets
from damcap.synth.mitsuba_render import (
    EnvLight, LayeredMaterial, build_scene, pass_sample_counts, render_view, sampler_count_ok, select_variant,
)

TINY = dict(views=8, resolution=32, spp=4, train_views=3)


@pytest.fixture(scope="module")
def sphere3_capture(tmp_path_factory):
    """Icosphere with 3 noise-region materials under a point light (needs no shared data)."""
    out = tmp_path_factory.mktemp("synth") / "sphere3"
    make_synthetic_capture(out, SynthOptions(object="sphere", light="point:30:40", materials=3, seed=5, **TINY))
    return out


@pytest.fixture(scope="module")
def bunny_capture(shared_data, tmp_path_factory):
    """The bunny with 3 materials under a rotated environment map."""
    out = tmp_path_factory.mktemp("synth") / "bunny"
    opts = SynthOptions(object=str(shared_data / "meshes" / "stanford-bunny.obj"),
                        light=f"env:{shared_data / 'envmaps' / 'studio.hdr'}:30", materials=3, seed=1, **TINY)
    make_synthetic_capture(out, opts)
    return out, opts


# --------------------------------------------------------------------------------------------
# pure pieces
# --------------------------------------------------------------------------------------------


def test_parse_light_spec():
    assert parse_light_spec("point").kind == "point" and parse_light_spec("point").azimuth_deg is None
    s = parse_light_spec("point:-30:12.5")
    assert (s.azimuth_deg, s.elevation_deg) == (-30.0, 12.5)
    s = parse_light_spec("env:/data/a:b.hdr:45")  # a colon inside the path survives
    assert (s.kind, s.path, s.rotation_deg) == ("env", "/data/a:b.hdr", 45.0)
    assert parse_light_spec("env:studio.hdr").rotation_deg == 0.0
    for bad in ("", "spot", "env", "env:", "point:x", "point:1:2:3", "point:0:95", "env::30", "point:nan"):
        with pytest.raises(DamcapError, match="--light"):
            parse_light_spec(bad)


def test_env_mean_luminance_weights_by_solid_angle():
    env = np.zeros((64, 128, 3))
    env[:32] = 1.0  # upper hemisphere white: half the sphere of directions
    assert env_mean_luminance(env) == pytest.approx(0.5, abs=1e-3)
    env = np.zeros((64, 128, 3))
    env[0] = 1.0  # only the top row: a tiny solid angle near the pole
    assert env_mean_luminance(env) < 1e-3


def test_point_light_gives_the_asked_irradiance():
    light = point_light(30.0, 40.0, distance=6.0, radius=0.1, irradiance=math.pi)
    assert np.linalg.norm(light.centre_world) == pytest.approx(6.0)
    assert light.centre_world[1] == pytest.approx(6 * math.sin(math.radians(40)))
    # irradiance of a small sphere source: L * pi * (r / d)^2
    assert light.radiance * math.pi * (0.1 / 6.0) ** 2 == pytest.approx(math.pi)


def test_train_split_is_consecutive_and_seeded():
    for seed in range(5):
        idx = train_split(seed, 32, 10)
        assert [(b - a) % 32 for a, b in zip(idx, idx[1:])] == [1] * 9
    assert len({train_split(s, 32, 10)[0] for s in range(20)}) > 5


def test_pass_counts_are_exact_for_mitsubas_sampler():
    import mitsuba as mi

    select_variant("auto")
    for n in range(1, 200):
        taken = mi.load_dict({"type": "multijitter", "sample_count": n}).sample_count()
        assert sampler_count_ok(n) == (taken == n), (n, taken)
    for spp, res in ((128, 128), (512, 256), (1000, 256), (7, 8), (4096, 128)):
        counts = pass_sample_counts(spp, res, res)
        assert sum(counts) == spp and all(sampler_count_ok(n) for n in counts)
        assert max(counts) * res * res <= 1 << 22


def test_fd_normals_and_coverage_agreement_on_an_analytic_sphere():
    cams = orbit_world_from_cam(1, 4.0, 20.0)
    intr = Intrinsics(60.0, 60.0, 24.0, 24.0, 48, 48)
    geo = frame_geometry(RayCaster(SceneGeometry(None, None, None, 1)), cams[0], intr, supersample=4)
    cos = fd_normal_cosines(geo.normal_world, geo.position_world, geo.coverage, cams[0][:3, 3])
    assert len(cos) > 500 and np.median(cos) > 0.9999
    assert coverage_agreement(geo.coverage, geo.coverage) == (0.0, 0.0, 0.0)
    mad, shift, area = coverage_agreement(geo.coverage, np.roll(geo.coverage, 1, axis=1))
    assert shift == pytest.approx(1.0, abs=1e-6) and area < 1e-6 and mad > 0.05
    # the sphere's silhouette: sub-pixel coverage only on a thin rim
    partial = (geo.coverage > 0) & (geo.coverage < 1)
    assert 0 < partial.sum() < 0.2 * (geo.coverage > 0).sum()
    np.testing.assert_allclose(subpixel_offsets(4).mean(0), 0, atol=1e-12)


def test_white_furnace_radiance_equals_albedo(tmp_path):
    """A diffuse sphere (convex: no interreflection) in a uniform environment of radiance 1 has
    radiance = albedo everywhere, silhouette pixels included (radiance is un-premultiplied)."""
    select_variant("auto")
    env = tmp_path / "white.exr"
    write_exr(env, np.full((8, 16, 3), 3.0, np.float32), ("R", "G", "B"), dtype="float")
    albedo = (0.6, 0.3, 0.1)
    light = EnvLight(str(env), 0.0, 1.0 / env_mean_luminance(read_exr(env)[0]))
    scene = build_scene([None], [LayeredMaterial(albedo, 0.0, (1.0, 1.0, 1.0), 0.2)], light, max_depth=4)
    cams, intr, _, _ = camera_setup(SynthOptions(views=2, resolution=24, train_views=1 + 1))
    geo = frame_geometry(RayCaster(SceneGeometry(None, None, None, 1)), cams[0], intr)
    rad_premult, alpha = render_view(scene, cams[0], intr, pass_spp=[8, 8], seeds=[1, 2])
    fr = compose_frame(rad_premult, alpha, geo)
    fg = geo.coverage > 0
    rim = fg & (geo.coverage < 1)
    rad = fr.radiance_lin
    np.testing.assert_allclose(rad[fg].mean(0), albedo, rtol=0.01)
    np.testing.assert_allclose(rad[rim].mean(0), albedo, rtol=0.08)  # un-premultiplied at the silhouette
    # per pixel: Monte Carlo noise scales all channels alike (a grey factor around 1)
    factor = rad[fg] / np.array(albedo)
    np.testing.assert_allclose(factor, factor[:, :1].repeat(3, 1), rtol=1e-3)
    assert np.percentile(np.abs(factor[:, 0] - 1), 90) < 0.3
    assert np.all(fr.radiance_lin[~fg] == 0)


# --------------------------------------------------------------------------------------------
# rendered captures
# --------------------------------------------------------------------------------------------


def test_tiny_captures_pass_validation(sphere3_capture, bunny_capture):
    for root in (sphere3_capture, bunny_capture[0]):
        assert validate_synthetic_capture(root) == []
        assert inspect_capture(root).problems == []
        cap = read_capture(root)
        assert cap.materials == 3 and len(cap.frames) == 8
        assert len(cap.train_filenames) == 3 and len(cap.test_filenames) == 5
        assert not (root / PARTIAL_MARKER).exists()
        src = cap.extra["damcap_source"]
        assert src["generator"] == "synth" and src["options"]["seed"] in (1, 5)
        assert src["damcap_package_version"] and "damcap_version" not in src


def test_contract_background_and_facing(bunny_capture):
    root, _ = bunny_capture
    cap = read_capture(root)
    covered_fraction = []
    for f in cap.frames:
        d = read_frame(cap, f)
        bg = d.coverage == 0
        covered_fraction.append(1 - bg.mean())
        assert np.all(d.radiance_lin[bg] == 0) and np.all(d.normal_world[bg] == 0) and np.all(d.weights[bg] == 0)
        v = f.camera_centre_world - d.position_world[~bg]
        assert ((d.normal_world[~bg] * v).sum(-1) > 0).all()
        np.testing.assert_allclose(d.weights[~bg].sum(-1), 1, atol=2e-3)
        img, names = read_exr(root / f.file_path)
        assert RENDER_ALPHA_CHANNEL in names
    assert 0.1 < np.mean(covered_fraction) < 0.6


def test_weights_agree_with_the_mesh_part_mitsuba_hits(bunny_capture):
    """Independent check: Mitsuba's own intersector, shapes matched by id(), at pixel centres."""
    root, opts = bunny_capture
    if select_variant("auto") != "llvm_ad_rgb":
        pytest.skip("needs the llvm variant for vectorised ray casting")
    import drjit as dr
    import mitsuba as mi

    desc = resolve_scene(opts)
    scene = build_scene(desc.parts, desc.materials, desc.light, opts.max_depth)
    shapes = {s.id(): s for s in scene.shapes()}
    cap = read_capture(root)
    agree, total, seen = 0, 0, set()
    for f in cap.frames:
        d = read_frame(cap, f)
        origin, dirs = pixel_rays_world(f.world_from_cam, *(getattr(f.intrinsics, k) for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")))
        dd = dirs.reshape(-1, 3).astype(np.float32)
        o = np.broadcast_to(origin.astype(np.float32), dd.shape)
        si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*[np.ascontiguousarray(o[:, k]) for k in range(3)]),
                                          mi.Vector3f(*[np.ascontiguousarray(dd[:, k]) for k in range(3)])))
        part = np.full(len(dd), -1)
        for k in range(3):
            part[np.array(si.shape == mi.ShapePtr(shapes[f"material_{k}"]), dtype=bool)] = k
        part = part.reshape(d.coverage.shape)
        interior = (d.coverage >= 1) & (d.weights.max(-1) >= 1)  # pixels wholly inside one region
        agree += int((np.argmax(d.weights, -1) == part)[interior].sum())
        total += int(interior.sum())
        seen |= set(np.unique(part[interior]).tolist())
        assert np.all(part[d.coverage > 0] >= 0)  # every covered pixel's centre ray hits the object in Mitsuba too
        dr.eval()
    assert total > 500 and agree / total >= 0.995, (agree, total)
    assert seen == {0, 1, 2}


class _Stop(Exception):
    """Interrupts a render from its progress callback (:func:`_stop_after`)."""


def _stop_after(frames: int):
    def progress(done, total, stats):
        if done == frames:
            raise _Stop
    return progress


def test_resume_skips_finished_frames_and_matches_a_full_render(tmp_path):
    opts = SynthOptions(object="sphere", light="point:10:50", materials=1, seed=9, views=6, resolution=24, spp=4, train_views=2)
    out = tmp_path / "cap"

    with pytest.raises(_Stop):
        make_synthetic_capture(out, opts, progress=_stop_after(2))
    assert not (out / "transforms.json").exists() and (out / PARTIAL_MARKER).exists()
    first = {p: (out / p).stat().st_mtime_ns for p in ("images/0000.exr", "geometry/0001.exr")}
    with pytest.raises(DamcapError, match="partial capture rendered with other options"):
        make_synthetic_capture(out, SynthOptions(**{**opts.__dict__, "spp": 8}))
    rendered = []
    make_synthetic_capture(out, opts, progress=lambda done, total, stats: rendered.append(done))
    assert rendered == [2, 3, 4, 5, 6]  # starts at 2 frames done
    assert {p: (out / p).stat().st_mtime_ns for p in first} == first
    assert validate_synthetic_capture(out) == []
    full = tmp_path / "full"
    make_synthetic_capture(full, opts)
    for name in ("images/0001.exr", "images/0004.exr", "geometry/0004.exr"):
        np.testing.assert_array_equal(read_exr(out / name)[0], read_exr(full / name)[0])
    # a finished capture with the same options is left as it is; other options are refused
    make_synthetic_capture(out, opts)
    with pytest.raises(DamcapError, match="already holds a capture"):
        make_synthetic_capture(out, SynthOptions(**{**opts.__dict__, "seed": 10}))


def _write_obj(path, scale: float) -> None:
    from damcap.common.shapes import icosphere

    m = icosphere(2)
    path.write_text("".join(f"v {x * scale:.6f} {y:.6f} {z:.6f}\n" for x, y, z in m.vertices)
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in m.triangles))


def test_a_changed_mesh_file_is_not_resumed(tmp_path):
    """Same options, same file name, other contents: neither a partial nor a finished capture of
    the old mesh is taken for the new one."""
    mesh = tmp_path / "obj.obj"
    _write_obj(mesh, 1.0)
    opts = SynthOptions(object=str(mesh), light="point:10:50", materials=1, seed=3, views=4, resolution=16, spp=2, train_views=2)
    before = input_digests(opts)
    assert set(before) == {"object"} and len(before["object"]) == 64

    out = tmp_path / "cap"
    with pytest.raises(_Stop):
        make_synthetic_capture(out, opts, progress=_stop_after(1))
    _write_obj(mesh, 0.7)
    assert input_digests(opts) != before
    with pytest.raises(DamcapError, match="other options or other input files"):
        make_synthetic_capture(out, opts)
    done = tmp_path / "done"
    make_synthetic_capture(done, opts)
    assert read_capture(done).extra["damcap_source"]["input_sha256"] == input_digests(opts)
    _write_obj(mesh, 1.0)
    with pytest.raises(DamcapError, match="already holds a capture made with other options or other input files"):
        make_synthetic_capture(done, opts)


def test_validation_names_damaged_frames(sphere3_capture, tmp_path):
    def damaged(fn):
        root = tmp_path / f"copy{len(list(tmp_path.iterdir()))}"
        shutil.copytree(sphere3_capture, root)
        fn(root)
        return " | ".join(validate_synthetic_capture(root))

    def edit(root, rel, change):
        pixels, names = read_exr(root / rel)
        pixels = change(pixels.copy(), names)
        write_exr(root / rel, pixels, names, dtype="float")

    def ch(names, *wanted):
        return [names.index(w) for w in wanted]

    flip = lambda p, n: (p.__setitem__((..., ch(n, *GEOMETRY_CHANNELS[:3])), -p[..., ch(n, *GEOMETRY_CHANNELS[:3])]), p)[1]  # noqa: E731
    assert "0002: " in damaged(lambda r: edit(r, "geometry/0002.exr", flip)) and "faces away" in damaged(lambda r: edit(r, "geometry/0002.exr", flip))
    double = lambda p, n: p * 2  # noqa: E731
    assert "0003: weights must sum to 1" in damaged(lambda r: edit(r, "weights/0003.exr", double))

    def nan(p, n):
        p[5, 5, 0] = np.nan
        return p
    assert "0000: 1 NaN/inf value(s) in radiance" in damaged(lambda r: edit(r, "images/0000.exr", nan))

    def shift(p, n):  # the whole geometry one pixel to the right: no longer on the pixel rays
        return np.roll(p, 1, axis=1)
    msg = damaged(lambda r: edit(r, "geometry/0001.exr", shift))
    assert "0001: " in msg and "pixel-centre rays" in msg

    def rotate_normals(p, n):  # normals in a wrong frame: off the positions' finite differences
        k = ch(n, *GEOMETRY_CHANNELS[:3])
        p[..., k] = p[..., [k[1], k[2], k[0]]]
        return p
    assert "finite differences" in damaged(lambda r: edit(r, "geometry/0004.exr", rotate_normals))

    def bright_background(p, n):
        p[0, 0, ch(n, "R")[0]] = 1.0
        return p
    assert "0006: 1 background pixel(s) with RGB != 0" in damaged(lambda r: edit(r, "images/0006.exr", bright_background))
    assert "transforms.json" in damaged(lambda r: (r / "transforms.json").unlink())


def test_bad_inputs_name_the_value(tmp_path, shared_data):
    with pytest.raises(DamcapError, match=r"nope\.obj: mesh file not found \(from --object"):
        make_synthetic_capture(tmp_path / "a", SynthOptions(object=str(tmp_path / "nope.obj"), **TINY))
    with pytest.raises(DamcapError, match=r"--light 'spot'"):
        make_synthetic_capture(tmp_path / "b", SynthOptions(light="spot", **TINY))
    with pytest.raises(DamcapError, match=r"missing\.hdr: environment map not found \(from --light 'env:"):
        make_synthetic_capture(tmp_path / "c", SynthOptions(light=f"env:{tmp_path / 'missing.hdr'}:10", **TINY))
    with pytest.raises(DamcapError, match=r"--materials must be an integer in \[1, 8\], got 0"):
        make_synthetic_capture(tmp_path / "d", SynthOptions(materials=0, **TINY))
    with pytest.raises(DamcapError, match="--train-views"):
        make_synthetic_capture(tmp_path / "e", SynthOptions(views=8, train_views=8, resolution=32))
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    with pytest.raises(DamcapError, match="exists and is not empty"):
        make_synthetic_capture(tmp_path / "full", SynthOptions(**TINY))
    assert (tmp_path / "full" / "notes.txt").read_text() == "mine"
    assert not any((tmp_path / n).exists() for n in "abcde")  # nothing written for a user mistake
    (tmp_path / "m.obj").write_text("v 0 0 0\n")
    with pytest.raises(DamcapError, match="m.obj: the mesh has no triangles"):
        make_synthetic_capture(tmp_path / "f", SynthOptions(object=str(tmp_path / "m.obj"), materials=3, **TINY))


def test_weight_channels_for_one_material(tmp_path):
    out = tmp_path / "one"
    make_synthetic_capture(out, SynthOptions(object="sphere", light="point", materials=1, seed=3, views=4, resolution=16, spp=2, train_views=2))
    cap = read_capture(out)
    d = read_frame(cap, cap.frames[0])
    assert cap.materials == 1 and d.weights.shape[-1] == 1
    np.testing.assert_array_equal(d.weights[..., 0], (d.coverage > 0).astype(np.float32))
    assert read_exr(out / cap.frames[0].weights_path)[1] == weight_channels(1)


def test_scalar_variant_renders_the_same_contract(tmp_path):
    """The fallback without libLLVM (forced here): slow, so only a few pixels."""
    out = tmp_path / "scalar"
    try:
        make_synthetic_capture(out, SynthOptions(object="sphere", light="point:0:30", materials=1, seed=2, views=3,
                                                 resolution=12, spp=2, train_views=2, variant="scalar_rgb"))
        assert validate_synthetic_capture(out) == []
        assert read_capture(out).extra["damcap_source"]["renderer"]["variant"] == "scalar_rgb"
    finally:
        select_variant("auto")


def test_an_exr_environment_map_renders_with_one_requested_thread(shared_data, tmp_path):
    """Regression: Mitsuba with a one-thread pool never returned from loading an OpenEXR map
    (synth-set --jobs 2 on 2 cores asks for 1 thread per worker)."""
    import subprocess
    import sys

    code = ("from damcap.synth.mitsuba_capture import SynthOptions, make_synthetic_capture; "
            f"make_synthetic_capture({str(tmp_path / 'c')!r}, SynthOptions(object='sphere', "
            f"light='env:{shared_data / 'envmaps' / 'museum.exr'}:0', views=3, train_views=2, resolution=16, spp=2), threads=1)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "c" / "transforms.json").is_file()
