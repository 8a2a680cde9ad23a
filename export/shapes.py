"""New shapes with named parts: a lidded pot (body, lid, handle) for several materials at once.

Each part is one or more closed smooth surfaces known in closed form (a superellipsoid of
revolution, ellipsoids, a torus), tessellated deterministically, with the exact normals of the
surface (the gradient of its implicit function), wound outward. ``damcap shape pot OUT.obj``
writes it as an OBJ with one ``g``/``usemtl`` group per part and its material library
(``OUT.mtl``), so that ``damcap export`` and ``damcap view`` give part k the k-th .dam.
The parts overlap where they meet (the handle enters the body, the lid sits in its top), as
separately modelled parts do; every part is watertight on its own.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from damcap.common.errors import DamcapError
from damcap.common.mesh import Mesh, signed_volume

POT_PARTS = ("body", "lid", "handle")
"""the pot's parts, in the order of its OBJ material groups (part k takes the k-th model)"""

#: each part's diffuse colour in the material library (it only tells the parts apart in other tools)
POT_MTL_KD = {"body": (0.6, 0.12, 0.1), "lid": (0.6, 0.6, 0.62), "handle": (0.8, 0.6, 0.2)}


def superellipsoid_of_revolution(a: float, b: float, exponent: float, rings: int, segments: int,
                                 centre: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Mesh:
    """The closed surface ``(hypot(x, z) / a)^e + (|y| / b)^e = 1`` about the y axis, with exact normals.

    ``exponent`` 2 is an ellipsoid (a sphere when ``a == b``); larger values flatten top and bottom.
    The profile is sampled at polar angles ``theta = pi * i / rings`` (``r = a sin(theta)^(2/e)``,
    ``y = -b cos(theta)^(2/e)``, signed), one vertex at each pole.

    Args:
        a: radius in the xz plane, scene units (> 0).
        b: half height along y, scene units (> 0).
        exponent: e >= 2.
        rings: profile intervals from pole to pole (>= 2).
        segments: intervals around the axis (>= 3).
        centre: (3,) where the surface's centre lies, scene units.

    Returns:
        float64 vertices (``2 + (rings - 1) * segments``), int64 triangles wound outward
        (``2 * segments * (rings - 1)``), float64 unit normals along the implicit function's gradient.

    >>> m = superellipsoid_of_revolution(1.0, 1.0, 2.0, 8, 12)
    >>> bool(np.allclose(np.linalg.norm(m.vertices, axis=1), 1) and np.allclose(m.vertex_normals, m.vertices))
    True
    """
    if not (a > 0 and b > 0 and exponent >= 2 and rings >= 2 and segments >= 3):
        raise ValueError(f"need a, b > 0, exponent >= 2, rings >= 2, segments >= 3; got {a}, {b}, {exponent}, {rings}, {segments}")
    theta = np.pi * np.arange(1, rings) / rings
    s, c = np.sin(theta), np.cos(theta)
    p = 2.0 / exponent
    r = a * s ** p
    y = -b * np.sign(c) * np.abs(c) ** p
    # gradient of F = (r / a)^e + (|y| / b)^e in the meridian plane (the positive factor e dropped)
    g_r = r ** (exponent - 1) / a ** exponent
    g_y = np.sign(y) * np.abs(y) ** (exponent - 1) / b ** exponent
    ring_v, ring_n = _revolved(r, y, g_r, g_y, segments)
    v = np.concatenate([[[0.0, -b, 0.0]], ring_v, [[0.0, b, 0.0]]]) + np.asarray(centre, np.float64)
    n = np.concatenate([[[0.0, -1.0, 0.0]], ring_n, [[0.0, 1.0, 0.0]]])
    return Mesh(v, _outward(v, _revolution_triangles(rings - 1, segments)), n)


def _revolved(r: np.ndarray, y: np.ndarray, n_r: np.ndarray, n_y: np.ndarray, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Profile points (r, y) and meridian normals (n_r, n_y), (P,) each, turned about y:
    ((P * segments, 3) positions, (P * segments, 3) unit normals), ring by ring."""
    phi = 2 * np.pi * np.arange(segments) / segments
    cp, sp = np.cos(phi)[None], np.sin(phi)[None]
    v = np.stack([r[:, None] * cp, np.broadcast_to(y[:, None], (len(y), segments)), r[:, None] * sp], -1).reshape(-1, 3)
    n = np.stack([n_r[:, None] * cp, np.broadcast_to(n_y[:, None], (len(y), segments)), n_r[:, None] * sp], -1).reshape(-1, 3)
    return v, n / np.linalg.norm(n, axis=1, keepdims=True)


def _revolution_triangles(ring_count: int, segments: int) -> np.ndarray:
    """Triangles of a pole (vertex 0), ``ring_count`` rings of ``segments`` vertices, a pole (last vertex)."""
    j = np.arange(segments)
    nxt = (j + 1) % segments
    top = 1 + ring_count * segments
    tris = [np.stack([np.zeros(segments, np.int64), 1 + nxt, 1 + j], 1)]
    for i in range(ring_count - 1):
        a, b = 1 + i * segments, 1 + (i + 1) * segments
        tris += [np.stack([a + j, a + nxt, b + j], 1), np.stack([b + j, a + nxt, b + nxt], 1)]
    last = 1 + (ring_count - 1) * segments
    tris.append(np.stack([np.full(segments, top), last + j, last + nxt], 1))
    return np.concatenate(tris).astype(np.int64)


def _outward(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``triangles`` wound so that the closed surface they bound has positive signed volume."""
    return triangles if signed_volume(vertices, triangles) > 0 else triangles[:, ::-1].copy()


def torus_z(major: float, minor: float, radial: int, tubular: int, centre: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Mesh:
    """A torus about the z axis (standing in the xy plane), with exact normals.

    Its vertices satisfy ``(hypot(x - cx, y - cy) - major)^2 + (z - cz)^2 = minor^2``.

    Args:
        major: distance from the centre to the tube's centre line, scene units.
        minor: tube radius, scene units (0 < minor < major).
        radial: intervals around the z axis (>= 3).
        tubular: intervals around the tube (>= 3).
        centre: (3,) scene units.

    Returns:
        ``radial * tubular`` float64 vertices, ``2 * radial * tubular`` int64 triangles wound
        outward, float64 unit normals pointing away from the tube's centre line.
    """
    if not (0 < minor < major and radial >= 3 and tubular >= 3):
        raise ValueError(f"need 0 < minor < major and >= 3 intervals; got {major}, {minor}, {radial}, {tubular}")
    u = 2 * np.pi * np.arange(radial) / radial
    w = 2 * np.pi * np.arange(tubular) / tubular
    cu, su = np.cos(u)[:, None], np.sin(u)[:, None]
    cw, sw = np.cos(w)[None], np.sin(w)[None]
    n = np.stack([cw * cu, cw * su, np.broadcast_to(sw, (radial, tubular))], -1).reshape(-1, 3)
    line = np.stack([major * cu, major * su, np.zeros_like(cu)], -1)
    v = (line + minor * n.reshape(radial, tubular, 3)).reshape(-1, 3) + np.asarray(centre, np.float64)
    i, j = np.meshgrid(np.arange(radial), np.arange(tubular), indexing="ij")
    a, b = i * tubular + j, ((i + 1) % radial) * tubular + j
    c, d = i * tubular + (j + 1) % tubular, ((i + 1) % radial) * tubular + (j + 1) % tubular
    t = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]).astype(np.int64)
    return Mesh(v, _outward(v, t), n)


def join_parts(parts: list[list[Mesh]]) -> Mesh:
    """One mesh of several parts, each a list of closed surfaces: vertices and triangles
    concatenated, ``triangle_groups`` the part's index, sorted by part."""
    vs, ts, ns, gs, offset = [], [], [], [], 0
    for k, surfaces in enumerate(parts):
        for m in surfaces:
            vs.append(m.vertices)
            ns.append(m.vertex_normals)
            ts.append(m.triangles + offset)
            gs.append(np.full(len(m.triangles), k, np.int32))
            offset += len(m.vertices)
    return Mesh(np.concatenate(vs), np.concatenate(ts), np.concatenate(ns), np.concatenate(gs))


def pot_mesh(segments: int = 128, rings: int = 48) -> tuple[Mesh, tuple[str, ...]]:
    """A lidded pot about the y axis: the body (a superellipsoid of revolution, 0.75 wide and 1.1
    tall), the lid (a flat ellipsoid seated in the body's top, with a round knob) and a handle (a
    torus standing in the xy plane, half inside the body), in scene units, centred near the origin.

    Args:
        segments: intervals around the y axis of the body and the lid (the handle takes 3/4, the knob 1/4).
        rings: pole-to-pole intervals of the body (the lid takes half, the knob a third; the
            handle's tube ``rings // 2``).

    Returns:
        (the mesh: float64 vertices and exact unit normals, int64 triangles wound outward,
        int32 ``triangle_groups`` indexing :data:`POT_PARTS`; the part names).
    """
    if segments < 12 or rings < 6:
        raise ValueError(f"a pot needs segments >= 12 and rings >= 6, got {segments}, {rings}")
    body = superellipsoid_of_revolution(0.75, 0.55, 2.6, rings, segments)
    lid = superellipsoid_of_revolution(0.52, 0.2, 2.0, rings // 2, segments, centre=(0.0, 0.45, 0.0))
    knob = superellipsoid_of_revolution(0.12, 0.12, 2.0, rings // 3, segments // 4, centre=(0.0, 0.73, 0.0))
    handle = torus_z(0.32, 0.07, 3 * segments // 4, rings // 2, centre=(0.72, 0.05, 0.0))
    return join_parts([[body], [lid, knob], [handle]]), POT_PARTS


def obj_text(mesh: Mesh, names: tuple[str, ...], material_library: str) -> str:
    """An OBJ file's text: positions and normals (``v``, ``vn``, 6 decimals), then per part a
    ``g NAME`` / ``usemtl NAME`` group of its faces (``f a//a b//b c//c``), parts in order.

    Args:
        mesh: vertices, unit ``vertex_normals`` and ``triangle_groups`` indexing ``names``.
        names: part names (letters, digits, ``_`` and ``-``).
        material_library: the ``mtllib`` file name (beside the OBJ).
    """
    if mesh.vertex_normals is None or mesh.triangle_groups is None:
        raise ValueError("obj_text needs vertex normals and triangle groups")
    bad = [n for n in names if not re.fullmatch(r"[A-Za-z0-9_-]+", n)]
    if bad:
        raise ValueError(f"part names must be letters, digits, '_' or '-': {bad}")
    lines = ["# damcap shape: one group per part; give damcap export / view one .dam per part, in this order: " + " ".join(names),
             f"mtllib {material_library}"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices]
    lines += [f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertex_normals]
    for k, name in enumerate(names):
        lines += [f"g {name}", f"usemtl {name}"]
        lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in mesh.triangles[mesh.triangle_groups == k] + 1]
    return "\n".join(lines) + "\n"


def mtl_text(names: tuple[str, ...], kd: dict[str, tuple[float, float, float]]) -> str:
    """The material library's text: one ``newmtl`` per part, in part order (the order
    :func:`damcap.common.mesh.load_mesh` numbers the parts by)."""
    lines = ["# damcap shape: each part's appearance is the .dam given for it; Kd only tells the parts apart"]
    for n in names:
        r, g, b = kd.get(n, (0.5, 0.5, 0.5))
        lines += [f"newmtl {n}", f"Kd {r:.3f} {g:.3f} {b:.3f}"]
    return "\n".join(lines) + "\n"


def write_parted_obj(mesh: Mesh, names: tuple[str, ...], path: str | os.PathLike, kd: dict | None = None) -> tuple[Path, Path]:
    """Write ``mesh`` as ``path`` (an OBJ, one group per part) and its material library beside
    it (same name, ``.mtl``), each atomically. Returns (OBJ path, MTL path)."""
    from damcap.common.atomic import write_text_atomic

    path = Path(path)
    if path.suffix.lower() != ".obj":
        raise DamcapError(f"{path}: a shape with parts is written as .obj (its parts are OBJ material groups)")
    mtl = path.with_suffix(".mtl")
    write_text_atomic(mtl, mtl_text(names, kd or {}))
    write_text_atomic(path, obj_text(mesh, names, mtl.name))
    return path, mtl


def obj_part_names(path: str | os.PathLike) -> list[str] | None:
    """The names of an OBJ's parts as :func:`damcap.common.mesh.load_mesh` numbers them: the
    materials its faces use (``usemtl``), in its material library's order; None when the file
    is not an OBJ, names no material library or the library cannot be read."""
    path = Path(path)
    if path.suffix.lower() != ".obj":
        return None
    used, libs = set(), []
    try:
        with open(path, encoding="utf-8", errors="replace") as fp:
            for line in fp:
                if line.startswith("usemtl"):
                    used.add(line[6:].strip())
                elif line.startswith("mtllib"):
                    libs.append(line[6:].strip())
        order = []
        for lib in libs:
            with open(path.parent / lib, encoding="utf-8", errors="replace") as fp:
                order += [ln[6:].strip() for ln in fp if ln.startswith("newmtl")]
    except OSError:
        return None
    names = [n for n in order if n in used]
    return names if names and len(names) == len(used) else None
