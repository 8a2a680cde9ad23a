"""Commands of learning-to-learn: train-hyper (the predictor) and predict (a DAM from one view)."""

from __future__ import annotations

import shlex
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from damcap.common.errors import DamcapError

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
    """Train the predictor network (learning-to-learn) on a corpus, on random closed-form scenes
    rendered on the fly (--procedural), or both. Data-parallel under
    `torchrun --nproc-per-node N -m damcap.cli.main train-hyper ...`."""
    import os

    import hashlib
    import json

    from damcap.appearance.hyper.file import save_predictor
    from functools import partial

    from damcap.appearance.hyper.train import corpus_training_captures, train_hyper
    from damcap.common.atomic import write_json_atomic
    from damcap.common.version import damcap_version
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
        "damcap_version": damcap_version(),
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
    predictor: Optional[str] = typer.Option(None, "--predictor", help="predictor file, or a shipped one by name: v10 (the default: up to 4 views, random "
                                            "closed-form scenes, trained through the readout solve, in its light frame), v3 (v10 before "
                                            "that training) or v1 "
                                            "(one view, trained on Mitsuba captures: the paper's); docs/learning-to-learn.md compares them"),
    device: str = typer.Option("cpu", help="cpu | cuda | auto"),
    *,
    opts: PredictOptions,
) -> None:
    """Predict a deep appearance map from a set of up to 4 views (one view with predictor v1) in
    milliseconds, say how well it re-synthesises the train views (and whether to refine), then
    either solve its output layer, then its first and output layers together, on the train pixels
    (default) or refine it."""
    from damcap.appearance.dam_file import save_dam
    from damcap.appearance.coverage import training_normal_histogram
    from damcap.appearance.fit import refine_dam
    from damcap.appearance.hyper.frame import rotation_to_up, terminator_fit, unit_direction
    from damcap.appearance.hyper.model import input_images, predict_from_images, predictor_inputs
    from damcap.appearance.hyper.file import load_predictor, predictor_path
    from damcap.appearance.hyper.predict import AUTO, refine_auto, refinement_needed, resynthesis_error, resynthesis_line, solve_prediction
    from damcap.appearance.views import load_views, samples_of
    from damcap.common.capture_folder import read_capture
    from damcap.common.device import resolve_device
    from damcap.common.version import damcap_version

    opts.validate()
    pred_path = predictor_path(predictor)
    check_paths([capture, pred_path], [file_out(output)])
    net, meta = load_predictor(pred_path)
    net.to(resolve_device(device))
    cap = read_capture(capture)
    train_views = load_views(cap, "train")
    try:
        ks, crops, capture_scale = predictor_inputs(train_views, net.arch.input_views, None if view is None else Path(view).stem)
    except DamcapError as e:
        raise DamcapError(f"{capture}: {e}") from None
    frames = [cap.split("train")[k] for k in ks]
    frame = frames[0]
    t0 = time.perf_counter()
    images, scale = input_images(crops, net.arch.input_size, capture_scale)
    # a light-frame predictor: its frame (frame.light_frame) is fitted once, for the network and the record
    light_fit = terminator_fit(images[None]) if net.arch.frame == "light" else None
    model = predict_from_images(net, images, scale, None if light_fit is None else rotation_to_up(light_fit)[0])
    predict_s = time.perf_counter() - t0
    samples = samples_of(train_views)
    err = resynthesis_error(model, train_views, samples)
    typer.echo(resynthesis_line(err, opts.refine_threshold))
    # where the frame put the light: a diagnosis of a poor prediction (frame.light_up_world)
    frame_record = {} if light_fit is None else {"light_frame_up_world": [float(x) for x in unit_direction(light_fit)[0]]}
    record = {"damcap_version": damcap_version(), "capture": str(capture.resolve()), "predictor": str(Path(pred_path).resolve()),
              "predictor_command": meta.get("training", {}).get("command"), "view": frame.file_path,
              "input_views": [f.file_path for f in frames],
              "predict_seconds": predict_s, "options": asdict(opts), "refine_steps": opts.refine_steps,
              "train_views": err.views, "train_dssim_predicted": err.dssim, "train_l1_predicted": err.l1,
              "refine_threshold": opts.refine_threshold, "refinement_needed": refinement_needed(err.dssim, opts.refine_threshold),
              **frame_record}
    extra = ""
    if not opts.refine_steps and (opts.readout_iterations or opts.joint_iterations):
        solved = solve_prediction(model, samples, opts)
        model, parts = solved.model, []
        if solved.readout is not None:
            after = resynthesis_error(solved.readout.model, train_views, samples)
            record.update(readout_seconds=solved.readout_seconds, readout_iterations_used=solved.readout.iterations,
                          train_dssim_readout=after.dssim, train_l1_readout=after.l1)
            parts.append(f"{1000 * solved.readout_seconds:.0f} ms solving its output layer on {min(len(samples), opts.readout_samples)} "
                         f"train pixels ({solved.readout.iterations} iterations)")
        if solved.joint is not None:
            after = resynthesis_error(model, train_views, samples)
            record.update(joint_seconds=solved.joint_seconds, joint_iterations_used=solved.joint.iterations,
                          train_dssim_joint=after.dssim, train_l1_joint=after.l1)
            parts.append(f"{1000 * solved.joint_seconds:.0f} ms solving its first and output layers together on "
                         f"{min(len(samples), opts.joint_samples)} ({solved.joint.iterations} iterations)")
        extra = " + " + " + ".join(parts) + f": train DSSIM {err.dssim:.4f} -> {after.dssim:.4f}, L1 {err.l1:.4f} -> {after.l1:.4f}"
    if opts.refine_steps == AUTO:
        t1 = time.perf_counter()
        model, auto = refine_auto(model, samples, max_steps=opts.refine_max_steps, patience_steps=opts.refine_patience,
                                  learning_rate=opts.refine_learning_rate,
                                  choose_progress=progress_bar(opts.refine_max_steps, "choose refine steps"),
                                  refine_progress=lambda n: progress_bar(n, "refine"))
        record.update(refine_seconds=time.perf_counter() - t1, refine_steps_used=auto.steps_used, refine_steps_run=auto.steps_run,
                      refine_stopped_by=auto.stopped_by, refine_held_out_views=[train_views[i].name for i in auto.held_out],
                      refine_holdout_curve=auto.curve)
        why = ("held-out views stopped improving" if auto.stopped_by == "patience"
               else f"held-out views still improving at --refine-max-steps {opts.refine_max_steps}")
        extra = f", refined {auto.steps_used} steps (auto: {why}; {auto.steps_run} tried)"
    elif opts.refine_steps:
        t1 = time.perf_counter()
        model, _, _ = refine_dam(model, samples, opts.refine_steps, opts.refine_learning_rate, progress=progress_bar(opts.refine_steps, "refine"))
        record.update(refine_seconds=time.perf_counter() - t1, refine_steps_used=opts.refine_steps)
        extra = f", refined {opts.refine_steps} steps"
    if opts.refine_steps:
        after = resynthesis_error(model, train_views, samples)
        record.update(train_dssim_refined=after.dssim, train_l1_refined=after.l1)
        extra += f": train DSSIM {err.dssim:.4f} -> {after.dssim:.4f}, L1 {err.l1:.4f} -> {after.l1:.4f}"
    save_dam(output, model, colorspace=cap.colorspace, made_by="predict", provenance=record, up_world=cap.up_world,
             normal_histogram=training_normal_histogram(samples))
    source = frame.file_path if len(frames) == 1 else f"{len(frames)} views ({', '.join(f.name for f in frames)})"
    typer.echo(f"wrote {output} (predicted from {source} in {1000 * predict_s:.0f} ms{extra})")
