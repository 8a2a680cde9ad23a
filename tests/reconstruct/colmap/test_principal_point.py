"""The principal point estimate: against COLMAP's synthetic truth, and the line that reports it."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_principal_point_estimate_matches_the_truth_within_its_uncertainty(seed):
    """COLMAP's synthetic scene (12 views of 300 points, 0.5 px image noise) seen by a camera whose
    principal point sits (+20, -12) px from the centre. Started from the centre, the estimate lands
    within 4 of its own standard deviations of the truth (measured: within 2.2), and that standard
    deviation is sub-pixel (measured 0.64-0.72 px). The reconstruction passed in is left as it was."""
    import pycolmap

    from damcap.reconstruct.colmap.principal_point import adjust_principal_point, principal_point_tilt_deg

    pycolmap.set_random_seed(seed)
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_cameras_per_rig, opts.num_frames_per_rig, opts.num_points3D = 1, 1, 12, 300
    opts.camera_params = [1280.0, 512.0 + 20.0, 384.0 - 12.0, 0.0]
    rec = pycolmap.synthesize_dataset(opts)
    noise = pycolmap.SyntheticNoiseOptions()
    noise.point2D_stddev = 0.5
    pycolmap.synthesize_noise(noise, rec)
    cam = rec.cameras[next(iter(rec.cameras))]
    params = np.array(cam.params)
    params[1:3] = [512.0, 384.0]
    cam.params = params
    rec.cameras[cam.camera_id] = cam

    est, copy = adjust_principal_point(rec, pycolmap, apply=False)
    assert est is not None and not est.used and copy is not rec
    sd = np.array(est.sd_px)
    assert np.all((sd > 0.1) & (sd < 2.0))
    assert np.all(np.abs(np.array(est.offset_px) - [20.0, -12.0]) < 4 * sd)
    assert est.tilt_deg == pytest.approx(principal_point_tilt_deg(est.offset_px, 1280.0), abs=0.01)
    assert est.coverage is not None and 0.5 <= est.coverage <= 1.0  # 300 points seen across the frames
    assert list(rec.cameras[cam.camera_id].params[1:3]) == [512.0, 384.0]
    # the copy carries the adjustment: a caller that decides to use the point takes it as it is
    on_copy = copy.cameras[cam.camera_id]
    assert [on_copy.principal_point_x - 512.0, on_copy.principal_point_y - 384.0] == pytest.approx(est.offset_px, abs=0.01)

    applied, same = adjust_principal_point(rec, pycolmap, apply=True)
    assert applied is not None and applied.used and same is rec
    assert applied.offset_px == pytest.approx(est.offset_px, abs=0.01)
    moved = rec.cameras[cam.camera_id]
    assert [moved.principal_point_x - 512.0, moved.principal_point_y - 384.0] == pytest.approx(applied.offset_px, abs=0.01)


def test_principal_point_line_says_how_far_and_whether_it_is_used():
    from damcap.cli.reconstruct_cmds import principal_point_line

    pp = {"offset_px": [3.0, -4.0], "sd_px": [1.0, 1.0], "tilt_deg": 0.25, "used": False}
    line = principal_point_line(pp)
    assert "(+3.0, -4.0) px" in line and "5.0 sigma off" in line and "turns every camera by 0.25 deg" in line
    assert "the cameras use it" in principal_point_line({**pp, "used": True})


@pytest.mark.parametrize("offset, sd, tilt, photos, used, coverage", [
    ([-6.9, -11.2], [2.0, 2.2], 0.55, 8, True, None),    # Herz-Jesu-P8: 6.2 sigma
    ([-4.1, -12.3], [3.8, 4.8], 0.54, 4, False, None),   # its first 4 photos: 2.8 sigma, too few photos
    ([-6.9, -11.2], [2.0, 2.2], 0.55, 4, False, None),   # significant, but 4 photos
    ([0.1, 59.1], [0.9, 20.1], 8.2, 24, False, None),    # a rendered turntable (truth: the centre): 2.9 sigma, 8 deg
    ([30.0, 0.0], [1.0, 1.0], 1.5, 50, False, None),     # significant but a tilt beyond 1 deg
    ([3.0, 0.0], [1.0, 1.0], 0.1, 5, True, None),        # exactly 3 sigma and 5 photos
    ([2.36, -11.23], [1.48, 3.22], 0.69, 36, False, 0.44),  # the rendered bunny on black, 800 px (truth: the centre)
    ([-6.9, -11.2], [2.0, 2.2], 0.55, 8, True, 0.75),       # Herz-Jesu-P8, points reaching just enough of the frame
])
def test_auto_uses_the_principal_point_only_where_the_photos_support_it(offset, sd, tilt, photos, used, coverage):
    from damcap.reconstruct.colmap.principal_point import PrincipalPointEstimate, photos_support_offset

    ok, why = photos_support_offset(PrincipalPointEstimate(offset, sd, tilt, False, coverage=coverage), photos)
    assert ok is used
    assert why.startswith("refined" if used else "kept at the centre") and f"{photos} photos" in why
