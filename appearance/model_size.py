"""Model only what a scene requires: the smallest DAM that reaches an accuracy asked for.

``damcap fit --target-dssim X`` fits DAMs of growing size (:data:`SIZE_LADDER`, ordered by
weight count) and keeps the first whose DSSIM on held-out *training* views is at most X. The
held-out views are the ones the fit's stopping rule already keeps out
(:func:`.fit.holdout_frames`), so the test split stays untouched for evaluation.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass, field, replace
from typing import Callable

from damcap.common.errors import DamcapError

from .baselines import ViewData
from .dam import DamArchitecture, DeepAppearanceMap
from .evaluate import score_view
from .fit import FitOptions, fit_dam, holdout_frames
from .render import render_frame
from .views import samples_of

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


def sizes_by_weight_count(encoding: str, ladder: tuple[tuple[int, int], ...] = SIZE_LADDER) -> list[tuple[int, int, int]]:
    """(width, depth, weights) of the ladder, smallest first.

    >>> sizes_by_weight_count("nr")[:2]
    [(8, 2, 136), (16, 2, 400)]
    """
    sized = [(w, d, DamArchitecture(width=w, depth=d, encoding=encoding).num_weights) for w, d in ladder]  # type: ignore[arg-type]
    return sorted(sized, key=lambda t: t[2])


def fit_to_target(train: list[ViewData], target_dssim: float, opts: FitOptions,
                  progress: Callable[[str], None] | None = None) -> SizeChoice:
    """Fit growing DAMs until one reaches ``target_dssim`` on the held-out training views.

    Args:
        train: the training views (at least 3, so that some can be held out).
        target_dssim: the accuracy asked for (mean DSSIM, capture-format.md).
        opts: fit options; width and depth are chosen here, the rest is used as given
            (``holdout_views`` >= 1 is required).
        progress: called with one line per size tried.

    Raises:
        DamcapError: a target outside (0, 1), or no held-out views to measure it on.
    """
    if not 0 < target_dssim < 1:
        raise DamcapError(f"--target-dssim must lie in (0, 1), got {target_dssim}")
    held = holdout_frames(len(train), opts.holdout_views)
    if not held:
        raise DamcapError(f"--target-dssim needs held-out training views: use --holdout-views >= 1 and at least 3 train views "
                          f"(got {opts.holdout_views} and {len(train)})")
    samples = samples_of(train)
    tried: list[dict[str, float]] = []
    best: tuple[float, DeepAppearanceMap, int, int] | None = None
    for width, depth, n_weights in sizes_by_weight_count(opts.encoding):
        result = fit_dam(samples, replace(opts, width=width, depth=depth))
        scores = [score_view(train[k], render_frame(result.model, train[k].data, train[k].centre_world)) for k in held]
        err = statistics.mean(s for s in scores if s is not None)
        tried.append({"width": width, "depth": depth, "weights": n_weights, "heldout_dssim": err, "seconds": result.seconds})
        if progress:
            progress(f"{width}x{depth} ({n_weights} weights): held-out DSSIM {err:.4f} in {result.seconds:.1f} s")
        if best is None or err < best[0]:
            best = (err, result.model, width, depth)
        if err <= target_dssim:
            return SizeChoice(result.model, width, depth, True, tried)
    assert best is not None
    return SizeChoice(best[1], best[2], best[3], False, tried)
