"""Commands of joint material estimation and segmentation: segment."""

from __future__ import annotations

from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from damcap.common.errors import DamcapError

from damcap.cli.app import command, progress_bar
from damcap.cli.paths import check_paths, file_out, folder_out, frame_output_names, holds, staged_folder
from damcap.cli.options import parse_choice

if TYPE_CHECKING:
    from damcap.appearance.segment.choose import ChooseOptions
    from damcap.appearance.segment.options import SegmentOptions


@command(opts="damcap.appearance.segment.options:SegmentOptions", choice="damcap.appearance.segment.choose:ChooseOptions",
         exclude={"opts": ("materials",)})  # --materials (a number or 'auto') is ChooseOptions'
def segment(
    capture: Path = typer.Argument(..., help="capture folder"),
    output: Path = typer.Option(..., "-o", "--output", help="output folder"),
    *,
    opts: SegmentOptions,
    choice: ChooseOptions,
) -> None:
    """Find the materials of a capture, unsupervised.

    n materials (n DAMs) and per-pixel soft weights, found jointly.
    """
    from damcap.appearance.segment.choose import choose_materials
    from damcap.appearance.segment.score import novel_view_dssim
    from damcap.appearance.segment.train import segment_materials
    from damcap.appearance.segment.file import legend_stem, save_segmentation_folder
    from damcap.appearance.views import load_views
    from damcap.common.capture_folder import read_capture
    from damcap.common.version import package_version

    n = choice.fixed_materials()
    auto = n is None
    base = replace(opts, materials=n) if n is not None else opts
    base.validate()
    check_paths([capture], [folder_out(output, replaces=holds("segment.json"))])
    cap = read_capture(capture)
    train = load_views(cap, "train")
    test = load_views(cap, "test") if cap.test_filenames else []
    total = base.init_steps + base.steps
    if choice.target_dssim is not None and not auto:
        raise DamcapError("--target-dssim chooses the number of materials itself: use it with --materials auto")
    reason = None
    if auto:
        chosen = choose_materials(train, test, base, max_materials=choice.max_materials, margin=choice.margin, min_gain=choice.min_gain,
                                  restarts=choice.restarts, min_share=choice.min_share, target_dssim=choice.target_dssim,
                                  progress=progress_bar(total, "segment"), run_log=typer.echo)
        model, curve, reason = chosen.model, chosen.curve, chosen.reason
        for row in curve:
            runs = ", ".join(f"{e:.4f}" for e in row["restarts"])
            typer.echo(f"  n = {row['materials']}: held-out DSSIM (seen surface) {row['heldout_dssim']:.4f} (runs: {runs}), "
                       f"material shares {', '.join(f'{x:.2f}' for x in row['shares'])}")
        typer.echo(f"chose n = {model.materials}: {reason}")
    else:
        model = segment_materials(train, base, progress=progress_bar(total, "segment"), log=typer.echo)
        curve = [{"materials": model.materials, "heldout_dssim": novel_view_dssim(model, test) if test else None, "seconds": model.seconds}]
    resolved = replace(base, materials=model.materials)
    provenance = {"damcap_package_version": package_version(), "options": asdict(resolved), "capture": str(capture.resolve())}
    # per-frame names by relative path where frames lie in several folders (images/0004, images2/0004)
    names = frame_output_names([f.file_path for f in cap.split("train")], "")
    with staged_folder(output, replace=True) as stage:  # everything moves into OUTPUT together, at the end
        save_segmentation_folder(stage, model, train, names, colorspace=cap.colorspace, provenance=provenance, up_world=cap.up_world,
                                 summary={"auto": auto, "choice": asdict(choice), "reason": reason, "curve": curve,
                                          "history": model.history, "seconds": model.seconds,
                                          "prior": model.prior_choice or None})
    typer.echo(f"wrote {model.materials} materials to {output} (material_*.dam, weights/*.exr, preview/*.png and their legend "
               f"preview/{legend_stem(names)}.png and .json, segmenter.safetensors)")


@command("segment-labels")
def segment_labels(
    segmentation: Path = typer.Argument(..., help="a folder written by damcap segment"),
    mesh: Path = typer.Option(..., "--mesh", help="OBJ/PLY shape to label (the captured object or a new shape)"),
    output: Path = typer.Option(..., "-o", "--output", help="per-vertex labels to write (.npy or .txt), for damcap export --labels"),
    align: str = typer.Option("sphere", parser=parse_choice("--align", ("sphere", "none")), metavar="[sphere|none]", help="sphere: map the mesh's bounding sphere onto the captured object's (a new shape) | none: the mesh is in the capture's world frame"),
    weights: Optional[Path] = typer.Option(None, "--weights", help="also write the soft (V, n) weights (.npy)"),
) -> None:
    """Carry a segmentation onto a mesh, one material per vertex.

    Each vertex gets the material of the nearest captured surface.
    """
    import numpy as np

    from damcap.appearance.segment.model import mesh_material_weights
    from damcap.appearance.segment.file import load_segmentation
    from damcap.common.atomic import write_npy_atomic, write_text_atomic
    from damcap.common.mesh import load_mesh, read_mesh

    check_paths([segmentation, mesh], [file_out(output), file_out(weights)])
    if output.suffix not in (".npy", ".txt"):
        raise DamcapError(f"{output}: labels are written as .npy or .txt; choose one of these suffixes")
    model = load_segmentation(segmentation)
    load_mesh(mesh)  # refuses what export cannot render (no triangles left after clean-up, ...)
    shape = read_mesh(mesh)  # the file's own vertex order: what export --labels reads
    w = mesh_material_weights(model, shape.vertices, align)
    labels = w.argmax(1).astype(np.int64)
    if output.suffix == ".npy":
        write_npy_atomic(output, labels)
    else:
        write_text_atomic(output, "\n".join(map(str, labels.tolist())) + "\n")
    if weights is not None:
        write_npy_atomic(weights, w)
    counts = np.bincount(labels, minlength=model.materials)
    typer.echo(f"wrote {output}: {len(labels)} vertices, per material {counts.tolist()}; render with "
               f"damcap export {segmentation}/material_*.dam --mesh {mesh} --labels {output}")
