"""``damcap view``: one self-contained HTML page (WebGL 2, no libraries) showing a mesh shaded by a
DAM in real time with orbit controls. The DAM runs in the fragment shader (:mod:`.glsl`)."""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass, field
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


def viewer_html(model: DeepAppearanceMap, mesh: Mesh, exposure_scale: float, camera: ViewerCamera = ViewerCamera(), title: str = "") -> str:
    """The page's HTML text.

    Args:
        model: the DAM (evaluated in the shader).
        mesh: the shape, already scaled into the unit sphere.
        exposure_scale: linear radiance multiplier before sRGB encoding (as ``display_srgb8``).
        camera: the initial view.
        title: a caption.
    """
    data = {
        "mesh": {
            "positions": _b64(mesh.vertices.astype("<f4")),
            "normals": _b64(mesh.vertex_normals.astype("<f4")),
            "indices": _b64(mesh.triangles.astype("<u4")),
        },
        "camera": {"azimuth_deg": camera.azimuth_deg, "elevation_deg": camera.elevation_deg,
                   "distance": camera.distance, "fov_deg": camera.fov_deg},
        "exposure_scale": float(exposure_scale),
        "title": title,
    }
    template = resources.files("damcap.export").joinpath("viewer_template.html").read_text(encoding="utf-8")
    return template.replace("/*__DAM_GLSL__*/", glsl_source(model)).replace("/*__DATA__*/", json.dumps(data))


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
