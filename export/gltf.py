"""A DAM baked onto a mesh for one view, as binary glTF 2.0 (``export --format glb``).

A DAM is not a PBR material: its radiance depends on the view, which glTF's materials cannot
express. What travels faithfully is the radiance for one chosen view, baked per vertex
(``COLOR_0``, linear) on an unlit material (``KHR_materials_unlit``), with that view stored as
the file's camera: from it, any glTF viewer shows what damcap renders, up to the interpolation of
colours across triangles (a denser mesh brings it closer); from other views it is the radiance
the chosen view saw.

Layout: one node per part (one DAM each), under a root node that turns the orbit's up axis onto
glTF's +y; the camera node sits under the same root. The container (a 12-byte header, a JSON
chunk and a binary chunk, each 4-byte aligned) follows the glTF 2.0 specification, section
"GLB File Format Specification".
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass

import numpy as np
import torch

from damcap.appearance.dam import DeepAppearanceMap
from damcap.common.cameras import rotation_between
from damcap.common.mesh import Mesh, midpoint_subdivision

GLB_MAGIC = 0x46546C67  # 'glTF'
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942
FLOAT, UNSIGNED_INT = 5126, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


@dataclass(frozen=True)
class PartMesh:
    """One part of a mesh as its own vertex list (vertices shared between parts are repeated)."""

    positions: np.ndarray
    """(V, 3) float32, world"""
    normals: np.ndarray
    """(V, 3) float32, unit, world"""
    triangles: np.ndarray
    """(T, 3) uint32, indices into this part's vertices"""


VIEW_DEPENDENCE_NOTE = ("the vertex colours are one view's radiance, baked for the file's camera ('baked_view'); the "
                        "view-dependent appearance (highlights that move as the view turns) is not in the file: "
                        "--format threejs or damcap view evaluate the DAM per view")
"""what a GLB's colours are and are not (stored in its extras and said when it is written)"""


def split_parts(mesh: Mesh, triangle_part: np.ndarray, parts: int) -> list[PartMesh]:
    """The mesh cut into ``parts`` vertex lists by each triangle's part (empty parts stay empty).

    >>> quad = Mesh(np.eye(4, 3), np.array([[0, 1, 2], [0, 2, 3]]), np.eye(4, 3))
    >>> [(len(p.positions), p.triangles.tolist()) for p in split_parts(quad, np.array([1, 1]), 3)]
    [(0, []), (4, [[0, 1, 2], [0, 2, 3]]), (0, [])]
    """
    out = []
    for k in range(parts):
        tris = mesh.triangles[triangle_part == k]
        used, inverse = np.unique(tris.ravel(), return_inverse=True)
        out.append(PartMesh(mesh.vertices[used].astype(np.float32), mesh.vertex_normals[used].astype(np.float32),
                            inverse.reshape(-1, 3).astype(np.uint32)))
    return out


def subdivide_midpoint(mesh: Mesh, triangle_part: np.ndarray) -> tuple[Mesh, np.ndarray]:
    """Each triangle cut into four at its edges' midpoints (positions on the flat triangle, normals
    the normalised mean of the edge's two), each child in its parent's part.

    Args:
        mesh: with vertex normals.
        triangle_part: (T,) part per triangle.

    Returns:
        (the finer mesh: V + E vertices, 4T triangles; (4T,) parts).

    >>> tri = Mesh(np.eye(3), np.array([[0, 1, 2]]), np.eye(3))
    >>> fine, part = subdivide_midpoint(tri, np.array([7]))
    >>> fine.vertices[3:].tolist()  # the midpoints of edges 01, 02, 12
    [[0.5, 0.5, 0.0], [0.5, 0.0, 0.5], [0.0, 0.5, 0.5]]
    >>> fine.triangles.tolist(), part.tolist()  # the corners' three children (same winding) and the middle one
    ([[0, 3, 4], [3, 1, 5], [4, 5, 2], [3, 5, 4]], [7, 7, 7, 7])
    """
    unique, children = midpoint_subdivision(mesh.triangles, len(mesh.vertices))
    v = np.asarray(mesh.vertices, np.float64)
    n = np.asarray(mesh.vertex_normals, np.float64)
    n_mid = n[unique[:, 0]] + n[unique[:, 1]]
    n_mid /= np.maximum(np.linalg.norm(n_mid, axis=1, keepdims=True), 1e-12)
    vertices = np.concatenate([v, 0.5 * (v[unique[:, 0]] + v[unique[:, 1]])])
    normals = np.concatenate([n, n_mid])
    fine = Mesh(vertices.astype(np.float32), children.reshape(-1, 3).astype(np.int32), normals.astype(np.float32))
    return fine, np.repeat(np.asarray(triangle_part), 4)


def vertex_radiance(model: DeepAppearanceMap, positions_world: np.ndarray, normals_world: np.ndarray,
                    camera_centre_world: np.ndarray) -> np.ndarray:
    """The DAM's radiance at each vertex seen from one camera centre (a pinhole's view directions).

    Args:
        model: the DAM (world-space view and normal in, linear radiance out).
        positions_world: (V, 3).
        normals_world: (V, 3) unit.
        camera_centre_world: (3,).

    Returns:
        (V, 3) float32 linear radiance, the capture's units.
    """
    v = np.asarray(camera_centre_world, np.float64)[None] - np.asarray(positions_world, np.float64)
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    if len(v) == 0:
        return np.zeros((0, 3), np.float32)
    with torch.no_grad():
        return model(torch.from_numpy(v.astype(np.float32)), torch.from_numpy(np.asarray(normals_world, np.float32))).numpy()


def gltf_from_world(up_world: np.ndarray) -> np.ndarray:
    """(4, 4) the rotation that takes the orbit's up axis onto glTF's +y (the root node's matrix).

    >>> np.round(gltf_from_world(np.array([0.0, 0.0, 1.0]))[:3, :3] @ [0, 0, 1], 6).tolist()
    [0.0, 1.0, 0.0]
    """
    m = np.eye(4)
    m[:3, :3] = rotation_between(np.asarray(up_world, np.float64), np.array([0.0, 1.0, 0.0]))
    return m


def _column_major(m: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(m, np.float64).T.ravel()]


def glb_bytes(parts: list[PartMesh], colours_lin: list[np.ndarray], root_matrix: np.ndarray, world_from_cam: np.ndarray,
              yfov_deg: float, extras: dict) -> bytes:
    """A binary glTF 2.0 file: one unlit, vertex-coloured primitive per non-empty part, and a camera.

    Args:
        parts: the mesh's parts (:func:`split_parts`), world coordinates.
        colours_lin: per part (V, 3) linear colours in [0, 1] (COLOR_0).
        root_matrix: (4, 4) the root node's transform (world -> glTF scene).
        world_from_cam: (4, 4) the camera (OpenGL axes, as glTF's: looking down -z, +y up), world.
        yfov_deg: the camera's vertical field of view, degrees (aspect ratio 1).
        extras: JSON-serialisable notes stored as the asset's ``extras``.

    Returns:
        the .glb file's bytes.
    """
    blob = bytearray()
    views: list[dict] = []
    accessors: list[dict] = []

    def add(array: np.ndarray, kind: str, target: int, component: int, minmax: bool = False) -> int:
        while len(blob) % 4:
            blob.append(0)
        data = np.ascontiguousarray(array).tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data), "target": target})
        blob.extend(data)
        acc = {"bufferView": len(views) - 1, "componentType": component, "count": int(len(array)), "type": kind}
        if minmax:
            acc["min"], acc["max"] = array.min(0).astype(float).tolist(), array.max(0).astype(float).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    meshes, nodes = [], []
    for k, (part, col) in enumerate(zip(parts, colours_lin)):
        if len(part.triangles) == 0:
            continue
        prim = {
            "attributes": {
                "POSITION": add(part.positions.astype("<f4"), "VEC3", ARRAY_BUFFER, FLOAT, minmax=True),
                "NORMAL": add(part.normals.astype("<f4"), "VEC3", ARRAY_BUFFER, FLOAT),
                "COLOR_0": add(np.clip(col, 0.0, 1.0).astype("<f4"), "VEC3", ARRAY_BUFFER, FLOAT),
            },
            "indices": add(part.triangles.ravel().astype("<u4"), "SCALAR", ELEMENT_ARRAY_BUFFER, UNSIGNED_INT),
            "material": 0,
            "mode": 4,
        }
        meshes.append({"name": f"part_{k}", "primitives": [prim]})
        nodes.append({"name": f"part_{k}", "mesh": len(meshes) - 1})
    nodes.append({"name": "baked_view", "camera": 0, "matrix": _column_major(world_from_cam)})
    nodes.append({"name": "damcap", "children": list(range(len(nodes))), "matrix": _column_major(root_matrix)})
    doc = {
        "asset": {"version": "2.0", "generator": "damcap export --format glb", "extras": extras},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{"nodes": [len(nodes) - 1]}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": [{"name": "dam_baked", "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                                                                     "metallicFactor": 0.0, "roughnessFactor": 1.0},
                       "extensions": {"KHR_materials_unlit": {}}}],
        "cameras": [{"type": "perspective", "perspective": {"yfov": math.radians(yfov_deg), "aspectRatio": 1.0,
                                                            "znear": 0.01, "zfar": 100.0}}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(blob)}],
    }
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    blob.extend(b"\0" * (-len(blob) % 4))
    total = 12 + 8 + len(text) + 8 + len(blob)
    return (struct.pack("<III", GLB_MAGIC, 2, total) + struct.pack("<II", len(text), CHUNK_JSON) + text
            + struct.pack("<II", len(blob), CHUNK_BIN) + bytes(blob))


def read_glb(data: bytes) -> tuple[dict, bytes]:
    """(the JSON document, the binary chunk) of a .glb file's bytes.

    Raises:
        ValueError: not a glTF 2.0 binary, or its lengths disagree.
    """
    if len(data) < 20:
        raise ValueError("too short for a GLB file")
    magic, version, total = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC or version != 2 or total != len(data):
        raise ValueError(f"not a glTF 2.0 binary (magic {magic:#x}, version {version}, length {total} of {len(data)})")
    n, kind = struct.unpack_from("<II", data, 12)
    if kind != CHUNK_JSON:
        raise ValueError("the first chunk is not JSON")
    doc = json.loads(data[20:20 + n])
    rest = 20 + n
    blob = b""
    if rest < len(data):
        m, kind = struct.unpack_from("<II", data, rest)
        if kind != CHUNK_BIN:
            raise ValueError("the second chunk is not BIN")
        blob = data[rest + 8:rest + 8 + m]
    return doc, blob


def accessor_array(doc: dict, blob: bytes, index: int) -> np.ndarray:
    """An accessor's data (FLOAT or UNSIGNED_INT, tightly packed) as an array (count, components)."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    comps = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc["type"]]
    dtype = {FLOAT: "<f4", UNSIGNED_INT: "<u4"}[acc["componentType"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return np.frombuffer(blob, dtype, acc["count"] * comps, start).reshape(acc["count"], comps)
