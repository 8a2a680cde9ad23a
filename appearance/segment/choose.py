"""Choosing the number of materials (``--materials auto``, ``--target-dssim``)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

from damcap.common.errors import DamcapError
from damcap.common.validate import FRACTION, check_ranges, in_range

from damcap.appearance.views import ViewData
from damcap.appearance.segment.model import SegmentationModel
from damcap.appearance.segment.options import MAX_SEGMENT_MATERIALS, SegmentOptions
from damcap.appearance.segment.score import material_shares, novel_view_dssim
from damcap.appearance.segment.train import segment_materials


@dataclass(frozen=True)
class ChooseOptions:
    """How ``damcap segment`` picks the number of materials (the segmentation itself: SegmentOptions)."""

    materials: str = "auto"
    """number of materials n, or 'auto' (the smallest n whose held-out error stops improving)"""
    max_materials: int = field(default=4, metadata=in_range(1, MAX_SEGMENT_MATERIALS))
    """largest n tried by --materials auto"""
    margin: float = field(default=0.1, metadata=in_range(0, 1, cli_panel="advanced"))
    """--materials auto keeps n when n + 1 improves held-out DSSIM by less than this fraction"""
    min_gain: float = field(default=0.01, metadata=in_range(0, 1, cli_panel="advanced"))
    """--materials auto keeps n also when n + 1 improves held-out DSSIM by less than this absolute amount"""
    restarts: int = field(default=2, metadata=in_range(1, 100, cli_panel="advanced"))
    """--materials auto: runs (seeds) per n, the best kept (the held-out error of one run is seed-noisy)"""
    min_share: float = field(default=0.01, metadata={**FRACTION, "cli_panel": "advanced"})
    """--materials auto: smallest share of the training pixels each material must win for n to count"""
    target_dssim: float | None = field(default=None, metadata=FRACTION)
    """with --materials auto: the fewest materials whose held-out DSSIM is at most this"""

    def validate(self) -> None:
        """Raise DamcapError naming the first value outside its range (--materials included)."""
        check_ranges(self)
        self.fixed_materials()

    def fixed_materials(self) -> int | None:
        """n of ``--materials N``; None for 'auto'.

        Raises:
            DamcapError: neither a number nor 'auto'.
        """
        if self.materials == "auto":
            return None
        try:
            n = int(self.materials)
        except ValueError:
            n = 0
        if not 1 <= n <= MAX_SEGMENT_MATERIALS:
            raise DamcapError(f"--materials must be 'auto' or an integer in [1, {MAX_SEGMENT_MATERIALS}], got {self.materials}")
        return n


@dataclass
class MaterialChoice:
    """The outcome of ``--materials auto`` (or of a target accuracy)."""

    model: SegmentationModel
    materials: int
    curve: list[dict[str, Any]]
    """per n tried: materials, heldout_dssim (the best restart's), per-restart errors, shares, seconds"""
    margin: float
    reason: str
    """why this n, in words"""


def choose_materials(train: list[ViewData], heldout: list[ViewData], opts: SegmentOptions, max_materials: int = ChooseOptions.max_materials,
                     margin: float = ChooseOptions.margin, min_gain: float = ChooseOptions.min_gain, restarts: int = ChooseOptions.restarts,
                     min_share: float = ChooseOptions.min_share, target_dssim: float | None = None,
                     progress: Callable[[int, int, dict[str, float]], None] | None = None,
                     log: Callable[[str], None] | None = None, run_log: Callable[[str], None] | None = None) -> MaterialChoice:
    """The smallest n whose held-out error stops improving: n is kept when n + 1 materials lower
    the held-out DSSIM by less than ``margin`` (relative) or less than ``min_gain`` (absolute),
    or when ``max_materials`` is reached.
    With ``target_dssim``: the smallest n whose held-out DSSIM is at most the target.

    The held-out error is the test split's DSSIM on the surface the training views saw
    (:func:`novel_view_dssim` with ``seen_only``), the best of ``restarts`` runs with different
    seeds: measured on closed-form captures, one run's novel-view DSSIM varies by up to 2x with
    the seed (the DAMs extrapolate to unseen inputs differently), more than one material more
    or less changes it. Near-perfect fits (DSSIM ~0.005) change by tens of percent between
    seeds, hence the absolute floor ``min_gain``. An n + 1 whose run leaves a material (almost)
    unused (largest weight on less than ``min_share`` of the training pixels) is no n + 1
    material model and never counts as an improvement.

    Args:
        train: views to fit.
        heldout: views to score (the test split), weights carried from the geometry.
        opts: segment options (``materials`` is ignored; ``seed`` is the first restart's).
        max_materials: the largest n tried.
        margin: relative improvement that justifies one more material (0.1 = 10 %).
        min_gain: absolute DSSIM improvement that one more material must also bring.
        restarts: runs per n (seeds ``seed``, ``seed + 1``, ...); the best is kept.
        min_share: smallest share of the training pixels a material must win.
        target_dssim: stop at the first n that reaches this held-out DSSIM instead.
        log: called with one line per n tried.
        run_log: each run's one-line messages (the predictor's prior: :func:`.train.segment_materials`).
    """
    if not heldout:
        raise DamcapError("--materials auto needs held-out views (a non-empty test split)")
    if restarts < 1 or max_materials < 1:
        raise DamcapError(f"--restarts and --max-materials must be >= 1, got {restarts} and {max_materials}")
    if target_dssim is not None and not 0 < target_dssim < 1:
        raise DamcapError(f"--target-dssim must lie in (0, 1), got {target_dssim}")
    curve: list[dict[str, Any]] = []
    best: SegmentationModel | None = None
    best_err = math.inf
    for n in range(1, max_materials + 1):
        runs = []
        for r in range(restarts):
            model = segment_materials(train, SegmentOptions(**{**asdict(opts), "materials": n, "seed": opts.seed + r}), progress, run_log)
            runs.append((novel_view_dssim(model, heldout, seen_only=True), model))
        err, model = min(runs, key=lambda t: t[0])
        shares = material_shares(model, train)
        used = bool(shares.min() >= min_share)
        curve.append({"materials": n, "heldout_dssim": err, "restarts": [e for e, _ in runs], "shares": shares.round(4).tolist(),
                      "all_used": used, "seconds": sum(m.seconds for _, m in runs)})
        if log:
            log(f"n = {n}: held-out DSSIM (seen surface) {err:.4f}, best of {restarts} run(s), "
                f"material shares {', '.join(f'{x:.2f}' for x in shares)}, {curve[-1]['seconds']:.0f} s")
        if target_dssim is not None:
            if used and err <= target_dssim:
                return MaterialChoice(model, n, curve, margin, f"the fewest materials whose held-out DSSIM {err:.4f} <= {target_dssim}")
            if best is None or (used and err < best_err):
                best, best_err = model, err
            continue
        if best is not None and not (used and err < best_err - max(margin * best_err, min_gain)):
            why = "left a material unused" if not used else f"improved held-out DSSIM by less than {margin:.0%} or {min_gain}"
            return MaterialChoice(best, best.materials, curve, margin, f"n = {n} {why}")
        best, best_err = model, err
    assert best is not None
    if target_dssim is not None:
        return MaterialChoice(best, best.materials, curve, margin, f"no n up to {max_materials} reached {target_dssim}; kept the most accurate")
    return MaterialChoice(best, best.materials, curve, margin, f"every n up to --max-materials {max_materials} improved")
