"""A predictor's orientation: the world turned so that the input's dominant light comes from +y.

Under one distant light a DAM is dark on one side of a great circle of normals (the terminator,
N.L = 0) and lit on the other. A predictor that works in the world orientation has to write that
circle, wherever the light is, into the DAM's first layer from what it sees; trained on scenes
lit from every direction it learns a blur instead (``bench/hyper_ood.md``, v10's section: v8's picture).
In an orientation where the light always comes from the same direction, the terminator is always
the same circle, and the mean DAM and its corrections can hold it sharp.

The light orientation is found from the predictor's input images by :func:`terminator_fit`: a
least-absolute-deviations fit of the covered pixels' radiance by ``c + max(0, b . N)``, a
Lambertian surface's clamped cosine, which puts b across the shadow's edge whatever part of the
object the views saw. (The least-squares fit of the log-compressed brightness by ``c + b . N``,
:func:`brightness_gradient`, the first-order spherical harmonic of the light, points at one
distant light only for normals spread evenly around it; v10 was trained with it and predicts
better with the terminator fit: bench/hyper_ood.md, *The terminator fit*.) Under an
environment b points at its brightest directions. Then the smallest rotation takes b to +y (the
world's up, so a light from above leaves the world as it was).
Rotating the whole world is an exact change of coordinates (object, cameras and lights turn
together), so nothing is lost: the predictor reads the rotated normals and view directions,
predicts a DAM in its light orientation, and :func:`.dam.rotated_world_weights` turns that DAM back.

Pure: tensors in, tensors out.
"""

from __future__ import annotations

import math
from typing import Literal, get_args

import numpy as np
import torch

from damcap.common.cameras import rotation_between

Orientation = Literal["world", "light"]
"""'world': the predictor reads and writes world coordinates (v1-v8); 'light': the world turned so
that its input's dominant light comes from +y (v10)"""
ORIENTATIONS: tuple[str, ...] = get_args(Orientation)

#: a fitted |b| below this (:func:`terminator_fit`'s, radiance-scale units per unit of N) has no direction: the light orientation is the world's
MIN_GRADIENT = 1e-4
#: Gauss-Newton iterations of :func:`terminator_fit`
TERMINATOR_ITERATIONS = 10


def covered_brightness(images: torch.Tensor, view_mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every pixel of each set of views as (normal, brightness, weight), the brightness being the
    mean of the log-compressed RGB.

    Args:
        images: (B, V, 9, S, S) predictor images (:func:`.model.predictor_image`: RGB as
            log1p(radiance / scale), normal_world, view_dir_world; 0 off the object).
        view_mask: (B, V) bool, the views present (default all).

    Returns:
        normals (B, M, 3), brightness (B, M) and weights (B, M): 1 on covered pixels of present
        views, else 0 (M = V S S), float32. A single set (B = 1) keeps its covered pixels alone
        (M = their count; the fits' sums are the same, and cheaper).
    """
    b, v = images.shape[:2]
    x = images.float()
    n = x[:, :, 3:6].permute(0, 1, 3, 4, 2).reshape(b, -1, 3)
    y = x[:, :, 0:3].mean(2).reshape(b, -1)
    covered = n.norm(dim=-1) > 0.5
    if view_mask is not None:
        covered = covered & view_mask[:, :, None].expand(b, v, images.shape[-1] * images.shape[-2]).reshape(b, -1)
    if b == 1:
        n, y, covered = n[:, covered[0]], y[:, covered[0]], covered[:, covered[0]]
    return n, y, covered.to(x.dtype)


def _weighted_solve(a: torch.Tensor, y: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """(B, K) least squares of y ~ a theta with weights w: (B, M, K), (B, M), (B, M); a tiny
    ridge keeps it solvable when the columns are alike or empty."""
    aw = a * w[..., None]
    normal = aw.transpose(1, 2) @ a
    rhs = (aw.transpose(1, 2) @ y[..., None])[..., 0]
    eye = torch.eye(a.shape[-1], dtype=a.dtype, device=a.device)
    ridge = 1e-6 * normal.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-12)
    return torch.linalg.solve(normal + ridge[:, None, None] * eye, rhs[..., None])[..., 0]


def brightness_gradient(images: torch.Tensor, view_mask: torch.Tensor | None = None, linear: bool = False) -> torch.Tensor:
    """Least-squares b of ``brightness ~ c + b . N`` over every covered pixel of each set of views
    (:func:`covered_brightness`): the first-order spherical harmonic of the light (v10 was
    trained with its direction as the light orientation's +y).

    Args:
        images: (B, V, 9, S, S) predictor images.
        view_mask: (B, V) bool, the views present (default all).
        linear: fit radiance / scale (expm1 of the images' RGB) instead of the log-compressed
            brightness.

    Returns:
        (B, 3) b, in brightness (or radiance-scale) units per unit of N (0 where a set has fewer
        than 4 covered pixels).
    """
    n, y, w = covered_brightness(images, view_mask)
    return _gradient(n, torch.expm1(y) if linear else y, w)


def _gradient(n: torch.Tensor, y: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """(B, 3) b of the least-squares ``y ~ c + b . n`` (0 with fewer than 4 pixels of weight)."""
    coef = _weighted_solve(torch.cat([torch.ones_like(n[..., :1]), n], -1), y, w)
    return torch.where((w.sum(1) >= 4)[:, None], coef[:, 1:], torch.zeros_like(coef[:, 1:]))


def terminator_fit(images: torch.Tensor, view_mask: torch.Tensor | None = None,
                   iterations: int = TERMINATOR_ITERATIONS, floor: float = 1e-3) -> torch.Tensor:
    """b of ``radiance ~ c + max(0, b . N)`` over every covered pixel of each set of views (the
    mean of RGB, linear, in units of the capture's radiance scale), by least absolute
    deviations: where the light's shadow edge (the terminator b . N = 0) lies.

    The linear fit (:func:`brightness_gradient`) points at one distant light only when the
    normals are spread evenly around it; the views of a capture see part of the object, and its
    direction is then pulled toward the normals they saw (5-17 deg on the issue-28 captures).
    This fit models a Lambertian surface's clamped cosine itself, so which normals were seen
    does not bias it, and absolute deviations let a highlight's pixels count as outliers.
    Gauss-Newton on the reweighted L1 (weights 1 / max(|residual|, ``floor``)), from c = the
    least radiance and b = twice the linear fit's gradient of the linear radiance (exact for
    normals spread evenly over the sphere: the linear fit of max(0, k N . L) is k L / 2).

    Args:
        images: (B, V, 9, S, S) predictor images; view_mask: (B, V) bool, the views present.
        iterations: Gauss-Newton iterations.
        floor: the reweighting's floor, in units of the radiance scale.

    Returns:
        (B, 3) b, in units of the radiance scale per unit of N; the start where the fit is not
        finite, and 0 where a set has fewer than 4 covered pixels.
    """
    n, y, w = covered_brightness(images, view_mask)
    y = torch.expm1(y)  # radiance / scale: a Lambertian surface's is exactly c + max(0, b . N)
    start = 2 * _gradient(n, y, w)  # brightness_gradient(images, view_mask, linear=True), doubled
    if y.shape[1] == 0:  # a single set with nothing covered
        return start
    c = torch.where(w > 0, y, torch.full_like(y, math.inf)).amin(1)
    c = torch.where(torch.isfinite(c), c, torch.zeros_like(c))
    b = start
    for _ in range(iterations):
        z = torch.einsum("bmi,bi->bm", n, b)
        resid = y - c[:, None] - z.clamp_min(0)
        jac = torch.cat([torch.ones_like(z)[..., None], (z > 0).to(n.dtype)[..., None] * n], -1)  # d(c + relu(b . N)) / d(c, b)
        step = _weighted_solve(jac, resid, w / resid.abs().clamp_min(floor))
        c, b = c + step[:, 0], b + step[:, 1:]
    ok = torch.isfinite(b).all(-1, keepdim=True)
    return torch.where(ok, b, start)


def rotation_to_up(direction: torch.Tensor) -> torch.Tensor:
    """The smallest rotation taking each direction to +y (:func:`damcap.common.cameras.rotation_between`).

    Args:
        direction: (B, 3), any length; shorter than :data:`MIN_GRADIENT` gives the identity.

    Returns:
        (B, 3, 3) rotations R with R d/|d| = +y, on ``direction``'s device.

    >>> r = rotation_to_up(torch.tensor([[1.0, 0, 0]]))
    >>> torch.allclose(r[0] @ torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0]))
    True
    """
    up = np.array([0.0, 1.0, 0.0])
    d = direction.detach().double().cpu().numpy()
    rot = np.stack([rotation_between(x, up) if np.linalg.norm(x) >= MIN_GRADIENT else np.eye(3) for x in d]).reshape(-1, 3, 3)
    return torch.from_numpy(rot).to(device=direction.device, dtype=torch.promote_types(direction.dtype, torch.float32))


def rotate_images(images: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """Predictor images with their normals and view directions turned by R (RGB unchanged).

    Args:
        images: (B, V, 9, S, S).
        rotation: (B, 3, 3).

    Returns:
        (B, V, 9, S, S), a new tensor.
    """
    rot = rotation.to(images.dtype)
    normal = torch.einsum("bij,bvjhw->bvihw", rot, images[:, :, 3:6])
    view = torch.einsum("bij,bvjhw->bvihw", rot, images[:, :, 6:9])
    return torch.cat([images[:, :, 0:3], normal, view], 2)


def unit_direction(b: torch.Tensor) -> torch.Tensor:
    """(B, 3) b / |b| of fitted (B, 3) b, 0 where |b| is below :data:`MIN_GRADIENT` (no direction:
    :func:`rotation_to_up` keeps the world's orientation there)."""
    length = b.norm(dim=-1, keepdim=True)
    return torch.where(length < MIN_GRADIENT, torch.zeros_like(b), b / length.clamp_min(1e-30))


def light_up_world(images: torch.Tensor, view_mask: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 3) the light orientation's +y in world coordinates: where each set's dominant light
    comes from, as the predictor sees it (the unit :func:`terminator_fit`; 0 where it has no direction)."""
    return unit_direction(terminator_fit(images, view_mask))


def light_rotation(images: torch.Tensor, view_mask: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 3, 3) R taking world vectors into each set's light orientation (its :func:`terminator_fit`'s b to +y)."""
    return rotation_to_up(terminator_fit(images, view_mask))
