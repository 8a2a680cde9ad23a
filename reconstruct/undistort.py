"""Photo cameras with lens distortion, and resampling a photo once into a pinhole image.

A :class:`PhotoCamera` holds a photo's camera in COLMAP's terms: the pinhole part (focal lengths,
principal point) and either OpenCV's distortion coefficients (k1, k2, p1, p2, k3, k4, k5, k6;
COLMAP's ``FULL_OPENCV``, of which SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV are
special cases) or, for COLMAP's other models (the fisheyes, FOV, thin prism, division), the
model's name and parameter vector. Where each pinhole pixel samples the photo is computed by
pycolmap's implementation of the model (``Camera.img_from_cam``), so every model COLMAP knows is
undistorted the same way. Image coordinates put pixel (i, j)'s centre at (j + 0.5, i + 0.5), as
COLMAP and the capture contract do; OpenCV puts it at (j, i), which :func:`undistort_maps`
accounts for.

Undistortion and resizing happen together, in one resampling of the photo (box-filtered first
when it shrinks by more than ``AREA_PRESHRINK``). The pinhole keeps the photo's focal length and
principal point, so a wide fisheye loses what lies beyond the pinhole's field of view.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from damcap.common.capture_folder import Intrinsics
from damcap.common.errors import DamcapError

#: COLMAP camera models and the names of their parameters (in COLMAP's order)
COLMAP_MODEL_PARAMS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
#: COLMAP models that have no pinhole image (a panorama): refused
NON_PINHOLE_MODELS = ("EQUIRECTANGULAR",)
#: a photo shrinking by a factor below this is box-filtered (cv2.INTER_AREA) before remapping
AREA_PRESHRINK = 0.75


@dataclass(frozen=True)
class PhotoCamera:
    """A photo's camera: pinhole plus OpenCV distortion, pixels, centres at +0.5."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = (0.0,) * 8
    """(k1, k2, p1, p2, k3, k4, k5, k6), OpenCV's / COLMAP FULL_OPENCV's order (when ``model`` is '')"""
    model: str = ""
    """'' for the OpenCV family above, else a COLMAP model outside it (e.g. 'OPENCV_FISHEYE')"""
    params: tuple[float, ...] = ()
    """that model's COLMAP parameter vector (its focal lengths and principal point are fx, fy, cx, cy)"""

    @property
    def is_pinhole(self) -> bool:
        return not self.model and not any(self.distortion)

    def colmap(self) -> tuple[str, list[float]]:
        """(COLMAP model name, parameters) of this camera."""
        if self.model:
            return self.model, list(self.params)
        return "FULL_OPENCV", [self.fx, self.fy, self.cx, self.cy, *self.distortion]

    def scaled(self, width: int, height: int) -> "PhotoCamera":
        """The same camera for the photo resized to ``width`` x ``height`` (distortion unchanged)."""
        sx, sy = width / self.width, height / self.height
        out = replace(self, width=width, height=height, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy)
        if self.model:
            cam = colmap_camera(self)
            cam.rescale(int(width), int(height))
            out = replace(out, params=tuple(float(v) for v in cam.params))
        return out

    def to_json(self) -> dict:
        d: dict = {"w": self.width, "h": self.height, "fl_x": self.fx, "fl_y": self.fy, "cx": self.cx, "cy": self.cy}
        if self.model:
            d.update({"camera_model": self.model, "colmap_params": list(self.params)})
        else:
            d.update({k: v for k, v in zip(DISTORTION_KEYS, self.distortion) if v})
        return d


def colmap_camera(camera: PhotoCamera):
    """The camera as a ``pycolmap.Camera`` (its model implements the projection)."""
    from damcap.reconstruct.colmap.database import import_pycolmap

    pycolmap = import_pycolmap()
    model, params = camera.colmap()
    return pycolmap.Camera(model=model, width=int(camera.width), height=int(camera.height), params=params)


def camera_from_colmap(model: str, width: int, height: int, params: np.ndarray | tuple[float, ...]) -> PhotoCamera:
    """A :class:`PhotoCamera` from a COLMAP camera model name and parameter vector.

    Raises:
        DamcapError: a model with no pinhole image (a panorama) or unknown to pycolmap, or the
            wrong parameter count.
    """
    p = [float(v) for v in params]
    names = COLMAP_MODEL_PARAMS.get(model)
    if names is not None:
        if len(p) != len(names):
            raise DamcapError(f"camera model {model} needs {len(names)} parameters ({', '.join(names)}), got {len(p)}")
        v = dict(zip(names, p))
        fx = v.get("fx", v.get("f"))
        fy = v.get("fy", v.get("f"))
        dist = tuple(v.get(k, 0.0) for k in DISTORTION_KEYS)
        return PhotoCamera(int(width), int(height), float(fx), float(fy), v["cx"], v["cy"], dist)  # type: ignore[arg-type]
    if model in NON_PINHOLE_MODELS:
        raise DamcapError(f"camera model {model} has no pinhole image (a panorama); damcap needs perspective photos")
    from damcap.reconstruct.colmap.database import import_pycolmap

    pycolmap = import_pycolmap()
    try:
        cam = pycolmap.Camera(model=model, width=int(width), height=int(height), params=p)
    except Exception:  # noqa: BLE001 (pycolmap raises several types for an unknown name)
        cam = None
    if cam is None or cam.model.name != model:
        raise DamcapError(f"camera model {model!r} is not a COLMAP camera model")
    if not cam.verify_params():
        raise DamcapError(f"camera model {model} needs the parameters {cam.params_info}, got {len(p)}")
    return PhotoCamera(int(width), int(height), float(cam.focal_length_x), float(cam.focal_length_y), float(cam.principal_point_x),
                       float(cam.principal_point_y), model=model, params=tuple(p))


def pinhole_for(camera: PhotoCamera, max_size: int | None = None) -> Intrinsics:
    """The pinhole camera a photo is resampled into: same focal lengths and principal point,
    scaled so that the longer side is at most ``max_size`` pixels.

    Args:
        camera: the photo's camera.
        max_size: longest side of the result, pixels (None = keep the photo's size).
    """
    s = 1.0 if not max_size else min(1.0, max_size / max(camera.width, camera.height))
    w, h = max(1, round(camera.width * s)), max(1, round(camera.height * s))
    sx, sy = w / camera.width, h / camera.height
    return Intrinsics(camera.fx * sx, camera.fy * sy, camera.cx * sx, camera.cy * sy, w, h)


def undistort_maps(camera: PhotoCamera, target: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of the pinhole ``target`` samples the distorted photo, for ``cv2.remap``.

    Returns:
        map_x, map_y: (h, w) float32 source coordinates in OpenCV's convention (pixel centres
        at integers, i.e. the contract's coordinate minus 0.5).
    """
    j, i = np.meshgrid(np.arange(target.w, dtype=np.float64) + 0.5, np.arange(target.h, dtype=np.float64) + 0.5)
    x = (j - target.cx) / target.fl_x
    y = (i - target.cy) / target.fl_y
    if camera.is_pinhole:
        u, v = camera.fx * x + camera.cx, camera.fy * y + camera.cy
    else:
        rays = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], 1)
        uv = np.asarray(colmap_camera(camera).img_from_cam(rays, check_cheirality=False), np.float64).reshape(target.h, target.w, 2)
        uv[~np.isfinite(uv)] = -1e6  # no image of that ray: outside the photo (black)
        u, v = uv[..., 0], uv[..., 1]
    return (u - 0.5).astype(np.float32), (v - 0.5).astype(np.float32)


def resample_to_pinhole(image: np.ndarray, camera: PhotoCamera, target: Intrinsics) -> np.ndarray:
    """Undistort and resize an image in one resampling (bilinear; box-filtered first when shrinking).

    Args:
        image: (H, W) or (H, W, C) float32 of the photo's size (linear radiance or a mask).
        camera: the photo's camera (its width/height must match ``image``).
        target: the pinhole camera to produce.

    Returns:
        (target.h, target.w[, C]) float32; 0 where the target sees outside the photo.
    """
    import cv2

    img = np.asarray(image, dtype=np.float32)
    if img.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"image is {img.shape[1]}x{img.shape[0]}, camera is {camera.width}x{camera.height}")
    scale = min(target.w / camera.width, target.h / camera.height)
    if scale < AREA_PRESHRINK:
        w, h = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        camera = camera.scaled(w, h)
    if camera.is_pinhole and (camera.width, camera.height) == (target.w, target.h) and np.allclose(
            (camera.fx, camera.fy, camera.cx, camera.cy), (target.fl_x, target.fl_y, target.cx, target.cy), atol=1e-9):
        return np.ascontiguousarray(img)
    map_x, map_y = undistort_maps(camera, target)
    out = cv2.remap(img, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.astype(np.float32)
