"""Commands of joint material estimation and segmentation: segment."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Optional

import typer

from damcap.common.errors import DamcapError

from damcap.cli.app import app, progress_bar, refuse_input_overlap


@app.command()
def segment(
    capture: Path = typer.Argument(..., help="capture folder"),
    output: Path = typer.Option(..., "-o", "--output", help="output folder"),
    materials: str = typer.Option("auto", help="number of materials n, or 'auto' (smallest n whose held-out error stops improving)"),
    max_materials: int = typer.Option(4, help="largest n tried by --materials auto"),
    margin: float = typer.Option(0.1, help="--materials auto keeps n when n + 1 improves held-out DSSIM by less than this fraction"),
    min_gain: float = typer.Option(0.01, help="--materials auto keeps n also when n + 1 improves held-out DSSIM by less than this absolute amount"),
    restarts: int = typer.Option(2, help="--materials auto: runs (seeds) per n, the best kept (the held-out error of one run is seed-noisy)"),
    target_dssim: Optional[float] = typer.Option(None, "--target-dssim", help="with --materials auto: the fewest materials whose held-out DSSIM is at most this"),
    steps: int = typer.Option(None, help="joint optimisation steps"),
    init_steps: int = typer.Option(None, help="initialisation steps (Psi learns the chromaticity k-means labels)"),
    sparsity_beta: float = typer.Option(None, help="weight of the sparsity cost"),
    prior_weight: float = typer.Option(None, help="weight of the initial (chromaticity k-means) labels during the joint phase; 0 = the paper's cost alone"),
    illumination_degree: int = typer.Option(None, help="initial clustering: degree (0-2) of the illumination tint modelled as a polynomial of the normal; 0 = plain chromaticity k-means"),
    init_colour: str = typer.Option(None, help="initial clustering: 'darkest-view' (the least bright observation of each surface point among the training views, closest to its diffuse colour) or 'pixel' (each pixel's own colour)"),
    colour_floor: float = typer.Option(None, help="initial clustering: pixels dimmer than this fraction of the radiance scale start unlabelled; those up to 0.02 are assigned to the nearest cluster (0.02 = bright pixels only)"),
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

    given = dict(steps=steps, init_steps=init_steps, sparsity_beta=sparsity_beta, prior_weight=prior_weight,
                 illumination_degree=illumination_degree, init_colour=init_colour, colour_floor=colour_floor, seed=seed, device=device)
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
    if target_dssim is not None and materials != "auto":
        raise DamcapError("--target-dssim chooses the number of materials itself: use it with --materials auto")
    reason = None
    if materials == "auto":
        choice = choose_materials(train, test, base, max_materials=max_materials, margin=margin, min_gain=min_gain, restarts=restarts,
                                  target_dssim=target_dssim, progress=progress_bar(total, "segment"))
        model, curve, reason = choice.model, choice.curve, choice.reason
        for row in curve:
            runs = ", ".join(f"{e:.4f}" for e in row["restarts"])
            typer.echo(f"  n = {row['materials']}: held-out DSSIM (seen surface) {row['heldout_dssim']:.4f} (runs: {runs}), "
                       f"material shares {', '.join(f'{x:.2f}' for x in row['shares'])}")
        typer.echo(f"chose n = {model.materials}: {reason}")
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
    write_json_atomic(output / "segment.json", {**provenance, "materials": model.materials, "auto": materials == "auto", "reason": reason,
                                                "curve": curve, "history": model.history, "seconds": model.seconds,
                                                "frames": [v.name for v in train]})
    typer.echo(f"wrote {model.materials} materials to {output} (material_*.dam, weights/*.exr, preview/*.png, segmenter.safetensors)")


@app.command("segment-labels")
def segment_labels(
    segmentation: Path = typer.Argument(..., help="a folder written by damcap segment"),
    mesh: Path = typer.Option(..., "--mesh", help="OBJ/PLY shape to label (the captured object or a new shape)"),
    output: Path = typer.Option(..., "-o", "--output", help="per-vertex labels to write (.npy or .txt), for damcap export --labels"),
    align: str = typer.Option("sphere", help="sphere: map the mesh's bounding sphere onto the captured object's (a new shape) | none: the mesh is in the capture's world frame"),
    weights: Optional[Path] = typer.Option(None, "--weights", help="also write the soft (V, n) weights (.npy)"),
) -> None:
    """Carry a segmentation onto a mesh: each vertex gets the material of the nearest captured surface."""
    import numpy as np

    from damcap.appearance.segment import mesh_material_weights
    from damcap.appearance.segment_file import load_segmentation
    from damcap.common.atomic import write_npy_atomic, write_text_atomic
    from damcap.common.mesh import load_mesh

    refuse_input_overlap(output, segmentation, mesh)
    if output.suffix not in (".npy", ".txt"):
        raise DamcapError(f"{output}: labels are written as .npy or .txt; choose one of these suffixes")
    model = load_segmentation(segmentation)
    shape = load_mesh(mesh)
    w = mesh_material_weights(model, shape.vertices, align)
    labels = w.argmax(1).astype(np.int64)
    if output.suffix == ".npy":
        write_npy_atomic(output, labels)
    else:
        write_text_atomic(output, "\n".join(map(str, labels.tolist())) + "\n")
    if weights is not None:
        refuse_input_overlap(weights, segmentation, mesh)
        write_npy_atomic(weights, w)
    counts = np.bincount(labels, minlength=model.materials)
    typer.echo(f"wrote {output}: {len(labels)} vertices, per material {counts.tolist()}; render with "
               f"damcap export {segmentation}/material_*.dam --mesh {mesh} --labels {output}")
