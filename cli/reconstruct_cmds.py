"""Commands of the reconstruct stage: ``damcap reconstruct PHOTOS/ -o CAPTURE/``."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from damcap.cli.app import command, stage_progress
from damcap.cli.paths import check_paths, folder_out, on_interrupt

if TYPE_CHECKING:
    from damcap.reconstruct.pipeline import GeometryJudge, ReconstructOptions


@command(opts="damcap.reconstruct.pipeline:ReconstructOptions")
def reconstruct(
    photos: Path = typer.Argument(..., help="folder of JPEG/PNG photos of one object, or a nerfstudio / instant-ngp dataset "
                                  "(transforms.json: its cameras and masks are used) or a COLMAP project (images/ + sparse/0)"),
    output: Path = typer.Option(..., "-o", "--output", help="capture folder to write (new, or a previous reconstruct output to resume)"),
    masks: Optional[Path] = typer.Option(None, "--masks", help="folder of object masks, same base names as the photos (white = object)"),
    poses: Optional[str] = typer.Option(None, "--poses", help="known cameras: transforms.json | poses_bounds.npy | colmap:DIR | strecha:DIR (Strecha et al.'s .camera files) (default: COLMAP registration)"),
    *,
    opts: ReconstructOptions,
    given: frozenset[str],
) -> None:
    """Photos -> capture folder: cameras, geometry, radiance.

    Cameras (COLMAP or known poses), geometry, linear radiance, per-pixel buffers and the
    train/test split.
    """
    from damcap.reconstruct.datasets import dataset_inputs
    from damcap.reconstruct.pipeline import WORK_FOLDER, reconstruct_capture

    check_paths([photos], [folder_out(output)])
    found = dataset_inputs(photos)
    if found.kind != "photos":
        ours = [flag for flag, value in (("--poses", poses), ("--masks", masks)) if value is not None]
        photos, poses, masks = found.photos, poses if poses is not None else found.poses, masks if masks is not None else found.masks
        typer.echo(f"input: {found.describe()}" + (f"; {' and '.join(ours)} from the command line instead" if ours else ""))
    # every input, the pose file (or COLMAP folder), the mesh and the response curve included, is
    # checked against the output before reconstruct_capture prepares (clears) the output folder
    prefix = next((p for p in ("colmap:", "strecha:") if poses is not None and poses.startswith(p)), "")
    pose_input = None if poses is None else Path(poses[len(prefix):])
    mesh_input = Path(opts.geometry.mode[len("mesh:"):]) if opts.geometry.mode.startswith("mesh:") and opts.geometry.mode[len("mesh:"):] else None
    check_paths([photos, masks, pose_input, mesh_input, opts.response], [folder_out(output)])

    def kept() -> str:
        work = output / WORK_FOLDER
        if work.is_dir():
            return f"the finished stages in {work} are kept; rerun the same command to resume"
        return "nothing was kept"

    # what it picked and why are report lines (stdout): stderr carries only the one error line of a refusal
    with on_interrupt(kept):
        judge = held_out_judge() if opts.auto_judge == "held-out" else None
        capture, report = reconstruct_capture(photos, output, opts, masks_dir=masks, poses=poses, progress=stage_progress(),
                                              log=typer.echo, explicit=given, judge=judge)
    reg = report.registration
    line = f"cameras: {report.registered}/{report.photos} photos ({reg.get('source')})"
    if reg.get("source") == "sfm":
        line += (f", {reg.get('points')} points, mean reprojection error {reg.get('mean_reprojection_error_px', float('nan')):.3f} px, "
                 f"{reg.get('pairs')} pairs ({reg.get('pairing')})")
    typer.echo(line)
    if reg.get("retry"):
        other = reg["retry"].get("skipped_first_octave") or reg["retry"].get("upsampled_first_octave")
        typer.echo(f"features: {reg.get('features')}; the other pass: {other}")
    if reg.get("source") == "sfm" and reg.get("principal_point"):
        typer.echo(principal_point_line(reg["principal_point"]))
    typer.echo(f"geometry: {report.geometry_mode} ({report.geometry_reason})")
    typer.echo(f"wrote {report.frames} frames to {output} (train {len(report.train)}, test {len(report.test)}; "
               f"{len(report.dropped)} dropped, {len(report.unregistered)} unregistered) in {report.seconds.get('total', 0):.1f} s")


def held_out_judge() -> GeometryJudge:
    """``--geometry auto``'s judge between two geometries (``--auto-judge held-out``): the train
    views both captures hold, a fit on each (:func:`damcap.appearance.fit_views.judge_fit`), the same views held out
    (:func:`damcap.appearance.fit_views.judge_geometries`)."""
    from damcap.reconstruct.pipeline import GeometryJudgement

    def judge(captures: dict[str, Path]) -> GeometryJudgement:
        from damcap.appearance.fit_views import judge_fit, judge_geometries
        from damcap.appearance.views import load_views
        from damcap.common.capture_folder import read_capture

        views = {g: load_views(read_capture(p), "train") for g, p in captures.items()}
        both = set.intersection(*({v.name for v in vs} for vs in views.values()))  # a frame one geometry missed trains neither
        verdict = judge_geometries({g: [v for v in vs if v.name in both] for g, vs in views.items()}, judge_fit())
        return GeometryJudgement(verdict.chosen, verdict.why(), verdict.record())

    return judge


def principal_point_line(pp: dict) -> str:
    """The report line for where the photos put the principal point (``SfmReport.principal_point``)."""
    from damcap.reconstruct.colmap.principal_point import offset_in_sigmas

    (dx, dy), (sx, sy) = pp["offset_px"], pp["sd_px"]
    where = (f"principal point: the photos put it ({dx:+.1f}, {dy:+.1f}) px from the image centre (1-sigma {sx:.1f}, "
             f"{sy:.1f} px: {offset_in_sigmas(pp['offset_px'], pp['sd_px']):.1f} sigma off); ")
    if pp.get("decision"):
        where += pp["decision"] + "; "
    if pp["used"]:
        return where + "the cameras use it (--principal-point centre keeps the centre)"
    return where + (f"the cameras keep the centre, COLMAP's convention (--principal-point refine uses it and turns every "
                    f"camera by {pp['tilt_deg']:.2f} deg)")
