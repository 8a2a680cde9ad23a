"""Commands of learning-to-learn: train-hyper (the predictor) and predict (a DAM from one view)."""

from __future__ import annotations

import shlex
import sys
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from damcap.common.errors import DamcapError

from damcap.appearance.hyper.file import DEFAULT_SHIPPED, PAPER_SHIPPED
from damcap.cli.app import command, progress_bar
from damcap.cli.paths import beside, check_paths, file_out, on_interrupt

if TYPE_CHECKING:
    from damcap.appearance.hyper.predict import PredictOptions
    from damcap.appearance.hyper.train import HyperTrainOptions
    from damcap.synth.procedural import ProceduralOptions


@command("train-hyper", opts="damcap.appearance.hyper.train:HyperTrainOptions", scene="damcap.synth.procedural:ProceduralOptions")
def train_hyper_cmd(
    dataset: Optional[Path] = typer.Argument(None, help="corpus folder written by `damcap synth-set` (its train split is used); "
                                             "not needed with --procedural 1"),
    output: Path = typer.Option(..., "-o", "--output", help="predictor file to write (safetensors); its recipe goes to the .json beside it"),
    resume: bool = typer.Option(True, "--resume/--no-resume", help="continue from OUTPUT.state if a run was interrupted"),
    *,
    opts: HyperTrainOptions,
    scene: ProceduralOptions,
) -> None:
    """Train the predictor network (learning-to-learn).

    On a corpus, on random closed-form scenes rendered on the fly (--procedural), or both.
    Data-parallel under `torchrun --nproc-per-node N -m damcap.cli.main train-hyper ...`.
    """
    import os

    import hashlib
    import json

    from damcap.appearance.hyper.file import save_predictor
    from functools import partial

    from damcap.appearance.hyper.train import corpus_training_captures, train_hyper
    from damcap.common.atomic import write_json_atomic
    from damcap.common.version import package_version
    from damcap.synth.procedural import render_scenes

    opts.validate()
    scene.validate()
    opts.architecture  # validates channels against the input size
    if dataset is None and opts.procedural < 1:
        raise DamcapError("train-hyper needs a corpus folder (DATASET), or --procedural 1 to train on random scenes alone")
    state = beside(output, ".state")  # refuses an empty output path first
    sidecar = output.with_name(output.stem + ".json")
    check_paths([dataset] if dataset is not None else [], [file_out(output), file_out(state), file_out(sidecar)])
    paths = corpus_training_captures(dataset) if dataset is not None and opts.procedural < 1 else []
    rank = int(os.environ.get("RANK", "0"))
    if not resume and state.exists() and rank == 0:
        state.unlink()
    log = lambda m: typer.echo(m, err=True)  # noqa: E731
    kept = lambda: (f"the training state {state} is kept; rerun the same command to resume" if state.is_file()  # noqa: E731
                    else "no training state was written yet; nothing was kept")
    with on_interrupt(kept):
        def snapshot(step: int, net, init: dict | None) -> None:
            save_predictor(output.with_name(f"{output.stem}.step{step}{output.suffix}"), net,
                           {"command": "damcap " + " ".join(shlex.quote(a) for a in sys.argv[1:]), "snapshot_step": step, "init": init})

        result = train_hyper(paths, opts, checkpoint_path=state, scenes=partial(render_scenes, opts=scene), snapshot=snapshot,
                             progress=progress_bar(opts.steps, "train-hyper"), log=log)
    if rank != 0:
        return
    training = {
        "damcap_package_version": package_version(),
        "command": "damcap " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
        "launcher": {"world_size": result.world_size, "torchrun": result.world_size > 1, "device": result.device},
        "corpus": str(dataset.resolve()) if dataset is not None else None, "train_captures": result.train_captures,
        "val_captures": result.val_captures, "options": {**asdict(opts), "channels": list(opts.channels)},
        "scenes": asdict(scene) if opts.procedural > 0 else None, "curve": result.curve, "best_step": result.best_step,
        "seconds": result.seconds, "init": result.init, "resumed_from": result.resumed_from, "rank_weight_sha256": result.rank_weight_sha256,
    }
    try:
        preset = json.loads((dataset / "corpus.json").read_text()).get("preset", {}).get("name") if dataset is not None else None
    except (OSError, ValueError, AttributeError):
        preset = None
    if preset:
        training["corpus_command"] = f"damcap synth-set {shlex.quote(str(dataset))} --preset {preset} --data-dir DATA"
    save_predictor(output, result.net, training)
    write_json_atomic(sidecar, {"predictor": output.name, "sha256": hashlib.sha256(output.read_bytes()).hexdigest(), **training})
    last = result.curve[-1] if result.curve else {}
    source = f"{len(result.train_captures)} training captures" + (f", {opts.procedural:.0%} of each batch random scenes" if opts.procedural else "")
    typer.echo(f"wrote {output} ({source}, best step {result.best_step}, "
               f"validation L1 {last.get('val_l1', float('nan')):.4f}, {result.seconds:.0f} s, {result.world_size} process(es))")


@command(opts="damcap.appearance.hyper.predict:PredictOptions")
def predict(
    capture: Path = typer.Argument(..., help="capture folder"),
    output: Path = typer.Option(..., "-o", "--output", help="model file to write (.dam)"),
    view: Optional[str] = typer.Option(None, "--view", help="(first) input frame (a train-split file_path or its stem); default: the best "
                                       "covered lit one; a predictor reading several views adds the lit views that spread the cameras most"),
    predictor: Optional[str] = typer.Option(None, "--predictor", help=f"predictor file, or a shipped one by name: {DEFAULT_SHIPPED} (the default: up "
                                            "to 4 views, random closed-form scenes, trained through the readout solve, in its light orientation) "
                                            f"or {PAPER_SHIPPED} (one view, trained on Mitsuba captures: the paper's); "
                                            "docs/learning-to-learn.md compares them"),
    device: str = typer.Option("cpu", help="cpu | cuda | auto"),
    *,
    opts: PredictOptions,
) -> None:
    """Predict a deep appearance map from up to 4 views.

    In milliseconds; says how well it re-synthesises the train views (and whether to refine), then
    either solves its output layer, then its first and output layers together, on the train pixels
    (default) or refines it.
    """
    from damcap.appearance.dam_file import save_dam
    from damcap.appearance.hyper.file import predictor_path
    from damcap.appearance.hyper.predict import predict_capture

    opts.validate()
    pred_path = predictor_path(predictor)
    check_paths([capture, pred_path], [file_out(output)])
    result = predict_capture(capture, opts, pred_path, view=view, device=device, log=typer.echo,
                             progress=lambda desc, total: progress_bar(total, desc))
    save_dam(output, result.model, colorspace=result.capture.colorspace, made_by="predict", provenance=result.record,
             up_world=result.capture.up_world, normal_histogram=result.normal_histogram)
    frames = result.input_frames
    source = frames[0].file_path if len(frames) == 1 else f"{len(frames)} views ({', '.join(f.name for f in frames)})"
    typer.echo(f"wrote {output} (predicted from {source} in {1000 * result.predict_seconds:.0f} ms{result.summary})")
