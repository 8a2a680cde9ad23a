"""Registration with COLMAP: stage fingerprints, the failure paths, resuming with the principal point refined.

The full registration of a synthetic photo set runs in test_reconstruct.py (end to end)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from damcap.common.errors import DamcapError
from damcap.reconstruct.colmap import register as register_module
from damcap.reconstruct.colmap.register import SfmOptions, SfmReport, fingerprint, octave_skipped, register_photos, wants_upsampled_retry


def test_fingerprint_is_stable_and_sensitive():
    a = fingerprint({"x": 1, "y": [1, 2]})
    assert a == fingerprint({"y": [1, 2], "x": 1}) and a != fingerprint({"x": 2, "y": [1, 2]}) and len(a) == 16


def test_unmatchable_photos_fail_clearly(tmp_path):
    from damcap.synth.photos import write_jpeg

    rng = np.random.default_rng(3)
    photos = tmp_path / "photos"
    photos.mkdir()
    names = []
    for k in range(4):  # unrelated random textures: features, but no geometry between photos
        write_jpeg(photos / f"noise_{k}.jpg", rng.integers(0, 256, (96, 96, 3), dtype=np.uint8), None)
        names.append(f"noise_{k}.jpg")
    with pytest.raises(DamcapError, match="COLMAP could not register the photos"):
        register_photos(photos, names, tmp_path / "work", SfmOptions(max_num_features=512))


def test_too_few_photos():
    with pytest.raises(DamcapError, match="at least 2 photos"):
        register_photos(".", ["one.jpg"], "/nonexistent/work", SfmOptions())


def test_refine_principal_point_is_one_more_adjustment_on_the_same_matches(tmp_path):
    """Photos from a camera whose principal point sits 14 px right and 10 px up of the centre.
    With principal_point="centre" it stays at the centre; with "refine", the second run reuses the
    features and matches, refines the point (it moves off the centre) and fits no worse.

    Not asserted: that it lands on the truth. With an object on a black background the
    principal point trades against the cameras' pitch and yaw (here it lands ~2 px off in x,
    ~20 px in y, and the reported 1-sigma is ~1 px in x and ~4.6 px in y: it flags the weak
    direction but understates the error); photos filled with texture, like the fox's, pin it down
    (bench/reconstruct.md)."""
    from damcap.common.capture_folder import Intrinsics
    from damcap.common.shapes import bumpy_blob
    from damcap.synth.photos import default_intrinsics, exposure_series, orbit_cameras, write_photo_set

    size, n = 256, 28
    centred = default_intrinsics(size)
    intr = Intrinsics(centred.fl_x, centred.fl_y, size / 2 + 14, size / 2 - 10, size, size)
    cams = orbit_cameras(n, 3.2, (0.0, 35.0), jitter_deg=4, seed=1)
    names = write_photo_set(tmp_path / "photos", bumpy_blob(subdivisions=5), cams, intr, exposure_series(n, 1),
                            light_dir_world=np.array([0.0, 1.0, 0.0]), seed=1)
    opts = SfmOptions(camera_model="SIMPLE_PINHOLE", principal_point="centre")
    photos = tmp_path / "photos" / "images"
    fixed, rep_fixed = register_photos(photos, names, tmp_path / "work", opts)
    refined, rep = register_photos(photos, names, tmp_path / "work", replace(opts, principal_point="refine"))
    assert rep_fixed.registered >= 0.8 * n
    assert rep.resumed == ["features", "matches"] and "principal_point" in rep.seconds
    c_fixed, c_refined = fixed.photos[0].camera, refined.photos[0].camera
    assert (c_fixed.cx, c_fixed.cy) == (size / 2, size / 2)
    assert np.hypot(c_refined.cx - size / 2, c_refined.cy - size / 2) > 2
    assert rep.mean_reprojection_error_px <= rep_fixed.mean_reprojection_error_px + 1e-6
    # both reports say where the photos put the point; only the refined run's cameras use it
    est_fixed, est = rep_fixed.principal_point, rep.principal_point
    assert est_fixed is not None and est is not None and not est_fixed["used"] and est["used"]
    assert est["offset_px"] == pytest.approx([c_refined.cx - size / 2, c_refined.cy - size / 2], abs=0.01)
    assert est_fixed["offset_px"] == pytest.approx(est["offset_px"], abs=0.5)  # the same adjustment, made on a copy

    # a finished registration from before the estimate existed gets it when resumed; its model is kept
    report_path = tmp_path / "work" / "registration.json"
    old = json.loads(report_path.read_text())
    del old["principal_point"]
    report_path.write_text(json.dumps(old))
    resumed, rep_resumed = register_photos(photos, names, tmp_path / "work", replace(opts, principal_point="refine"))
    assert rep_resumed.resumed == ["features", "matches", "mapping"]
    assert rep_resumed.principal_point["used"] and rep_resumed.principal_point["offset_px"] == pytest.approx(est["offset_px"], abs=0.5)
    assert (resumed.photos[0].camera.cx, resumed.photos[0].camera.cy) == (c_refined.cx, c_refined.cy)
    assert json.loads(report_path.read_text())["principal_point"] == rep_resumed.principal_point


def test_the_first_octave_is_skipped_only_for_large_photos():
    assert octave_skipped({(912, 912)}, SfmOptions())             # cape photos: 912 >= 800
    assert not octave_skipped({(640, 480)}, SfmOptions())
    assert not octave_skipped({(4000, 3000)}, SfmOptions(upsample_below=1025))  # capped at max_image_size 1024
    assert octave_skipped({(4000, 3000), (100, 100)}, SfmOptions())  # the longest photo decides


@pytest.mark.parametrize("registered, photos, skipped, below, want", [
    (2, 30, True, 0.95, True), (28, 30, True, 0.95, True), (29, 30, True, 0.95, False),
    (2, 30, False, 0.95, False), (2, 30, True, 0.0, False),
    # the boundary: 38 of 40 is exactly 95 %, and a set at 95 % is retried (plain pycolmap registered all 40 of such a set)
    (38, 40, True, 0.95, True), (39, 40, True, 0.95, False), (19, 20, True, 0.95, True), (40, 40, True, 1.0, True),
])
def test_retry_rule(registered, photos, skipped, below, want):
    assert wants_upsampled_retry(registered, photos, skipped, below) is want


def _fake_pass(results):
    """A stand-in for one registration pass: ``results[upsampled]`` registered photos (or an error)."""
    from damcap.reconstruct.poses import Registration

    calls = []

    def once(photo_dir, names, work_dir, opts, masks, progress, content, masks_given=False):
        upsampled = opts.upsample_below > opts.max_image_size
        calls.append((work_dir.name, upsampled))
        n = results[upsampled]
        if isinstance(n, Exception):
            raise n
        rep = SfmReport(photos=len(names), registered=n, points=0, mean_reprojection_error_px=0.0, pairs=0, pairing="exhaustive",
                        seconds={"features": 1.0}, unregistered={}, resumed=[])
        reg = Registration(photos=[], source="sfm")
        reg.stats = {}
        return reg, rep
    return once, calls


@pytest.mark.parametrize("first, second, kept, passes", [
    (2, 15, "upsampled first octave (retry)", 2),       # a sparse set: the retry registers more
    (30, 15, "skipped first octave", 1),                # all registered: no retry
    (20, 10, "skipped first octave", 2),                # the retry registers fewer: the first is kept
    (DamcapError("COLMAP could not register the photos"), 12, "upsampled first octave (retry)", 2),
])
def test_sparse_sets_are_registered_again_with_the_upsampled_octave(tmp_path, monkeypatch, first, second, kept, passes):
    from damcap.synth.photos import write_jpeg

    names = [f"p{k}.jpg" for k in range(30)]
    (tmp_path / "photos").mkdir()
    for nm in names:
        write_jpeg(tmp_path / "photos" / nm, np.zeros((900, 900, 3), np.uint8), None)
    once, calls = _fake_pass({False: first, True: second})
    monkeypatch.setattr(register_module, "_register_once", once)
    reg, rep = register_photos(tmp_path / "photos", names, tmp_path / "work", SfmOptions())
    assert rep.features == kept and len(calls) == passes
    if passes == 2:
        assert calls[1] == ("upsampled", True) and rep.retry is not None
    if kept.endswith("(retry)"):
        assert rep.seconds["features"] == (1.0 if isinstance(first, Exception) else 2.0)  # both passes' time


def test_a_set_at_exactly_95_percent_is_registered_again(tmp_path, monkeypatch):
    """38 of 40 photos is 95 %: the upsampled retry runs (it did not when the rule was 'fewer than'),
    and the registration with more photos is kept."""
    from damcap.synth.photos import write_jpeg

    names = [f"p{k:02d}.jpg" for k in range(40)]
    (tmp_path / "photos").mkdir()
    for nm in names:
        write_jpeg(tmp_path / "photos" / nm, np.zeros((900, 900, 3), np.uint8), None)
    once, calls = _fake_pass({False: 38, True: 40})
    monkeypatch.setattr(register_module, "_register_once", once)
    reg, rep = register_photos(tmp_path / "photos", names, tmp_path / "work", SfmOptions())
    assert len(calls) == 2 and rep.registered == 40 and rep.features == "upsampled first octave (retry)"


def test_when_no_pass_registers_the_first_error_is_raised(tmp_path, monkeypatch):
    from damcap.synth.photos import write_jpeg

    (tmp_path / "photos").mkdir()
    for k in range(3):
        write_jpeg(tmp_path / "photos" / f"p{k}.jpg", np.zeros((900, 900, 3), np.uint8), None)
    once, _ = _fake_pass({False: DamcapError("first pass failed"), True: DamcapError("second pass failed")})
    monkeypatch.setattr(register_module, "_register_once", once)
    with pytest.raises(DamcapError, match="first pass failed"):
        register_photos(tmp_path / "photos", [f"p{k}.jpg" for k in range(3)], tmp_path / "work", SfmOptions())


@pytest.mark.parametrize("budget, reused", [(64, True), (16384, False)])
def test_the_contrast_probe_s_photos_are_not_extracted_twice(tmp_path, monkeypatch, budget, reused):
    """With the low-contrast probe on, the probed photos' features are stored from the probe when
    the set keeps the probe's threshold (a budget the photos fill), exactly as extracting them again
    would give; at the lower threshold (a budget they leave mostly empty) every photo is extracted."""
    import pycolmap

    from damcap.common.shapes import bumpy_blob
    from damcap.synth.photos import default_intrinsics, exposure_series, orbit_cameras, write_photo_set

    n = 6
    names = write_photo_set(tmp_path / "photos", bumpy_blob(subdivisions=4), orbit_cameras(n, 3.2, (0.0, 30.0), seed=2),
                            default_intrinsics(128), exposure_series(n, 1), light_dir_world=np.array([0.0, 1.0, 0.0]), seed=2)
    photos = tmp_path / "photos" / "images"
    extracted: list[str] = []
    real = pycolmap.extract_features

    def counting(db, image_dir, image_names, **kw):
        if not str(db).endswith("probe.db"):
            extracted.extend(image_names)
        return real(db, image_dir, image_names=image_names, **kw)

    def features(opts: SfmOptions, work) -> dict:
        work.mkdir()
        db_path, _, _ = register_module._features_and_matches(photos, names, work, opts, None, lambda *a: None,
                                                              register_module._Stages(work), {}, [])
        db = pycolmap.Database.open(str(db_path))
        try:
            return {im.name: (db.read_keypoints(im.image_id), np.asarray(db.read_descriptors(im.image_id).data))
                    for im in db.read_all_images()}
        finally:
            db.close()

    monkeypatch.setattr(pycolmap, "extract_features", counting)
    opts = SfmOptions(max_num_features=budget, low_contrast_peak_threshold=0.003, num_threads=1)
    probed = features(opts, tmp_path / "probed")
    if not reused:
        assert sorted(extracted) == sorted(names)
    else:
        assert len(extracted) == n - register_module.PEAK_PROBE_PHOTOS and len(set(extracted)) == len(extracted)
        plain = features(replace(opts, low_contrast_peak_threshold=None), tmp_path / "plain")
        assert plain.keys() == probed.keys()
        for name in names:
            np.testing.assert_array_equal(plain[name][0], probed[name][0])
            np.testing.assert_array_equal(plain[name][1], probed[name][1])


def _odd_named_copy(src, names, dst):
    """The photos copied under names with spaces, a '#', a leading dash and non-ASCII letters."""
    import shutil

    odd = {1: "ß café #1.jpg", 2: "-dash.jpg", 3: "naïve_ü.jpg"}
    dst.mkdir()
    out = []
    for k, name in enumerate(names):
        new = odd.get(k, f"Photo {k:04d}.jpg")
        shutil.copy(src / name, dst / new)
        out.append(new)
    return out


@pytest.fixture(scope="module")
def arc_photos(tmp_path_factory):
    """10 photos 12 degrees apart on an arc, 192 px: the smallest set here that registers whole."""
    from damcap.common.shapes import bumpy_blob
    from damcap.synth.photos import default_intrinsics, exposure_series, orbit_cameras, write_photo_set

    root = tmp_path_factory.mktemp("arc")
    n = 10
    cams = orbit_cameras(30, 3.2, (25.0,), jitter_deg=4, seed=1)[:n]
    names = write_photo_set(root / "set", bumpy_blob(subdivisions=5), cams, default_intrinsics(192), exposure_series(n, 1),
                            light_dir_world=np.array([0.0, 1.0, 0.0]), seed=1)
    return root / "set" / "images", names


@pytest.mark.parametrize("pairing", ["exhaustive", "sequential"])
def test_photo_names_are_opaque(tmp_path, arc_photos, pairing):
    """Photos named with spaces, '#', a leading dash or non-ASCII letters register as their plain-named
    copies do (once, 'Photo 0000.jpg' reached COLMAP's pair list as 'Photo' and nothing matched)."""
    photos, names = arc_photos
    odd = _odd_named_copy(photos, names, tmp_path / "odd")
    opts = SfmOptions(pairing=pairing, sequential_overlap=3)
    plain_reg, plain = register_photos(photos, names, tmp_path / "plain", opts)
    reg, rep = register_photos(tmp_path / "odd", odd, tmp_path / "work", opts)
    assert plain.registered == len(names) == 10
    assert rep.registered == plain.registered and rep.unregistered == {} and rep.pairs == plain.pairs
    assert sorted(p.name for p in reg.photos) == sorted(odd)
    assert not (tmp_path / "work" / "database.db.aliases.json").exists()  # the database holds the photo names again
    # resumed from the database: the names it holds are the photos' names
    again, rep_again = register_photos(tmp_path / "odd", odd, tmp_path / "work", replace(opts, principal_point="centre"))
    assert rep_again.resumed == ["features", "matches"] and rep_again.registered == 10


def test_pairs_colmap_did_not_match_fail_loudly(tmp_path, arc_photos, monkeypatch):
    """Were photo names written into COLMAP's pair list as they are (the old way), the pairs with a
    space in a name would go unmatched; that stops the run with a sentence, not 'unregistered'."""
    import contextlib

    photos, names = arc_photos
    odd = _odd_named_copy(photos, names, tmp_path / "odd")
    monkeypatch.setattr(register_module, "images_named_for_pair_lists",
                        lambda db_path: contextlib.nullcontext({n: n for n in odd}))
    monkeypatch.setattr(register_module, "pair_list_text", lambda pairs: "".join(f"{a} {b}\n" for a, b in pairs))
    with pytest.raises(DamcapError, match=r"COLMAP matched 1 of the 45 photo pairs it was given; not e.g. 'Photo 0000.jpg' with"):
        register_photos(tmp_path / "odd", odd, tmp_path / "work", SfmOptions(pairing="exhaustive"))
