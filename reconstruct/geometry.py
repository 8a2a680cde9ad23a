"""Geometry for a capture from what a CPU has: silhouettes, sparse points, a sphere, or a user mesh.

COLMAP's dense stereo needs CUDA (not in the pycolmap wheel), so ``--geometry`` offers:

- ``visual-hull``: space carving from the object masks and calibrated cameras (a voxel is kept
  while every camera that sees it sees the object there), smoothed, meshed with Open3D's
  isosurface extraction (Flying Edges) and Taubin-smoothed. Exact on convex objects, never
  inside concavities.
- ``poisson``: screened Poisson surface reconstruction (Open3D) of the SfM points with normals
  estimated from neighbours and turned toward a camera that sees each point.
- ``sphere``: an analytic sphere fitted to the silhouettes (each silhouette ray is tangent to
  the sphere) or to the points: model only what the scene requires.
- ``dense``: multi-view stereo (:func:`damcap.reconstruct.dense.dense_geometry`: plane sweep in
  torch, fused by screened Poisson), trimmed by the silhouettes when masks are given. It reaches
  into concavities the visual hull bridges; it needs texture to match.
- ``mesh:FILE``: a user mesh in the cameras' world frame (the input poses' frame), aligned to the
  silhouettes or points by scaled ICP when it does not fit them as given.
- ``auto``: with masks, the sphere when the silhouettes fit one within ``sphere_max_rms`` of its
  radius, else the visual hull; without masks, the sphere test on the points, else Poisson.
  Past the sphere test the pipeline also builds the dense geometry and keeps whichever surface
  the photos agree with better (:mod:`damcap.reconstruct.photo_consistency`; ``--no-auto-dense``
  skips it).

Everything here works in the normalised frame (:mod:`normalize`) on arrays; cameras are OpenGL
camera-to-world with pinhole :class:`~damcap.common.capture_folder.Intrinsics`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from damcap.common.capture_folder import Intrinsics
from damcap.common.errors import DamcapError
from damcap.common.validate import COUNT_OR_ZERO, FRACTION, in_range

from damcap.reconstruct.normalize import transform_points
from damcap.common.mesh import Mesh, load_mesh, signed_volume, vertex_normals_area_weighted
from damcap.common.raycast import MeshRaycaster
from damcap.common.shapes import sphere_mesh

GeometryMode = Literal["auto", "visual-hull", "poisson", "sphere", "dense", "mesh"]
MeshAlign = Literal["auto", "none", "icp"]
#: largest visual-hull grid side, voxels
MAX_VOXELS = 2048
#: mask value above which a pixel is the object
MASK_THRESHOLD = 0.5
#: a mask reaches the photo's border when an object pixel lies within this fraction of the
#: photo's size of an edge (:func:`mask_touches_border`)
BORDER_BAND = 0.005
#: the visual hull judges a voxel only where at least this many photos judge it ...
MIN_VIEWS_JUDGING = 3
#: ... and at least this fraction of them (:func:`min_views_judging`): where fewer photos hold a
#: voxel, silhouettes that leave the frame cannot close the hull (a long object cut by the frame)
SEEN_FRACTION = 0.25
#: the sparse points bound the hull's grid when there are at least this many on the object ...
MIN_BOX_POINTS = 20
#: ... by their robust box grown by this fraction of its size on every side
POINTS_MARGIN = 0.25


@dataclass(frozen=True)
class GeometryOptions:
    """How ``damcap reconstruct`` builds the geometry (its "Geometry" options)."""

    mode: str = field(default="auto", metadata={"cli_flag": "--geometry"})
    """'auto', 'visual-hull', 'poisson', 'sphere', 'dense' (multi-view stereo) or 'mesh:FILE'"""
    voxels: int = field(default=160, metadata=in_range(16, MAX_VOXELS))
    """visual hull: voxels along the longest side of the object's box"""
    hull_tolerance: int = field(default=0, metadata={**COUNT_OR_ZERO, "cli_panel": "advanced"})
    """visual hull: views allowed to see background where the object is (forgives bad masks)"""
    smooth_iterations: int = field(default=10, metadata=in_range(0, 100000, cli_panel="advanced"))
    """Taubin smoothing iterations of the visual hull / Poisson mesh (0 = none)"""
    poisson_depth: int = field(default=8, metadata=in_range(1, 16, cli_panel="advanced"))
    """Poisson octree depth (surface detail ~ object size / 2^depth)"""
    sphere_max_rms: float = field(default=0.01, metadata={**FRACTION, "cli_panel": "advanced"})
    """auto: a sphere fits when its rms residual is below this fraction of its radius"""
    mesh_align: MeshAlign = "auto"
    """whether a --geometry mesh:FILE is aligned to the cameras. 'none' (the mesh is in the
    cameras' frame), 'icp' (always align to the silhouettes/points), 'auto' (align when it does
    not fit them as given)"""


@dataclass
class GeometryInputs:
    """What the geometry builders see (normalised frame)."""

    world_from_cams: np.ndarray
    """(N, 4, 4) float64 OpenGL camera-to-world"""
    intrinsics: list[Intrinsics]
    """N pinhole cameras (of the masks' resolution)"""
    masks: list[np.ndarray] | None = None
    """N (h, w) float32 in [0, 1] (1 = object), or None"""
    points_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """(P, 3) sparse points"""
    points_seen_from: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.int64))
    """(P,) index of a camera observing each point"""
    images: list[np.ndarray] | None = None
    """N (h, w, 3) float32 linear photos at the intrinsics' resolution (dense stereo), or None"""


@dataclass
class GeometryResult:
    """The mesh to ray cast and what was done."""

    mesh: Mesh
    mode: str
    """the mode used ('visual-hull', 'poisson', 'sphere', 'mesh')"""
    reason: str
    """what was built and why (printed for 'auto')"""
    sphere: tuple[np.ndarray, float] | None = None
    """(centre (3,), radius) when the geometry is an analytic sphere (normals are set analytically)"""
    stats: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Projection helpers
# --------------------------------------------------------------------------------------------

def project_points(points_world: np.ndarray, world_from_cam: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates of world points in a pinhole camera (pixel (i, j) centre at (j+.5, i+.5)).

    Args:
        points_world: (P, 3).
        world_from_cam: (4, 4) OpenGL camera-to-world.
        intr: pinhole intrinsics.

    Returns:
        uv: (P, 2) (u right, v down), pixels; float32 for float32 points, else float64.
        in_front: (P,) bool, the point is in front of the camera.
    """
    pts = np.asarray(points_world)
    dt = pts.dtype if pts.dtype in (np.float32, np.float64) else np.float64
    p = (pts.astype(dt, copy=False) - world_from_cam[:3, 3].astype(dt)) @ world_from_cam[:3, :3].astype(dt)
    depth = -p[:, 2]
    in_front = depth > 1e-9
    inv = 1.0 / np.where(in_front, depth, 1.0)
    uv = np.empty((len(p), 2), dt)
    uv[:, 0] = intr.fl_x * p[:, 0] * inv + intr.cx
    uv[:, 1] = -intr.fl_y * p[:, 1] * inv + intr.cy
    return uv, in_front


def sample_bilinear(image: np.ndarray, uv: np.ndarray, outside: float) -> np.ndarray:
    """Bilinear samples of a (h, w) image at (P, 2) pixel coordinates; ``outside`` beyond the borders."""
    import cv2

    n = len(uv)
    cols = 1024
    rows = -(-n // cols)
    pad = rows * cols - n
    mx = np.concatenate([uv[:, 0] - 0.5, np.full(pad, -10.0)]).astype(np.float32).reshape(rows, cols)
    my = np.concatenate([uv[:, 1] - 0.5, np.full(pad, -10.0)]).astype(np.float32).reshape(rows, cols)
    out = cv2.remap(np.ascontiguousarray(image, dtype=np.float32), mx, my, interpolation=cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=float(outside))
    return out.reshape(-1)[:n]


# --------------------------------------------------------------------------------------------
# Visual hull
# --------------------------------------------------------------------------------------------

def mask_touches_border(mask: np.ndarray) -> bool:
    """Whether the object reaches the photo's border: a mask pixel within ``BORDER_BAND`` of the
    photo's size (at least 2 px) from an edge is the object. Then the object may go on past the
    frame; a mask that stops a pixel or two short of the edge counts as reaching it.

    >>> m = np.zeros((100, 100), np.float32); m[40:60, 40:97] = 1
    >>> mask_touches_border(m), mask_touches_border(m[:, :98])
    (False, True)
    """
    h, w = mask.shape
    b = max(2, int(np.ceil(BORDER_BAND * max(h, w))))
    on = mask > MASK_THRESHOLD
    return bool(on[:b].any() or on[-b:].any() or on[:, :b].any() or on[:, -b:].any())


def mask_values_and_judged(points_world: np.ndarray, mask: np.ndarray, world_from_cam: np.ndarray, intr: Intrinsics,
                           border: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A photo's mask value at each point, as carving reads it, and whether the photo judges the point.

    Inside the photo (in front of the camera): the bilinear mask value, judged. Outside the photo:
    background (0, judged) when the object lies wholly inside the photo (:func:`mask_touches_border`
    is False), else unknown (1, not judged: the object may go on past the frame). Behind the
    camera: unknown.

    Args:
        points_world: (P, 3).
        mask: (h, w) float32 in [0, 1].
        world_from_cam: (4, 4) OpenGL camera-to-world.
        intr: the mask's pinhole camera.
        border: :func:`mask_touches_border` of the mask, when known.

    Returns:
        (P,) float32 in [0, 1]; (P,) bool.
    """
    uv, front = project_points(points_world, world_from_cam, intr)
    if border is None:
        border = mask_touches_border(mask)
    h, w = mask.shape
    inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    vals = sample_bilinear(mask, uv, outside=1.0 if border else 0.0)
    judged = inside if border else front
    vals[~judged] = 1.0
    return vals, judged


def mask_values_at(points_world: np.ndarray, mask: np.ndarray, world_from_cam: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """A photo's mask value at each point, as carving reads it (:func:`mask_values_and_judged`):
    (P,) float32 in [0, 1]."""
    return mask_values_and_judged(points_world, mask, world_from_cam, intr)[0]


def views_judging(points_world: np.ndarray, masks: list[np.ndarray], world_from_cams: np.ndarray,
                  intrinsics: list[Intrinsics]) -> np.ndarray:
    """How many photos judge each point (:func:`mask_values_and_judged`): (P,) int32."""
    pts = np.asarray(points_world, np.float32)
    count = np.zeros(len(pts), np.int32)
    for mask, m, intr in zip(masks, world_from_cams, intrinsics):
        uv, front = project_points(pts, m, intr)
        if mask_touches_border(mask):
            count += front & (uv[:, 0] >= 0) & (uv[:, 0] < intr.w) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.h)
        else:
            count += front
    return count


def min_views_judging(n_cameras: int, tolerance: int = 0) -> int:
    """Photos that must judge a voxel for the hull to keep it: at least ``MIN_VIEWS_JUDGING`` and
    ``SEEN_FRACTION`` of the cameras, and two more than the views allowed to disagree; never more
    than there are cameras.

    >>> min_views_judging(40), min_views_judging(14), min_views_judging(4), min_views_judging(40, tolerance=9)
    (10, 4, 3, 11)
    """
    return int(min(n_cameras, max(MIN_VIEWS_JUDGING, tolerance + 2, int(np.ceil(SEEN_FRACTION * n_cameras)))))


def points_box(points_world: np.ndarray, margin: float = POINTS_MARGIN) -> tuple[np.ndarray, np.ndarray] | None:
    """The sparse points' robust box (their 2nd and 98th percentiles per axis) grown by ``margin``
    of its size on every side; None for fewer than ``MIN_BOX_POINTS`` points.

    >>> lo, hi = points_box(np.linspace(0, 1, 101)[:, None].repeat(3, 1))
    >>> np.round(lo, 3).tolist(), np.round(hi, 3).tolist()
    ([-0.22, -0.22, -0.22], [1.22, 1.22, 1.22])
    """
    pts = np.asarray(points_world, np.float64)
    if len(pts) < MIN_BOX_POINTS:
        return None
    lo, hi = np.quantile(pts, (0.02, 0.98), axis=0)
    pad = margin * float((hi - lo).max())
    return lo - pad, hi + pad


def carve(masks: list[np.ndarray], world_from_cams: np.ndarray, intrinsics: list[Intrinsics], points_world: np.ndarray,
          tolerance: int = 0) -> np.ndarray:
    """Soft occupancy of points by silhouette carving.

    A point's occupancy is the (tolerance+1)-th smallest mask value over the cameras
    (:func:`mask_values_and_judged`): a photo carves where the point lands on its background, and
    outside it only when the object lies wholly inside it; behind a camera is unknown. A point no
    photo judges stays at 1: the grid is bounded by :func:`hull_bounds`, not by this.

    Args:
        masks: N (h, w) float32 in [0, 1].
        world_from_cams: (N, 4, 4).
        intrinsics: N pinhole cameras.
        points_world: (P, 3).
        tolerance: views allowed to disagree.

    Returns:
        (P,) float32 in [0, 1].
    """
    smallest = np.ones((tolerance + 1, len(points_world)), np.float32)
    pts = np.asarray(points_world, dtype=np.float32)  # float32: carving is memory-bound
    alive = np.arange(len(pts))  # points not yet carved to 0 by tolerance + 1 views: only they can change
    for mask, m, intr in zip(masks, world_from_cams, intrinsics):
        if len(alive) == 0:
            break
        x = mask_values_at(pts[alive], mask, m, intr)
        sm = smallest[:, alive]
        for k in range(tolerance + 1):  # insert into the sorted list of the smallest values
            lo = np.minimum(sm[k], x)
            x = np.maximum(sm[k], x)
            sm[k] = lo
        smallest[:, alive] = sm
        alive = alive[sm[tolerance] > 0]
    return smallest[tolerance]


def grid_box(box_min: np.ndarray, box_max: np.ndarray, voxels: int) -> tuple[np.ndarray, float, tuple[int, int, int]]:
    size = float((box_max - box_min).max()) / voxels
    dims = tuple(int(max(2, np.ceil((box_max[a] - box_min[a]) / size))) for a in range(3))
    return box_min, size, dims  # type: ignore[return-value]


def voxel_centres(origin: np.ndarray, size: float, dims: tuple[int, int, int]) -> np.ndarray:
    """(Z*Y*X, 3) voxel centres, z slowest (the [z, y, x] order Open3D's isosurface expects)."""
    zz, yy, xx = np.meshgrid(*(np.arange(dims[a]) for a in (2, 1, 0)), indexing="ij")
    idx = np.stack([xx, yy, zz], axis=-1).reshape(-1, 3)
    return origin + (idx + 0.5) * size


def isosurface_mesh(volume_zyx: np.ndarray, origin: np.ndarray, voxel_size: float, level: float = 0.5) -> Mesh:
    """Triangle mesh of the ``level`` set of a [z, y, x] volume (Open3D Flying Edges), outward-facing.

    Args:
        volume_zyx: (Z, Y, X) float32; larger values inside.
        origin: (3,) world position of voxel [0, 0, 0]'s centre.
        voxel_size: scene units.
        level: iso value.

    Raises:
        DamcapError: the volume has no surface at ``level``.
    """
    import open3d as o3d

    vol = np.pad(np.asarray(volume_zyx, dtype=np.float32), 1, constant_values=0.0)  # closes open boundaries
    tm = o3d.t.geometry.TriangleMesh.create_isosurfaces(o3d.core.Tensor(vol), [float(level)])
    if tm.triangle.indices.shape[0] == 0:
        raise DamcapError("the carved volume is empty: no voxel is inside every silhouette (check the masks and cameras)")
    verts = tm.vertex.positions.numpy().astype(np.float64)
    tris = tm.triangle.indices.numpy().astype(np.int32)
    verts = origin + (verts - 1.0) * voxel_size
    mesh = clean_surface(verts, tris)
    if signed_volume(mesh.vertices, mesh.triangles) < 0:
        mesh = Mesh(mesh.vertices, mesh.triangles[:, ::-1].copy(), -mesh.vertex_normals, mesh.triangle_groups)
    return mesh


def clean_surface(verts: np.ndarray, tris: np.ndarray, smooth_iterations: int = 0, keep_largest: bool = True) -> Mesh:
    """Tidy a reconstructed surface with Open3D: weld equal vertices, drop triangles with a repeated
    index, keep the largest connected part, Taubin-smooth, recompute normals (float32 result).

    Unlike :func:`damcap.common.mesh.clean_mesh` (drops zero-area triangles, keeps the file's
    vertices), this changes the surface; it is for marching-cubes and Poisson output only.
    """
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris))
    m.remove_duplicated_vertices()
    m.remove_degenerate_triangles()
    m.remove_unreferenced_vertices()
    if keep_largest and len(m.triangles):
        clusters, counts, _ = m.cluster_connected_triangles()
        clusters = np.asarray(clusters)
        if len(counts) > 1:
            m.remove_triangles_by_mask(clusters != int(np.argmax(np.asarray(counts))))
            m.remove_unreferenced_vertices()
    if smooth_iterations > 0:
        m = m.filter_smooth_taubin(number_of_iterations=smooth_iterations)
    v = np.asarray(m.vertices, np.float64)
    t = np.asarray(m.triangles, np.int32)
    if len(t) == 0:
        raise DamcapError("the mesh has no triangles left after clean-up")
    n = vertex_normals_area_weighted(v, t)
    return Mesh(v.astype(np.float32), t, n.astype(np.float32), np.zeros(len(t), np.int32))


def unjudged_voxels(centres: np.ndarray, occupancy: np.ndarray, masks: list[np.ndarray], world_from_cams: np.ndarray,
                    intrinsics: list[Intrinsics], min_views: int, box: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Voxels the silhouettes cannot judge: kept by the carve (occupancy > 0) but judged by fewer
    than ``min_views`` photos (:func:`views_judging`) or outside ``box`` (the sparse points' box).
    Carved voxels are judged.

    Args:
        centres: (V, 3) voxel centres.
        occupancy: (V,) carved occupancy.
        min_views: :func:`min_views_judging`.
        box: (min (3,), max (3,)) or None.

    Returns:
        (V,) bool.
    """
    out = np.zeros(len(centres), bool)
    alive = np.flatnonzero(occupancy > 0)
    if len(alive) == 0:
        return out
    pts = centres[alive]
    bad = views_judging(pts, masks, world_from_cams, intrinsics) < min_views
    if box is not None:
        bad |= ~np.all((pts >= box[0]) & (pts <= box[1]), axis=1)
    out[alive[bad]] = True
    return out


def reaches_limits(occupied_zyx: np.ndarray, unjudged_zyx: np.ndarray) -> bool:
    """Whether an occupied voxel lies on the grid's faces or beside (6-neighbours) a voxel the
    silhouettes cannot judge: the hull ends there at its bounds, not at a silhouette."""
    from scipy.ndimage import binary_dilation

    occ = np.asarray(occupied_zyx, bool)
    if not occ.any():
        return False
    faces = occ[[0, -1]].any() or occ[:, [0, -1]].any() or occ[:, :, [0, -1]].any()
    return bool(faces or (binary_dilation(unjudged_zyx) & occ).any())


@dataclass
class HullBounds:
    """Where the visual hull is carved: a box around the coarse hull, within what the cameras see."""

    box_min: np.ndarray
    box_max: np.ndarray
    touches: bool
    """the coarse hull reaches the limit of what the silhouettes judge (the search cube, the region
    judged by ``min_views`` photos, the sparse points' box): the object leaves the photos there, or
    the masks or cameras are wrong"""
    min_views: int
    """photos that must judge a voxel (:func:`min_views_judging`)"""
    points_box: tuple[np.ndarray, np.ndarray] | None
    """the sparse points' box that bounds the grid, or None"""


def hull_bounds(masks: list[np.ndarray], world_from_cams: np.ndarray, intrinsics: list[Intrinsics], tolerance: int = 0,
                search_radius: float | None = None, coarse: int = 48,
                points_world: np.ndarray | None = None) -> HullBounds | None:
    """The box around the visual hull: a coarse carve (``coarse`` voxels a side) of a cube around
    the origin, without the voxels fewer than :func:`min_views_judging` photos judge and those
    outside the sparse points' box (:func:`points_box`, when given), padded by a voxel or two.

    Args:
        masks, world_from_cams, intrinsics, tolerance: as :func:`carve`; cameras in the normalised
            frame (the object near the origin).
        search_radius: half-size of the cube (default: 0.9 x the nearest camera's distance).
        coarse: voxels along the cube's side.
        points_world: (P, 3) sparse points on the object, or None.

    Returns:
        the bounds, or None when no voxel the cameras judge is inside the silhouettes.
    """
    cams = np.asarray(world_from_cams, np.float64)
    r = search_radius or 0.9 * float(np.linalg.norm(cams[:, :3, 3], axis=1).min())
    origin, size, dims = grid_box(np.full(3, -r), np.full(3, r), coarse)
    centres = voxel_centres(origin, size, dims)
    occ = carve(masks, cams, intrinsics, centres, tolerance)
    k = min_views_judging(len(cams), tolerance)
    pbox = points_box(points_world) if points_world is not None else None
    unjudged = unjudged_voxels(centres, occ, masks, cams, intrinsics, k, pbox)
    occ[unjudged] = 0.0
    occ = occ.reshape(dims[::-1])
    kept = occ > 0.2  # generous: the coarse grid only bounds the object
    inside = np.argwhere(kept)
    if len(inside) == 0:
        return None
    zyx_lo, zyx_hi = inside.min(0), inside.max(0)
    return HullBounds(origin + (zyx_lo[::-1] - 1.5) * size, origin + (zyx_hi[::-1] + 2.5) * size,
                      reaches_limits(kept, unjudged.reshape(dims[::-1])), k, pbox)


def hull_box(masks: list[np.ndarray], world_from_cams: np.ndarray, intrinsics: list[Intrinsics], tolerance: int = 0,
             search_radius: float | None = None, coarse: int = 48,
             points_world: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """(box_min (3,), box_max (3,)) of :func:`hull_bounds`, or None."""
    b = hull_bounds(masks, world_from_cams, intrinsics, tolerance, search_radius, coarse, points_world)
    return None if b is None else (b.box_min, b.box_max)


@dataclass
class HullGrid:
    """A carved grid: occupancy of its voxels, without those the silhouettes cannot judge."""

    origin: np.ndarray
    """(3,) corner of voxel [0, 0, 0]"""
    size: float
    """voxel side"""
    dims: tuple[int, int, int]
    """(X, Y, Z) voxels"""
    occupancy: np.ndarray
    """(Z, Y, X) float32 carved occupancy, 0 where the silhouettes cannot judge"""
    unjudged: np.ndarray
    """(Z, Y, X) bool, :func:`unjudged_voxels`"""
    bounds: HullBounds
    touches: bool
    """the hull reaches the limits of what the silhouettes judge (:func:`reaches_limits`, or its bounds do)"""

    def centres(self) -> np.ndarray:
        return voxel_centres(self.origin, self.size, self.dims)


def carve_hull_grid(masks: list[np.ndarray], world_from_cams: np.ndarray, intrinsics: list[Intrinsics], tolerance: int = 0,
                    voxels: int = 160, points_world: np.ndarray | None = None,
                    search_radius: float | None = None) -> HullGrid | None:
    """The visual hull's grid: :func:`hull_bounds`, then ``voxels`` along its longest side carved,
    the voxels too few photos judge (or outside the sparse points' box) set to 0.

    Returns:
        the grid, or None when no voxel the photos judge is inside the silhouettes.
    """
    bounds = hull_bounds(masks, world_from_cams, intrinsics, tolerance, search_radius, points_world=points_world)
    if bounds is None:
        return None
    origin, size, dims = grid_box(bounds.box_min, bounds.box_max, voxels)
    centres = voxel_centres(origin, size, dims)
    occ = carve(masks, world_from_cams, intrinsics, centres, tolerance)
    unjudged = unjudged_voxels(centres, occ, masks, world_from_cams, intrinsics, bounds.min_views, bounds.points_box)
    occ[unjudged] = 0.0
    occ = occ.reshape(dims[::-1])
    unjudged = unjudged.reshape(dims[::-1])
    return HullGrid(origin, size, dims, occ, unjudged, bounds, bounds.touches or reaches_limits(occ > 0.5, unjudged))


#: the line reconstruct prints for a visual hull that reaches the limits of what its cameras see
UNBOUNDED_HULL = ("the visual hull reaches the edge of what the photos judge (the object leaves the frame in "
                  "photos that would close it, or it is seen by too few of them there): its surface there is the "
                  "edge of the region, not the object's")


def visual_hull(inputs: GeometryInputs, voxels: int = 160, tolerance: int = 0, smooth_iterations: int = 10,
                search_radius: float | None = None) -> tuple[Mesh, dict[str, Any]]:
    """Visual hull mesh from masks and cameras: a coarse pass finds the object's box
    (:func:`hull_bounds`: within the region enough photos judge and the sparse points' box), a
    fine pass carves it with ``voxels`` along its longest side; voxels too few photos judge are
    left out of it too.

    Args:
        inputs: cameras and masks (required); its sparse points on the object bound the grid.
        voxels: fine grid resolution.
        tolerance: views allowed to disagree.
        smooth_iterations: Taubin iterations.
        search_radius: half-size of the coarse search cube around the origin (default: 0.9 x
            the nearest camera's distance).

    Returns:
        mesh, stats (box, voxel size, ``touches_box``: the hull reaches the limits of what the
        cameras judge, :data:`UNBOUNDED_HULL`).
    """
    from scipy.ndimage import gaussian_filter

    if not inputs.masks:
        raise DamcapError("the visual hull needs object masks (--masks DIR)")
    pts = _object_points(inputs)
    grid = carve_hull_grid(inputs.masks, inputs.world_from_cams, inputs.intrinsics, tolerance, voxels,
                           pts if len(pts) else None, search_radius)
    if grid is None:
        raise DamcapError("the visual hull is empty: no point is inside every silhouette; check that the masks "
                          "are white on the object and that they belong to these photos")
    bounds, origin, size, dims, touches = grid.bounds, grid.origin, grid.size, grid.dims, grid.touches
    box_lo, box_hi = bounds.box_min, bounds.box_max
    occ = gaussian_filter(grid.occupancy, sigma=0.7, mode="constant")
    mesh = isosurface_mesh(occ, origin + 0.5 * size, size)
    mesh = clean_surface(mesh.vertices, mesh.triangles, smooth_iterations)
    return mesh, {"voxel_size": size, "grid": list(dims), "box_min": box_lo.tolist(), "box_max": box_hi.tolist(),
                  "touches_box": touches, "min_views_judging": bounds.min_views,
                  "points_box": None if bounds.points_box is None else [bounds.points_box[0].tolist(), bounds.points_box[1].tolist()],
                  "triangles": int(len(mesh.triangles))}


# --------------------------------------------------------------------------------------------
# Sphere
# --------------------------------------------------------------------------------------------

def fit_sphere_points(points: np.ndarray, iterations: int = 3) -> tuple[np.ndarray, float, float]:
    """Least-squares sphere through points (algebraic fit, then outliers beyond 3 MADs dropped).

    Args:
        points: (P, 3), P >= 4.

    Returns:
        centre (3,), radius, rms of |p - c| - r over the kept points.

    >>> c, r, e = fit_sphere_points(np.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]) + 2)
    >>> np.round(c, 6).tolist(), round(r, 6), round(e, 6)
    ([2.0, 2.0, 2.0], 1.0, 0.0)
    """
    p = np.asarray(points, dtype=np.float64)
    keep = np.ones(len(p), bool)
    c, r = p.mean(0), 1.0
    for _ in range(iterations):
        q = p[keep]
        a = np.concatenate([2 * q, np.ones((len(q), 1))], axis=1)
        sol = np.linalg.lstsq(a, (q * q).sum(1), rcond=None)[0]
        c = sol[:3]
        r = float(np.sqrt(max(sol[3] + c @ c, 1e-24)))
        res = np.linalg.norm(p - c, axis=1) - r
        mad = np.median(np.abs(res[keep] - np.median(res[keep]))) + 1e-12
        new = np.abs(res) < 3 * 1.4826 * mad + 1e-9 * r
        if new.sum() < 4 or (new == keep).all():
            break
        keep = new
    res = np.linalg.norm(p[keep] - c, axis=1) - r
    return c, r, float(np.sqrt(np.mean(res ** 2)))


def silhouette_points(mask: np.ndarray, level: float = MASK_THRESHOLD) -> np.ndarray:
    """Sub-pixel points where a soft mask crosses ``level`` between horizontal or vertical
    neighbours (linear interpolation of the two pixel centres), away from the image border.

    Args:
        mask: (h, w) float in [0, 1] (anti-aliased coverage gives sub-pixel accuracy).

    Returns:
        (K, 2) image coordinates (u right, v down), pixel (i, j) centre at (j + 0.5, i + 0.5).

    >>> m = np.zeros((5, 6)); m[2, 2] = 1.0; m[2, 3] = 0.75
    >>> silhouette_points(m)[:2].tolist()
    [[2.0, 2.5], [3.8333333333333335, 2.5]]
    """
    m = np.asarray(mask, dtype=np.float64)
    out = []
    for axis in (1, 0):
        a = m[:, :-1] if axis == 1 else m[:-1, :]
        b = m[:, 1:] if axis == 1 else m[1:, :]
        ii, jj = np.nonzero((a - level) * (b - level) < 0)
        t = (a[ii, jj] - level) / (a[ii, jj] - b[ii, jj])
        u = jj + 0.5 + (t if axis == 1 else 0.0)
        v = ii + 0.5 + (t if axis == 0 else 0.0)
        out.append(np.stack([u, v], axis=1))
    pts = np.concatenate(out)
    h, w = m.shape
    keep = (pts[:, 0] > 1.5) & (pts[:, 0] < w - 1.5) & (pts[:, 1] > 1.5) & (pts[:, 1] < h - 1.5)
    return pts[keep]


def silhouette_rays(masks: list[np.ndarray], world_from_cams: np.ndarray, intrinsics: list[Intrinsics],
                    per_view: int = 200, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """World rays through sub-pixel silhouette points (:func:`silhouette_points`) of every view.

    Returns:
        origins: (R, 3); dirs: (R, 3) unit.
    """
    rng = np.random.default_rng(seed)
    origins, dirs = [], []
    for mask, m, intr in zip(masks, world_from_cams, intrinsics):
        pts = silhouette_points(mask)
        if len(pts) == 0:
            continue
        pts = pts[rng.choice(len(pts), min(per_view, len(pts)), replace=False)]
        u, v = pts[:, 0], pts[:, 1]
        d_cam = np.stack([(u - intr.cx) / intr.fl_x, -(v - intr.cy) / intr.fl_y, -np.ones_like(u)], axis=1)
        d = d_cam @ m[:3, :3].T
        dirs.append(d / np.linalg.norm(d, axis=1, keepdims=True))
        origins.append(np.broadcast_to(m[:3, 3], d.shape))
    if not dirs:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(origins), np.concatenate(dirs)


def fit_sphere_silhouettes(origins: np.ndarray, dirs: np.ndarray, centre0: np.ndarray, radius0: float) -> tuple[np.ndarray, float, float]:
    """Sphere tangent to silhouette rays: minimise sum (dist(centre, ray) - r)^2 (robust loss).

    Args:
        origins, dirs: (R, 3) rays (unit dirs).
        centre0, radius0: initial guess.

    Returns:
        centre (3,), radius, rms residual.
    """
    from scipy.optimize import least_squares

    def residual(x: np.ndarray) -> np.ndarray:
        w = x[:3] - origins
        t = np.einsum("ij,ij->i", w, dirs)
        return np.linalg.norm(w - t[:, None] * dirs, axis=1) - x[3]

    sol = least_squares(residual, np.concatenate([centre0, [radius0]]), loss="soft_l1", f_scale=0.01 * radius0)
    res = residual(sol.x)
    return sol.x[:3], float(abs(sol.x[3])), float(np.sqrt(np.mean(res ** 2)))


def sphere_fit(inputs: GeometryInputs) -> tuple[np.ndarray, float, float, str]:
    """The sphere that best explains the inputs: silhouettes when there are masks, else points.

    Returns:
        centre, radius, rms residual (scene units), what it was fitted to.

    Raises:
        DamcapError: neither masks nor at least 20 points.
    """
    pts = _object_points(inputs)
    if inputs.masks:
        origins, dirs = silhouette_rays(inputs.masks, inputs.world_from_cams, inputs.intrinsics)
        if len(origins) >= 20:
            c0, r0 = (fit_sphere_points(pts)[:2] if len(pts) >= 20 else (np.zeros(3), 1.0))
            c, r, rms = fit_sphere_silhouettes(origins, dirs, c0, r0)
            return c, r, rms, f"{len(origins)} silhouette rays"
    if len(pts) >= 20:
        c, r, rms = fit_sphere_points(pts)
        return c, r, rms, f"{len(pts)} sparse points"
    raise DamcapError("a sphere fit needs object masks (--masks) or at least 20 sparse points")


# --------------------------------------------------------------------------------------------
# Poisson from points
# --------------------------------------------------------------------------------------------

def _object_points(inputs: GeometryInputs, min_inside: float = 0.7) -> np.ndarray:
    """Sparse points, without those that project onto background in the masks (when given)."""
    pts = np.asarray(inputs.points_world, dtype=np.float64)
    if not len(pts) or not inputs.masks:
        return pts
    inside = np.zeros(len(pts))
    seen = np.zeros(len(pts))
    for mask, m, intr in zip(inputs.masks, inputs.world_from_cams, inputs.intrinsics):
        uv, front = project_points(pts, m, intr)
        ok = front & (uv[:, 0] >= 0) & (uv[:, 0] < intr.w) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.h)
        vals = sample_bilinear(mask, uv, outside=0.0)
        seen += ok
        inside += ok & (vals > MASK_THRESHOLD)
    return pts[(seen > 0) & (inside >= min_inside * seen)]


def fuse_poisson(points_world: np.ndarray, normals_world: np.ndarray, depth: int, density_quantile: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Screened Poisson surface (Kazhdan & Hoppe 2013, Open3D) of oriented points, its least
    supported vertices (lowest ``density_quantile`` of density) removed.

    Open3D runs PoissonRecon on one thread here: with its default thread pool it crashes the
    process now and then (a segmentation fault, Open3D issue 6828; it killed a CI run of the
    test suite); one thread costs about 1.4x the wall time on two cores (depth 8, 200k points).

    Args:
        points_world: (P, 3).
        normals_world: (P, 3) unit, outward.
        depth: octree depth.
        density_quantile: fraction of the least dense vertices removed.

    Returns:
        vertices (V, 3) float64, triangles (T, 3) int32.
    """
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points_world, np.float64)))
    pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals_world, np.float64))
    mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth, linear_fit=True, n_threads=1)
    dens = np.asarray(dens)
    if density_quantile > 0 and len(dens):
        mesh.remove_vertices_by_mask(dens < np.quantile(dens, density_quantile))
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles, np.int32)


def poisson_mesh(inputs: GeometryInputs, depth: int = 8, smooth_iterations: int = 5, density_quantile: float = 0.05) -> tuple[Mesh, dict[str, Any]]:
    """Screened Poisson surface of the sparse points (Kazhdan & Hoppe 2013, via Open3D).

    Normals come from 30 nearest neighbours, turned toward a camera observing each point;
    vertices in the lowest ``density_quantile`` of point support are trimmed; the mesh is
    cropped to the points' box (+5%).

    Raises:
        DamcapError: fewer than 100 usable points.
    """
    import open3d as o3d

    pts_all = np.asarray(inputs.points_world, dtype=np.float64)
    pts = _object_points(inputs)
    if len(pts) < 100:
        raise DamcapError(f"Poisson meshing needs at least 100 sparse points on the object, got {len(pts)}; "
                          "use --geometry visual-hull with --masks, sphere, or mesh:FILE")
    keep_idx = {tuple(p) for p in pts}
    seen_from = np.array([inputs.points_seen_from[k] for k, p in enumerate(pts_all) if tuple(p) in keep_idx]) \
        if len(inputs.points_seen_from) == len(pts_all) else np.zeros(len(pts), np.int64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd, kept = pcd.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.5)
    kept = np.asarray(kept)
    seen_from = seen_from[kept]
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=30))
    n = np.asarray(pcd.normals)
    p = np.asarray(pcd.points)
    to_cam = inputs.world_from_cams[seen_from, :3, 3] - p
    n *= np.where(np.einsum("ij,ij->i", n, to_cam) < 0, -1.0, 1.0)[:, None]
    verts, tris = fuse_poisson(p, n, depth, density_quantile)
    lo, hi = p.min(0), p.max(0)
    pad = 0.05 * (hi - lo)
    box = np.all((verts >= lo - pad) & (verts <= hi + pad), axis=1)
    out = clean_surface(verts, tris[box[tris].all(1)], smooth_iterations)  # unreferenced vertices go there
    return out, {"points_used": int(len(p)), "points_given": int(len(pts_all)), "triangles": int(len(out.triangles))}


# --------------------------------------------------------------------------------------------
# User mesh
# --------------------------------------------------------------------------------------------

def cameras_seeing(mesh: Mesh, world_from_cams: np.ndarray, intrinsics: list[Intrinsics], max_vertices: int = 5000) -> int:
    """How many cameras see any part of the mesh (a vertex in front, inside the image)."""
    v = mesh.vertices[:: max(1, len(mesh.vertices) // max_vertices)].astype(np.float64)
    count = 0
    for m, intr in zip(world_from_cams, intrinsics):
        uv, front = project_points(v, m, intr)
        ok = front & (uv[:, 0] >= 0) & (uv[:, 0] < intr.w) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.h)
        count += bool(ok.any())
    return count


def silhouette_iou(mesh: Mesh, inputs: GeometryInputs, max_views: int = 8) -> float:
    """Mean IoU of the mesh's ray-cast coverage and the masks over up to ``max_views`` views."""
    rc = MeshRaycaster(mesh)
    idx = np.linspace(0, len(inputs.intrinsics) - 1, min(max_views, len(inputs.intrinsics))).round().astype(int)
    ious = []
    for k in idx:
        intr = inputs.intrinsics[k]
        b = rc.buffers(inputs.world_from_cams[k], intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h, supersample=1)
        a, m = b.coverage > 0.5, inputs.masks[k] > MASK_THRESHOLD  # type: ignore[index]
        union = (a | m).sum()
        ious.append((a & m).sum() / union if union else 0.0)
    return float(np.mean(ious))


def _transform_mesh(mesh: Mesh, norm_from_world: np.ndarray) -> Mesh:
    v = transform_points(norm_from_world, mesh.vertices)
    lin = norm_from_world[:3, :3]
    # normals: the inverse transpose, divided by its scale so that unit normals stay unit whatever
    # the input's units (the floor below is then only for zero normals, not for s = 1e12)
    n = mesh.vertex_normals.astype(np.float64) @ (np.linalg.inv(lin) * np.cbrt(abs(np.linalg.det(lin))))
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    tris = mesh.triangles if np.linalg.det(lin) > 0 else mesh.triangles[:, ::-1].copy()
    return Mesh(v.astype(np.float32), tris, n.astype(np.float32), mesh.triangle_groups)


def align_mesh(mesh: Mesh, target_points: np.ndarray, seed: int = 0) -> tuple[np.ndarray, float]:
    """Similarity that aligns a mesh to target points: principal axes (4 proper sign choices x
    3 axis orders) as starts, each refined by scaled point-to-point ICP (Open3D); the best fit wins.

    Args:
        mesh: the mesh to move.
        target_points: (P, 3) points on the object's surface (hull vertices or SfM points).

    Returns:
        target_from_mesh: (4, 4) similarity; rms: inlier rms distance, scene units.
    """
    import itertools

    import open3d as o3d

    rng = np.random.default_rng(seed)
    src = mesh.vertices.astype(np.float64)
    src = src[rng.choice(len(src), min(len(src), 20000), replace=False)]
    dst = np.asarray(target_points, dtype=np.float64)
    dst = dst[rng.choice(len(dst), min(len(dst), 20000), replace=False)]

    def frame(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        c = p.mean(0)
        _, s, vt = np.linalg.svd(p - c, full_matrices=False)
        return c, vt, float(np.sqrt((((p - c) ** 2).sum(1)).mean()))

    cs, vs, rs = frame(src)
    cd, vd, rd = frame(dst)
    s = rd / max(rs, 1e-12)
    pcd_s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    pcd_d = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dst))
    best = (np.inf, np.eye(4))
    thr = 0.1 * rd
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            r = vd.T @ np.diag(signs) @ vs[list(perm)]
            if np.linalg.det(r) < 0:
                continue
            init = np.eye(4)
            init[:3, :3] = s * r
            init[:3, 3] = cd - s * r @ cs
            res = o3d.pipelines.registration.registration_icp(
                pcd_s, pcd_d, thr, init, o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=True),
                o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=60))
            score = res.inlier_rmse / max(res.fitness, 1e-3) ** 2 if res.fitness > 0 else np.inf
            if score < best[0]:
                best = (score, np.asarray(res.transformation))
    t = best[1]
    d = np.asarray(pcd_s.transform(t).compute_point_cloud_distance(pcd_d))
    return t, float(np.sqrt(np.mean(np.minimum(d, thr) ** 2)))


def user_mesh(path: Path, norm_from_world: np.ndarray, inputs: GeometryInputs, align: MeshAlign = "auto",
              hull_points: np.ndarray | None = None) -> tuple[Mesh, str, dict[str, Any]]:
    """A user mesh brought into the normalised frame, aligned when needed, checked for visibility.

    Args:
        path: OBJ/PLY file, in the world frame of the input cameras.
        norm_from_world: (4, 4) normalisation applied to the cameras.
        inputs: normalised cameras, masks, points.
        align: 'none', 'icp' or 'auto'.
        hull_points: (P, 3) surface points to align to (visual hull vertices) or None (SfM points).

    Raises:
        DamcapError: no camera sees the mesh (after alignment, when alignment ran).
    """
    mesh = _transform_mesh(load_mesh(path), norm_from_world)
    target = hull_points if hull_points is not None and len(hull_points) else _object_points(inputs)
    stats: dict[str, Any] = {}
    seen = cameras_seeing(mesh, inputs.world_from_cams, inputs.intrinsics)
    fits = None
    if align == "auto" and seen:
        if inputs.masks:
            fits = silhouette_iou(mesh, inputs)
            stats["silhouette_iou_as_given"] = fits
            fits = fits > 0.7
        else:
            fits = True  # nothing to judge it by: trust the user's frame
    do_align = align == "icp" or (align == "auto" and not fits and len(target) >= 20)
    note = "as given"
    if do_align:
        if len(target) < 20:
            raise DamcapError(f"{path}: cannot align the mesh: no masks and fewer than 20 sparse points to align to")
        t, rms = align_mesh(mesh, target)
        mesh = _transform_mesh(mesh, t)
        stats["alignment_rms"] = rms
        note = f"aligned by scaled ICP to {'the visual hull' if hull_points is not None else 'the sparse points'} (rms {rms:.3g})"
        seen = cameras_seeing(mesh, inputs.world_from_cams, inputs.intrinsics)
    if seen == 0:
        c = mesh.vertices.mean(0)
        raise DamcapError(
            f"{path}: no camera sees this mesh (its centre is at {np.round(c, 3).tolist()} in the normalised frame, the "
            "cameras look at the origin); give the mesh in the cameras' world frame, or use --mesh-align icp with --masks")
    if inputs.masks:
        stats["silhouette_iou"] = silhouette_iou(mesh, inputs)
    stats["cameras_seeing"] = seen
    return mesh, note, stats


# --------------------------------------------------------------------------------------------
# Dispatch
# --------------------------------------------------------------------------------------------

def parse_mode(mode: str) -> tuple[GeometryMode, Path | None]:
    """``'mesh:FILE'`` -> ('mesh', FILE); other modes -> (mode, None).

    Raises:
        DamcapError: an unknown mode.
    """
    if mode.startswith("mesh:"):
        p = Path(mode[5:])
        if not mode[5:]:
            raise DamcapError("--geometry mesh:FILE needs a file name after 'mesh:'")
        return "mesh", p
    if mode not in ("auto", "visual-hull", "poisson", "sphere", "dense"):
        raise DamcapError(f"--geometry {mode!r}: use auto, visual-hull, poisson, sphere, dense or mesh:FILE")
    return mode, None  # type: ignore[return-value]


def build_geometry(inputs: GeometryInputs, opts: GeometryOptions = GeometryOptions(),
                   norm_from_world: np.ndarray | None = None) -> GeometryResult:
    """Build the capture's geometry in the normalised frame.

    Args:
        inputs: normalised cameras, masks and points.
        opts: the mode and its knobs.
        norm_from_world: (4, 4) normalisation of the cameras (brings a user mesh along).

    Raises:
        DamcapError: the chosen mode lacks what it needs (masks, points, a readable mesh).
    """
    mode, path = parse_mode(opts.mode)
    has_masks = bool(inputs.masks)
    if mode == "auto":
        try:
            c, r, rms, what = sphere_fit(inputs)
            sphere_ok = rms < opts.sphere_max_rms * r
        except DamcapError:
            c, r, rms, what, sphere_ok = np.zeros(3), 0.0, float("inf"), "", False
        if sphere_ok:
            return GeometryResult(sphere_mesh(c, r), "sphere",
                                  f"auto: sphere, since {what} fit a sphere within {rms / r:.2%} of its radius "
                                  f"(threshold {opts.sphere_max_rms:.0%})", (c, r), {"rms": rms, "radius": r})
        why_not = f"not a sphere (fit rms {rms / r:.1%} of radius)" if r > 0 else "no sphere fit"
        if has_masks:
            mesh, stats = visual_hull(inputs, opts.voxels, opts.hull_tolerance, opts.smooth_iterations)
            return GeometryResult(mesh, "visual-hull", f"auto: visual hull, since masks are given and the object is {why_not}",
                                  None, stats)
        n_pts = len(inputs.points_world)
        if n_pts < 100:
            raise DamcapError(f"--geometry auto: no masks and only {n_pts} sparse points; give --masks DIR (visual hull), "
                              "--geometry sphere, or --geometry mesh:FILE")
        mesh, stats = poisson_mesh(inputs, opts.poisson_depth, opts.smooth_iterations)
        return GeometryResult(mesh, "poisson", f"auto: Poisson surface of the sparse points, since there are no masks "
                                               f"and the object is {why_not}", None, stats)
    if mode == "visual-hull":
        mesh, stats = visual_hull(inputs, opts.voxels, opts.hull_tolerance, opts.smooth_iterations)
        return GeometryResult(mesh, mode, f"visual hull of {len(inputs.masks or [])} silhouettes", None, stats)
    if mode == "poisson":
        mesh, stats = poisson_mesh(inputs, opts.poisson_depth, opts.smooth_iterations)
        return GeometryResult(mesh, mode, f"Poisson surface of {stats['points_used']} sparse points", None, stats)
    if mode == "dense":  # built on this module's pieces, so it lives above it
        raise DamcapError("--geometry dense is built by damcap.reconstruct.dense.dense_geometry, not build_geometry")
    if mode == "sphere":
        c, r, rms, what = sphere_fit(inputs)
        return GeometryResult(sphere_mesh(c, r), mode, f"sphere fitted to {what} (rms {rms / r:.2%} of radius)",
                              (c, r), {"rms": rms, "radius": r, "centre": c.tolist()})
    assert path is not None
    hull = None
    if has_masks and opts.mesh_align != "none":
        hull = visual_hull(inputs, min(opts.voxels, 96), opts.hull_tolerance, opts.smooth_iterations)[0].vertices
    mesh, note, stats = user_mesh(path, norm_from_world if norm_from_world is not None else np.eye(4), inputs,
                                  opts.mesh_align, hull)
    return GeometryResult(mesh, "mesh", f"user mesh {path.name}, {note}", None, stats)
