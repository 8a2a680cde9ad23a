"""Commands of the capture stage: hdr (merge one bracket), linearize (single-exposure photos)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, List

import typer

from damcap.common.errors import DamcapError

from damcap.cli.app import command
from damcap.cli.paths import beside, check_paths, file_out, folder_out, holds, staged_folder

if TYPE_CHECKING:
    from damcap.capture.hdr import HdrOptions
    from damcap.capture.linearize import LinearizeOptions
    from damcap.capture.video import VideoFrameOptions


@command(opts="damcap.capture.hdr:HdrOptions")
def hdr(
    files: List[Path] = typer.Argument(..., help="one bracket: RAW files, or 8/16-bit JPEG/PNG/TIFF"),
    output: Path = typer.Option(..., "-o", "--output", help="merged radiance map to write (.exr)"),
    *,
    opts: HdrOptions,
) -> None:
    """Merge one exposure bracket into one linear radiance map.

    The EXR holds R, G, B and the clipped mask.
    """
    from damcap.capture.hdr import merge_bracket_files, write_hdr

    opts.validate()
    check_paths(files, [file_out(output), file_out(beside(output, ".json"))])
    if output.suffix.lower() != ".exr":
        raise DamcapError(f"{output}: the output must be an .exr file")
    result = merge_bracket_files(files, opts)  # its warnings: one line each (cli.main)
    record = write_hdr(output, result, opts)
    lo, hi = float(result.radiance_lin.min()), float(result.radiance_lin.max())
    typer.echo(f"wrote {output} ({result.radiance_lin.shape[1]}x{result.radiance_lin.shape[0]}, {len(files)} {result.kind} "
               f"frames, {result.colorspace}, range {lo:.4g} .. {hi:.4g}, {int(result.clipped.sum())} clipped pixel(s)); "
               f"record: {record}")


@command(opts="damcap.capture.linearize:LinearizeOptions")
def linearize(
    photos: Path = typer.Argument(..., help="folder of single-exposure photos (JPEG, PNG, TIFF or RAW)"),
    output: Path = typer.Option(..., "-o", "--output", help="folder for one linear EXR per photo"),
    *,
    opts: LinearizeOptions,
) -> None:
    """Undo each photo's tone curve and divide out its exposure.

    The exposure comes from EXIF, so radiance compares across photos.
    """
    from damcap.capture.linearize import linearize_files, list_photos
    from damcap.cli.app import stage_progress
    from damcap.common.atomic import write_json_atomic
    from damcap.common.version import package_version

    opts.validate()
    check_paths([photos], [folder_out(output, replaces=holds("linearize.json"))])
    files = list_photos(photos)
    # the EXRs and linearize.json replace OUTPUT (an earlier linearize output) together, at the end
    with staged_folder(output, replace=True) as stage:
        record = linearize_files(files, stage, opts, progress=stage_progress())  # its warnings: one line each (cli.main)
        record = {"damcap_package_version": package_version(), "photos_folder": str(photos.resolve()), **record}
        write_json_atomic(stage / "linearize.json", record)
    scales = [r["scale"] for r in record["photos"]]
    typer.echo(f"wrote {len(files)} linear EXR(s) to {output} (reference exposure {record['reference_exposure']:.4g}, "
               f"scales {min(scales):.3g} .. {max(scales):.3g}); record: {output / 'linearize.json'}")


@command("frames", opts="damcap.capture.video:VideoFrameOptions")
def frames(
    video: Path = typer.Argument(..., help="video of the object (MP4, MOV, ...; anything FFmpeg decodes)"),
    output: Path = typer.Option(..., "-o", "--output", help="folder of photos to write (the input of damcap reconstruct)"),
    *,
    opts: VideoFrameOptions,
) -> None:
    """Video -> photos: the sharpest video frame of each stretch.

    Video -> photos: the sharpest video frame of each of --count equal stretches of the video
    (JPEG), and frames.json recording which video frame each photo is.
    """
    from damcap.capture.video import extract_video_frames
    from damcap.cli.app import stage_progress

    opts.validate()
    check_paths([video], [folder_out(output, replaces=holds("frames.json"))])
    with staged_folder(output, replace=True) as stage:
        record = extract_video_frames(video, stage, opts, progress=stage_progress())
    typer.echo(f"wrote {record['count']} photos of {record['video_frames_decoded']} video frames to {output} (frames.json says which); "
               f"next: damcap reconstruct {output} -o CAPTURE")
