"""damcap: from photos of a real object to a reusable model of its appearance, a Deep Appearance
Map (Maximov, Leal-Taixé, Fritz, Ritschel, ICCV 2019).

The stages live in subpackages (``damcap.capture``, ``damcap.reconstruct``, ``damcap.appearance``,
``damcap.export``, ``damcap.synth``, ``damcap.common``, ``damcap.cli``) and pass data to each other
only through capture folders (docs/capture-format.md). This module is the short public API for
scripts: the capture folder, fitting, saving and loading a DAM, rendering and evaluating. Names
are imported on first use: ``import damcap`` is cheap, and importing a stage (``damcap.common``)
does not load the others through it.

Capture folders (:mod:`damcap.common.capture_folder`):
    ``read_capture(root) -> Capture``, ``read_frame(capture, frame) -> FrameData``,
    ``write_capture(capture, frames_data)``, ``inspect_capture(root) -> CaptureSummary``.
Views and pixels of a split (:mod:`damcap.appearance.views`):
    ``load_views(capture, "train") -> list[ViewData]``, ``samples_of(views) -> PixelSamples``.
Fit, save, load (:mod:`damcap.appearance.fit`, :mod:`damcap.appearance.dam_file`):
    ``fit_dam(samples, FitOptions()) -> FitResult`` (``.model`` is a :class:`DeepAppearanceMap`),
    ``save_dam(path, model, colorspace=..., made_by=...)``, ``load_dam(path) -> (model, metadata)``.
Render and evaluate (:mod:`damcap.appearance.render`, :mod:`damcap.appearance.evaluate`):
    ``render_frame(model, frame_data, camera_centre_world) -> (H, W, 3) linear radiance``,
    ``evaluate_split(train_views, target_views, {"name": model}) -> {method: MethodScores}``,
    ``dssim(reference_lin, prediction_lin, coverage)`` (the metric every number in damcap uses).
Errors: every user mistake raises :class:`DamcapError` with a one-line message.

A fit from a script (what ``damcap fit`` does, without the progress bar and the checkpoint)::

    import damcap
    capture = damcap.read_capture("my_capture")
    train = damcap.load_views(capture, "train")
    result = damcap.fit_dam(damcap.samples_of(train), damcap.FitOptions(steps=2000))
    damcap.save_dam("model.dam", result.model, colorspace=capture.colorspace, made_by="fit")
    scores = damcap.evaluate_split(train, damcap.load_views(capture, "test"), {"DAM": result.model})

>>> import damcap
>>> isinstance(damcap.__version__, str)
True
>>> damcap.read_capture.__module__
'damcap.common.capture_folder'
"""

from __future__ import annotations

import os as _os

# OpenMP's worker threads sleep at a barrier instead of spinning (unless the user set the policy):
# with torch on both cores of a 2-core machine that another job shares, spinning made a 200-step fit
# take 166 s instead of 4.6 s (docs/model.md, "Speed and memory"). Set before torch loads.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import importlib
from typing import Any

#: public name -> the module that defines it (imported on first access, PEP 562)
_API = {
    "DamcapError": "damcap.common.errors",
    "Capture": "damcap.common.capture_folder",
    "Frame": "damcap.common.capture_folder",
    "FrameData": "damcap.common.capture_folder",
    "read_capture": "damcap.common.capture_folder",
    "read_frame": "damcap.common.capture_folder",
    "write_capture": "damcap.common.capture_folder",
    "inspect_capture": "damcap.common.capture_folder",
    "ViewData": "damcap.appearance.views",
    "load_views": "damcap.appearance.views",
    "samples_of": "damcap.appearance.views",
    "DamArchitecture": "damcap.appearance.dam",
    "DeepAppearanceMap": "damcap.appearance.dam",
    "FitOptions": "damcap.appearance.fit",
    "FitResult": "damcap.appearance.fit",
    "fit_dam": "damcap.appearance.fit",
    "save_dam": "damcap.appearance.dam_file",
    "load_dam": "damcap.appearance.dam_file",
    "render_frame": "damcap.appearance.render",
    "evaluate_split": "damcap.appearance.evaluate",
    "MethodScores": "damcap.appearance.evaluate",
    "dssim": "damcap.appearance.metrics",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str) -> Any:
    if name == "__version__":
        from damcap.common.version import package_version

        value = package_version()
    elif name in _API:
        value = getattr(importlib.import_module(_API[name]), name)
    else:
        raise AttributeError(f"module 'damcap' has no attribute {name!r}")
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
