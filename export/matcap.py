"""A DAM as a matcap: the material on a sphere seen from one chosen view (``export --format matcap``).

A matcap (material capture) is the image of a sphere under orthographic projection: pixel (x, y)
of the unit disk shows the surface whose camera-space normal is (x, y, sqrt(1 - x^2 - y^2)), all
seen from the same direction. Any DCC tool or web page shades a mesh with it by looking the
colour up from the camera-space normal. A DAM is a function of (view, normal), so its matcap is
exact for that one view (the camera's direction), which :func:`matcap_camera` puts where the
export's orbit starts; from other views it is the approximation every matcap makes.
"""

from __future__ import annotations

import numpy as np
import torch

from damcap.appearance.dam import DeepAppearanceMap


def matcap_normals(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera-space normals of a matcap (OpenGL camera axes: x right, y up, +z toward the viewer).

    Args:
        size: side of the square image, pixels.

    Returns:
        normal_cam (size, size, 3) float64, unit inside the disk, 0 outside; inside (size, size)
        bool: the pixel centre lies in the disk.

    >>> n, inside = matcap_normals(2)
    >>> bool(inside.all()), np.round(n[0, 1], 3).tolist()  # top-right pixel centre (0.5, 0.5)
    (True, [0.5, 0.5, 0.707])
    """
    c = (np.arange(size) + 0.5) / size * 2 - 1
    x, y = np.meshgrid(c, -c)
    r2 = x * x + y * y
    inside = r2 < 1
    z = np.sqrt(np.clip(1 - r2, 0, None))
    n = np.stack([x, y, z], -1) * inside[..., None]
    return n, inside


def matcap_normals_world(size: int, world_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The world normals a matcap shows: (M, 3) float32, one per pixel inside the disk, and the
    (size, size) bool disk (:func:`matcap_normals` turned by the camera's rotation).

    >>> n, inside = matcap_normals_world(2, np.eye(4))
    >>> n.shape, bool(inside.all())
    ((4, 3), True)
    """
    n_cam, inside = matcap_normals(size)
    return (n_cam[inside] @ np.asarray(world_from_cam, np.float64)[:3, :3].T).astype(np.float32), inside


def render_matcap(model: DeepAppearanceMap, size: int, world_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The DAM's matcap seen by a camera (its rotation alone matters: the projection is orthographic).

    Args:
        model: the DAM (world-space view and normal in, linear radiance out).
        size: side of the image, pixels.
        world_from_cam: (4, 4) camera-to-world, OpenGL axes.

    Returns:
        radiance_lin (size, size, 3) float32 (0 outside the disk) and coverage (size, size)
        float32 (1 inside, 0 outside).
    """
    n_world, inside = matcap_normals_world(size, world_from_cam)
    view = np.asarray(world_from_cam, np.float64)[:3, 2].astype(np.float32)
    v_world = np.broadcast_to(view, n_world.shape).copy()  # every pixel looks back along the camera's +z
    out = np.zeros((size, size, 3), np.float32)
    with torch.no_grad():
        out[inside] = model(torch.from_numpy(v_world), torch.from_numpy(n_world)).numpy()
    return out, inside.astype(np.float32)
