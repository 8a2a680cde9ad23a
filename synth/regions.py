"""Material regions of a synthetic object: smooth noise fields, per-face labels, sub-meshes.

A mesh is split into material regions by smooth random 3D fields (sums of random plane waves):
each face takes the material whose field is largest at its centroid, so the regions are blobs
with curved, natural boundaries rather than a single cut (Maximov et al. 2019, Sec. 4: "three
materials ... in a complex spatial arrangement"). Pure numpy; the mesh type, reader and
normals are :mod:`damcap.common.mesh`'s.
"""

from __future__ import annotations

import numpy as np

from damcap.common.mesh import Mesh, face_normals_area

#: how synth computes smooth vertex normals (:func:`~damcap.common.mesh.vertex_normals_area_weighted`):
#: a vertex whose summed area normal has squared length <= 1e-20 gets +z
SYNTH_NORMAL_EPS = 1e-20
SYNTH_ISOLATED_NORMAL = (0.0, 0.0, 1.0)


def smooth_noise_fields(points: np.ndarray, n_fields: int, seed: int, waves: int = 6,
                        frequency_range: tuple[float, float] = (0.35, 0.9)) -> np.ndarray:
    """Smooth random scalar fields in 3D: each a sum of ``waves`` random plane waves.

    Args:
        points: (P, 3) positions inside the unit sphere.
        n_fields: number of independent fields.
        seed: random seed (same seed, same fields).
        waves: plane waves per field.
        frequency_range: wave frequencies, cycles per scene unit (the object spans 2 units).

    Returns:
        (P, n_fields) float64, values roughly in [-2, 2].
    """
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(n_fields, waves, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    freq = rng.uniform(*frequency_range, size=(n_fields, waves, 1))
    phase = rng.uniform(0, 2 * np.pi, size=(n_fields, waves))
    amp = rng.uniform(0.5, 1.0, size=(n_fields, waves)) / np.sqrt(waves / 2)
    arg = 2 * np.pi * np.einsum("pc,fwc->pfw", points, dirs * freq) + phase
    return (amp * np.sin(arg)).sum(-1)


def material_labels(mesh: Mesh, n_materials: int, seed: int, min_fraction: float = 0.2,
                    iterations: int = 200) -> np.ndarray:
    """Material index per face from smooth noise regions, balanced so every material covers
    at least ``min_fraction`` of the surface area where that is reachable.

    Args:
        mesh: the (normalised) mesh.
        n_materials: number of materials (1 gives all zeros).
        seed: random seed of the noise fields.
        min_fraction: least area fraction per material aimed at (<= 1 / n_materials).
        iterations: bias-balancing steps.

    Returns:
        (F,) int64 labels in [0, n_materials).
    """
    if n_materials == 1:
        return np.zeros(len(mesh.triangles), np.int64)
    centroid = mesh.vertices[mesh.triangles].mean(1)
    area = 0.5 * np.linalg.norm(face_normals_area(mesh.vertices, mesh.triangles), axis=-1)
    area = area / area.sum()
    fields = smooth_noise_fields(centroid, n_materials, seed)
    bias = np.zeros(n_materials)
    target = min(min_fraction, 1.0 / n_materials)
    labels = np.argmax(fields, -1)
    for _ in range(iterations):
        labels = np.argmax(fields + bias, -1)
        frac = np.bincount(labels, weights=area, minlength=n_materials)
        if frac.min() >= target:
            break
        bias += 0.05 * (1.0 / n_materials - frac)
    return labels.astype(np.int64)


def submesh(mesh: Mesh, normals: np.ndarray, face_mask: np.ndarray) -> tuple[Mesh, np.ndarray]:
    """The faces selected by ``face_mask`` as their own mesh, with the same vertex normals
    (so shading is continuous across material boundaries).

    Args:
        mesh: the whole mesh.
        normals: (V, 3) its vertex normals.
        face_mask: (F,) bool.

    Returns:
        the sub-mesh (only the vertices it uses) and its (V', 3) vertex normals.
    """
    f = mesh.triangles[face_mask]
    used, inverse = np.unique(f.ravel(), return_inverse=True)
    return Mesh(mesh.vertices[used], inverse.reshape(-1, 3).astype(np.int64)), normals[used]
