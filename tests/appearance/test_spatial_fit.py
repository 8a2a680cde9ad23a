"""--spatial on closed-form spheres: kept where the surface has a texture, not where it has none."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from damcap.appearance.fit import FitOptions, fit_dam
from damcap.appearance.spatial_fit import choose_spatial, mean_dssim, training_footprint
from damcap.appearance.views import ViewData, samples_of
from damcap.common.capture_folder import FrameData
from damcap.common.errors import DamcapError
from damcap.synth.closed_form import ClosedFormOptions, render_closed_form


def _log_albedo(position_world: np.ndarray) -> np.ndarray:
    """(..., 3) a smooth RGB pattern over the unit sphere (print-like bands)."""
    x, y, z = position_world[..., 0], position_world[..., 1], position_world[..., 2]
    return np.stack([0.6 * np.sin(12 * x + 1), 0.5 * np.cos(10 * z), 0.4 * np.sin(9 * y + 6 * x)], -1)


def _views(textured: bool) -> tuple[list[ViewData], list[ViewData]]:
    """Sphere under one light, 16 views at 48 px on a ring; every other view trains."""
    cams, _, frames, _ = render_closed_form(ClosedFormOptions(views=16, resolution=48, train_views=8, seed=3, supersample=1))
    views = []
    for k, (m, f) in enumerate(zip(cams, frames)):
        rad = f.radiance_lin * np.exp(_log_albedo(f.position_world)).astype(np.float32) if textured else f.radiance_lin
        views.append(ViewData(f"v{k}", FrameData(rad, f.normal_world, f.position_world, f.coverage), m))
    return views[::2], views[1::2]


@pytest.fixture(scope="module")
def fitted():
    out = {}
    for textured in (True, False):
        train, test = _views(textured)
        # the uniform sphere gets the default steps: a DAM fitted less leaves errors an albedo
        # over the sphere (where position = normal) can take up, and auto then rightly keeps it
        opts = FitOptions(steps=400 if textured else FitOptions.steps, seed=0, spatial="off", normal_refine="off")
        out[textured] = (train, test, fit_dam(samples_of(train), opts).model, opts)
    return out


@pytest.mark.slow
def test_auto_keeps_the_albedo_of_a_textured_surface_and_it_cuts_novel_view_error(fitted):
    train, test, model, opts = fitted[True]
    d = choose_spatial(model, train, replace(opts, spatial="auto"))
    assert d.kept and d.model.spatial is not None
    assert d.heldout_dssim["albedo"] < 0.8 * d.heldout_dssim["off"]
    without, with_albedo = mean_dssim(model, test), mean_dssim(d.model, test)
    assert with_albedo < 0.25 * without, (without, with_albedo)
    # the voxel follows the pixels' footprint on the surface
    assert d.voxel_size == pytest.approx(opts.spatial_voxel_px * training_footprint(train))
    rec = d.record()
    assert rec["kept"] and rec["voxels"] == d.model.spatial.keys.size


def test_auto_leaves_a_uniform_surface_to_the_dam(fitted):
    train, test, model, opts = fitted[False]
    d = choose_spatial(model, train, replace(opts, spatial="auto"))
    assert not d.kept and d.model.spatial is None
    assert d.heldout_dssim["off"] - d.heldout_dssim["albedo"] < opts.spatial_min_gain_abs
    assert "not kept" in d.summary()


def test_albedo_is_applied_when_asked_and_off_returns_the_dam_alone(fitted):
    train, _, model, opts = fitted[False]
    forced = choose_spatial(model, train, replace(opts, spatial="albedo"))
    assert forced.kept and forced.model.spatial is not None and not forced.heldout_dssim
    off = choose_spatial(forced.model, train, opts)  # spatial='off' drops a factor the model carries
    assert off.model.spatial is None and off.summary() == "spatial factor: off"


def test_auto_needs_held_out_views(fitted):
    train, _, model, opts = fitted[True]
    with pytest.raises(DamcapError, match="held-out training views"):
        choose_spatial(model, train, replace(opts, spatial="auto", holdout_views=0))


def test_fit_command_writes_the_factor_and_refuses_it_with_a_target(small_capture, tmp_path, capsys):
    from damcap.appearance.dam_file import load_dam
    from tests.conftest import assert_one_line_error, run_cli

    out = tmp_path / "m.dam"
    code, _, err = run_cli(["fit", small_capture, "-o", out, "--steps", "60", "--spatial", "albedo", "--normal-refine", "off"], capsys)
    assert code == 0 and "spatial factor: albedo texture of" in err, err
    model, meta = load_dam(out)
    assert model.spatial is not None and meta["format_version"] == 2
    assert meta["provenance"]["spatial"]["kept"] and meta["provenance"]["options"]["spatial"] == "albedo"
    code, stdout, err = run_cli(["evaluate", small_capture, "--model", out], capsys)
    assert code == 0 and "DAM" in stdout, err
    code, _, err = run_cli(["fit", small_capture, "-o", tmp_path / "t.dam", "--target-dssim", "0.5", "--spatial", "auto"], capsys)
    assert_one_line_error(code, err, "--target-dssim sizes the DAM alone")
    code, _, err = run_cli(["fit", small_capture, "-o", tmp_path / "t.dam", "--spatial", "texture"], capsys)
    assert_one_line_error(code, err, "--spatial", "texture")
