"""Procedural shapes to put appearance on: ``make demo`` exports its DAM onto one of them.

Run ``python -m damcap.common.shapes torus OUT.obj`` (or ``sphere``) to write one as an OBJ that
``damcap export --mesh`` reads like any user mesh.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from damcap.common.errors import DamcapError

SHAPES = ("torus", "sphere")


def torus_mesh(major: float = 0.9, minor: float = 0.4, radial: int = 60, tubular: int = 24):
    """A torus about the y axis (the capture contract's up axis), as an Open3D triangle mesh.

    Args:
        major: distance from the centre to the tube's centre line, scene units.
        minor: tube radius, scene units (< major).
        radial: segments around the y axis.
        tubular: segments around the tube.

    Returns:
        ``open3d.geometry.TriangleMesh`` with ``radial * tubular`` vertices, centred at the origin.
    """
    import open3d as o3d

    if not 0 < minor < major or radial < 3 or tubular < 3:
        raise DamcapError(f"a torus needs 0 < minor < major and >= 3 segments, got major={major}, minor={minor}, "
                          f"radial={radial}, tubular={tubular}")
    m = o3d.geometry.TriangleMesh.create_torus(torus_radius=major, tube_radius=minor, radial_resolution=radial,
                                               tubular_resolution=tubular)
    v = np.asarray(m.vertices)[:, [0, 2, 1]] * [1.0, 1.0, -1.0]  # Open3D's torus turns about z; ours about y
    m.vertices = o3d.utility.Vector3dVector(v)
    return m


def shape_mesh(name: str):
    """The named shape (one of :data:`SHAPES`) as an Open3D triangle mesh in the unit sphere's scale."""
    import open3d as o3d

    if name == "torus":
        return torus_mesh()
    if name == "sphere":
        return o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=48)
    raise DamcapError(f"unknown shape {name!r}; choose one of {', '.join(SHAPES)}")


def write_shape(name: str, path: str | os.PathLike) -> Path:
    """Write the named shape as an OBJ or PLY file (by ``path``'s suffix), atomically."""
    import open3d as o3d

    from damcap.common.atomic import atomic_path

    path = Path(path)
    if path.suffix.lower() not in (".obj", ".ply"):
        raise DamcapError(f"{path}: write the shape as .obj or .ply")
    mesh = shape_mesh(name)
    with atomic_path(path, keep_name=True) as tmp:  # an OBJ names its object after the file
        if not o3d.io.write_triangle_mesh(str(tmp), mesh):
            raise DamcapError(f"{path}: Open3D could not write the mesh")
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Write a procedural shape as an OBJ/PLY mesh.")
    ap.add_argument("shape", choices=SHAPES)
    ap.add_argument("output", type=Path, help=".obj or .ply file to write")
    args = ap.parse_args(argv)
    try:
        print(f"wrote {write_shape(args.shape, args.output)}")
    except DamcapError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
