"""Model only what a scene requires: the smallest DAM that reaches an accuracy asked for.

``damcap fit --target-dssim X`` fits DAMs of growing size (:data:`SIZE_LADDER`, ordered by
weight count) and keeps the first whose DSSIM on held-out *training* views is at most X. The
held-out views are the ones the fit's stopping rule already keeps out
(:func:`.fit.held_out`), so the test split stays untouched for evaluation.

Resuming: with a ``checkpoint_path`` (``damcap fit`` uses ``OUTPUT.ckpt``), the size in progress
checkpoints to its own file beside it (``OUTPUT.ckpt.w16d2``, :func:`.fit.fit_dam`'s checkpoints)
and every finished size's result (held-out DSSIM, seconds, the weights) is recorded atomically
in ``OUTPUT.ckpt.sizes``. A rerun with the same fit options and training views reuses the
finished sizes and resumes the one in progress, so it chooses what an uninterrupted run would;
a record made with other options or views is discarded (and the ladder starts afresh). The
target itself may differ between runs: a finished size's fit does not depend on it. The files
are removed when the run completes.
"""

from __future__ import annotations

import json
import os
import statistics
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

from damcap.common.errors import DamcapError

from damcap.appearance.views import ViewData
from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
from damcap.appearance.evaluate import score_view
from damcap.appearance.fit import FitOptions, fit_dam, held_out, load_checkpoint, save_checkpoint
from damcap.appearance.render import render_frame
from damcap.appearance.views import samples_of
from damcap.appearance.pixels import PixelSamples

#: (width, depth) candidates; tried in order of weight count. (32, 4) is the paper's 3360 weights.
SIZE_LADDER: tuple[tuple[int, int], ...] = ((8, 2), (16, 2), (16, 3), (32, 3), (32, 4), (64, 4))


@dataclass
class SizeChoice:
    """The outcome of a target-accuracy fit."""

    model: DeepAppearanceMap
    width: int
    depth: int
    reached: bool
    """False when no size reached the target (the model is then the most accurate one tried)"""
    tried: list[dict[str, float]] = field(default_factory=list)
    """per size tried: width, depth, weights, heldout_dssim, seconds"""


def sizes_by_weight_count(encoding: str, ladder: tuple[tuple[int, int], ...] = SIZE_LADDER,
                          separable: bool = False) -> list[tuple[int, int, int]]:
    """(width, depth, weights) of the ladder, smallest first.

    >>> sizes_by_weight_count("nr")[:2]
    [(8, 2, 136), (16, 2, 400)]
    >>> sizes_by_weight_count("nr", separable=True)[:2]
    [(8, 2, 80), (16, 2, 224)]
    """
    sized = [(w, d, DamArchitecture(width=w, depth=d, encoding=encoding, separable=separable).num_weights)  # type: ignore[arg-type]
             for w, d in ladder]
    return sorted(sized, key=lambda t: t[2])


def size_checkpoint_path(checkpoint_path: str | os.PathLike, width: int, depth: int) -> Path:
    """Where the fit of one ladder size checkpoints: ``CKPT.w{width}d{depth}``.

    >>> size_checkpoint_path("m.dam.ckpt", 16, 2).name
    'm.dam.ckpt.w16d2'
    """
    p = Path(checkpoint_path)
    return p.with_name(f"{p.name}.w{width}d{depth}")


def sizes_record_path(checkpoint_path: str | os.PathLike) -> Path:
    """Where the finished sizes' results are recorded: ``CKPT.sizes``."""
    p = Path(checkpoint_path)
    return p.with_name(p.name + ".sizes")


def target_checkpoint_files(checkpoint_path: str | os.PathLike, ladder: tuple[tuple[int, int], ...] = SIZE_LADDER) -> list[Path]:
    """The sidecar files a target run may leave beside ``checkpoint_path`` (existing ones only)."""
    paths = [sizes_record_path(checkpoint_path)] + [size_checkpoint_path(checkpoint_path, w, d) for w, d in ladder]
    return [p for p in paths if p.is_file()]


def remove_target_checkpoints(checkpoint_path: str | os.PathLike, ladder: tuple[tuple[int, int], ...] = SIZE_LADDER) -> None:
    """Delete the sidecar files of a target run (``--no-resume``, or a completed run)."""
    for p in target_checkpoint_files(checkpoint_path, ladder):
        p.unlink(missing_ok=True)


def _ladder_key(opts: FitOptions, train: list[ViewData], samples: PixelSamples) -> str:
    """What finished sizes depend on: the fit options other than width/depth, the views, their
    pixels (bit for bit: another capture under the same frame names differs) and the version."""
    from damcap.common.fingerprint import fingerprint
    from damcap.common.version import package_version

    o = {k: v for k, v in asdict(opts).items() if k not in ("width", "depth")}
    data = fingerprint(package_version(), samples.view_dir_world, samples.normal_world, samples.radiance_lin, samples.weight,
                       samples.frame_index)
    return json.dumps({"options": o, "frames": [v.name for v in train], "n_samples": len(samples), "data": data}, sort_keys=True)


def _load_finished(path: Path, key: str, progress: Callable[[str], None] | None) -> dict[tuple[int, int], dict[str, Any]]:
    """Finished sizes recorded at ``path`` by a run with the same ``key`` ({} otherwise)."""
    if not path.is_file():
        return {}
    state = load_checkpoint(path)  # an unreadable record warns and reads as {}
    if state and state.get("key") != key:
        if progress:
            progress(f"{path}: recorded with other fit options, training views or damcap version; fitting every size afresh")
        return {}
    return {(int(r["width"]), int(r["depth"])): r for r in state.get("finished", [])}


def fit_to_target(train: list[ViewData], target_dssim: float, opts: FitOptions,
                  progress: Callable[[str], None] | None = None, *,
                  checkpoint_path: str | os.PathLike | None = None,
                  fit_progress: Callable[[int, int, dict[str, float]], None] | None = None) -> SizeChoice:
    """Fit growing DAMs until one reaches ``target_dssim`` on the held-out training views.

    Args:
        train: the training views (at least 3, so that some can be held out).
        target_dssim: the accuracy asked for (mean DSSIM, docs/capture-format.md).
        opts: fit options; width and depth are chosen here, the rest is used as given
            (``holdout_views`` >= 1 is required).
        progress: called with one line per size tried (and one when a record is discarded).
        checkpoint_path: base path of the run's checkpoints (see the module docstring); None =
            no checkpoints. Existing ones made with the same options are resumed.
        fit_progress: passed to every size's :func:`.fit.fit_dam` as its ``progress``.

    Raises:
        DamcapError: a target outside (0, 1), or no held-out views to measure it on.
    """
    if not 0 < target_dssim < 1:
        raise DamcapError(f"--target-dssim must lie in (0, 1), got {target_dssim}")
    held = held_out(train, opts)
    if not held:
        raise DamcapError(f"--target-dssim needs held-out training views: use --holdout-views >= 1 and at least 3 train views "
                          f"(got {opts.holdout_views} and {len(train)})")
    samples = samples_of(train)
    key = _ladder_key(opts, train, samples)
    record = sizes_record_path(checkpoint_path) if checkpoint_path is not None else None
    finished = _load_finished(record, key, progress) if record is not None else {}
    tried: list[dict[str, float]] = []
    best: tuple[float, DeepAppearanceMap, int, int] | None = None
    chosen: SizeChoice | None = None
    for width, depth, n_weights in sizes_by_weight_count(opts.encoding, separable=opts.separable):
        size_opts = replace(opts, width=width, depth=depth)
        done = finished.get((width, depth))
        if done is not None:
            model = DeepAppearanceMap(size_opts.architecture, float(done["radiance_scale"]), done["weights"])
            err, seconds, note = float(done["heldout_dssim"]), float(done["seconds"]), " (recorded)"
        else:
            ckpt = size_checkpoint_path(checkpoint_path, width, depth) if checkpoint_path is not None else None
            result = fit_dam(samples, size_opts, checkpoint_path=ckpt, progress=fit_progress, held_frames=held)
            model, seconds = result.model, result.seconds
            note = f" (resumed from step {result.resumed_from})" if result.resumed_from else ""
            scores = [score_view(train[k], render_frame(model, train[k].data, train[k].centre_world)) for k in held]
            err = statistics.mean(s for s in scores if s is not None)
            if record is not None:
                finished[(width, depth)] = {"width": width, "depth": depth, "heldout_dssim": err, "seconds": seconds,
                                            "radiance_scale": model.radiance_scale, "weights": model.get_flat_weights()}
                save_checkpoint(record, {"key": key, "finished": list(finished.values())})
        tried.append({"width": width, "depth": depth, "weights": n_weights, "heldout_dssim": err, "seconds": seconds})
        if progress:
            progress(f"{width}x{depth} ({n_weights} weights): held-out DSSIM {err:.4f} in {seconds:.1f} s{note}")
        if best is None or err < best[0]:
            best = (err, model, width, depth)
        if err <= target_dssim:
            chosen = SizeChoice(model, width, depth, True, tried)
            break
    if chosen is None:
        assert best is not None
        chosen = SizeChoice(best[1], best[2], best[3], False, tried)
    if checkpoint_path is not None:
        remove_target_checkpoints(checkpoint_path)
    return chosen
