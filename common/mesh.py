"""Triangle meshes: the one mesh type every stage uses, reading, normals, volume, clean-up, normalisation.

Everything here is pure numpy except the two file readers:

* :func:`read_mesh`: positions and faces exactly as the file writes them (float64, the file's
  vertex order, no welding), for synth, which must render the very triangles of the corpus.
  OBJ and PLY are parsed here (Open3D's reader splits vertices at texture seams, reorders
  some OBJ files, rounds OBJ positions to float32 and reads no PLY ``tristrips``); other formats
  (OFF, glTF/GLB) go through Open3D.
* :func:`load_mesh`: Open3D's reader plus repairs (welding, degenerate and duplicate triangles,
  normals from the file, OBJ material groups), float32, for reconstruct and export.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damcap.common.errors import DamcapError
from damcap.common.native_stderr import native_stderr_caught

#: mesh file types :func:`read_mesh` understands (STL is left out: a triangle soup, no shared vertices)
MESH_SUFFIXES = (".obj", ".ply", ".off", ".glb", ".gltf")


@dataclass
class Mesh:
    """A triangle mesh as plain arrays.

    The dtypes are the producer's: :func:`load_mesh` and the shapes of reconstruct/export give
    float32 vertices and int32 triangles; :func:`read_mesh` and synth keep float64 / int64.
    """

    vertices: np.ndarray
    """(V, 3) float32 or float64 positions, object or world space (scene units)"""
    triangles: np.ndarray
    """(T, 3) int32 or int64 vertex indices, counter-clockwise seen from outside where known"""
    vertex_normals: np.ndarray | None = None
    """(V, 3) unit normals (area-weighted where computed), or None when not (yet) known"""
    triangle_groups: np.ndarray | None = None
    """(T,) int32 part index per triangle (OBJ material groups: the k-th material used, in the
    material library's order, is part k; 0 when none), or None"""

    def __post_init__(self) -> None:
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"vertices must be (V, 3), got {self.vertices.shape}")
        if self.triangles.ndim != 2 or self.triangles.shape[1] != 3:
            raise ValueError(f"triangles must be (T, 3), got {self.triangles.shape}")


# --------------------------------------------------------------------------------------------
# Reading (the I/O edge)
# --------------------------------------------------------------------------------------------


def read_mesh(path: str | os.PathLike) -> Mesh:
    """Read a triangle mesh's positions and faces exactly as the file has them.

    OBJ: ``v`` and ``f`` lines (``f a/b/c`` forms and negative indices allowed; polygons are
    fan-triangulated). PLY: ASCII or binary, a ``vertex`` element with ``x y z`` and a ``face``
    element (lists, fan-triangulated) and/or a ``tristrips`` element (strips split at -1).
    OFF, glTF and GLB: Open3D's reader (vertices as Open3D gives them). Normals and texture
    coordinates in the file are ignored (smooth normals are recomputed).

    Returns:
        a mesh with float64 vertices, int64 triangles and no normals or groups.

    Raises:
        DamcapError: missing file, unknown suffix, unparsable content, or no triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise DamcapError(f"{path}: mesh file not found")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise DamcapError(f"{path}: unknown mesh type {path.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}")
    try:
        if suffix == ".obj":
            positions, faces = _read_obj(path)
        elif suffix == ".ply":
            positions, faces = _read_ply(path)
        else:
            positions, faces = _read_open3d(path)
    except (ValueError, IndexError, UnicodeDecodeError) as e:
        raise DamcapError(f"{path}: cannot parse the mesh ({e})") from None
    if len(faces) == 0:
        raise DamcapError(f"{path}: the mesh has no triangles")
    if faces.min() < 0 or faces.max() >= len(positions):
        raise DamcapError(f"{path}: face indices out of range (0..{len(positions) - 1})")
    if not np.all(np.isfinite(positions)):
        raise DamcapError(f"{path}: vertex positions contain NaN or inf")
    return Mesh(positions, faces)


def _read_open3d(path: Path) -> tuple[np.ndarray, np.ndarray]:
    m = _open3d_read(path)
    return np.asarray(m.vertices, np.float64).reshape(-1, 3).copy(), np.asarray(m.triangles, np.int64).reshape(-1, 3).copy()


def _open3d_read(path: Path):
    """Open3D's mesh reader, its own stderr lines (RPly's) caught: a reader error refuses the file.

    Raises:
        DamcapError: the reader reported an error (damaged or truncated file), quoting it.
    """
    import open3d as o3d

    with native_stderr_caught() as printed:
        mesh = o3d.io.read_triangle_mesh(str(path))
    errors = [ln for ln in printed if "error" in ln.lower()]
    if errors:
        raise DamcapError(f"{path}: cannot read the mesh, the file is damaged or truncated ({errors[0][:200]})")
    return mesh


def _fan(polygons: list[list[int]]) -> np.ndarray:
    tris = [(p[0], p[k], p[k + 1]) for p in polygons for k in range(1, len(p) - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
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
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), _fan(polys)


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


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
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
    return np.ascontiguousarray(positions, dtype=np.float64), faces.astype(np.int64)


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


def load_mesh(path: str | os.PathLike) -> Mesh:
    """Read an OBJ/PLY/OFF/GLB mesh with Open3D; repair what can be repaired.

    Degenerate and duplicate triangles and unreferenced vertices are removed; vertex normals are
    (re)computed when missing or non-finite.

    Returns:
        a mesh with float32 vertices and normals, int32 triangles and int32 groups.

    Raises:
        DamcapError: missing file, unreadable file, or no triangles left.
    """
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise DamcapError(f"{path}: mesh file not found")
    mesh = _open3d_read(path)
    if len(mesh.triangles) == 0:
        raise DamcapError(f"{path}: no triangles could be read (empty mesh or unsupported format; use OBJ or PLY)")
    groups = np.asarray(mesh.triangle_material_ids, np.int32) if mesh.has_triangle_material_ids() else None
    if groups is not None and len(groups) == len(mesh.triangles):
        # Open3D numbers an OBJ's materials from 1 (0 is its default material): part k is the
        # k-th material used, in the material library's order
        groups = np.unique(groups, return_inverse=True)[1].astype(np.int32).reshape(-1)
        # Open3D's clean-up below reorders triangles; carry groups through as a triangle attribute
        mesh.triangle_material_ids = o3d.utility.IntVector(groups.tolist())
    mesh.remove_duplicated_vertices()
    mesh.remove_degenerate_triangles()
    mesh.remove_duplicated_triangles()
    mesh.remove_unreferenced_vertices()
    tris = np.asarray(mesh.triangles, np.int32)
    verts = np.asarray(mesh.vertices, np.float64)
    if len(tris) == 0:
        raise DamcapError(f"{path}: every triangle is degenerate; nothing to render")
    if not np.isfinite(verts).all():
        raise DamcapError(f"{path}: vertex positions contain NaN or inf")
    area = np.linalg.norm(face_normals_area(verts, tris), axis=1)
    if area.max() <= 0:
        raise DamcapError(f"{path}: all triangles have zero area")
    normals = np.asarray(mesh.vertex_normals, np.float64) if mesh.has_vertex_normals() else np.zeros((0, 3))
    if normals.shape != verts.shape or not np.isfinite(normals).all() or (np.linalg.norm(normals, axis=1) < 1e-6).any():
        normals = vertex_normals_area_weighted(verts, tris)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    g = np.asarray(mesh.triangle_material_ids, np.int32) if mesh.has_triangle_material_ids() else np.zeros(len(tris), np.int32)
    if len(g) != len(tris):
        g = np.zeros(len(tris), np.int32)
    return Mesh(verts.astype(np.float32), tris, normals.astype(np.float32), g)


FILE_VERTEX_TOL = 1e-5
"""a loaded vertex is a file vertex when they lie within this fraction of the mesh's extent"""


def file_vertex_order(path: str | os.PathLike, loaded_vertices: np.ndarray) -> tuple[np.ndarray, int]:
    """Where each vertex :func:`load_mesh` returned sits in the file: per-vertex data written in the
    file's vertex order (``damcap export --labels``) is read through this. Open3D's OBJ reader
    splits and reorders vertices, and :func:`load_mesh`'s clean-up merges and drops some; positions
    identify them, within :data:`FILE_VERTEX_TOL` of the mesh's extent (the first file vertex wins
    where several coincide).

    Args:
        path: the mesh file.
        loaded_vertices: (V, 3) the vertices :func:`load_mesh` returned for it.

    Returns:
        (V,) int64 file vertex index per loaded vertex, and the file's vertex count.

    Raises:
        DamcapError: a loaded vertex matches no file vertex.
    """
    from scipy.spatial import cKDTree

    file_v = np.asarray(read_mesh(path).vertices, np.float64)
    loaded = np.asarray(loaded_vertices, np.float64)
    # the two readers parse the same text into floats that may differ in the last bits (measured:
    # 1.2e-7 on a unit torus) and in the sign of zero: match within a tolerance, not bit for bit
    extent = float(np.ptp(file_v, axis=0).max()) if len(file_v) else 0.0
    tol = FILE_VERTEX_TOL * max(extent, 1e-30)
    near = cKDTree(file_v).query_ball_point(loaded, tol) if len(file_v) else [[] for _ in loaded]
    order = np.array([min(c) if c else -1 for c in near], np.int64)
    if (order < 0).any():
        raise DamcapError(f"{path}: {int((order < 0).sum())} of the loaded mesh's vertices match no vertex of the file; "
                          "per-vertex data in the file's order cannot be placed on it")
    return order, len(file_v)


# --------------------------------------------------------------------------------------------
# Pure mesh operations
# --------------------------------------------------------------------------------------------


def midpoint_subdivision(triangles: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """The topology of one midpoint subdivision: each triangle cut into four at its edges' midpoints.

    Args:
        triangles: (T, 3) vertex indices.
        n_vertices: vertices before; the midpoints are numbered after them, one per edge.

    Returns:
        (E, 2) int64 the edges' end vertices (midpoint k, vertex ``n_vertices + k``, lies between
        them), and (T, 4, 3) int64 each triangle's children: its three corners' (same winding)
        and the middle one.

    >>> edges, children = midpoint_subdivision(np.array([[0, 1, 2]]), 3)
    >>> edges.tolist(), children.tolist()  # midpoints 3, 4, 5 of edges 01, 02, 12
    ([[0, 1], [0, 2], [1, 2]], [[[0, 3, 4], [3, 1, 5], [4, 5, 2], [3, 5, 4]]])
    """
    t = np.asarray(triangles, np.int64)
    keys = np.sort(np.stack([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]], 1).reshape(-1, 2), axis=1)
    edges, index = np.unique(keys, axis=0, return_inverse=True)
    mid = n_vertices + index.reshape(-1, 3)  # (T, 3): the midpoints of edges 01, 12, 20
    a, b, c = t[:, 0], t[:, 1], t[:, 2]
    ab, bc, ca = mid[:, 0], mid[:, 1], mid[:, 2]
    children = np.stack([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)], 1)
    return edges, children


def face_normals_area(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unnormalised face normals (cross products): length = 2 x face area.

    Args:
        vertices: (V, 3).
        triangles: (T, 3).

    Returns:
        (T, 3), the vertices' dtype.

    >>> face_normals_area(np.array([[0., 0, 0], [2, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]])).tolist()
    [[0.0, 0.0, 2.0]]
    """
    return np.cross(vertices[triangles[:, 1]] - vertices[triangles[:, 0]], vertices[triangles[:, 2]] - vertices[triangles[:, 0]])


def vertex_normals_area_weighted(vertices: np.ndarray, triangles: np.ndarray, eps: float = 0.0,
                                 isolated_normal: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(V, 3) float64 unit vertex normals: the sum of adjacent face normals weighted by face area.

    Scale-free by default: the sum has units of area (square scene units, as small as 1e-24 for
    a mesh of size 1e-11), so it is divided by its own length without an absolute floor.

    Args:
        vertices: (V, 3) float32 or float64.
        triangles: (T, 3) counter-clockwise (outward) vertex indices.
        eps: squared length of the sum at or below which a vertex counts as isolated (0: only a
            vertex without area, unreferenced or on degenerate triangles only). synth uses 1e-20.
        isolated_normal: the normal an isolated vertex gets (synth: +z; default: the zero vector).

    Returns:
        (V, 3) float64, on the side the triangles wind counter-clockwise.
    """
    v = vertices.astype(np.float64)
    fn = face_normals_area(v, triangles)
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, triangles[:, k], fn)
    sq = (n * n).sum(-1, keepdims=True)
    ok = sq > eps
    return np.where(ok, n / np.sqrt(np.where(ok, sq, 1.0)), np.asarray(isolated_normal, np.float64))


def signed_volume(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """Signed volume enclosed by a closed mesh (positive when faces wind counter-clockwise
    seen from outside), by the divergence theorem: sum over faces of v0 . (v1 x v2) / 6.

    Args:
        vertices: (V, 3).
        triangles: (T, 3).

    Returns:
        cubic scene units, float64.

    >>> signed_volume(np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]), np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
    0.16666666666666666
    """
    v = vertices.astype(np.float64)
    return float(np.einsum("ij,ij->i", v[triangles[:, 0]], np.cross(v[triangles[:, 1]], v[triangles[:, 2]])).sum() / 6)


def clean_mesh(mesh: Mesh, eps: float = 1e-20) -> Mesh:
    """Drop degenerate triangles (repeated indices or squared doubled area <= ``eps``) and then
    unreferenced vertices; normals and groups follow their vertices and triangles.

    Args:
        mesh: any mesh (not changed).
        eps: squared length of the cross product (4 area^2, scene units^4) at or below which a
            triangle is degenerate.

    Returns:
        a new mesh, vertices in their old order, dtypes kept.
    """
    f = mesh.triangles
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    ok &= (face_normals_area(mesh.vertices, f) ** 2).sum(-1) > eps
    used, inverse = np.unique(f[ok].ravel(), return_inverse=True)
    return Mesh(mesh.vertices[used].copy(), inverse.reshape(-1, 3).astype(f.dtype),
                None if mesh.vertex_normals is None else mesh.vertex_normals[used],
                None if mesh.triangle_groups is None else mesh.triangle_groups[ok])


def unit_sphere_transform(vertices: np.ndarray, eps: float = 1e-12) -> tuple[np.ndarray, float]:
    """What :func:`normalise_to_unit_sphere` applies: ``(v - centre) / radius``, the centre of the
    bounding box and the distance of the farthest vertex from it (at least ``eps``).

    >>> c, r = unit_sphere_transform(np.array([[0.0, 0, 0], [2, 0, 0], [0, 4, 0]]))
    >>> c.tolist(), round(r, 6)
    ([1.0, 2.0, 0.0], 2.236068)
    """
    v = np.asarray(vertices)
    centre = (v.min(0) + v.max(0)) / 2
    return centre, max(float(np.linalg.norm(v - centre, axis=1).max()), eps)


def normalise_to_unit_sphere(mesh: Mesh, clean: bool = False, fix_winding: bool = False, eps: float = 1e-12) -> Mesh:
    """Centre the mesh's bounding box at the origin and scale it so its farthest vertex lies at
    distance 1.

    Args:
        mesh: the mesh (not changed).
        clean: first drop degenerate triangles and unreferenced vertices (:func:`clean_mesh`);
            synth does, export does not (it keeps the file's vertices for per-vertex labels).
        fix_winding: wind the triangles outward (positive :func:`signed_volume`), negating the
            normals when it flips them; synth does, export does not (its ray caster turns
            normals toward the camera anyway).
        eps: least radius divided by (scene units), against a mesh shrunk to a point.

    Returns:
        a new mesh, vertices in the input's dtype; normals and groups carried along.

    Raises:
        DamcapError: ``clean`` left no triangle.
    """
    m = clean_mesh(mesh) if clean else mesh
    if len(m.triangles) == 0:
        raise DamcapError("the mesh has no non-degenerate triangles")
    v = m.vertices
    centre, radius = unit_sphere_transform(v, eps)
    p = ((v - centre) / radius).astype(v.dtype)
    out = Mesh(p, m.triangles, m.vertex_normals, m.triangle_groups)
    if fix_winding and signed_volume(p, m.triangles) < 0:
        out = Mesh(p, m.triangles[:, ::-1].copy(), None if m.vertex_normals is None else -m.vertex_normals, m.triangle_groups)
    return out


def bounding_sphere(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (of the bounding box) and radius (farthest vertex) of a vertex set.

    Args:
        vertices: (V, 3).

    Returns:
        centre: (3,); radius: scene units.
    """
    v = np.asarray(vertices, dtype=np.float64)
    centre = (v.min(0) + v.max(0)) / 2
    return centre, float(np.linalg.norm(v - centre, axis=1).max())


def to_open3d(mesh: Mesh):
    """The mesh as an ``open3d.geometry.TriangleMesh`` (float64 vertices, triangles only: no
    normals or groups, so a file written from it holds what the shape's arrays hold)."""
    import open3d as o3d

    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices, np.float64)),
                                     o3d.utility.Vector3iVector(np.asarray(mesh.triangles, np.int32)))
