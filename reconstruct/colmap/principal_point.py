"""Where the photos put the principal point: one bundle adjustment with it free, its 1-sigma from
COLMAP's covariance (``BACovariance``) scaled by the residual variance."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np




@dataclass
class PrincipalPointEstimate:
    """Where the photos put the principal point of their one shared camera.

    From a bundle adjustment with the principal point free (on a copy of the reconstruction when
    the registration keeps it at the centre) and that adjustment's covariance (COLMAP's
    ``BACovariance``) scaled by the residual variance. The standard deviation measures noise
    only: a camera model that does not fit the lens can move the point by more.
    """

    offset_px: list[float]
    """(dx, dy): principal point minus the image centre, photo pixels"""
    sd_px: list[float]
    """1-sigma of (dx, dy), photo pixels"""
    tilt_deg: float
    """atan(|offset| / focal): how far every camera turns when this point replaces the centre"""
    used: bool
    """the registration's cameras use this point (``principal_point`` 'refine', or 'auto' when
    :func:`photos_support_offset`); else the centre"""
    decision: str = ""
    """why the point is used or not (the rule's figures under 'auto')"""
    coverage: float | None = None
    """:func:`frame_coverage` of the median photo's registered points (None: not measured)"""


#: 'auto' refines the principal point when its offset is at least this many standard deviations ...
PP_MIN_SIGMAS = 3.0
#: ... from at least this many registered photos ...
PP_MIN_PHOTOS = 5
#: ... and it turns the cameras by at most this much (a larger tilt means the photos trade it
#: against the cameras' pitch and yaw: a textured blob on black, 256-384 px, put it 8 deg off) ...
PP_MAX_TILT_DEG = 1.0
#: ... and the registered points reach across the frame: in the median photo at least this
#: fraction of a :data:`PP_GRID` x :data:`PP_GRID` grid's cells hold one. An object alone in the
#: middle of the frame lets the point trade against the cameras' tilt unseen by the covariance:
#: the rendered bunny on black (36 photos of 800 px, bench/registration_gt.md, truth the centre)
#: put it 3.8 sigma, 0.69 deg off, and using it took the median rotation error from 0.14 to 0.66
#: deg; Strecha's first 5 or 6 photos (truth 0.46 deg off) 3.3-4.5 sigma, where using it helps
PP_MIN_COVERAGE = 0.75
#: the grid of :func:`frame_coverage`, cells per side
PP_GRID = 4


def frame_coverage(xy_px: np.ndarray, width: int, height: int, grid: int = PP_GRID) -> float:
    """Fraction of a ``grid`` x ``grid`` partition of the image that holds at least one point.

    Args:
        xy_px: (N, 2) image points, pixels (x right, y down; the image spans [0, width] x [0, height]).
        width, height: image size, pixels.

    >>> frame_coverage(np.array([[10.0, 10.0], [390.0, 390.0], [10.0, 390.0], [390.0, 10.0]]), 400, 400, 2)
    1.0
    >>> frame_coverage(np.array([[200.0, 200.0], [210.0, 190.0]]), 400, 400, 4)
    0.125
    """
    if len(xy_px) == 0:
        return 0.0
    cx = np.clip((np.asarray(xy_px[:, 0]) / width * grid).astype(int), 0, grid - 1)
    cy = np.clip((np.asarray(xy_px[:, 1]) / height * grid).astype(int), 0, grid - 1)
    return float(len(np.unique(cy * grid + cx))) / grid ** 2


def photos_support_offset(estimate: PrincipalPointEstimate, photos: int) -> tuple[bool, str]:
    """Whether the photos pin the principal point off the centre (the 'auto' rule) and why.

    Measured (bench/registration_gt.md, ground-truth cameras of Strecha's scenes, principal point
    (-7.4, -8.35) px off): Herz-Jesu-P8 6.2 sigma, 8 photos, tilt 0.55 deg: refining takes the
    rotation error from 0.625 to 0.157 deg; castle-P19 14.7 sigma: 0.766 -> 0.460 deg; with 4
    photos the estimate is 2.8 sigma (kept centred). A textured blob on black (tests): 1.3 sigma, or
    2.9 sigma at 8.2 deg tilt on a rendered turntable, whose truth is the centre: kept centred.

    >>> photos_support_offset(PrincipalPointEstimate([-6.9, -11.2], [2.0, 2.2], 0.55, False), 8)[0]
    True
    >>> photos_support_offset(PrincipalPointEstimate([0.1, 59.1], [0.9, 20.1], 8.2, False), 24)
    (False, 'kept at the centre: 2.9 sigma (needs 3), 24 photos, tilt 8.20 deg (at most 1)')
    >>> photos_support_offset(PrincipalPointEstimate([2.36, -11.23], [1.48, 3.22], 0.69, False, coverage=0.5), 36)
    (False, 'kept at the centre: 3.8 sigma (needs 3), 36 photos, tilt 0.69 deg (at most 1), points on 50 % of the frame (needs 75 %)')
    """
    sig = offset_in_sigmas(estimate.offset_px, estimate.sd_px)
    covered = estimate.coverage is None or estimate.coverage >= PP_MIN_COVERAGE
    ok = sig >= PP_MIN_SIGMAS and photos >= PP_MIN_PHOTOS and estimate.tilt_deg <= PP_MAX_TILT_DEG and covered
    figures = (f"{sig:.1f} sigma (needs {PP_MIN_SIGMAS:g}), {photos} photos" + ("" if photos >= PP_MIN_PHOTOS else f" (needs {PP_MIN_PHOTOS})")
               + f", tilt {estimate.tilt_deg:.2f} deg (at most {PP_MAX_TILT_DEG:g})"
               + ("" if estimate.coverage is None else f", points on {100 * estimate.coverage:.0f} % of the frame "
                                                       f"(needs {100 * PP_MIN_COVERAGE:.0f} %)"))
    return ok, ("refined: " if ok else "kept at the centre: ") + figures


def residual_variance(final_cost: float, residuals: int, parameters: int) -> float:
    """Variance of one residual after a least-squares fit: ``2 cost / (residuals - parameters)``.

    Args:
        final_cost: Ceres' cost, half the sum of squared residuals (px^2).
        residuals: number of scalar residuals.
        parameters: number of free parameters (effective, after the gauge is fixed).

    Returns:
        sigma^2 in px^2 (the cost's own mean when there are no spare residuals).

    >>> residual_variance(50.0, 110, 10)
    1.0
    """
    return 2.0 * final_cost / max(residuals - parameters, 1)


def principal_point_tilt_deg(offset_px: Sequence[float], focal_px: float) -> float:
    """How far a camera turns when its principal point moves by ``offset_px``: atan(|offset| / f).

    >>> round(principal_point_tilt_deg([3.0, 4.0], 5.0 / math.tan(math.radians(1.0))), 6)
    1.0
    """
    return math.degrees(math.atan2(math.hypot(*offset_px), focal_px))


def offset_in_sigmas(offset_px: Sequence[float], sd_px: Sequence[float]) -> float:
    """How many standard deviations a principal point lies from the image centre:
    hypot(dx / sx, dy / sy).

    >>> offset_in_sigmas([3.0, -4.0], [1.0, 1.0])
    5.0
    """
    return math.hypot(*(d / max(sd, 1e-9) for d, sd in zip(offset_px, sd_px)))


def adjust_principal_point(rec: Any, pycolmap: Any, apply: bool) -> tuple[PrincipalPointEstimate | None, Any]:
    """One global bundle adjustment with the principal point free (colmap2nerf's last step),
    and where it puts the point.

    Args:
        rec: a ``pycolmap.Reconstruction``.
        pycolmap: the module.
        apply: adjust ``rec`` itself (its cameras then use the point); else a copy, and ``rec``
            is unchanged.

    Returns:
        The estimate, or None when the photos use several cameras or COLMAP cannot estimate the
        covariance (the adjustment is made all the same); and the adjusted reconstruction (``rec``
        itself when ``apply``, else the copy: a caller that decides to use the point takes it
        instead of adjusting again).
    """
    if rec.num_cameras() != 1 and not apply:
        return None, rec
    work = rec if apply else pycolmap.Reconstruction(rec)
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_principal_point = True
    ba.print_summary = False
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in work.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(ba, config, work)
    summary = adjuster.solve().ceres_summary
    if work.num_cameras() != 1:
        return None, work
    camera = work.cameras[next(iter(work.cameras))]
    cov = pycolmap.estimate_ba_covariance(pycolmap.BACovarianceOptions(), work, adjuster)
    block = cov.get_other_params_cov(camera.params) if cov is not None else None
    if block is None or block.shape != (len(camera.params), len(camera.params)):
        return None, work
    var = residual_variance(summary.final_cost, summary.num_residuals_reduced, summary.num_effective_parameters_reduced)
    sd = np.sqrt(np.maximum(np.diag(block)[list(camera.principal_point_idxs())], 0.0) * var)
    offset = [camera.principal_point_x - camera.width / 2, camera.principal_point_y - camera.height / 2]
    coverage = [frame_coverage(np.array([p.xy for p in im.points2D if p.has_point3D()]).reshape(-1, 2), camera.width, camera.height)
                for im in (work.image(i) for i in work.reg_image_ids())]
    return PrincipalPointEstimate(offset_px=[round(float(v), 2) for v in offset], sd_px=[round(float(v), 3) for v in sd],
                                  tilt_deg=round(principal_point_tilt_deg(offset, camera.mean_focal_length()), 3), used=apply,
                                  coverage=round(float(np.median(coverage)), 3) if coverage else None), work
