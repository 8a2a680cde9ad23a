"""``damcap view``: one self-contained HTML page (WebGL 2, no libraries) showing a mesh shaded by
DAMs in real time with orbit controls: one DAM per part of the mesh, each in its own fragment
shader (:mod:`.glsl`)."""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass, field
from typing import Sequence
from importlib import resources

import numpy as np

from damcap.appearance.dam import DeepAppearanceMap
from damcap.common.mesh import Mesh
from damcap.common.validate import AZIMUTH_DEG, CAMERA_DISTANCE, ELEVATION_DEG, FOV_DEG

from damcap.export.glsl import glsl_source


@dataclass(frozen=True)
class ViewerCamera:
    """The page's initial orbit camera (same convention as :class:`export.turntable.OrbitOptions`)."""

    azimuth_deg: float = field(default=30.0, metadata={**AZIMUTH_DEG, "cli_flag": "--azimuth"})
    """initial camera azimuth, degrees"""
    elevation_deg: float = field(default=20.0, metadata={**ELEVATION_DEG, "cli_flag": "--elevation"})
    """initial camera elevation, degrees"""
    distance: float = field(default=3.0, metadata=CAMERA_DISTANCE)
    """camera distance from the origin (the mesh is scaled into the unit sphere)"""
    fov_deg: float = field(default=45.0, metadata={**FOV_DEG, "cli_flag": "--fov"})
    """full field of view, degrees"""


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")


def part_ranges(triangle_part: np.ndarray, parts: int) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Triangles ordered by part, and each part's range in that order.

    Args:
        triangle_part: (T,) int part index per triangle, in [0, parts).
        parts: number of parts (models).

    Returns:
        ((T,) int64 triangle order, stable within a part; per part (first triangle, count)).

    >>> part_ranges(np.array([1, 0, 1, 0, 0]), 3)
    (array([1, 3, 4, 0, 2]), [(0, 3), (3, 2), (5, 0)])
    """
    part = np.asarray(triangle_part, np.int64)
    if len(part) and (part.min() < 0 or part.max() >= parts):
        raise ValueError(f"part indices must lie in [0, {parts}), got {int(part.min())}..{int(part.max())}")
    counts = np.bincount(part, minlength=parts)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return np.argsort(part, kind="stable"), [(int(f), int(c)) for f, c in zip(first, counts)]


def viewer_html(models: DeepAppearanceMap | Sequence[DeepAppearanceMap], mesh: Mesh, exposure_scale: float,
                camera: ViewerCamera = ViewerCamera(), title: str = "", triangle_part: np.ndarray | None = None,
                part_names: Sequence[str] | None = None) -> str:
    """The page's HTML text: part k of the mesh drawn with ``models[k]``, each in its own shader.

    Args:
        models: the DAM, or one DAM per part (each evaluated in its own fragment shader).
        mesh: the shape, already scaled into the unit sphere.
        exposure_scale: linear radiance multiplier before sRGB encoding (as ``display_srgb8``), one for all parts.
        camera: the initial view.
        title: a caption.
        triangle_part: (T,) part (model index) per triangle; None: every triangle is part 0.
        part_names: a name per part (the page's ``DATA.parts[k].name``); default 'part k'.
    """
    dams = [models] if isinstance(models, DeepAppearanceMap) else list(models)
    if not dams:
        raise ValueError("viewer_html needs at least one model")
    part = np.zeros(len(mesh.triangles), np.int64) if triangle_part is None else np.asarray(triangle_part)
    if part.shape != (len(mesh.triangles),):
        raise ValueError(f"one part index per triangle expected, got shape {part.shape} for {len(mesh.triangles)} triangles")
    names = [f"part {k}" for k in range(len(dams))] if part_names is None else [str(n) for n in part_names]
    if len(names) != len(dams):
        raise ValueError(f"{len(names)} part names for {len(dams)} models")
    order, ranges = part_ranges(part, len(dams))
    data = {
        "mesh": {
            "positions": _b64(mesh.vertices.astype("<f4")),
            "normals": _b64(mesh.vertex_normals.astype("<f4")),
            "indices": _b64(mesh.triangles[order].astype("<u4")),
        },
        # part k: triangles [first, first + count) of the index buffer, drawn with dam_glsl[k]
        "parts": [{"name": n, "first": f, "count": c} for n, (f, c) in zip(names, ranges)],
        "dam_glsl": [glsl_source(d) for d in dams],
        "camera": {"azimuth_deg": camera.azimuth_deg, "elevation_deg": camera.elevation_deg,
                   "distance": camera.distance, "fov_deg": camera.fov_deg},
        "exposure_scale": float(exposure_scale),
        "title": title,
    }
    template = resources.files("damcap.export").joinpath("viewer_template.html").read_text(encoding="utf-8")
    # "</" never appears inside the script (GLSL has none; titles are escaped), so the JSON cannot end it
    return template.replace("/*__DATA__*/", json.dumps(data).replace("</", "<\\/"))


def page_server(page: bytes, name: str, port: int = 0, host: str = "127.0.0.1"):
    """An HTTP server (not yet serving) that answers ``GET /NAME`` with ``page``.

    Only that page is served: every other path (``/`` too) is 404, so nothing else in the page's folder is
    exposed. Bound to ``host`` (loopback by default); ``port`` 0 picks a free port (read it from
    ``server.server_address[1]``). Use as a context manager and call ``serve_forever()``.
    """
    import http.server
    from urllib.parse import unquote, urlsplit

    paths = {"/" + name}

    class PageHandler(http.server.BaseHTTPRequestHandler):
        def _answer(self, body: bool) -> None:
            if unquote(urlsplit(self.path).path) not in paths:
                self.send_error(404, "not found")
                return
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(page)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            if body:
                self.wfile.write(page)

        def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
            self._answer(True)

        def do_HEAD(self) -> None:  # noqa: N802
            self._answer(False)

        def log_message(self, format: str, *args) -> None:  # noqa: A002 (quiet: no per-request lines)
            pass

    return http.server.ThreadingHTTPServer((host, port), PageHandler)
