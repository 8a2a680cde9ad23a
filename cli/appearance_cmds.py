"""Commands of the appearance stage: inspect, fit, render, evaluate."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from damcap.common.errors import DamcapError

from damcap.cli.app import command, progress_bar
from damcap.cli.paths import beside, check_paths, file_out, folder_out, frame_output_names, holds, on_interrupt, staged_folder
from damcap.cli.options import parse_choice, parse_float, parse_int
from damcap.common.validate import MAX_MATERIALS

if TYPE_CHECKING:
    from damcap.appearance.fit import FitOptions
    from damcap.paper.tables import TableOptions


@command()
def inspect(capture: Path = typer.Argument(..., help="capture folder")) -> None:
    """Summarise a capture folder and validate every file in it."""
    from rich.console import Console
    from rich.table import Table

    from damcap.common.capture_folder import inspect_capture

    s = inspect_capture(capture)
    t = Table(title=str(capture), show_header=False)
    for k, v in [
        ("frames", s.frames), ("resolution", f"{s.resolution[0]}x{s.resolution[1]}"),
        ("mean coverage (A > 0.5)", f"{s.coverage_mean:.1%}"),
        ("radiance range (foreground)", f"{s.radiance_min:.4g} .. {s.radiance_max:.4g} (median {s.radiance_p50:.4g})"),
        ("splits", f"train {s.train}, test {s.test}"), ("materials", s.materials or "unknown"),
        ("colorspace", s.colorspace),
    ]:
        t.add_row(k, str(v))
    Console().print(t)
    if s.problems:
        for p in s.problems:
            typer.echo(f"problem: {p}", err=True)
        raise DamcapError(f"{capture}: {len(s.problems)} problem(s) found")
    typer.echo("valid capture")


@command(opts="damcap.appearance.fit:FitOptions")
def fit(
    capture: Path = typer.Argument(..., help="capture folder"),
    output: Path = typer.Option(..., "-o", "--output", help="model file to write (.dam)"),
    split: str = typer.Option("train", parser=parse_choice("--split", ("train", "all")), metavar="[train|all]", help="frames to fit"),
    resume: bool = typer.Option(True, "--resume/--no-resume", help="continue from OUTPUT.ckpt if a run was interrupted"),
    target_dssim: Optional[float] = typer.Option(None, "--target-dssim", parser=parse_float("--target-dssim"),
                                                 help="fit growing DAMs and keep the smallest whose DSSIM on the held-out train views is at most this"),
    *,
    opts: FitOptions,
    given: frozenset[str],
) -> None:
    """Fit a deep appearance map to a capture.

    L1 or quantile data cost, optional adversarial cost.
    """
    from damcap.appearance.coverage import training_normal_histogram
    from damcap.appearance.dam_file import save_dam
    from damcap.appearance.fit import held_out
    from damcap.appearance.fit_views import fit_views
    from damcap.appearance.views import load_views, samples_of
    from damcap.common.capture_folder import read_capture
    from damcap.common.version import package_version

    opts.validate()  # numeric options and --precision, before reading the capture
    opts.architecture  # validates width/depth/encoding/activation
    ckpt = beside(output, ".ckpt")
    check_paths([capture], [file_out(output), file_out(ckpt)])
    cap = read_capture(capture)
    views = load_views(cap, split)  # type: ignore[arg-type]
    held = len(held_out(views, opts))  # two views always train
    if "holdout_views" in given and held < opts.holdout_views:
        raise DamcapError(f"--holdout-views must leave 2 of the {len(views)} training views of {capture} to fit "
                          f"(at most {held}), got {opts.holdout_views}")
    opts = _surface_factors_for(opts, given, held, target_dssim is not None, lambda m: typer.echo(m, err=True))
    if target_dssim is not None:
        if opts.spatial != "off" or opts.normal_refine != "off":
            raise DamcapError("--target-dssim sizes the DAM alone; leave out --spatial and --normal-refine (or use them without "
                              "--target-dssim)")
        _fit_to_target(capture, cap, views, split, target_dssim, opts, output, width_or_depth_given=bool({"width", "depth"} & given),
                       resume=resume)
        return
    if not resume and ckpt.exists():
        ckpt.unlink()
    say = lambda message: typer.echo(message, err=True)  # noqa: E731
    # an interrupt during the refinement or the spatial factor keeps the fit's checkpoint too: a rerun resumes the fit, then redoes them
    with on_interrupt(lambda: _checkpoint_kept(ckpt, opts.checkpoint_every)):
        out = fit_views(views, opts, checkpoint_path=ckpt, progress=progress_bar(opts.steps, "fit"),
                        refine_progress=_bar_per_run(opts.normal_refine_steps, "normal refinement"), log=say)
    save_dam(output, out.model, colorspace=cap.colorspace, made_by="fit", provenance={
        "damcap_package_version": package_version(), "options": asdict(opts), "capture": str(capture.resolve()),
        "split": split, "frames": [v.name for v in views], **out.record(views),
    }, up_world=cap.up_world, normal_histogram=training_normal_histogram(samples_of(views)))
    ckpt.unlink(missing_ok=True)  # only now that the model is saved
    typer.echo(f"wrote {output} ({out.result.model.arch.num_weights} weights, {out.samples} pixels, "
               f"best step {out.result.best_step}, {out.seconds:.1f} s)")


def _surface_factors_for(opts, given: frozenset[str], held: int, sizing: bool, say) -> "FitOptions":
    """The 'auto' surface factors by default, except where they cannot decide: with --target-dssim
    (it sizes the DAM alone) or without held-out views; said in one line. Asked for explicitly,
    they stay (and the library or --target-dssim refuses them in one line)."""
    from dataclasses import replace

    defaults = [k for k in ("normal_refine", "spatial") if k not in given and getattr(opts, k) == "auto"]
    if not defaults or (held and not sizing):
        return opts
    if not sizing and "holdout_views" not in given:  # --holdout-views 0 asks for none: nothing to say
        say(f"note: normal refinement and the spatial factor decide on held-out views and {held} are held out; both off "
            f"(--holdout-views >= 1 with 3 or more train views lets them decide)")
    return replace(opts, **{k: "off" for k in defaults})


def _bar_per_run(steps: int, desc: str):
    """A ``progress(step, loss)`` callback drawing a new bar each time a run starts again at step 1."""
    bars = []

    def update(step: int, loss: float) -> None:
        if step == 1 or not bars:
            bars.append(progress_bar(steps, desc))
        bars[-1](step, steps, {"loss": loss})

    return update


def _checkpoint_kept(ckpt: Path, every: int) -> str:
    """The interrupt line of fit: what a rerun resumes from."""
    if ckpt.is_file():
        return f"the checkpoint {ckpt} is kept; rerun the same command to resume"
    return f"no checkpoint was written yet (one every {every} steps, to {ckpt}); nothing was kept"


def _fit_to_target(capture: Path, cap, views, split: str, target: float, opts, output: Path, width_or_depth_given: bool,
                   resume: bool = True) -> None:
    """``fit --target-dssim``: the smallest DAM of the size ladder that reaches the target.

    Checkpoints beside the output (OUTPUT.ckpt.sizes, OUTPUT.ckpt.wWdD); a rerun resumes them
    unless ``resume`` is False.
    """
    from dataclasses import asdict

    from damcap.appearance.coverage import training_normal_histogram
    from damcap.appearance.dam_file import save_dam
    from damcap.appearance.model_size import fit_to_target, remove_target_checkpoints, target_checkpoint_files
    from damcap.appearance.views import samples_of
    from damcap.common.version import package_version

    if width_or_depth_given:
        raise DamcapError("--target-dssim chooses the width and depth itself; leave out --width and --depth")
    if opts.adversarial:
        raise DamcapError("--target-dssim fits without the adversarial cost; leave out --adversarial")
    ckpt = output.with_name(output.name + ".ckpt")
    if not resume:
        remove_target_checkpoints(ckpt)
    existing = target_checkpoint_files(ckpt)
    if existing:
        typer.echo(f"resuming from {', '.join(p.name for p in existing)} in {output.parent}", err=True)
    def kept() -> str:
        files = target_checkpoint_files(ckpt)
        if files:
            return f"the checkpoints {', '.join(str(p) for p in files)} are kept; rerun the same command to resume"
        return "no checkpoint was written yet; nothing was kept"

    with on_interrupt(kept):
        choice = fit_to_target(views, target, opts, progress=lambda line: typer.echo(line, err=True), checkpoint_path=ckpt)
    save_dam(output, choice.model, colorspace=cap.colorspace, made_by="fit", provenance={
        "damcap_package_version": package_version(), "options": asdict(opts), "capture": str(capture.resolve()), "split": split,
        "frames": [v.name for v in views], "target_dssim": target, "target_reached": choice.reached, "sizes_tried": choice.tried,
    }, up_world=cap.up_world, normal_histogram=training_normal_histogram(samples_of(views)))
    n = choice.model.arch.num_weights
    err = next(t["heldout_dssim"] for t in choice.tried if t["width"] == choice.width and t["depth"] == choice.depth)
    if choice.reached:
        typer.echo(f"wrote {output}: {choice.width}x{choice.depth} ({n} weights) is the smallest DAM that reaches "
                   f"held-out DSSIM {err:.4f} <= {target}")
    else:
        typer.echo(f"wrote {output}: no size reached {target}; the most accurate was {choice.width}x{choice.depth} "
                   f"({n} weights, held-out DSSIM {err:.4f}). More steps (--steps) or more train views may help.")


@command()
def render(
    model: Path = typer.Argument(..., help="model file (.dam)"),
    capture: Path = typer.Argument(..., help="capture folder (cameras and geometry)"),
    output: Path = typer.Option(..., "-o", "--output", help="folder for one EXR per frame"),
    split: str = typer.Option("test", parser=parse_choice("--split", ("test", "train", "all")), metavar="[test|train|all]",
                              help="frames to render"),
) -> None:
    """Render the model into every frame of a split.

    One linear EXR per frame, background 0.
    """
    import numpy as np

    from damcap.appearance.dam_file import load_dam
    from damcap.appearance.render import render_frame
    from damcap.common.atomic import write_json_atomic
    from damcap.common.capture_folder import RADIANCE_CHANNELS, read_capture, read_frame
    from damcap.common.exr import write_exr
    from damcap.common.version import package_version

    check_paths([model, capture], [folder_out(output, replaces=holds("render.json"))])  # an earlier render is replaced, nothing else touched
    dam, meta = load_dam(model)
    cap = read_capture(capture)
    frames = cap.split(split)  # type: ignore[arg-type]
    names = frame_output_names([f.file_path for f in frames], ".exr")  # unique: images/0004 and images2/0004 never collide
    if "render.json" in names:
        raise DamcapError(f"{capture}: a frame would be written as render.json; rename the frame")
    from damcap.cli.app import make_bar

    with staged_folder(output, replace=True) as stage:
        for f, name in make_bar(len(frames), "render", "frame", list(zip(frames, names))):
            img = render_frame(dam, read_frame(cap, f, with_weights=False), f.camera_centre_world)
            if not np.isfinite(img).all():  # load_dam's overflow check probes directions; this is the frame's own
                raise DamcapError(f"{model}: the model's radiance overflows float32 (inf or NaN) on frame {f.file_path}")
            write_exr(stage / name, img, RADIANCE_CHANNELS, dtype="float",
                      attributes={"damcap:colorspace": meta.get("colorspace", "lin_rec709")})
        write_json_atomic(stage / "render.json", {"damcap_package_version": package_version(), "model": str(model.resolve()),
                                                   "capture": str(capture.resolve()), "split": split,
                                                   "frames": [f.file_path for f in frames],
                                                   "outputs": dict(zip((f.file_path for f in frames), names))})
    typer.echo(f"wrote {len(frames)} frames to {output}")


@command(table="damcap.paper.tables:TableOptions", hidden=("table",))
def evaluate(
    capture: Optional[Path] = typer.Argument(None, help="capture folder"),
    model: Optional[list[Path]] = typer.Option(None, "--model", help="model file (.dam), repeatable (e.g. a predicted and a fitted one); without it only the baselines"),
    json_path: Optional[Path] = typer.Option(None, "--json", help="write the results as JSON"),
    plot: Optional[Path] = typer.Option(None, "--plot", help="sorted per-frame DSSIM plot (PNG); default next to --json"),
    segmentation: Optional[Path] = typer.Option(None, "--segmentation", help="a folder written by damcap segment"),
    kmeans: Optional[int] = typer.Option(None, "--kmeans", parser=parse_int("--kmeans", (1, MAX_MATERIALS)), metavar="INTEGER",
                                         help="also the k-means baseline with this many materials"),
    # the paper's tables, now 'damcap tables': still accepted here (hidden) for existing scripts
    table1: Optional[list[Path]] = typer.Option(None, "--table1", hidden=True),
    table2: Optional[Path] = typer.Option(None, "--table2", hidden=True),
    out: Optional[Path] = typer.Option(None, "--out", hidden=True),
    predictor: Optional[Path] = typer.Option(None, "--predictor", hidden=True),
    table_materials: str = typer.Option("auto", "--table-materials", hidden=True),
    fresh: bool = typer.Option(False, "--fresh", hidden=True),
    *,
    table: TableOptions,
    given: frozenset[str],
) -> None:
    """Mean DSSIM of the model, RM and RM++, same and novel view.

    Same view (train) and novel view (test), for the model, RM and RM++ (and segmentations: ours
    and the k-means baseline). The paper's tables: damcap tables.
    """
    if table1 or table2:
        from damcap.cli.tables_cmds import run_tables

        if capture is not None or model or segmentation or kmeans is not None or json_path or plot:
            raise DamcapError("--table1 / --table2 run every method themselves: give no CAPTURE, --model, --segmentation, --kmeans, --json or --plot")
        typer.echo("note: the paper's tables are now 'damcap tables' (same options: damcap tables --table1 CORPUS / --table2 CAPTURE "
                   "--out DIR); evaluate still runs them", err=True)
        run_tables(table1, table2, out, predictor, table_materials, fresh, table)
        return
    table_only = [flag for flag, on in (("--out", out is not None), ("--predictor", predictor is not None),
                                        ("--table-materials", table_materials != "auto"), ("--fresh", fresh)) if on]
    table_only += [f"--{name.replace('.', '-').replace('_', '-')}" for name in sorted(given)]
    if table_only:
        raise DamcapError(f"{table_only[0]} is an option of the paper's tables (damcap tables --table1 / --table2); "
                          "without them evaluate scores the given models")
    if capture is None:
        raise DamcapError("evaluate needs a CAPTURE folder (the paper's tables: damcap tables --table1 CORPUS / --table2 CAPTURE)")
    from rich.console import Console
    from rich.table import Table

    from damcap.appearance.dam_file import load_dam
    from damcap.appearance.evaluate import evaluate_split, plot_sorted_dssim
    from damcap.appearance.views import load_views
    from damcap.common.atomic import write_json_atomic
    from damcap.common.capture_folder import read_capture
    from damcap.common.version import package_version

    model_paths = list(model or [])
    if plot is None and json_path is not None:
        plot = json_path.with_suffix(".png")
    check_paths([capture, *model_paths, segmentation], [file_out(json_path), file_out(plot)])
    models, made_by = {}, {}
    for path in model_paths:
        dam, meta = load_dam(path)
        label = "DAM" if len(model_paths) == 1 else f"{meta.get('made_by', 'DAM')}: {path.stem}"
        if label in models:
            raise DamcapError(f"{path}: two models would share the label {label!r}; give the files different names")
        models[label], made_by[label] = dam, meta.get("made_by")
    segs = {}
    if segmentation is not None:  # the whole folder is checked before any scoring
        from damcap.appearance.segment.file import load_segmentation

        segs["segment"] = load_segmentation(segmentation)
    cap = read_capture(capture)
    train = load_views(cap, "train")
    test = load_views(cap, "test")
    from damcap.appearance.pixels import FOREGROUND_COVERAGE
    from damcap.common.validate import require_foreground

    require_foreground([v.data.coverage for v in train + test], FOREGROUND_COVERAGE, capture)  # nothing to score: refused before any output
    from damcap.cli.app import stage_progress

    progress = stage_progress()
    results = {"train": evaluate_split(train, train, models, progress=progress, split="same view"),
               "test": evaluate_split(train, test, models, progress=progress, split="novel view")}
    if kmeans is not None:
        from damcap.appearance.segment.kmeans_baseline import kmeans_baseline

        segs["k-means"] = kmeans_baseline(train, kmeans)
    if segs:
        from damcap.appearance.evaluate import MethodScores
        from damcap.appearance.segment.score import segmentation_scores

        for name, seg in segs.items():
            for split, targets in (("train", train), ("test", test)):
                for source, per_frame in segmentation_scores(seg, train, targets, same_view=split == "train").items():
                    results[split][f"{name} ({source})"] = MethodScores(per_frame)
    table = Table(title=f"mean DSSIM (lower is better): {capture}")
    table.add_column("method")
    table.add_column("same view (train)", justify="right")
    table.add_column("novel view (test)", justify="right")
    for method in results["test"]:
        same = results["train"].get(method)
        table.add_row(method, f"{same.mean:.4f}" if same else "-", f"{results['test'][method].mean:.4f}")
    Console().print(table)
    ratios = {f"{p} / {f}": {split: results[split][p].mean / max(results[split][f].mean, 1e-12) for split in ("train", "test")}
              for p in models if made_by[p] == "predict" for f in models if made_by[f] == "fit"}
    for name, r in ratios.items():
        typer.echo(f"{name}: novel-view DSSIM x{r['test']:.3f}, same-view x{r['train']:.3f} (predicted vs SGD fit)")
    if plot is not None:
        plot_sorted_dssim(results, plot, title=capture.name)
        typer.echo(f"plot: {plot}")
    if json_path is not None:
        write_json_atomic(json_path, {
            "damcap_package_version": package_version(), "capture": str(capture.resolve()),
            "model": str(model_paths[0].resolve()) if len(model_paths) == 1 else None,
            "models": {label: {"path": str(p.resolve()), "made_by": made_by[label]} for label, p in zip(models, model_paths)},
            "ratios": ratios, "metric": "DSSIM (capture-format.md)",
            "results": {split: {m: {"mean": s.mean, "per_frame": s.per_frame, **({"note": s.note} if s.note else {}),
                                    **({"per_source_mean": s.per_source} if s.per_source else {})}
                                for m, s in res.items()} for split, res in results.items()},
        })
        typer.echo(f"json: {json_path}")
