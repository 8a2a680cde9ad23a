"""Commands of the synthetic data: closed-form (a capture known in closed form), synth (one
Mitsuba capture), synth-set (the corpus), synth-photos (a textured photo set), synth-studio (a
path-traced photo set of a multi-material object), shape (a mesh)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from damcap.common.data_dir import DATA_ENV, shared_data_dir
from damcap.common.errors import DamcapError

from damcap.cli.app import command, progress_bar
from damcap.cli.paths import check_paths, file_out, folder_out, on_interrupt, staged_folder
from damcap.cli.options import parse_choice

if TYPE_CHECKING:
    from damcap.synth.closed_form import ClosedFormOptions
    from damcap.synth.corpus import CorpusOptions
    from damcap.synth.mitsuba_capture import SynthOptions
    from damcap.synth.photos import PhotoSetOptions
    from damcap.synth.studio import StudioOptions


@command("closed-form", opts="damcap.synth.closed_form:ClosedFormOptions")
def closed_form(
    out: Path = typer.Argument(..., help="new capture folder"),
    *,
    opts: ClosedFormOptions,
) -> None:
    """Write a capture whose appearance is known in closed form.

    Lambert + GGX, distant light.
    """
    from damcap.synth.closed_form import make_closed_form_capture

    check_paths([], [folder_out(out, replaces=_closed_form_capture)])
    with staged_folder(out, replace=True) as stage:  # the capture appears (or replaces the earlier one) whole, at the end
        cap = make_closed_form_capture(stage, opts)
    typer.echo(f"wrote {len(cap.frames)} frames to {out}")


def _closed_form_capture(folder: Path) -> bool:
    """Whether ``folder`` is an earlier ``closed-form`` output (its transforms.json says so)."""
    from damcap.common.validate import load_json_file

    try:
        doc = load_json_file(folder / "transforms.json", "transforms.json")
    except (DamcapError, OSError):
        return False
    source = doc.get("damcap_source") if isinstance(doc, dict) else None
    return isinstance(source, dict) and source.get("generator") == "closed-form"


@command(opts="damcap.synth.mitsuba_capture:SynthOptions")
def synth(
    out: Path = typer.Argument(..., help="new capture folder (or a partial one to resume, same options)"),
    *,
    opts: SynthOptions,
) -> None:
    """Render one synthetic capture with Mitsuba 3, validated.

    The paper's data set.
    """
    from damcap.synth.mitsuba_capture import make_synthetic_capture

    mesh = Path(opts.object) if Path(opts.object).suffix.lower() in (".obj", ".ply") else None  # a mesh file, or a named shape
    check_paths([mesh], [folder_out(out)])
    bar = progress_bar(opts.views, "synth")
    with on_interrupt(lambda: f"the frames rendered so far in {out} are kept; rerun the same command to resume"
                      if out.is_dir() else "nothing was kept"):
        cap = make_synthetic_capture(out, opts, progress=lambda done, total, stats: bar(done, total, stats))
    typer.echo(f"wrote {len(cap.frames)} frames to {out} (train {len(cap.train_filenames)}, test {len(cap.test_filenames)}, "
               f"{cap.materials} material(s)); validated")


@command("synth-set", opts="damcap.synth.corpus:CorpusOptions")
def synth_set(
    out: Path = typer.Argument(..., help="corpus folder (rerun to resume)"),
    data: Optional[Path] = typer.Option(None, "--data-dir", "--data", envvar=DATA_ENV, show_envvar=True,
                                        help="shared data folder with meshes/ and envmaps/ (default: ../shared/data from the current folder)"),
    *,
    opts: CorpusOptions,
) -> None:
    """Render the synthetic corpus: resumable and parallel.

    Render the synthetic corpus: resumable, parallel, with a held-out part listed in corpus.json.
    With --shard I/N, only shard I of N (for N processes or a job array sharing OUT); corpus.json is
    then written by one final run without --shard after every shard has finished.
    """
    from damcap.cli.app import make_bar

    from damcap.synth.corpus import make_corpus

    opts.validate()

    data_dir = shared_data_dir(data)
    if not (data_dir / "meshes").is_dir() or not (data_dir / "envmaps").is_dir():
        raise DamcapError(f"{data_dir}: no meshes/ and envmaps/ here; pass --data-dir (or set {DATA_ENV}) with the shared data folder")
    check_paths([data_dir], [folder_out(out)])
    preset = opts.preset
    shard = opts.shard
    label = f"synth-set {preset}" + (f" shard {shard[0]}/{shard[1]}" if shard else "")
    bar = None

    def on_capture(entry, finished: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = make_bar(total, label, "capture", leave=True)
        bar.n = finished
        bar.set_postfix_str(f"{entry.name}: {entry.status}", refresh=True)

    try:
        with on_interrupt(lambda: f"the captures finished in {out} are kept; rerun the same command to resume"):
            entries = make_corpus(out, preset, data_dir, jobs=opts.jobs, dry_run=opts.dry_run, on_capture=on_capture, shard=shard)
    finally:
        if bar is not None:
            bar.close()
    counts = {s: sum(e.status == s for e in entries) for s in ("done", "skipped", "pending")}
    what = (f"{out}/corpus.json: {len(entries)} captures" if shard is None
            else f"{out} shard {shard[0]}/{shard[1]}: {len(entries)} captures")
    tail = "" if shard is None else "; once every shard has finished, run the same command without --shard: it writes corpus.json"
    typer.echo(f"{what} ({sum(e.split == 'train' for e in entries)} train, "
               f"{sum(e.split == 'heldout' for e in entries)} held out); rendered {counts['done']}, "
               f"already there {counts['skipped']}, not rendered {counts['pending']}{tail}")


@command("synth-photos", opts="damcap.synth.photos:PhotoSetOptions")
def synth_photos(
    out: Path = typer.Argument(..., help="new folder for images/, masks/ and transforms.json"),
    *,
    opts: PhotoSetOptions,
) -> None:
    """Photograph a textured synthetic object for reconstruct.

    Photograph a textured synthetic object (an orbit or a turntable, on black or in a textured
    room): JPEGs with EXIF exposure, masks, ground-truth cameras (the input of damcap reconstruct;
    samples/photos_blob).
    """
    from damcap.synth.photos import make_photo_set

    check_paths([], [folder_out(out)])
    if (out / "images").exists():
        raise DamcapError(f"{out}/images exists; choose a new folder")
    opts.validate()
    names = make_photo_set(out, opts)
    where = " in a textured room" if opts.room else ""
    typer.echo(f"wrote {len(names)} photos ({opts.motion}{where}), masks and transforms.json (ground truth, object frame) to {out}")


@command("synth-studio", opts="damcap.synth.studio:StudioOptions")
def synth_studio(
    out: Path = typer.Argument(..., help="new folder for images/, masks/ and transforms.json (a rerun resumes it)"),
    *,
    opts: StudioOptions,
) -> None:
    """Photograph a multi-material object in a path-traced studio.

    Photograph a multi-material object on a textured board under an environment map, path traced by
    Mitsuba 3: JPEGs with EXIF exposure, masks, ground-truth cameras and the scene's materials (the
    input of damcap reconstruct; samples/photos_studio, make demo).
    """
    from damcap.synth.studio import make_studio_photos

    check_paths([Path(opts.object), Path(opts.env)] if opts.object and opts.env else [], [folder_out(out)])
    opts.validate()
    bar = progress_bar(opts.views, "synth-studio")
    with on_interrupt(lambda: f"the photos written so far are kept; rerun the same command to finish {out}"):
        names = make_studio_photos(out, opts, progress=lambda k, n: bar(k, n, {}))
    typer.echo(f"wrote {len(names)} photos of {Path(opts.object).name} ({opts.materials}) under {Path(opts.env).name}, "
               f"masks and transforms.json (ground-truth cameras and materials) to {out}")


@command()
def shape(
    name: str = typer.Argument(..., parser=parse_choice("SHAPE", ("torus", "sphere", "pot")), metavar="[torus|sphere|pot]",
                               help="the procedural shape (pot: a lidded pot in three parts, body, lid and handle)"),
    output: Path = typer.Argument(..., help=".obj or .ply file to write (pot: .obj, with its .mtl beside it)"),
) -> None:
    """Write a procedural shape as an OBJ/PLY mesh.

    For damcap export --mesh. The pot's parts are OBJ material groups (body, lid, handle): give
    export and view one .dam per part, in that order.
    """
    if name == "pot":
        from damcap.export.shapes import POT_MTL_KD, pot_mesh, write_parted_obj

        if output.suffix.lower() != ".obj":
            raise DamcapError(f"{output}: the pot is written as .obj (its parts are OBJ material groups)")
        check_paths([], [file_out(output), file_out(output.with_suffix(".mtl"))])
        mesh, names = pot_mesh()
        obj, mtl = write_parted_obj(mesh, names, output, POT_MTL_KD)
        typer.echo(f"wrote {obj} and {mtl.name} ({len(mesh.triangles)} triangles; parts {', '.join(names)}: "
                   "give one .dam per part, in this order)")
        return
    from damcap.common.shapes import write_shape

    check_paths([], [file_out(output)])
    typer.echo(f"wrote {write_shape(name, output)}")
