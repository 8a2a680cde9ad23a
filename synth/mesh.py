"""Triangle meshes for the synthetic data set: reading, normalising, smooth normals, material regions.

Everything here is pure numpy except :func:`read_mesh` (the one file reader). A mesh is split into
material regions by smooth random 3D fields (sums of random plane waves): each face takes the
material whose field is largest at its centroid, so the regions are blobs with curved, natural
boundaries rather than a single cut (Maximov et al. 2019, Sec. 4: "three materials ... in a
complex spatial arrangement").
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damcap.common.errors import DamcapError

#: mesh file types :func:`read_mesh` understands
MESH_SUFFIXES = (".obj", ".ply")


@dataclass(frozen=True)
class TriangleMesh:
    """An indexed triangle mesh."""

    positions: np.ndarray
    """(V, 3) float64 vertex positions, object or world space (scene units)"""
    faces: np.ndarray
    """(F, 3) int64 vertex indices, counter-clockwise seen from outside where known"""

    def __post_init__(self) -> None:
        if self.positions.ndim != 2 or self.positions.shape[1] != 3:
            raise ValueError(f"positions must be (V, 3), got {self.positions.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"faces must be (F, 3), got {self.faces.shape}")


# --------------------------------------------------------------------------------------------
# Reading (the I/O edge)
# --------------------------------------------------------------------------------------------


def read_mesh(path: str | os.PathLike) -> TriangleMesh:
    """Read a triangle mesh from an OBJ or PLY file (positions and faces only).

    OBJ: ``v`` and ``f`` lines (``f a/b/c`` forms and negative indices allowed; polygons are
    fan-triangulated). PLY: ASCII or binary, a ``vertex`` element with ``x y z`` and a ``face``
    element (lists, fan-triangulated) and/or a ``tristrips`` element (strips split at -1).
    Normals and texture coordinates in the file are ignored (smooth normals are recomputed).

    Raises:
        DamcapError: missing file, unknown suffix, unparsable content, or no triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise DamcapError(f"{path}: mesh file not found; give an .obj or .ply file or 'sphere'")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise DamcapError(f"{path}: unknown mesh type {path.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}")
    try:
        mesh = _read_obj(path) if suffix == ".obj" else _read_ply(path)
    except (ValueError, IndexError, UnicodeDecodeError) as e:
        raise DamcapError(f"{path}: cannot parse the mesh ({e})") from None
    if len(mesh.faces) == 0:
        raise DamcapError(f"{path}: the mesh has no triangles")
    if mesh.faces.min() < 0 or mesh.faces.max() >= len(mesh.positions):
        raise DamcapError(f"{path}: face indices out of range (0..{len(mesh.positions) - 1})")
    if not np.all(np.isfinite(mesh.positions)):
        raise DamcapError(f"{path}: vertex positions contain NaN or inf")
    return mesh


def _fan(polygons: list[list[int]]) -> np.ndarray:
    tris = [(p[0], p[k], p[k + 1]) for p in polygons for k in range(1, len(p) - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def _read_obj(path: Path) -> TriangleMesh:
    verts: list[list[float]] = []
    polys: list[list[int]] = []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                idx = []
                for tok in line.split()[1:]:
                    k = int(tok.split("/")[0])
                    idx.append(k - 1 if k > 0 else len(verts) + k)
                polys.append(idx)
    return TriangleMesh(np.asarray(verts, dtype=np.float64).reshape(-1, 3), _fan(polys))


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _strips_to_triangles(strip: np.ndarray) -> np.ndarray:
    """Triangles of triangle strips separated by -1, alternating winding, degenerates dropped."""
    tris = []
    for s in np.split(strip, np.nonzero(strip < 0)[0]):
        s = s[s >= 0]
        for k in range(len(s) - 2):
            a, b, c = (s[k], s[k + 1], s[k + 2]) if k % 2 == 0 else (s[k + 1], s[k], s[k + 2])
            if a != b and b != c and a != c:
                tris.append((a, b, c))
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def _read_ply(path: Path) -> TriangleMesh:
    raw = path.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError("not a PLY file (no 'ply' magic or 'end_header')")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    body_start = end + len(b"end_header")
    body_start += 2 if raw[body_start:body_start + 2] == b"\r\n" else 1
    fmt = "ascii"
    elements: list[tuple[str, int, list[tuple[str, str, str | None]]]] = []  # name, count, [(name, type, list count type)]
    for line in header:
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property" and elements:
            if tok[1] == "list":
                elements[-1][2].append((tok[4], _PLY_TYPES[tok[3]], _PLY_TYPES[tok[2]]))
            else:
                elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]], None))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"unknown PLY format {fmt!r}")
    endian = ">" if fmt == "binary_big_endian" else "<"
    positions = None
    triangles: list[np.ndarray] = []
    if fmt == "ascii":
        tokens = raw[body_start:].split()
        pos = 0
        for name, count, props in elements:
            if all(p[2] is None for p in props):
                n = count * len(props)
                table = np.asarray(tokens[pos:pos + n], dtype=np.float64).reshape(count, len(props))
                pos += n
                if name == "vertex":
                    names = [p[0] for p in props]
                    positions = table[:, [names.index(c) for c in "xyz"]]
                continue
            rows = []
            for _ in range(count):
                row = []
                for _pname, _t, ltype in props:
                    if ltype is None:
                        row.append(int(float(tokens[pos])))
                        pos += 1
                    else:
                        k = int(tokens[pos])
                        row.append([int(t) for t in tokens[pos + 1:pos + 1 + k]])
                        pos += 1 + k
                rows.append(row)
            triangles.extend(_ply_list_triangles(name, props, rows))
    else:
        pos = body_start
        for name, count, props in elements:
            if all(p[2] is None for p in props):
                dt = np.dtype([(p[0], endian + p[1]) for p in props])
                table = np.frombuffer(raw, dtype=dt, count=count, offset=pos)
                pos += dt.itemsize * count
                if name == "vertex":
                    positions = np.stack([table[c].astype(np.float64) for c in "xyz"], axis=-1)
                continue
            if len(props) == 1 and count > 0:  # one list per row: the common case, vectorised when regular
                ltype, vtype = np.dtype(endian + props[0][2]), np.dtype(endian + props[0][1])
                first = int(np.frombuffer(raw, ltype, 1, pos)[0])
                dt = np.dtype([("n", ltype), ("v", vtype, (first,))])
                if pos + dt.itemsize * count <= len(raw):
                    table = np.frombuffer(raw, dt, count, pos)
                    if np.all(table["n"] == first):
                        pos += dt.itemsize * count
                        rows = [[row] for row in table["v"].astype(np.int64)]
                        triangles.extend(_ply_list_triangles(name, props, rows))
                        continue
            rows = []
            for _ in range(count):
                row = []
                for _pname, t, ltype in props:
                    if ltype is None:
                        row.append(int(np.frombuffer(raw, endian + t, 1, pos)[0]))
                        pos += np.dtype(t).itemsize
                    else:
                        k = int(np.frombuffer(raw, endian + ltype, 1, pos)[0])
                        pos += np.dtype(ltype).itemsize
                        row.append(np.frombuffer(raw, endian + t, k, pos).astype(np.int64))
                        pos += np.dtype(t).itemsize * k
                rows.append(row)
            triangles.extend(_ply_list_triangles(name, props, rows))
    if positions is None:
        raise ValueError("no 'vertex' element with x, y, z")
    faces = np.concatenate(triangles) if triangles else np.zeros((0, 3), np.int64)
    return TriangleMesh(np.ascontiguousarray(positions, dtype=np.float64), faces.astype(np.int64))


def _ply_list_triangles(name: str, props: list, rows: list) -> list[np.ndarray]:
    lists = [i for i, p in enumerate(props) if p[2] is not None and re.fullmatch(r"vertex_ind(ex|ices)", p[0])]
    if not lists:
        return []
    k = lists[0]
    if name == "tristrips":
        return [_strips_to_triangles(np.asarray(r[k], dtype=np.int64)) for r in rows]
    if name == "face":
        return [_fan([list(np.asarray(r[k]).tolist()) for r in rows])]
    return []


# --------------------------------------------------------------------------------------------
# Pure mesh operations
# --------------------------------------------------------------------------------------------


def face_normals_area(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unnormalised face normals (cross products): length = 2 x face area.

    Args:
        positions: (V, 3).
        faces: (F, 3).

    Returns:
        (F, 3) float64.
    """
    p = positions[faces]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def clean_mesh(mesh: TriangleMesh, eps: float = 1e-20) -> TriangleMesh:
    """Drop degenerate faces (repeated indices or area^2 <= eps) and unreferenced vertices."""
    f = mesh.faces
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    ok &= (face_normals_area(mesh.positions, f) ** 2).sum(-1) > eps
    f = f[ok]
    used, inverse = np.unique(f.ravel(), return_inverse=True)
    return TriangleMesh(mesh.positions[used].copy(), inverse.reshape(-1, 3).astype(np.int64))


def signed_volume(mesh: TriangleMesh) -> float:
    """Signed volume enclosed by the mesh (positive when faces wind counter-clockwise outside).

    >>> round(signed_volume(icosphere(3)), 2)  # inscribed in the unit sphere: a bit under 4/3 pi
    4.15
    """
    p = mesh.positions[mesh.faces]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


def normalise_to_unit_sphere(mesh: TriangleMesh) -> TriangleMesh:
    """Clean the mesh, centre its bounding box at the origin, scale it into the unit sphere, and
    wind its faces outward (positive signed volume).

    Returns:
        a new mesh whose farthest vertex lies at distance 1 from the origin.
    """
    m = clean_mesh(mesh)
    if len(m.faces) == 0:
        raise DamcapError("the mesh has no non-degenerate triangles")
    centre = 0.5 * (m.positions.min(0) + m.positions.max(0))
    p = m.positions - centre
    p /= np.linalg.norm(p, axis=-1).max()
    faces = m.faces
    out = TriangleMesh(p, faces)
    if signed_volume(out) < 0:
        out = TriangleMesh(p, faces[:, ::-1].copy())
    return out


def vertex_normals(mesh: TriangleMesh, eps: float = 1e-20) -> np.ndarray:
    """Smooth vertex normals: area-weighted sums of the adjacent faces' normals, normalised.

    Args:
        mesh: the mesh.
        eps: squared length below which a vertex normal is replaced by +z (isolated vertex).

    Returns:
        (V, 3) float64 unit normals, on the side the faces wind counter-clockwise.
    """
    fn = face_normals_area(mesh.positions, mesh.faces)
    n = np.zeros_like(mesh.positions)
    for k in range(3):
        np.add.at(n, mesh.faces[:, k], fn)
    sq = (n**2).sum(-1, keepdims=True)
    return np.where(sq > eps, n / np.sqrt(np.maximum(sq, eps)), np.array([0.0, 0.0, 1.0]))


def icosphere(subdivisions: int) -> TriangleMesh:
    """Unit sphere: an icosahedron subdivided ``subdivisions`` times (20 * 4^s faces), outward.

    >>> icosphere(2).faces.shape
    (320, 3)
    """
    t = (1 + 5**0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6),
         (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10),
         (8, 6, 7), (9, 8, 1)]
    pos = np.asarray(v, dtype=np.float64)
    pos /= np.linalg.norm(pos, axis=-1, keepdims=True)
    faces = np.asarray(f, dtype=np.int64)
    for _ in range(subdivisions):
        edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        key = np.sort(edges, axis=1)
        uniq, inv = np.unique(key, axis=0, return_inverse=True)
        mid = pos[uniq[:, 0]] + pos[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=-1, keepdims=True)
        m = len(pos) + inv.reshape(3, -1)  # midpoints of edges (0,1), (1,2), (2,0) per face
        pos = np.concatenate([pos, mid])
        a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
        faces = np.concatenate([np.stack([a, m[0], m[2]], 1), np.stack([m[0], b, m[1]], 1),
                                np.stack([m[2], m[1], c], 1), np.stack([m[0], m[1], m[2]], 1)])
    return TriangleMesh(pos, faces)


# --------------------------------------------------------------------------------------------
# Material regions
# --------------------------------------------------------------------------------------------


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


def material_labels(mesh: TriangleMesh, n_materials: int, seed: int, min_fraction: float = 0.2,
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
        return np.zeros(len(mesh.faces), np.int64)
    centroid = mesh.positions[mesh.faces].mean(1)
    area = 0.5 * np.linalg.norm(face_normals_area(mesh.positions, mesh.faces), axis=-1)
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


def submesh(mesh: TriangleMesh, normals: np.ndarray, face_mask: np.ndarray) -> tuple[TriangleMesh, np.ndarray]:
    """The faces selected by ``face_mask`` as their own mesh, with the same vertex normals
    (so shading is continuous across material boundaries).

    Args:
        mesh: the whole mesh.
        normals: (V, 3) its vertex normals.
        face_mask: (F,) bool.

    Returns:
        the sub-mesh (only the vertices it uses) and its (V', 3) vertex normals.
    """
    f = mesh.faces[face_mask]
    used, inverse = np.unique(f.ravel(), return_inverse=True)
    return TriangleMesh(mesh.positions[used], inverse.reshape(-1, 3).astype(np.int64)), normals[used]
