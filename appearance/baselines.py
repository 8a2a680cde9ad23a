"""The paper's reflectance-map baselines, as docs/capture-format.md defines them.

RM++: for each target frame, the training view with the nearest camera centre; every covered
target pixel copies the colour of the covered source pixel (A > 0.5) whose camera-space normal
has the largest cosine with the target pixel's camera-space normal (no interpolation).
RM: the same lookup from ONE source image for all evaluated frames, the one with the lowest mean
DSSIM (an oracle). Evaluated on the training frames themselves, both leave the frame out.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from damcap.appearance.pixels import FOREGROUND_COVERAGE, normal_cam
from damcap.appearance.views import ViewData


class ReflectanceMap:
    """One source view as a lookup table from camera-space normal to colour."""

    def __init__(self, source: ViewData) -> None:
        fg = source.data.coverage > FOREGROUND_COVERAGE
        n = normal_cam(source.data.normal_world[fg], source.world_from_cam)
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        self.colours = source.data.radiance_lin[fg]
        self.tree = cKDTree(n) if len(n) else None

    def lookup(self, target: ViewData) -> np.ndarray:
        """(H, W, 3) image of the target's covered pixels (A > 0) coloured from this source.

        For unit vectors the nearest neighbour in Euclidean distance is the largest cosine.
        """
        covered = target.data.coverage > 0
        out = np.zeros(target.data.coverage.shape + (3,), np.float32)
        if self.tree is None or not covered.any():
            return out
        n = normal_cam(target.data.normal_world[covered], target.world_from_cam)
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        _, idx = self.tree.query(n, k=1)
        out[covered] = self.colours[idx]
        return out


def nearest_source(target: ViewData, sources: list[ViewData], exclude_same: bool) -> int:
    """Index of the source whose camera centre is nearest the target's (optionally not itself)."""
    d = np.array([np.linalg.norm(s.centre_world - target.centre_world) for s in sources])
    if exclude_same:
        d = np.where([s.name == target.name for s in sources], np.inf, d)
    if not np.isfinite(d).any():
        raise ValueError("RM++ needs at least one other source view")
    return int(np.argmin(d))


def rm_plus_plus(sources: list[ViewData], targets: list[ViewData]) -> list[np.ndarray]:
    """RM++ predictions of every target (a target that is also a source never uses itself)."""
    maps: dict[int, ReflectanceMap] = {}
    out = []
    for t in targets:
        k = nearest_source(t, sources, exclude_same=True)
        if k not in maps:
            maps[k] = ReflectanceMap(sources[k])
        out.append(maps[k].lookup(t))
    return out


def rm_oracle(sources: list[ViewData], targets: list[ViewData], score: Callable[[ViewData, np.ndarray], float | None]
              ) -> tuple[list[np.ndarray], str, dict[str, float]]:
    """RM: the single source image with the lowest mean score over the targets (an oracle).

    Args:
        sources: candidate source views.
        targets: evaluated views.
        score: (target, prediction) -> DSSIM (None for a frame without foreground).

    Returns:
        predictions per target, the chosen source's name, and every source's mean score over the
        targets (name -> score; the chosen one is the lowest: RM is the best of them, so with
        many similar sources it gains by selection alone). A target that is itself the chosen
        source (same-view evaluation) is predicted from its own best other source, so no frame
        ever copies itself; the chosen source minimises the mean over the other targets.
    """
    if len(sources) < 2 and any(t.name == sources[0].name for t in targets):
        raise ValueError("RM needs at least two source views for a same-view evaluation")
    maps = [ReflectanceMap(s) for s in sources]
    preds: list[list[np.ndarray | None]] = []
    scores = np.full((len(sources), len(targets)), np.nan)
    for i, (s, rm) in enumerate(zip(sources, maps)):
        row: list[np.ndarray | None] = []
        for j, t in enumerate(targets):
            if t.name == s.name:
                row.append(None)
                continue
            p = rm.lookup(t)
            row.append(p)
            v = score(t, p)
            if v is not None:
                scores[i, j] = v
        preds.append(row)
    mean = np.array([np.nanmean(r) if np.isfinite(r).any() else np.inf for r in scores])
    best = int(np.argmin(mean))
    out = []
    for j, t in enumerate(targets):
        p = preds[best][j]
        if p is None:  # the target is the chosen source: its own best other source
            col = np.where(np.isfinite(scores[:, j]), scores[:, j], np.inf)
            p = preds[int(np.argmin(col))][j]
            if p is None:
                p = np.zeros(t.data.coverage.shape + (3,), np.float32)
        out.append(p)
    return out, sources[best].name, {s.name: float(m) for s, m in zip(sources, mean)}
