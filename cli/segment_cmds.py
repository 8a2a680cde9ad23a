"""Commands of joint material estimation and segmentation: segment."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import typer

from damcap.common.errors import DamcapError

from .app import app, progress_bar, refuse_input_overlap


@app.command()
def segment(
    capture: Path = typer.Argument(..., help="capture folder"),
    output: Path = typer.Option(..., "-o", "--output", help="output folder"),
    materials: str = typer.Option("auto", help="number of materials n, or 'auto' (smallest n whose held-out error stops improving)"),
    max_materials: int = typer.Option(4, help="largest n tried by --materials auto"),
    margin: float = typer.Option(0.1, help="--materials auto keeps n when n + 1 improves held-out DSSIM by less than this fraction"),
    steps: int = typer.Option(None, help="joint optimisation steps"),
    init_steps: int = typer.Option(None, help="initialisation steps (Psi learns the chromaticity k-means labels)"),
    sparsity_beta: float = typer.Option(None, help="weight of the sparsity cost"),
    seed: int = typer.Option(None),
    device: str = typer.Option(None, help="cpu | cuda | auto"),
) -> None:
    """Find n materials (n DAMs) and per-pixel soft weights jointly, unsupervised."""
    from damcap.appearance.segment import SegmentOptions, choose_materials, false_colour, novel_view_dssim, segment_materials
    from damcap.appearance.segment_file import save_segmentation
    from damcap.appearance.views import load_views
    from damcap.common.atomic import write_json_atomic
    from damcap.common.capture_folder import read_capture, weight_channels
    from damcap.common.exr import write_exr, write_png
    from damcap.common.version import damcap_version

    given = dict(steps=steps, init_steps=init_steps, sparsity_beta=sparsity_beta, seed=seed, device=device)
    base = SegmentOptions(**{k: v for k, v in given.items() if v is not None})
    if materials != "auto":
        try:
            n = int(materials)
        except ValueError:
            raise DamcapError(f"--materials must be a number or 'auto', got {materials!r}") from None
        base = SegmentOptions(**{**asdict(base), "materials": n})
    base.validate()
    refuse_input_overlap(output, capture)
    cap = read_capture(capture)
    train = load_views(cap, "train")
    test = load_views(cap, "test") if cap.test_filenames else []
    total = base.init_steps + base.steps
    if materials == "auto":
        choice = choose_materials(train, test, base, max_materials=max_materials, margin=margin, progress=progress_bar(total, "segment"))
        model, curve = choice.model, choice.curve
        for row in curve:
            typer.echo(f"  n = {row['materials']}: held-out DSSIM {row['heldout_dssim']:.4f}")
        typer.echo(f"chose n = {model.materials} (next n improved held-out DSSIM by less than {margin:.0%})")
    else:
        model = segment_materials(train, base, progress=progress_bar(total, "segment"))
        curve = [{"materials": model.materials, "heldout_dssim": novel_view_dssim(model, test) if test else None, "seconds": model.seconds}]
    opts = SegmentOptions(**{**asdict(base), "materials": model.materials})
    provenance = {"damcap_version": damcap_version(), "options": asdict(opts), "capture": str(capture.resolve())}
    save_segmentation(output, model, colorspace=cap.colorspace, provenance=provenance)
    for v in train:
        w = model.weights_of(v)
        write_exr(output / "weights" / f"{v.name}.exr", w, weight_channels(model.materials), dtype="half")
        write_png(output / "preview" / f"{v.name}.png", false_colour(w, v.data.coverage))
    write_json_atomic(output / "segment.json", {**provenance, "materials": model.materials, "auto": materials == "auto",
                                                "curve": curve, "history": model.history, "seconds": model.seconds,
                                                "frames": [v.name for v in train]})
    typer.echo(f"wrote {model.materials} materials to {output} (material_*.dam, weights/*.exr, preview/*.png, segmenter.safetensors)")
