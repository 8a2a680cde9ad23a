"""Splits by where the cameras are (reconstruct/split.py)."""

from __future__ import annotations

import numpy as np

from damcap.reconstruct.split import arc_split, camera_split, ring_split


def _ring(n: int, elevation_deg: float) -> np.ndarray:
    a = np.arange(n) * 2 * np.pi / n
    e = np.radians(elevation_deg)
    return np.stack([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.full(n, np.sin(e))], 1)


def test_ring_split_trains_on_one_band_and_tests_the_others():
    dirs = np.concatenate([_ring(10, 10), _ring(10, 45), _ring(10, 45.5)[:3]])
    train, test = ring_split(dirs, np.array([0, 0, 1.0]), 5)
    assert all(i >= 10 for i in train) and len(train) == 5  # the fuller band (45 deg) trains
    assert test == list(range(10))  # the 10 deg ring is 35 deg away
    # spread in azimuth (farthest-point order): no gap between training cameras wider than 3 of the ring's steps
    az = sorted(np.degrees(np.arctan2(dirs[train, 1], dirs[train, 0])) % 360)
    assert max(np.diff(az + [az[0] + 360])) <= 3 * 36 + 1e-6


def test_one_ring_holds_out_the_arc_opposite_the_first_camera():
    dirs = _ring(12, 20)
    assert ring_split(dirs, np.array([0, 0, 1.0]), 4)[1] == []
    train, test = arc_split(dirs, np.array([0, 0, 1.0]), 4)
    assert test == [5, 6, 7] and 0 in train and not set(train) & set(test)
    assert camera_split(dirs, np.array([0, 0, 1.0]), 4) == (train, test)
    # the up direction matters: the same ring seen with x up is a band of elevations
    two_rings = np.concatenate([_ring(8, 0), _ring(8, 60)])
    assert camera_split(two_rings, np.array([0, 0, 1.0]), 4)[1] == list(range(8, 16)) or \
        camera_split(two_rings, np.array([0, 0, 1.0]), 4)[1] == list(range(8))
