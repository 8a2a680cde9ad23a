"""Registration with COLMAP: stage fingerprints, the failure paths, resuming with the principal point refined.

The full registration of a synthetic photo set runs in test_reconstruct.py (end to end)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from damcap.common.errors import DamcapError
from damcap.reconstruct.colmap.register import SfmOptions, fingerprint, register_photos


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
    Without refine_principal_point it stays at the centre; with it, the second run reuses the
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
    opts = SfmOptions(camera_model="SIMPLE_PINHOLE")
    photos = tmp_path / "photos" / "images"
    fixed, rep_fixed = register_photos(photos, names, tmp_path / "work", opts)
    refined, rep = register_photos(photos, names, tmp_path / "work", replace(opts, refine_principal_point=True))
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
    resumed, rep_resumed = register_photos(photos, names, tmp_path / "work", replace(opts, refine_principal_point=True))
    assert rep_resumed.resumed == ["features", "matches", "mapping"]
    assert rep_resumed.principal_point["used"] and rep_resumed.principal_point["offset_px"] == pytest.approx(est["offset_px"], abs=0.5)
    assert (resumed.photos[0].camera.cx, resumed.photos[0].camera.cy) == (c_refined.cx, c_refined.cy)
    assert json.loads(report_path.read_text())["principal_point"] == rep_resumed.principal_point
