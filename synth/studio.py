"""Studio photo sets: a multi-material object on a textured board, path traced (Mitsuba 3).

What a user's capture of a real object looks like, with every answer known: the object (any
mesh, normalised into the unit sphere) is split into material regions (:mod:`.regions`), each a
texture-free physically based material (glossy plastic, polished or rough metal), and stands on
a textured board that gives registration its features; an environment map lights it; the camera
orbits it. Written like photos from a camera: 8-bit sRGB JPEGs with EXIF exposure that varies
like auto exposure, object masks (from the mesh, as a user's masking tool would give them) and
the ground-truth cameras (``transforms.json``, nerfstudio keys, OpenGL axes). The input of
``damcap reconstruct`` (``make demo`` uses ``samples/photos_studio``).

The scene is fully determined by :class:`StudioOptions` (and the input files' contents), so the
same command re-creates it, for example to render the materials on another shape as the truth
an export is compared against. A rerun of an interrupted command keeps the photos already
written (the options recorded in ``.studio_partial.json`` must match).
"""

from __future__ import annotations

import fnmatch
import json
import os
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from damcap.common.atomic import write_json_atomic, write_text_atomic
from damcap.common.capture_folder import Intrinsics
from damcap.common.colour import display_srgb8
from damcap.common.errors import DamcapError
from damcap.common.exr import read_exr, write_png
from damcap.common.mesh import Mesh, normalise_to_unit_sphere, read_mesh, vertex_normals_area_weighted
from damcap.common.raycast import MeshRaycaster
from damcap.common.validate import CAMERA_DISTANCE, ELEVATION_DEG, MAX_IMAGE_SIDE, SEED, check_ranges, in_range, require_resolution

from damcap.synth.photos import default_intrinsics, exposure_series, orbit_cameras, room_albedo, write_jpeg
from damcap.synth.regions import SYNTH_ISOLATED_NORMAL, SYNTH_NORMAL_EPS, material_labels, submesh

STUDIO_MATERIALS: dict[str, dict[str, Any]] = {
    "red-plastic": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.08,
                    "diffuse_reflectance": {"type": "rgb", "value": [0.55, 0.06, 0.04]}},
    "blue-plastic": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.15,
                     "diffuse_reflectance": {"type": "rgb", "value": [0.04, 0.12, 0.45]}},
    "white-plastic": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2,
                      "diffuse_reflectance": {"type": "rgb", "value": [0.7, 0.7, 0.68]}},
    "gold": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.12, "material": "Au"},
    "copper": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.2, "material": "Cu"},
    "aluminium": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3, "material": "Al"},
}
"""the materials a studio object can be made of: Mitsuba BSDF descriptions (GGX microfacets;
conductors with measured complex IORs)"""
PARTIAL_MARKER = ".studio_partial.json"
BOARD_TEXELS = 1024
"""board texture resolution per side"""
BOARD_TEXTURE_SCALE = 1.5
"""procedural texture units per scene unit on the board (about 5 px per finest blotch at 320 px)"""
WHITE_POINT = 0.95
"""the photos' exposure puts the 99.5th percentile of the first photo's radiance here (at the
set's median exposure)"""


@dataclass(frozen=True)
class StudioOptions:
    """Options of ``damcap synth-studio``."""

    object: str = ""
    """mesh file of the object (.obj, .ply, ...), normalised into the unit sphere, standing on the board"""
    env: str = ""
    """environment map (.hdr or .exr, equirectangular) that lights the scene (normalised to mean luminance 1)"""
    env_rotation_deg: float = field(default=0.0, metadata=in_range(-360, 360))
    """environment map rotation about +y, degrees"""
    materials: str = "red-plastic,gold,aluminium"
    """comma-separated materials of the object's regions, one region each (names: STUDIO_MATERIALS)"""
    views: int = field(default=24, metadata=in_range(3, 1000))
    """photos around the object, split evenly over the rings"""
    size: int = field(default=320, metadata=in_range(8, MAX_IMAGE_SIDE))
    """photo width and height, pixels"""
    elevation_deg: float = field(default=30.0, metadata={**ELEVATION_DEG, "cli_flag": "--elevation"})
    """mean elevation of the camera rings above the board, degrees"""
    rings: int = field(default=2, metadata=in_range(1, 8))
    """camera rings, the ring step apart in elevation, centred on the mean elevation. Two rings, as
    photogrammetry guides advise, let the visual hull carve what one ring cannot: the demo's three
    materials, segmented, score 0.59x RM++ on novel views from rings at 15 and 45 deg against
    0.71x from one ring at 30 (bench/demo.md)"""
    ring_step_deg: float = field(default=30.0, metadata=in_range(0, 90))
    """elevation between neighbouring rings, degrees"""
    jitter_deg: float = field(default=3.0, metadata=in_range(0, 90, cli_flag="--jitter"))
    """random azimuth and elevation jitter of each camera, degrees"""
    distance: float = field(default=3.4, metadata=CAMERA_DISTANCE)
    """camera distance from the object's centre (object radius 1)"""
    board_size: float = field(default=2.4, metadata=in_range(1.01, 100, cli_panel="advanced"))
    """half the board's edge, in object radii"""
    board_saturation: float = field(default=0.35, metadata=in_range(0, 1, cli_panel="advanced"))
    """colourfulness of the board's printed pattern (0: grey; 1: the full colours)"""
    spp: int = field(default=128, metadata=in_range(1, 1 << 16))
    """path-tracing samples per pixel"""
    max_depth: int = field(default=6, metadata=in_range(2, 64, cli_panel="advanced"))
    """the path tracer's longest path"""
    seed: int = field(default=0, metadata=SEED)
    """seeds the material regions, the board's pattern, the cameras' jitter, the exposures and the path tracer"""

    def material_names(self) -> list[str]:
        return [m.strip() for m in self.materials.split(",") if m.strip()]

    def validate(self) -> None:
        """Raise DamcapError naming the first bad value."""
        check_ranges(self)
        require_resolution(self.size, self.size, 4 * 32, f"--size {self.size}: a photo")
        for flag, path in (("--object", self.object), ("--env", self.env)):
            if not path or not Path(path).is_file():
                raise DamcapError(f"{flag} {path!r}: file not found; give an existing {'mesh' if flag == '--object' else '.hdr or .exr'} file")
        rings = ring_elevations_deg(self.elevation_deg, self.rings, self.ring_step_deg)
        if not all(-90.0 < e < 90.0 for e in rings):
            raise DamcapError(f"--elevation {self.elevation_deg:g} with --rings {self.rings} --ring-step-deg {self.ring_step_deg:g} "
                              f"puts rings at {', '.join(f'{e:g}' for e in rings)} deg; keep every ring within (-90, 90)")
        names = self.material_names()
        unknown = [m for m in names if m not in STUDIO_MATERIALS]
        if unknown or not 1 <= len(names) <= 8:
            raise DamcapError(f"--materials {self.materials!r}: give 1 to 8 of {', '.join(STUDIO_MATERIALS)}, comma-separated"
                              + (f" ({', '.join(unknown)} unknown)" if unknown else ""))


def ring_elevations_deg(mean_deg: float, rings: int, step_deg: float) -> tuple[float, ...]:
    """Elevations of ``rings`` camera rings ``step_deg`` apart, centred on ``mean_deg`` (degrees).

    >>> ring_elevations_deg(30.0, 2, 30.0), ring_elevations_deg(30.0, 1, 30.0), ring_elevations_deg(40.0, 3, 20.0)
    ((15.0, 45.0), (30.0,), (20.0, 40.0, 60.0))
    """
    return tuple(mean_deg + (k - (rings - 1) / 2) * step_deg for k in range(rings))


def board_albedo(half_size: float, saturation: float, seed: int, texels: int = BOARD_TEXELS) -> np.ndarray:
    """(texels, texels, 3) float32 albedo of the board: the procedural room pattern on the plane,
    its colours mixed toward their luminance by ``1 - saturation``."""
    u = (np.arange(texels) + 0.5) / texels
    x, z = np.meshgrid((u - 0.5) * 2 * half_size, (u - 0.5) * 2 * half_size)
    pts = np.stack([x, np.zeros_like(x), z], -1).reshape(-1, 3)
    rgb = room_albedo(pts, BOARD_TEXTURE_SCALE, seed).astype(np.float64)
    grey = rgb @ np.array([0.2126, 0.7152, 0.0722])
    out = grey[:, None] + saturation * (rgb - grey[:, None])
    return np.clip(out, 0.02, 0.95).reshape(texels, texels, 3).astype(np.float32)


def studio_object(opts: StudioOptions) -> tuple[Mesh, np.ndarray, np.ndarray]:
    """The object: (mesh in the unit sphere, (V, 3) vertex normals, (F,) material label per face)."""
    mesh = normalise_to_unit_sphere(read_mesh(opts.object), clean=True, fix_winding=True)
    normals = vertex_normals_area_weighted(mesh.vertices, mesh.triangles, SYNTH_NORMAL_EPS, SYNTH_ISOLATED_NORMAL)
    labels = material_labels(mesh, len(opts.material_names()), int(np.random.default_rng([opts.seed, 3]).integers(2**31)))
    return mesh, normals, labels


def _record(opts: StudioOptions, mesh: Mesh, labels: np.ndarray, env_scale: float, gain: float, median_factor: float) -> dict[str, Any]:
    names = opts.material_names()
    return {"options": asdict(opts), "object_file": Path(opts.object).name, "env_file": Path(opts.env).name,
            "env_scale": env_scale, "materials": [{"name": n, "bsdf": STUDIO_MATERIALS[n]} for n in names],
            "face_share": np.bincount(labels, minlength=len(names)).tolist(), "faces": len(mesh.triangles),
            # a photo's linear value (before the sRGB curve, 8-bit rounding and clipping at 1) is the
            # rendered radiance x exposure_gain x its EXIF factor (time x ISO / f-number^2)
            "exposure_gain": gain, "median_exposure_factor": median_factor}


def capture_radiance_scale(record: dict[str, Any]) -> float:
    """What a studio render is multiplied by to be in the units of the capture ``damcap
    reconstruct`` makes from its photos: a photo's linear value is radiance x ``exposure_gain`` x
    its EXIF factor, and reconstruct divides the factor out relative to the set's median one.

    >>> capture_radiance_scale({"exposure_gain": 2.0, "median_exposure_factor": 0.25})
    0.5
    """
    return float(record["exposure_gain"]) * float(record["median_exposure_factor"])


def env_scale(opts: StudioOptions) -> float:
    """What the environment map is multiplied by: 1 / its mean luminance.

    Raises:
        DamcapError: an unreadable or black map.
    """
    from damcap.synth.mitsuba_capture import env_mean_luminance

    env_pixels, _ = read_exr(opts.env)
    mean = env_mean_luminance(env_pixels)
    if not mean > 0:
        raise DamcapError(f"{opts.env}: environment map is black (mean luminance {mean})")
    return 1.0 / mean


def studio_scene(opts: StudioOptions, mesh: Mesh, normals: np.ndarray, face_material: np.ndarray, env_multiplier: float) -> Any:
    """The Mitsuba scene of a studio set with ``mesh`` as its object: face f is made of material
    ``opts.material_names()[face_material[f]]``, the board lies under the mesh's lowest point
    (world y) and the environment map is normalised as for the photos.

    Args:
        opts: the set's options (the environment file must be readable).
        mesh: the object, scene units (the set's objects fit in the unit sphere).
        normals: (V, 3) vertex normals.
        face_material: (F,) int index into the set's materials; a material no face uses is left out.
        env_multiplier: the environment map's scale (:func:`env_scale`).

    Raises:
        DamcapError: an index outside the materials.
    """
    from damcap.synth.mitsuba_render import Board, EnvLight, build_scene

    names = opts.material_names()
    if len(face_material) != len(mesh.triangles) or face_material.min() < 0 or face_material.max() >= len(names):
        raise DamcapError(f"face materials must index the set's {len(names)} materials ({', '.join(names)}), one per face")
    used = [k for k in range(len(names)) if (face_material == k).any()]
    board = Board(float(mesh.vertices[:, 1].min()), opts.board_size, board_albedo(opts.board_size, opts.board_saturation, opts.seed))
    return build_scene([submesh(mesh, normals, face_material == k) for k in used], [STUDIO_MATERIALS[names[k]] for k in used],
                       EnvLight(str(Path(opts.env).resolve()), opts.env_rotation_deg, env_multiplier), opts.max_depth, board)


def render_on_shape(opts: StudioOptions, mesh: Mesh, face_material: np.ndarray, world_from_cam: np.ndarray, intr: Intrinsics,
                    spp: int | None = None, seed: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A studio set's materials and light on another shape, path traced: the truth that an export
    of the set's DAMs onto that shape is compared against.

    Args:
        opts: the set's options (``transforms.json``'s ``damcap_studio.options``).
        mesh: the shape in the set's world (y up, standing on the board at its lowest point).
        face_material: (F,) the set's material index of each face.
        world_from_cam: (N, 4, 4) cameras, OpenGL axes, in the set's world.
        intr: their pinhole (square pixels).
        spp: samples per pixel (default: the set's).
        seed: the path tracer's seed (default: the set's); two seeds give two independent
            renders, whose difference is the truth's own noise.

    Returns:
        radiance_lin (N, H, W, 3) float32 as rendered (times :func:`capture_radiance_scale` for
        the capture's units) and alpha (N, H, W) float32; the board and background are rendered too.
    """
    from damcap.synth.mitsuba_render import pass_sample_counts, render_view, select_variant, set_render_threads

    select_variant("auto")
    set_render_threads(os.cpu_count() or 2)
    normals = vertex_normals_area_weighted(mesh.vertices, mesh.triangles, SYNTH_NORMAL_EPS, SYNTH_ISOLATED_NORMAL)
    scene = studio_scene(opts, mesh, normals, np.asarray(face_material, np.int64), env_scale(opts))
    passes = pass_sample_counts(spp or opts.spp, intr.w, intr.h)
    seed = opts.seed if seed is None else seed
    out = [render_view(scene, m, intr, passes, [seed * 100_003 + 7 * k + j for j in range(len(passes))])
           for k, m in enumerate(np.asarray(world_from_cam, np.float64))]
    return np.stack([r for r, _ in out]), np.stack([a for _, a in out])


def make_studio_photos(out: str | os.PathLike, opts: StudioOptions, progress: Callable[[int, int], None] | None = None) -> list[str]:
    """Render the photo set of ``opts`` into ``out`` (see the module docstring); returns the photo names.

    Raises:
        DamcapError: bad options or input files; ``out`` holds another command's photos.
    """
    from damcap.synth.mitsuba_render import pass_sample_counts, render_view, select_variant, set_render_threads

    opts.validate()
    out = Path(out)
    marker = out / PARTIAL_MARKER
    record_opts = json.dumps(asdict(opts), sort_keys=True)
    if marker.is_file() and marker.read_text() != record_opts:
        raise DamcapError(f"{out}: holds an interrupted synth-studio run with other options; choose a new folder or rerun those options")
    if not marker.is_file():
        # a run killed while writing the marker left only its temporary file: the folder is still new
        left = [p for p in out.iterdir() if not fnmatch.fnmatchcase(p.name, f".{marker.stem}.*.tmp{marker.suffix}")] \
            if out.exists() else []
        if left:
            raise DamcapError(f"{out}: not empty; choose a new folder")
        write_text_atomic(marker, record_opts)  # first, whole or not at all: a run killed after it leaves a folder its rerun resumes
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "masks").mkdir(parents=True, exist_ok=True)
    mesh, normals, labels = studio_object(opts)
    names = opts.material_names()
    empty = [names[k] for k in range(len(names)) if not (labels == k).any()]
    if empty:
        raise DamcapError(f"{opts.object}: the region(s) of {', '.join(empty)} got no faces (mesh too coarse?); try another --seed")
    select_variant("auto")
    set_render_threads(os.cpu_count() or 2)
    env_multiplier = env_scale(opts)
    scene = studio_scene(opts, mesh, normals, labels, env_multiplier)
    cams = orbit_cameras(opts.views, opts.distance, ring_elevations_deg(opts.elevation_deg, opts.rings, opts.ring_step_deg),
                         jitter_deg=opts.jitter_deg, seed=opts.seed)
    intr = default_intrinsics(opts.size)
    exposures = exposure_series(opts.views, opts.seed)
    median_factor = float(np.median([e.factor for e in exposures]))
    spp = pass_sample_counts(opts.spp, intr.w, intr.h)
    rc = MeshRaycaster(replace(mesh, vertex_normals=normals))
    gain_file = out / ".studio_gain.json"  # the exposure is set on the first photo; a resumed run reuses it
    gain = json.loads(gain_file.read_text())["gain"] if gain_file.is_file() else None
    photos, frames = [], []
    for k, (m, ex) in enumerate(zip(cams, exposures)):
        name = f"IMG_{k:04d}"
        photos.append(f"{name}.jpg")
        frames.append({"file_path": f"images/{name}.jpg", "mask_path": f"masks/{name}.png", "transform_matrix": m.tolist()})
        if (out / "images" / f"{name}.jpg").is_file() and (out / "masks" / f"{name}.png").is_file() and gain is not None:
            if progress:
                progress(k + 1, opts.views)
            continue
        rad, _ = render_view(scene, m, intr, spp, [opts.seed * 100_003 + k * 101 + j for j in range(len(spp))])
        if gain is None:
            gain = WHITE_POINT / max(float(np.percentile(rad, 99.5)) * median_factor, 1e-12)
            write_json_atomic(gain_file, {"gain": gain})
        write_jpeg(out / "images" / f"{name}.jpg", display_srgb8(rad, gain * ex.factor), ex)
        cover = rc.buffers(m, intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h, supersample=4).coverage
        write_png(out / "masks" / f"{name}.png", np.where(cover > 0.5, 255, 0).astype(np.uint8))
        if progress:
            progress(k + 1, opts.views)
    write_json_atomic(out / "transforms.json", {"camera_model": "OPENCV", **intr.to_json(), "frames": frames,
                                                "damcap_studio": _record(opts, mesh, labels, env_multiplier, float(gain), median_factor)})
    marker.unlink()
    gain_file.unlink(missing_ok=True)
    return photos
