"""Commands of the reconstruct stage: ``damcap reconstruct PHOTOS/ -o CAPTURE/``."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from damcap.common.errors import DamcapError

from damcap.cli.app import app

def stage_progress():
    """A ``(stage, done, total)`` callback: one tqdm bar per stage (silent when not a terminal)."""
    from tqdm import tqdm

    state: dict = {"stage": None, "bar": None}

    def update(stage: str, done: int, total: int) -> None:
        if stage != state["stage"]:
            if state["bar"] is not None:
                state["bar"].close()
            state["stage"] = stage
            state["bar"] = tqdm(total=total, desc=stage, unit="step", dynamic_ncols=True, leave=False, disable=None)
        bar = state["bar"]
        bar.total = total
        bar.n = done
        bar.refresh()
        if done >= total:
            bar.close()
            state["stage"], state["bar"] = None, None

    return update


@app.command()
def reconstruct(
    photos: Path = typer.Argument(..., help="folder of JPEG/PNG photos of one object"),
    output: Path = typer.Option(..., "-o", "--output", help="capture folder to write (new, or a previous reconstruct output to resume)"),
    masks: Optional[Path] = typer.Option(None, "--masks", help="folder of object masks, same base names as the photos (white = object)"),
    poses: Optional[str] = typer.Option(None, "--poses", help="known cameras: transforms.json | poses_bounds.npy | colmap:DIR (default: COLMAP registration)"),
    geometry: str = typer.Option("auto", "--geometry", help="auto | visual-hull | poisson | sphere | mesh:FILE"),
    mesh_align: str = typer.Option("auto", help="mesh:FILE alignment: auto | none | icp"),
    voxels: int = typer.Option(160, help="visual hull: voxels along the object's longest side"),
    hull_tolerance: int = typer.Option(0, help="visual hull: views allowed to disagree with the object (bad masks)"),
    poisson_depth: int = typer.Option(8, help="Poisson octree depth"),
    smooth_iterations: int = typer.Option(10, help="Taubin smoothing iterations of carved/Poisson meshes"),
    sphere_max_rms: float = typer.Option(0.01, help="auto: sphere when it fits within this fraction of its radius"),
    max_image_size: int = typer.Option(1024, help="registration: longest image side for features, pixels"),
    max_num_features: int = typer.Option(4096, help="registration: SIFT features per photo"),
    upsample_below: int = typer.Option(800, help="registration: SIFT doubles images whose longer side is below this"),
    pairing: str = typer.Option("auto", help="registration: auto | exhaustive | sequential | retrieval"),
    sequential_overlap: int = typer.Option(5, help="registration: ring neighbours on each side (file order)"),
    retrieval_neighbours: int = typer.Option(8, help="registration: most similar photos matched per photo"),
    camera_model: str = typer.Option("SIMPLE_RADIAL", help="registration: SIMPLE_PINHOLE | PINHOLE | SIMPLE_RADIAL | RADIAL | OPENCV"),
    refine_principal_point: bool = typer.Option(False, "--refine-principal-point/--centred-principal-point",
                                                help="registration: refine the principal point after mapping (as instant-ngp's colmap2nerf; default: image centre, as COLMAP and LLFF)"),
    single_camera: bool = typer.Option(True, "--single-camera/--camera-per-photo", help="registration: photos of one size share one camera"),
    mask_features: bool = typer.Option(False, "--mask-features/--no-mask-features", help="registration: restrict features to the masks (turntables)"),
    capture_size: int = typer.Option(512, help="longest side of the capture images, pixels"),
    train_views: int = typer.Option(10, help="frames in the train split"),
    split: str = typer.Option("consecutive", help="train split: consecutive | spread"),
    split_start: int = typer.Option(0, help="first train frame of a consecutive split"),
    min_registered: int = typer.Option(3, help="fewest registered photos that make a capture"),
    min_registered_fraction: float = typer.Option(0.5, help="fewest registered photos, as a fraction"),
    ignore_exposure: bool = typer.Option(False, "--ignore-exposure", help="only undo the tone curve (photos at one fixed exposure)"),
    mask_coverage: bool = typer.Option(True, "--mask-coverage/--no-mask-coverage", help="limit coverage A to the masks"),
    supersample: int = typer.Option(3, help="sub-pixel grid per axis for coverage at silhouettes"),
    dtype: str = typer.Option("half", help="radiance storage: half | float"),
    threads: int = typer.Option(-1, help="CPU threads for COLMAP (-1 = all)"),
    seed: int = typer.Option(0, help="seed of COLMAP's RANSAC and mapping"),
) -> None:
    """Photos -> capture folder: cameras (COLMAP or known poses), geometry, linear radiance, buffers, split."""
    from damcap.reconstruct.pipeline import ReconstructOptions, reconstruct_capture

    choices = {"mesh_align": (mesh_align, ("auto", "none", "icp")), "pairing": (pairing, ("auto", "exhaustive", "sequential", "retrieval")),
               "camera_model": (camera_model, ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")),
               "split": (split, ("consecutive", "spread")), "dtype": (dtype, ("half", "float"))}
    for name, (value, allowed) in choices.items():
        if value not in allowed:
            raise DamcapError(f"--{name.replace('_', '-')} {value!r}: use one of {', '.join(allowed)}")
    opts = ReconstructOptions(
        geometry=geometry, mesh_align=mesh_align, voxels=voxels, hull_tolerance=hull_tolerance,  # type: ignore[arg-type]
        poisson_depth=poisson_depth, smooth_iterations=smooth_iterations, sphere_max_rms=sphere_max_rms,
        max_image_size=max_image_size, max_num_features=max_num_features, upsample_below=upsample_below, pairing=pairing,  # type: ignore[arg-type]
        sequential_overlap=sequential_overlap, retrieval_neighbours=retrieval_neighbours,
        camera_model=camera_model, refine_principal_point=refine_principal_point, single_camera=single_camera, mask_features=mask_features, capture_size=capture_size,  # type: ignore[arg-type]
        train_views=train_views, split=split, split_start=split_start, min_registered=min_registered,  # type: ignore[arg-type]
        min_registered_fraction=min_registered_fraction, ignore_exposure=ignore_exposure, mask_coverage=mask_coverage, supersample=supersample,
        dtype=dtype, threads=threads, seed=seed)  # type: ignore[arg-type]
    capture, report = reconstruct_capture(photos, output, opts, masks_dir=masks, poses=poses, progress=stage_progress(),
                                          log=lambda msg: typer.echo(msg, err=True))
    reg = report.registration
    line = f"cameras: {report.registered}/{report.photos} photos ({reg.get('source')})"
    if reg.get("source") == "sfm":
        line += (f", {reg.get('points')} points, mean reprojection error {reg.get('mean_reprojection_error_px', float('nan')):.3f} px, "
                 f"{reg.get('pairs')} pairs ({reg.get('pairing')})")
    typer.echo(line)
    if reg.get("source") == "sfm" and reg.get("principal_point"):
        typer.echo(principal_point_line(reg["principal_point"]))
    typer.echo(f"geometry: {report.geometry_mode} ({report.geometry_reason})")
    typer.echo(f"wrote {report.frames} frames to {output} (train {len(report.train)}, test {len(report.test)}; "
               f"{len(report.dropped)} dropped, {len(report.unregistered)} unregistered) in {report.seconds.get('total', 0):.1f} s")


def principal_point_line(pp: dict) -> str:
    """The report line for where the photos put the principal point (``SfmReport.principal_point``)."""
    from damcap.reconstruct.sfm import offset_in_sigmas

    (dx, dy), (sx, sy) = pp["offset_px"], pp["sd_px"]
    where = (f"principal point: the photos put it ({dx:+.1f}, {dy:+.1f}) px from the image centre (1-sigma {sx:.1f}, "
             f"{sy:.1f} px: {offset_in_sigmas(pp['offset_px'], pp['sd_px']):.1f} sigma off); ")
    if pp["used"]:
        return where + "the cameras use it (--refine-principal-point)"
    return where + (f"the cameras keep the centre, COLMAP's convention (--refine-principal-point uses it and turns every "
                    f"camera by {pp['tilt_deg']:.2f} deg)")
