"""common/validate.py: NaN-proof, bounded checks of numbers from files and options; every options
dataclass refuses NaN and inf in each of its float fields, naming the field."""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest

from damcap.appearance.fit import FitOptions
from damcap.appearance.hyper.train import HyperTrainOptions
from damcap.appearance.segment.options import SegmentOptions
from damcap.capture.hdr import HdrOptions
from damcap.capture.linearize import LinearizeOptions
from damcap.common.errors import DamcapError
from damcap.common.validate import (
    MAX_IMAGE_SIDE, Range, bounded_int, check_ranges, check_value, finite_in, in_range, load_json_file, loads_json,
    machine_memory_bytes, number_kind, require_memory, require_resolution,
)
from damcap.export.turntable import ExportOptions, OrbitOptions
from damcap.reconstruct.pipeline import ReconstructOptions
from damcap.synth.mitsuba_capture import SynthOptions
from damcap.synth.photos import PhotoSetOptions

OPTIONS_CLASSES = (HdrOptions, LinearizeOptions, ReconstructOptions, FitOptions, HyperTrainOptions, SegmentOptions,
                   OrbitOptions, ExportOptions, SynthOptions, PhotoSetOptions)


def _float_fields(cls):
    return [f for f in dataclasses.fields(cls) if "float" in str(f.type) and "list" not in str(f.type)]


FLOAT_CASES = [(cls, f, bad) for cls in OPTIONS_CLASSES for f in _float_fields(cls)
               for bad in (math.nan, math.inf, -math.inf, 1e39)]


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------

class TestFiniteIn:
    def test_float64_finite_but_float32_infinite(self):
        assert finite_in(1e39, "float64", "scale") == 1e39
        with pytest.raises(DamcapError, match=r"a\.dam: scale must be a finite float32 number \(\|x\| <= 3\.403e\+38\), got 1e\+39"):
            finite_in(1e39, "float32", "scale", "a.dam")

    @pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, np.float64("nan"), "1.0", None, True, [1.0]])
    def test_refuses_non_finite_and_non_numbers(self, bad):
        with pytest.raises(DamcapError, match="scale must be"):
            finite_in(bad, "float32", "scale", "f.json")

    def test_accepts_numpy_and_ints(self):
        assert finite_in(np.float32(2.5), "float32", "x") == 2.5
        assert finite_in(3, "float16", "x") == 3.0
        with pytest.raises(DamcapError, match="float16"):
            finite_in(70000, "float16", "x")

    def test_huge_int_is_not_an_overflow_traceback(self):
        with pytest.raises(DamcapError, match="finite float64"):
            finite_in(10 ** 400, "float64", "x")


class TestBoundedInt:
    def test_bound_is_named(self):
        with pytest.raises(DamcapError, match=r"f\.dam: DAM width must be an integer in \[1, 4096\], got 1000000000000"):
            bounded_int(10 ** 12, 1, 4096, "DAM width", "f.dam")

    @pytest.mark.parametrize("bad", [0, -1, 5000, 2.5, math.nan, math.inf, "3", None, True])
    def test_refuses(self, bad):
        with pytest.raises(DamcapError, match=r"in \[1, 4096\]"):
            bounded_int(bad, 1, 4096, "width")

    def test_accepts_whole_floats_and_numpy_ints(self):
        assert bounded_int(3.0, 1, 4, "n") == 3
        assert bounded_int(np.int64(4), 1, 4, "n") == 4


class TestRange:
    @pytest.mark.parametrize("rng, inside, outside", [
        (Range(1, 10), [1, 5, 10], [0, 11, math.nan]),
        (Range(0, 1, lo_open=True), [1e-30, 0.5, 1], [0, -1e-30, 1.0000001, math.nan]),
        (Range(-90, 90, lo_open=True, hi_open=True), [-89.999, 0, 89.999], [-90, 90]),
        (Range(0, None), [0, 1e30], [-1e-30, math.nan]),
        (Range(None, 3, hi_open=True), [-1e30, 2.999], [3]),
    ])
    def test_contains_respects_open_and_closed_ends(self, rng, inside, outside):
        assert all(rng.contains(v) for v in inside)
        assert not any(rng.contains(v) for v in outside)

    def test_text_writes_whole_bounds_in_full(self):
        assert Range(1, 10 ** 9).text() == "[1, 1000000000]"
        assert Range(0, 1, lo_open=True).text() == "(0, 1]"
        assert Range(0, 0.02, lo_open=True).text() == "(0, 0.02]"
        assert Range(0, None).text() == ">= 0" and Range(0, None, lo_open=True).text() == "> 0"

    def test_in_range_keeps_other_metadata(self):
        meta = in_range(8, 64, cli_flag="--res")
        assert meta["cli_flag"] == "--res" and meta["range"] == Range(8, 64)

    @pytest.mark.parametrize("value, integer, shown, message", [
        (0, True, "0", "--n must be an integer in [1, 10], got 0"),
        ("abc", True, "abc", "--n must be an integer in [1, 10], got abc"),
        (True, True, None, "--n must be an integer in [1, 10], got True"),
        (1e300, False, "1e300", "--n must be a finite number in [1, 10], got 1e300"),  # inf in float32
        (math.nan, False, "nan", "--n must be a finite number in [1, 10], got nan"),
    ])
    def test_check_value_names_what_the_bound_and_the_value_as_typed(self, value, integer, shown, message):
        with pytest.raises(DamcapError) as e:
            check_value(value, Range(1, 10), integer=integer, what="--n", shown=shown)
        assert str(e.value) == message

    def test_check_value_without_a_range_still_refuses_non_finite_floats(self):
        assert check_value(3.4e38, None, integer=False, what="x") == 3.4e38
        with pytest.raises(DamcapError, match="x must be a finite number, got 1e39"):
            check_value(1e39, None, integer=False, what="x", shown="1e39")

    def test_number_kind(self):
        assert number_kind(int) is int and number_kind(float | None) is float
        assert number_kind(tuple[int, ...]) is int and number_kind(list[float] | None) is float
        assert number_kind(str) is None and number_kind(bool) is None


class TestMemory:
    def test_resolution_beyond_memory_names_the_gib(self):
        with pytest.raises(DamcapError, match=r"would need [\d.e+]+ GiB of memory; this machine allows"):
            require_resolution(60000, 60000, 4 * 1024, "a frame", "transforms.json")
        with pytest.raises(DamcapError, match=rf"\[1, {MAX_IMAGE_SIDE}\]"):
            require_resolution(10 ** 6, 1, 4, "a frame")
        assert require_resolution(64, 32, 4, "a frame") == (64, 32)

    def test_machine_memory_is_plausible(self):
        assert 2 ** 28 <= machine_memory_bytes() <= 2 ** 50
        require_memory(1024, "a small buffer")
        with pytest.raises(DamcapError, match="GiB"):
            require_memory(math.nan, "a NaN-sized buffer")


class TestJson:
    def test_deeply_nested_json_is_one_line_naming_the_file(self, tmp_path):
        path = tmp_path / "deep.json"
        path.write_text("[" * 100000)
        t0 = time.perf_counter()
        with pytest.raises(DamcapError, match=r"deep\.json: .* nested too deeply") as e:
            load_json_file(path, "pose file")
        assert time.perf_counter() - t0 < 2.0
        assert "\n" not in str(e.value)

    def test_size_limit_and_bad_json(self, tmp_path):
        path = tmp_path / "big.json"
        path.write_text("[" + "0," * 1000 + "0]")
        with pytest.raises(DamcapError, match=r"big\.json: .* larger than"):
            load_json_file(path, "record", max_bytes=100)
        assert len(load_json_file(path)) == 1001
        with pytest.raises(DamcapError, match="x.json: invalid JSON"):
            loads_json("{nope", "x.json")
        (tmp_path / "bin.json").write_bytes(b"\xff\xfe")
        with pytest.raises(DamcapError, match="bin.json: cannot read"):
            load_json_file(tmp_path / "bin.json")


# ---------------------------------------------------------------------------------------------
# options dataclasses
# ---------------------------------------------------------------------------------------------

class TestOptionsFloats:
    def test_every_class_has_float_fields_covered(self):
        assert all(_float_fields(cls) for cls in OPTIONS_CLASSES if cls is not ExportOptions)

    @pytest.mark.parametrize("cls", OPTIONS_CLASSES, ids=lambda c: c.__name__)
    def test_defaults_validate(self, cls):
        cls().validate()

    @pytest.mark.parametrize("cls, f, bad", FLOAT_CASES, ids=lambda v: getattr(v, "__name__", getattr(v, "name", repr(v))))
    def test_nan_and_inf_are_refused_naming_the_field(self, cls, f, bad):
        opts = dataclasses.replace(cls(), **{f.name: bad})
        with pytest.raises(DamcapError) as e:
            opts.validate()
        names = {"--" + f.name.replace("_", "-"), f.metadata.get("cli_flag", "")} - {""}
        assert any(n in str(e.value) for n in names), str(e.value)

    def test_check_ranges_sees_list_items(self):
        with pytest.raises(DamcapError, match="--exposures"):
            check_ranges(HdrOptions(exposures_s=[0.1, math.nan]))


COUNT_CASES = [
    (FitOptions, "steps"), (FitOptions, "batch_size"), (FitOptions, "width"), (FitOptions, "depth"),
    (HyperTrainOptions, "steps"), (HyperTrainOptions, "batch_size"), (HyperTrainOptions, "input_size"),
    (SegmentOptions, "materials"), (SegmentOptions, "steps"), (SegmentOptions, "batch_pixels"),
    (SegmentOptions, "psi_resolution"), (SegmentOptions, "psi_channels"), (SegmentOptions, "width"),
    (ReconstructOptions, "geometry.voxels"), (ReconstructOptions, "capture_size"), (ReconstructOptions, "supersample"),
    (ReconstructOptions, "train_views"), (ReconstructOptions, "geometry.poisson_depth"), (ReconstructOptions, "sfm.max_num_features"),
    (ReconstructOptions, "dense.max_views"),
    (OrbitOptions, "views"), (OrbitOptions, "resolution"), (OrbitOptions, "supersample"), (ExportOptions, "fps"),
    (SynthOptions, "views"), (SynthOptions, "spp"), (PhotoSetOptions, "views"), (PhotoSetOptions, "size"),
    (HdrOptions, "response_samples"),
]


def _replaced(options, name: str, value):
    """``options`` with the field ``name`` (``"geometry.voxels"``: a nested options dataclass's) set to ``value``."""
    head, _, rest = name.partition(".")
    return dataclasses.replace(options, **{head: _replaced(getattr(options, head), rest, value) if rest else value})


class TestOptionsCounts:
    @pytest.mark.parametrize("cls, name", COUNT_CASES, ids=lambda v: getattr(v, "__name__", v))
    @pytest.mark.parametrize("bad", [0, -1])
    def test_zero_and_negative_counts_are_refused(self, cls, name, bad):
        with pytest.raises(DamcapError):
            _replaced(cls(), name, bad).validate()

    @pytest.mark.parametrize("cls, name", COUNT_CASES, ids=lambda v: getattr(v, "__name__", v))
    def test_huge_counts_are_refused_quickly_naming_a_bound(self, cls, name):
        t0 = time.perf_counter()
        with pytest.raises(DamcapError, match=r"<= \d+|\[\-?\d+, \d+\]|between|GiB|must lie in") as e:
            _replaced(cls(), name, 10 ** 12).validate()
        assert time.perf_counter() - t0 < 2.0
        assert "\n" not in str(e.value)

    def test_hyper_channels_are_bounded(self):
        with pytest.raises(DamcapError, match=r"--channels must be an integer in \[1, 4096\]"):
            HyperTrainOptions(channels=(16, 10 ** 9)).validate()
        with pytest.raises(DamcapError, match=r"\[1, 16\]"):
            HyperTrainOptions(channels=(4,) * 40, input_size=4096).validate()

    def test_check_ranges_is_nan_proof_and_names_the_bound(self):
        with pytest.raises(DamcapError, match=r"^--steps must be an integer in \[1, 1000000000\], got 1000000000000$"):
            check_ranges(FitOptions(steps=10 ** 12))
        with pytest.raises(DamcapError, match=r"^--learning-rate must be a finite number in \(0, 10\], got nan$"):
            check_ranges(FitOptions(learning_rate=math.nan))
        with pytest.raises(DamcapError, match=r"^--steps must be an integer in"):
            check_ranges(FitOptions(steps=2.0))  # an int option given a float by a library caller



class TestCannotBeRight:
    def test_camera_centres(self):
        from damcap.common.validate import check_camera_centres

        ring = np.array([[3 * np.cos(a), 0.5, 3 * np.sin(a)] for a in np.linspace(0, 6, 10)])
        names = [f"f{k}" for k in range(10)]
        check_camera_centres(ring, names, "t.json")
        check_camera_centres(ring * 1e30, names, "t.json")  # any unit, while float32 holds it
        for far, needle in ((1e300, "f4: camera centre .* beyond float32's range"), (np.inf, "f4: camera centre .* beyond float32"),
                            (np.nan, "f4: camera centre .* beyond float32"), (3e6 * 3, r"f4: camera centre .* times farther .* at most 1e\+06")):
            bad = ring.copy()
            bad[4, 0] = far
            with pytest.raises(DamcapError, match=f"^t.json: {needle}"):
                check_camera_centres(bad, names, "t.json")
        bad = ring.copy()
        bad[4, 0] = 3e5 * 3  # 1e5 times the ring's scale: a distant camera, not an impossible one
        check_camera_centres(bad, names, "t.json")

    @pytest.mark.parametrize("name, head, says", [("a.exr", b"\x89PNG\r\n\x1a\n....", "PNG"), ("a.png", b"\xff\xd8\xff\xe0", "JPEG"),
                                                  ("a.exr", b"", "empty"), ("a.npy", b"{\"a\": 1}", "JSON text"),
                                                  ("a.exr", b"v/1\x00xx", "unknown")])
    def test_content_that_is_not_the_named_format(self, tmp_path, name, head, says):
        from damcap.common.validate import check_format

        (tmp_path / name).write_bytes(head)
        with pytest.raises(DamcapError, match=f"{name}: named .{name.split('.')[1]} but its content is {says}, not "):
            check_format(tmp_path / name)

    def test_content_of_the_named_format_passes(self, tmp_path):
        from damcap.common.validate import check_format

        for name, head in (("a.EXR", b"\x76\x2f\x31\x01\x02"), ("b.tif", b"MM\x00*"), ("c.hdr", b"#?RADIANCE"), ("d.jpeg", b"\xff\xd8\xff\xdb")):
            (tmp_path / name).write_bytes(head)
            check_format(tmp_path / name)

    def test_no_signal(self):
        from damcap.common.validate import no_signal, require_foreground

        assert no_signal(np.zeros((3, 3)), 0.0, None) == "black everywhere (largest value 0)"
        assert no_signal(np.full((3, 3), np.nan), 0.0, None).startswith("black everywhere (largest value nan")
        assert no_signal(np.full((3, 3), 5), 5, None) == "black everywhere (largest value 5)"
        assert no_signal(np.full((3, 3), 250), 5, 250) == "saturated everywhere (smallest value 250, saturation at 250)"
        assert no_signal(np.array([0, 6, 255]), 5, 250) is None
        assert no_signal(np.zeros(0), 0, None) == "empty (no pixel)"
        require_foreground([np.zeros((2, 2)), np.array([[0.0, 0.6]])], 0.5, "cap")
        with pytest.raises(DamcapError, match=r"^cap: no frame has a foreground pixel \(largest coverage 0.5, foreground is above 0.5\)"):
            require_foreground([np.zeros((2, 2)), np.full((2, 2), 0.5)], 0.5, "cap")
        with pytest.raises(DamcapError, match="largest coverage 0,"):
            require_foreground([], 0.5, "cap")
