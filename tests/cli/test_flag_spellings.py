"""Every flag spelling ``damcap reconstruct`` and ``damcap evaluate`` accepted before their options
were regrouped (nested options dataclasses, the paper's tables moved to ``damcap tables``) still
parses: users' scripts and the Makefile use them. The lists are frozen from the commands as they
were; a flag may move to a help panel or be hidden, never disappear."""

from __future__ import annotations

import pytest
import typer

import damcap.cli.main  # noqa: F401  (registers every command)
from damcap.cli.app import build_app

RECONSTRUCT_FLAGS = (
    '--auto-dense', '--auto-dense-margin', '--camera-model', '--camera-per-photo', '--capture-size', '--clipped',
    '--dense-planes', '--dense-size', '--dense-views', '--dtype', '--geometry', '--hull-tolerance',
    '--ignore-exposure', '--mask-coverage', '--mask-features', '--masks', '--max-image-size', '--max-num-features',
    '--max-reprojection-px', '--mesh-align', '--min-registered', '--min-registered-fraction',
    '--min-silhouette-precision', '--min-silhouette-recall', '--no-auto-dense', '--no-ignore-exposure',
    '--no-mask-coverage', '--output', '--pairing', '--poisson-depth', '--poses', '--principal-point', '--response',
    '--retrieval-neighbours', '--retry-upsampled-below', '--seed', '--self-check', '--sequential-overlap',
    '--single-camera', '--smooth-iterations', '--sphere-max-rms', '--split', '--split-start', '--supersample',
    '--threads', '--train-views', '--upsample-below', '--voxels', '-o',
)

EVALUATE_FLAGS = (
    '--fit-activation', '--fit-adversarial', '--fit-adversarial-alpha', '--fit-batch-size', '--fit-checkpoint-every',
    '--fit-depth', '--fit-device', '--fit-encoding', '--fit-eval-every', '--fit-holdout-views', '--fit-learning-rate',
    '--fit-normal-refine', '--fit-normal-refine-min-gain', '--fit-normal-refine-min-gain-abs',
    '--fit-normal-refine-prior', '--fit-normal-refine-steps', '--fit-normal-refine-voxel-px', '--fit-precision',
    '--fit-quantile', '--fit-seed', '--fit-separable', '--fit-spatial', '--fit-spatial-min-gain',
    '--fit-spatial-min-gain-abs', '--fit-spatial-prior', '--fit-spatial-voxel-px', '--fit-steps', '--fit-weight-decay',
    '--fit-width', '--fresh', '--json', '--kmeans', '--kmeans-steps', '--model', '--no-fit-adversarial',
    '--no-fit-separable', '--out', '--plot', '--predictor', '--refine-steps', '--segment-batch-pixels',
    '--segment-colour-floor', '--segment-depth', '--segment-device', '--segment-encoding', '--segment-frames-per-step',
    '--segment-illumination-degree', '--segment-init-colour', '--segment-init-steps', '--segment-learning-rate',
    '--segment-materials', '--segment-prior-weight', '--segment-psi-channels', '--segment-psi-resolution',
    '--segment-seed', '--segment-sparsity-beta', '--segment-steps', '--segment-width', '--segmentation',
    '--table-materials', '--table1', '--table2',
)


def _flags(name: str) -> set[str]:
    click_cmd = typer.main.get_command(build_app(name)).commands[name]  # type: ignore[attr-defined]
    return {f for p in click_cmd.params for f in (*p.opts, *p.secondary_opts) if f.startswith("-")}


@pytest.mark.parametrize(("name", "old"), [("reconstruct", RECONSTRUCT_FLAGS), ("evaluate", EVALUATE_FLAGS)])
def test_every_old_flag_spelling_still_parses(name, old):
    missing = sorted(set(old) - _flags(name))
    assert not missing, f"damcap {name} lost flag(s): {missing}"


def test_train_hyper_still_parses_frame_the_old_spelling_of_orientation(tmp_path, capsys, monkeypatch):
    """``--frame world|light`` named the predictor's orientation before it had its own word;
    bench/train_predictor.sh's recipes and the shipped v10's recorded command use it."""
    from damcap.appearance.hyper import train as train_module
    from damcap.cli.main import main
    from damcap.common.errors import DamcapError

    assert {"--orientation", "--frame"} <= _flags("train-hyper")
    seen = []

    def stop(paths, opts, **kw):
        seen.append(opts.orientation)
        raise DamcapError("stopped by the test")

    monkeypatch.setattr(train_module, "train_hyper", stop)
    monkeypatch.chdir(tmp_path)
    for flag in ("--frame", "--orientation"):
        assert main(["train-hyper", "-o", "p.safetensors", "--procedural", "1", flag, "light"]) != 0
    assert seen == ["light", "light"]
    assert "stopped by the test" in capsys.readouterr().err
    monkeypatch.setenv("COLUMNS", "200")
    assert main(["train-hyper", "--help-all"]) == 0
    out = capsys.readouterr().out
    assert "--orientation" in out and "--frame" not in out
