"""Commands of the capture stage: hdr (merge one bracket), linearize (single-exposure photos)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import List, Optional

import typer

from damcap.common.errors import DamcapError

from damcap.cli.app import app, refuse_input_overlap


def _echo_warning(message, category, filename, lineno, file=None, line=None) -> None:
    typer.echo(f"warning: {message}", err=True)


@app.command()
def hdr(
    files: List[Path] = typer.Argument(..., help="one bracket: RAW files, or 8/16-bit JPEG/PNG/TIFF"),
    output: Path = typer.Option(..., "-o", "--output", help="merged radiance map to write (.exr)"),
    exposures: Optional[str] = typer.Option(None, "--exposures", help="exposure time of each file in seconds, comma-separated "
                                            "(e.g. 1/250,1/60,1/15); overrides EXIF"),
    align: bool = typer.Option(False, "--align/--no-align", help="align hand-held frames (translation, median threshold bitmaps)"),
    colorspace: str = typer.Option("lin_rec709", "--colorspace", help="lin_rec709 | acescg"),
    response: str = typer.Option("debevec", "--response", help="LDR only: debevec (recover the curve) | srgb"),
    reference_exposure: Optional[float] = typer.Option(None, "--reference-exposure", help="exposure factor the output is "
                                                       "relative to (s x ISO/100 / f-number^2); default: the bracket's median"),
    saturation_fraction: float = typer.Option(0.99, "--saturation-fraction", help="RAW only: raw values above this "
                                              "fraction of the black-to-white range count as clipped"),
    response_samples: int = typer.Option(2000, "--response-samples", help="LDR only: pixels sampled for the response"),
    smoothness: float = typer.Option(12.0, "--smoothness", help="LDR only: Debevec smoothness weight"),
    flat_fraction: float = typer.Option(0.1, "--flat-fraction", help="LDR only: sample among this fraction of flattest pixels"),
    sample_phase: float = typer.Option(0.0, "--sample-phase", help="LDR only: another equally valid set of sample pixels "
                                       "(a shift in [0, 1) of their brightness ranks)"),
    iterations: int = typer.Option(2, "--iterations", help="LDR only: reweighting rounds of response and weights"),
    dtype: str = typer.Option("float", "--dtype", help="EXR storage: float | half"),
) -> None:
    """Merge one exposure bracket into one linear radiance map (EXR: R, G, B, clipped)."""
    from damcap.capture.exif import parse_exposure_list
    from damcap.capture.hdr import HdrOptions, merge_bracket_files, write_hdr

    opts = HdrOptions(exposures_s=parse_exposure_list(exposures) if exposures else None, align=align,
                      colorspace=colorspace, response=response, reference_exposure=reference_exposure,  # type: ignore[arg-type]
                      saturation_fraction=saturation_fraction, response_samples=response_samples, smoothness=smoothness,
                      flat_fraction=flat_fraction, sample_phase=sample_phase, iterations=iterations, dtype=dtype)  # type: ignore[arg-type]
    opts.validate()
    refuse_input_overlap(output, *files)
    if output.suffix.lower() != ".exr":
        raise DamcapError(f"{output}: the output must be an .exr file")
    with warnings.catch_warnings():
        warnings.showwarning = _echo_warning
        result = merge_bracket_files(files, opts)
    record = write_hdr(output, result, opts)
    lo, hi = float(result.radiance_lin.min()), float(result.radiance_lin.max())
    typer.echo(f"wrote {output} ({result.radiance_lin.shape[1]}x{result.radiance_lin.shape[0]}, {len(files)} {result.kind} "
               f"frames, {result.colorspace}, range {lo:.4g} .. {hi:.4g}, {int(result.clipped.sum())} clipped pixel(s)); "
               f"record: {record}")


@app.command()
def linearize(
    photos: Path = typer.Argument(..., help="folder of single-exposure photos (JPEG, PNG, TIFF or RAW)"),
    output: Path = typer.Option(..., "-o", "--output", help="folder for one linear EXR per photo"),
    colorspace: str = typer.Option("lin_rec709", "--colorspace", help="lin_rec709 | acescg"),
    reference_exposure: Optional[float] = typer.Option(None, "--reference-exposure", help="exposure factor the outputs are "
                                                       "relative to (s x ISO/100 / f-number^2); default: the photos' median"),
    ignore_exposure: bool = typer.Option(False, "--ignore-exposure", help="only undo the tone curve (photos at one fixed exposure)"),
    clip_level: float = typer.Option(0.99, "--clip-level", help="encoded value at or above which a pixel is flagged clipped"),
    dtype: str = typer.Option("half", "--dtype", help="EXR storage: half | float"),
) -> None:
    """Undo each photo's tone curve and divide out its exposure (EXIF), so radiance compares across photos."""
    from damcap.capture.linearize import LinearizeOptions, linearize_files, list_photos
    from damcap.common.atomic import write_json_atomic
    from damcap.common.version import damcap_version

    opts = LinearizeOptions(colorspace=colorspace, reference_exposure=reference_exposure,  # type: ignore[arg-type]
                            ignore_exposure=ignore_exposure, dtype=dtype, clip_level=clip_level)  # type: ignore[arg-type]
    opts.validate()
    refuse_input_overlap(output, photos)
    files = list_photos(photos)
    with warnings.catch_warnings():
        warnings.showwarning = _echo_warning
        record = linearize_files(files, output, opts)
    record = {"damcap_version": damcap_version(), "photos_folder": str(photos.resolve()), **record}
    write_json_atomic(output / "linearize.json", record)
    scales = [r["scale"] for r in record["photos"]]
    typer.echo(f"wrote {len(files)} linear EXR(s) to {output} (reference exposure {record['reference_exposure']:.4g}, "
               f"scales {min(scales):.3g} .. {max(scales):.3g}); record: {output / 'linearize.json'}")
