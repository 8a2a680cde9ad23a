"""A predictor's own frame: the world turned so that the input's dominant light comes from +y.

Under one distant light a DAM is dark on one side of a great circle of normals (the terminator,
N.L = 0) and lit on the other. A predictor that works in world coordinates has to write that
circle, wherever the light is, into the DAM's first layer from what it sees; trained on scenes
lit from every direction it learns a blur instead (``docs/learning-to-learn.md``, v8's picture).
In a frame where the light always comes from the same direction, the terminator is always the
same circle, and the mean DAM and its corrections can hold it sharp.

The frame is found in closed form from the predictor's input images: the least-squares fit of
the (log-compressed) brightness of the covered pixels by ``c + b . N`` (the first-order spherical
harmonic of the light, whose vector part points at the brightest directions of the environment:
for one distant light over normals spread around it, exactly at the light), then the smallest
rotation taking b to +y (the world's up, so a light from above leaves the world as it was).
Rotating the whole world is an exact change of coordinates (object, cameras and lights turn
together), so nothing is lost: the predictor reads the rotated normals and view directions,
predicts a DAM in its frame, and :func:`.dam.rotated_world_weights` turns that DAM back.

Pure: tensors in, tensors out.
"""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np
import torch

from damcap.common.cameras import rotation_between

Frame = Literal["world", "light"]
"""'world': the predictor reads and writes world coordinates (v1-v8); 'light': its own frame (v10)"""
FRAMES: tuple[str, ...] = get_args(Frame)

#: a brightness gradient |b| below this (log1p units per unit of N) has no direction: the frame is the world
MIN_GRADIENT = 1e-4


def brightness_gradient(images: torch.Tensor, view_mask: torch.Tensor | None = None) -> torch.Tensor:
    """Least-squares b of ``brightness ~ c + b . N`` over every covered pixel of each set of views.

    Args:
        images: (B, V, 9, S, S) predictor images (:func:`.model.predictor_image`: RGB as
            log1p(radiance / scale), normal_world, view_dir_world; 0 off the object).
        view_mask: (B, V) bool, the views present (default all).

    Returns:
        (B, 3) b, in brightness units per unit of N (0 where a set has fewer than 4 covered pixels).
    """
    b, v = images.shape[:2]
    x = images.float()
    n = x[:, :, 3:6].permute(0, 1, 3, 4, 2).reshape(b, -1, 3)
    y = x[:, :, 0:3].mean(2).reshape(b, -1)
    covered = n.norm(dim=-1) > 0.5
    if view_mask is not None:
        covered = covered & view_mask[:, :, None].expand(b, v, images.shape[-1] * images.shape[-2]).reshape(b, -1)
    w = covered.to(x.dtype)
    a = torch.cat([torch.ones_like(n[..., :1]), n], -1)  # (B, M, 4)
    normal = torch.einsum("bm,bmi,bmj->bij", w, a, a)
    rhs = torch.einsum("bm,bmi,bm->bi", w, a, y)
    enough = w.sum(1) >= 4
    normal = torch.where(enough[:, None, None], normal, torch.eye(4, dtype=x.dtype, device=x.device).expand(b, 4, 4))
    ridge = 1e-6 * normal.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-12)  # normals all alike: still solvable
    coef = torch.linalg.solve(normal + ridge[:, None, None] * torch.eye(4, dtype=x.dtype, device=x.device), rhs[..., None])[..., 0]
    return torch.where(enough[:, None], coef[:, 1:], torch.zeros_like(coef[:, 1:]))


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


def light_up_world(images: torch.Tensor, view_mask: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 3) the light frame's +y in world coordinates: where each set's dominant light comes
    from, as the frame sees it (the unit brightness gradient; 0 where it has no direction)."""
    b = brightness_gradient(images, view_mask)
    length = b.norm(dim=-1, keepdim=True)
    return torch.where(length < MIN_GRADIENT, torch.zeros_like(b), b / length.clamp_min(1e-30))


def light_frame(images: torch.Tensor, view_mask: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 3, 3) R taking world vectors into each set's light frame (its brightness gradient to +y)."""
    return rotation_to_up(brightness_gradient(images, view_mask))
