"""Helpers shared by the reconstruct tests: cameras at known poses, photo sizes."""

from __future__ import annotations

import numpy as np

from damcap.common.cameras import look_at_world_from_cam


#: float64 round trips through text files (JSON keeps 17 digits, .npy is exact)
ATOL = 1e-9


def _cameras(n: int = 5, seed: int = 0) -> np.ndarray:
    """(n, 4, 4) OpenGL camera-to-world, random centres looking near the origin."""
    rng = np.random.default_rng(seed)
    mats = []
    for _ in range(n):
        c = rng.normal(size=3)
        c = 3.0 * c / np.linalg.norm(c)
        mats.append(look_at_world_from_cam(c, 0.1 * rng.normal(size=3), np.array([0.0, 1.0, 0.2])))
    return np.stack(mats)


def _sizes(n: int, w: int = 64, h: int = 48) -> dict[str, tuple[int, int]]:
    return {f"IMG_{k:02d}.jpg": (w, h) for k in range(n)}
