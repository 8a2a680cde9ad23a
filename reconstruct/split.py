"""Train/test splits by where the cameras are (``reconstruct --split rings``): novel views that
lie on other rings of cameras, or on an arc of the one ring, so that a capture's test split asks
what a user's novel views ask (extrapolation), not what a neighbour between two training views asks.

Pure: unit camera directions in, frame indices out.
"""

from __future__ import annotations

import numpy as np


def ring_split(directions: np.ndarray, up: np.ndarray, train_views: int, band_deg: float = 20.0,
               gap_deg: float = 15.0) -> tuple[list[int], list[int]]:
    """A split by camera rings: train on one elevation band, test on the cameras far above or below it.

    The band is the ``band_deg``-wide window of elevations holding the most cameras (ties: the
    higher one); ``train_views`` of its cameras spread in azimuth train (farthest-point order
    from the first); the test views are all cameras whose elevation differs from the band's
    mean by more than ``gap_deg``.

    Args:
        directions: (N, 3) unit vectors from the object's centre to the cameras.
        up: (3,) the capture's up direction.

    >>> a = np.arange(12) * np.pi / 6
    >>> ring = lambda e: np.stack([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.full(12, np.sin(e))], 1)
    >>> tr, te = ring_split(np.concatenate([ring(0.26), ring(0.79)]), np.array([0, 0, 1.0]), 6)
    >>> sorted(tr), te
    ([12, 14, 15, 18, 21, 23], [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11])
    """
    up = up / np.linalg.norm(up)
    elev = np.degrees(np.arcsin(np.clip(directions @ up, -1, 1)))
    starts = np.sort(elev)
    counts = [(int(((elev >= s) & (elev <= s + band_deg)).sum()), s) for s in starts]
    best = max(c for c, _ in counts)
    lo = max(s for c, s in counts if c == best)
    band = np.flatnonzero((elev >= lo) & (elev <= lo + band_deg))
    mean = float(elev[band].mean())
    horiz = directions[band] - np.outer(directions[band] @ up, up)
    az = np.arctan2(horiz @ np.cross(up, horiz[0] / np.linalg.norm(horiz[0])), horiz @ (horiz[0] / np.linalg.norm(horiz[0])))
    chosen = [0]
    while len(chosen) < min(train_views, len(band)):
        gap = np.min(np.abs(np.angle(np.exp(1j * (az[:, None] - az[None, chosen])))), axis=1)
        chosen.append(int(np.argmax(gap)))
    train = [int(band[k]) for k in chosen]
    test = [int(i) for i in np.flatnonzero(np.abs(elev - mean) > gap_deg)]
    return train, test


def arc_split(directions: np.ndarray, up: np.ndarray, train_views: int, arc_deg: float = 90.0) -> tuple[list[int], list[int]]:
    """A split for one ring of cameras: the cameras within ``arc_deg`` / 2 of the azimuth opposite
    camera 0 are the novel views; ``train_views`` of the others, spread in azimuth, train.

    >>> a = np.arange(12) * np.pi / 6
    >>> tr, te = arc_split(np.stack([np.cos(a), np.sin(a), 0 * a], 1), np.array([0, 0, 1.0]), 4)
    >>> te, sorted(tr)
    ([5, 6, 7], [0, 2, 4, 8])
    """
    up = up / np.linalg.norm(up)
    horiz = directions - np.outer(directions @ up, up)
    x = horiz[0] / np.linalg.norm(horiz[0])
    az = np.degrees(np.arctan2(horiz @ np.cross(up, x), horiz @ x))
    off = np.abs((az - 180.0 + 180.0) % 360.0 - 180.0)  # angle from the azimuth opposite camera 0
    test = [int(i) for i in np.flatnonzero(off <= arc_deg / 2 + 1e-6)]
    rest = np.array([i for i in range(len(directions)) if i not in test])
    chosen = [0]
    while len(chosen) < min(train_views, len(rest)):
        gap = np.min(np.abs(((az[rest][:, None] - az[rest][None, chosen]) + 180.0) % 360.0 - 180.0), axis=1)
        chosen.append(int(np.argmax(gap)))
    return [int(rest[k]) for k in chosen], test


def camera_split(directions: np.ndarray, up: np.ndarray, train_views: int, gap_deg: float = 15.0) -> tuple[list[int], list[int]]:
    """:func:`ring_split`, or :func:`arc_split` where every camera lies within ``gap_deg`` of the
    training band's elevation (one ring).

    >>> a = np.arange(8) * np.pi / 4
    >>> camera_split(np.stack([np.cos(a), np.sin(a), 0 * a], 1), np.array([0, 0, 1.0]), 3)[1]
    [3, 4, 5]
    """
    train, test = ring_split(directions, up, train_views, gap_deg=gap_deg)
    return (train, test) if test else arc_split(directions, up, train_views)
