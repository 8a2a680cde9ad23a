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

from damcap.export.glsl import glsl_source


@dataclass(frozen=True)
class ViewerCamera:
    """The page's initial orbit camera (same convention as :class:`export.turntable.OrbitOptions`)."""

    azimuth_deg: float = field(default=30.0, metadata={"cli_flag": "--azimuth"})
    """initial camera azimuth, degrees"""
    elevation_deg: float = field(default=20.0, metadata={"cli_flag": "--elevation"})
    """initial camera elevation, degrees"""
    distance: float = 3.0
    """camera distance from the origin (the mesh is scaled into the unit sphere)"""
    fov_deg: float = field(default=45.0, metadata={"cli_flag": "--fov"})
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
