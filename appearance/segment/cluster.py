"""The initial clustering: chromaticity k-means of each surface point's darkest observation, with the
illumination's tint modelled as a polynomial of the normal; the paper's RGB + normal features."""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree


from damcap.appearance.views import ViewData
from damcap.appearance.pixels import FOREGROUND_COVERAGE
from damcap.appearance.segment.options import BRIGHT_FRACTION, SegmentOptions


def kmeans_features(radiance_lin: np.ndarray, normal_world: np.ndarray, radiance_scale: float, eps: float = 1e-6) -> np.ndarray:
    """Per-pixel features for k-means: RGB and normal, both groups scaled to the same spread.

    RGB is divided by the radiance scale and compressed with x / (1 + x) (HDR highlights would
    otherwise dominate); then each group (3 RGB, 3 normal components) is centred and divided by
    its own root-mean-square spread, so colour and orientation weigh equally in the distance.

    Args:
        radiance_lin: (P, 3) linear radiance.
        normal_world: (P, 3) unit normals.
        radiance_scale: > 0.
        eps: floor of a group's spread (a constant colour stays constant).

    Returns:
        (P, 6) float32.
    """
    rgb = radiance_lin / radiance_scale
    rgb = rgb / (1 + rgb)

    def standardise(x: np.ndarray) -> np.ndarray:
        x = x - x.mean(0)
        return x / max(float(np.sqrt((x * x).sum(1).mean())), eps)

    return np.concatenate([standardise(rgb), standardise(normal_world)], axis=1).astype(np.float32)


def chromaticity_features(radiance_lin: np.ndarray, radiance_scale: float, dark_fraction: float = BRIGHT_FRACTION, eps: float = 1e-8) -> tuple[np.ndarray, np.ndarray]:
    """Shading-invariant colour features for initialising the joint segmentation.

    Chromaticity rgb / (r + g + b) does not change with the amount of light a pixel receives,
    so clusters follow materials rather than lit and unlit sides.

    Args:
        radiance_lin: (P, 3) linear radiance.
        radiance_scale: > 0 (the capture's 95th percentile).
        dark_fraction: pixels darker than this fraction of the scale carry no usable colour.
        eps: floor of the denominator.

    Returns:
        features: (P, 3) float32 chromaticities; bright: (P,) bool, the pixels with usable colour.
    """
    total = radiance_lin.sum(1, keepdims=True)
    chroma = radiance_lin / np.maximum(total, eps)
    return chroma.astype(np.float32), lit_mask(radiance_lin, radiance_scale, dark_fraction)


def lit_mask(radiance_lin: np.ndarray, radiance_scale: float, fraction: float) -> np.ndarray:
    """(P,) bool: pixels whose mean radiance over the channels exceeds ``fraction`` of the scale.

    Args:
        radiance_lin: (P, 3) linear radiance.
        radiance_scale: > 0 (the capture's 95th percentile).
        fraction: of the scale.
    """
    return radiance_lin.sum(1) > 3 * fraction * radiance_scale


def darkest_observation(position_world: np.ndarray, normal_world: np.ndarray, frame_index: np.ndarray, brightness: np.ndarray,
                        radius_world: float, min_cos: float = 0.9) -> np.ndarray:
    """For every pixel, the least bright observation of the same surface point in any frame.

    Two pixels of different frames observe the same surface point when their world positions lie
    within ``radius_world`` of each other and their normals agree (cosine above ``min_cos``; a
    thin part's far side does not count). Each frame contributes its nearest pixel; the pixel
    itself is always a candidate.

    Args:
        position_world: (P, 3) world positions of the pixels of all frames.
        normal_world: (P, 3) their unit normals.
        frame_index: (P,) int, the frame each pixel belongs to.
        brightness: (P,) e.g. r + g + b of the linear radiance.
        radius_world: world units, about half the pixel footprint (see :func:`pixel_spacing`).
        min_cos: normals' agreement.

    Returns:
        (P,) int64 index of the darkest observation of each pixel's surface point.
    """
    pos = np.asarray(position_world, np.float64)
    nrm = np.asarray(normal_world, np.float64)
    best = np.arange(len(pos))
    best_b = np.asarray(brightness, np.float64).copy()
    for f in np.unique(frame_index):
        idx_f = np.flatnonzero(frame_index == f)
        dist, j = cKDTree(pos[idx_f]).query(pos, k=1, distance_upper_bound=radius_world)
        found = np.isfinite(dist)
        cand = idx_f[j[found]]
        rows = np.flatnonzero(found)
        same = (nrm[cand] * nrm[rows]).sum(1) > min_cos
        rows, cand = rows[same], cand[same]
        darker = brightness[cand] < best_b[rows]
        best[rows[darker]] = cand[darker]
        best_b[rows[darker]] = brightness[cand[darker]]
    return best.astype(np.int64)


def pixel_spacing(position_world: list[np.ndarray]) -> float:
    """World distance between neighbouring pixels: median over frames of the median distance
    from a pixel to its nearest neighbour in the same frame.

    Args:
        position_world: per frame, (P_f, 3) the foreground pixels' world positions.
    """
    meds = [float(np.median(cKDTree(p).query(p, k=2)[0][:, 1])) for p in position_world if len(p) > 1]
    return float(np.median(meds)) if meds else 0.0


def kmeans(features: np.ndarray, k: int, seed: int, iterations: int = 50, restarts: int = 4) -> np.ndarray:
    """Lloyd's k-means with k-means++ seeding; the best of ``restarts`` runs.

    Args:
        features: (P, D) float32.
        k: clusters.
        seed: random seed.

    Returns:
        (P,) int64 labels in [0, k).
    """
    x = torch.from_numpy(np.ascontiguousarray(features)).float()
    gen = torch.Generator().manual_seed(seed)
    best, best_cost = None, math.inf
    sub = x[torch.randperm(x.shape[0], generator=gen)[:20000]]
    for _ in range(restarts):
        centres = sub[torch.randint(0, sub.shape[0], (1,), generator=gen)]
        for _ in range(1, k):  # k-means++
            d2 = torch.cdist(sub, centres).min(1).values ** 2
            centres = torch.cat([centres, sub[torch.multinomial(d2 + 1e-12, 1, generator=gen)]])
        for _ in range(iterations):
            lab = torch.cdist(sub, centres).argmin(1)
            new = torch.stack([sub[lab == j].mean(0) if (lab == j).any() else centres[j] for j in range(k)])
            if torch.allclose(new, centres):
                break
            centres = new
        cost = float((torch.cdist(sub, centres).min(1).values ** 2).sum())
        if cost < best_cost:
            best, best_cost = centres, cost
    labels = torch.cat([torch.cdist(x[s:s + 65536], best).argmin(1) for s in range(0, x.shape[0], 65536)])
    return labels.numpy().astype(np.int64)


def normal_polynomial(normal_world: np.ndarray, degree: int) -> np.ndarray:
    """Polynomial basis of a unit normal without the constant term (the real spherical harmonics'
    shapes: degree 1 adds x, y, z; degree 2 adds xy, xz, yz, x^2 - y^2, 3z^2 - 1).

    Args:
        normal_world: (P, 3) unit normals.
        degree: 0, 1 or 2.

    Returns:
        (P, D) float64, D = 0, 3 or 8.

    >>> normal_polynomial(np.array([[0.0, 0.0, 1.0]]), 2).tolist()
    [[0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 2.0]]
    """
    n = np.asarray(normal_world, dtype=np.float64)
    if degree == 0:
        return np.zeros((len(n), 0))
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    cols = [x, y, z]
    if degree >= 2:
        cols += [x * y, x * z, y * z, x * x - y * y, 3 * z * z - 1]
    return np.stack(cols, axis=1)


def illumination_aware_kmeans(chroma: np.ndarray, normal_world: np.ndarray, k: int, seed: int, degree: int = 2,
                              iterations: int = 30, ridge: float = 1e-2, eps: float = 1e-6, fit: np.ndarray | None = None) -> np.ndarray:
    """Cluster colours into materials while a smooth illumination colour varies with the normal.

    Model: ``log chroma_i = a_{label_i} + B(n_i) theta + s_i``: a log-chromaticity per material
    ``a``, an illumination tint that is a polynomial ``B`` of the world normal shared by all
    materials (the diffuse irradiance of a distant environment is smooth in the normal), and a
    per-pixel grey level ``s`` (removed by centring over the channels). Alternates labels (nearest
    ``a``), the materials' ``a`` (means) and ``theta`` (ridge least squares), starting from plain
    k-means on the log chromaticity. Degree 0 is that k-means alone.

    Args:
        chroma: (P, 3) chromaticities (see :func:`chromaticity_features`) of lit pixels.
        normal_world: (P, 3) their unit normals.
        k: clusters.
        seed: k-means seed.
        degree: polynomial degree, 0..2.
        iterations: alternation rounds at most (stops when the labels settle).
        ridge: ridge on theta, relative to the number of pixels.
        eps: floor of a chromaticity before the log.
        fit: (P,) bool, the pixels the clusters and the tint are fitted to (default: all). The
            others (e.g. too dim to shape the clusters) are only assigned: nearest material
            after removing the fitted tint.

    Returns:
        (P,) int64 labels in [0, k).
    """
    f_all = np.log(np.maximum(np.asarray(chroma, dtype=np.float64), eps))
    f_all -= f_all.mean(axis=1, keepdims=True)
    fit = np.ones(len(f_all), bool) if fit is None else np.asarray(fit, bool)
    f = f_all[fit]
    labels = kmeans(f.astype(np.float32), k, seed)
    basis_all = normal_polynomial(normal_world, degree)
    basis_mean = basis_all[fit].mean(axis=0) if fit.any() else np.zeros(basis_all.shape[1])
    basis = basis_all[fit] - basis_mean
    theta = np.zeros((basis.shape[1], 3))
    if basis.shape[1] == 0:
        return _assign_rest(labels, fit, f_all, _cluster_means(f, labels, k))
    normal_eq = basis.T @ basis + ridge * len(basis) * np.eye(basis.shape[1])
    tint = np.zeros_like(f)
    for _ in range(iterations):
        untinted = f - tint
        centres = np.stack([untinted[labels == j].mean(0) if (labels == j).any() else np.zeros(3) for j in range(k)])
        theta = np.linalg.solve(normal_eq, basis.T @ (f - centres[labels]))
        tint = basis @ theta
        d2 = (((f - tint)[:, None, :] - centres[None]) ** 2).sum(-1)
        new = d2.argmin(1)
        if np.array_equal(new, labels):
            break
        labels = new
    return _assign_rest(labels, fit, f_all - (basis_all - basis_mean) @ theta, centres)


def _cluster_means(features: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """(k, D) mean feature per label; an empty cluster's centre is infinitely far."""
    return np.stack([features[labels == j].mean(0) if (labels == j).any() else np.full(features.shape[1], np.inf) for j in range(k)])


def _assign_rest(fit_labels: np.ndarray, fit: np.ndarray, features: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(P,) labels: ``fit_labels`` on the fitted pixels, the nearest centre elsewhere."""
    labels = np.empty(len(fit), np.int64)
    labels[fit] = fit_labels
    rest = ~fit
    if rest.any():
        labels[rest] = (((features[rest][:, None, :] - centres[None]) ** 2).sum(-1)).argmin(1)
    return labels


def initial_labels(views: list[ViewData], radiance_scale: float, opts: SegmentOptions) -> list[np.ndarray]:
    """The clustering the joint training starts from: one material label per foreground pixel.

    k-means on the chromaticity of the bright pixels (of each pixel's own colour or of its
    surface point's darkest observation, ``opts.init_colour``), with the illumination's tint
    modelled as a polynomial of the normal (``opts.illumination_degree``); pixels between
    ``opts.colour_floor`` and the bright level are assigned to the nearest cluster.

    Args:
        views: training views.
        radiance_scale: the capture's radiance scale (:func:`.fit.radiance_scale_of`).
        opts: materials, seed, init_colour, colour_floor, illumination_degree.

    Returns:
        per view, (P_f,) int64 labels of its foreground pixels (row-major order) in [0, n);
        -1 where a pixel is too dark to show its colour.
    """
    opts.validate()
    n = opts.materials
    fgs = [v.data.coverage > FOREGROUND_COVERAGE for v in views]
    rad = np.concatenate([v.data.radiance_lin[fg] for v, fg in zip(views, fgs)])
    nrm = np.concatenate([v.data.normal_world[fg] for v, fg in zip(views, fgs)])
    chroma, bright = chromaticity_features(rad, radiance_scale)
    usable = np.flatnonzero(lit_mask(rad, radiance_scale, opts.colour_floor))  # includes the bright pixels
    if opts.init_colour == "darkest-view" and len(usable):
        fg_pos = [v.data.position_world[fg] for v, fg in zip(views, fgs)]
        frame = np.concatenate([np.full(len(p), i) for i, p in enumerate(fg_pos)])
        darkest = darkest_observation(np.concatenate(fg_pos)[usable], nrm[usable], frame[usable], rad[usable].sum(1),
                                      0.5 * pixel_spacing(fg_pos))
        chroma = chroma.copy()
        chroma[usable] = chroma[usable][darkest]
    labels = np.full(len(chroma), -1, np.int64)
    fit = bright[usable]  # the clusters are fitted to the bright pixels; dim ones are only assigned
    if fit.sum() < n:  # nothing lit enough to tell colours apart
        labels[:] = np.arange(len(chroma)) % n
    elif opts.illumination_degree == 0:
        fit_labels = kmeans(chroma[usable][fit], n, opts.seed)
        labels[usable] = _assign_rest(fit_labels, fit, chroma[usable], _cluster_means(chroma[usable][fit], fit_labels, n))
    else:
        labels[usable] = illumination_aware_kmeans(chroma[usable], nrm[usable], n, opts.seed, opts.illumination_degree, fit=fit)
    return np.split(labels, np.cumsum([int(fg.sum()) for fg in fgs])[:-1])
