"""`.dam` files: round trip, and refusal of anything else without executing it."""

from __future__ import annotations

import json
import os
import pickle
import time

import pytest
import torch
from safetensors.torch import load_file, save_file
from safetensors.torch import save as st_save

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
from damcap.appearance.dam_file import load_dam, save_dam
from damcap.common.errors import DamcapError


def test_round_trip(tmp_path):
    m = DeepAppearanceMap(DamArchitecture(width=16, depth=3, encoding="vnr"), radiance_scale=2.5)
    save_dam(tmp_path / "m.dam", m, colorspace="lin_rec709", made_by="fit", provenance={"seed": 3})
    back, meta = load_dam(tmp_path / "m.dam")
    assert back.arch == m.arch and back.radiance_scale == 2.5
    torch.testing.assert_close(back.get_flat_weights(), m.get_flat_weights())
    assert meta["made_by"] == "fit" and meta["provenance"] == {"seed": 3} and meta["format_version"] == 1


class _Exploit:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


def test_refuses_pickle_without_executing_it(tmp_path):
    marker = str(tmp_path / "pwned")
    (tmp_path / "evil.dam").write_bytes(pickle.dumps(_Exploit(marker)))
    torch.save({"weights": _Exploit(marker)}, tmp_path / "evil2.dam")
    for name in ("evil.dam", "evil2.dam"):
        with pytest.raises(DamcapError, match="not a damcap .dam model file"):
            load_dam(tmp_path / name)
    assert not os.path.exists(marker)


def test_refuses_random_bytes_and_truncation(tmp_path):
    (tmp_path / "rand.dam").write_bytes(os.urandom(4096))
    with pytest.raises(DamcapError, match="rand.dam: not a damcap .dam model file"):
        load_dam(tmp_path / "rand.dam")
    m = DeepAppearanceMap(DamArchitecture())
    save_dam(tmp_path / "ok.dam", m, colorspace="lin_rec709", made_by="fit")
    data = (tmp_path / "ok.dam").read_bytes()
    for cut in (4, 20, len(data) // 2, len(data) - 1):
        (tmp_path / "cut.dam").write_bytes(data[:cut])
        with pytest.raises(DamcapError, match="cut.dam"):
            load_dam(tmp_path / "cut.dam")


def test_refuses_foreign_safetensors_and_bad_metadata(tmp_path):
    (tmp_path / "plain.safetensors").write_bytes(st_save({"x": torch.zeros(3)}))
    with pytest.raises(DamcapError, match="without damcap metadata"):
        load_dam(tmp_path / "plain.safetensors")
    arch = DamArchitecture()
    meta = {"format_version": 7, "architecture": arch.to_json(), "radiance_scale": 1.0}
    (tmp_path / "new.dam").write_bytes(st_save({"weights": torch.zeros(arch.num_weights)}, metadata={"damcap": json.dumps(meta)}))
    with pytest.raises(DamcapError, match="newer than this damcap reads"):
        load_dam(tmp_path / "new.dam")
    meta["format_version"] = 1
    (tmp_path / "short.dam").write_bytes(st_save({"weights": torch.zeros(10)}, metadata={"damcap": json.dumps(meta)}))
    with pytest.raises(DamcapError, match="needs \\(3360,\\)"):
        load_dam(tmp_path / "short.dam")
    (tmp_path / "nan.dam").write_bytes(st_save({"weights": torch.full((3360,), float("nan"))}, metadata={"damcap": json.dumps(meta)}))
    with pytest.raises(DamcapError, match="NaN"):
        load_dam(tmp_path / "nan.dam")
    with pytest.raises(DamcapError, match="not found"):
        load_dam(tmp_path / "missing.dam")


class TestHostileMetadata:
    """Every number in a .dam's metadata is checked before anything is allocated from it."""

    @staticmethod
    def _write(path, arch_json, scale=1.0, weights=None):
        meta = {"format_version": 1, "architecture": arch_json, "radiance_scale": scale}
        w = torch.zeros(DamArchitecture().num_weights) if weights is None else weights
        path.write_bytes(st_save({"weights": w}, metadata={"damcap": json.dumps(meta)}))
        return path

    @pytest.mark.parametrize("field, value, bound", [("width", 10 ** 12, r"\[1, 4096\]"), ("depth", 10 ** 12, r"\[1, 64\]"),
                                                      ("width", 0, r"\[1, 4096\]"), ("depth", -3, r"\[1, 64\]")])
    def test_huge_or_bad_architecture_is_refused_quickly_naming_the_bound(self, tmp_path, field, value, bound):
        path = self._write(tmp_path / "hostile.dam", {**DamArchitecture().to_json(), field: value})
        assert path.stat().st_size < 20_000
        t0 = time.perf_counter()
        with pytest.raises(DamcapError, match=rf"hostile\.dam: invalid architecture: DAM {field} must be an integer in {bound}"):
            load_dam(path)
        assert time.perf_counter() - t0 < 2.0

    @pytest.mark.parametrize("field, value, shown", [("width", 8.0, "8.0"), ("depth", 2.0, "2.0"), ("width", True, "True"),
                                                      ("depth", False, "False"), ("width", 2.5, "2.5"), ("depth", "4", "'4'"),
                                                      ("width", None, "None"), ("depth", [2], r"\[2\]")])
    def test_an_integer_of_the_architecture_must_be_a_json_integer(self, tmp_path, field, value, shown):
        """32.0 is no layer width: a whole float once reached the GLSL exporter's slices as a float."""
        path = tmp_path / "m.dam"
        save_dam(path, DeepAppearanceMap(DamArchitecture(width=8, depth=2)), colorspace="lin_rec709", made_by="test")
        _, meta = load_dam(path)
        tensors = load_file(path)
        meta["architecture"][field] = value
        save_file(tensors, tmp_path / "hostile.dam", metadata={"damcap": json.dumps(meta)})
        with pytest.raises(DamcapError, match=rf"^\S*hostile\.dam: metadata 'architecture\.{field}' must be an integer, got {shown}$"):
            load_dam(tmp_path / "hostile.dam")

    def test_export_glsl_of_a_whole_float_width_is_one_line(self, tmp_path, capsys):
        from damcap.cli.main import main

        path = tmp_path / "m.dam"
        save_dam(path, DeepAppearanceMap(DamArchitecture(width=8, depth=2)), colorspace="lin_rec709", made_by="test")
        _, meta = load_dam(path)
        meta["architecture"]["width"] = 8.0
        save_file(load_file(path), tmp_path / "w.dam", metadata={"damcap": json.dumps(meta)})
        code = main(["export", str(tmp_path / "w.dam"), "--format", "glsl", "-o", str(tmp_path / "out")])
        out, err = capsys.readouterr()
        assert code == 2 and "Traceback" not in err and err.count("\n") == 1, err
        assert err == f"error: {tmp_path / 'w.dam'}: metadata 'architecture.width' must be an integer, got 8.0\n"
        assert not (tmp_path / "out").exists()

    def test_a_whole_float_given_in_python_is_kept_as_an_int(self):
        arch = DamArchitecture(width=8.0, depth=2.0)
        assert type(arch.width) is int and type(arch.depth) is int and arch == DamArchitecture(width=8, depth=2)
        assert DeepAppearanceMap(arch).get_flat_weights().shape == (DamArchitecture(width=8, depth=2).num_weights,)

    @pytest.mark.parametrize("scale", [1e39, -1e39, float("inf"), float("nan"), 0.0, -1.0, 1e-50, "x", None])
    def test_radiance_scale_must_be_finite_and_positive_in_float32(self, tmp_path, scale):
        path = self._write(tmp_path / "scale.dam", DamArchitecture().to_json(), scale=scale)
        with pytest.raises(DamcapError, match=r"scale\.dam: radiance_scale must be"):
            load_dam(path)

    def test_float64_weights_beyond_float32_are_refused(self, tmp_path):
        w = torch.zeros(DamArchitecture().num_weights, dtype=torch.float64)
        w[5] = 1e39
        path = self._write(tmp_path / "w64.dam", DamArchitecture().to_json(), weights=w)
        with pytest.raises(DamcapError, match=r"w64\.dam: weights contain NaN or inf"):
            load_dam(path)

    def test_integer_weights_are_refused(self, tmp_path):
        path = self._write(tmp_path / "int.dam", DamArchitecture().to_json(),
                           weights=torch.zeros(DamArchitecture().num_weights, dtype=torch.int32))
        with pytest.raises(DamcapError, match=r"int\.dam: weights are torch\.int32"):
            load_dam(path)

    def test_deeply_nested_metadata_is_one_line(self, tmp_path):
        path = tmp_path / "deep.dam"
        path.write_bytes(st_save({"weights": torch.zeros(3360)}, metadata={"damcap": "[" * 100000}))
        with pytest.raises(DamcapError, match=r"deep\.dam: damcap metadata is nested too deeply") as e:
            load_dam(path)
        assert "\n" not in str(e.value)

    def test_architecture_not_an_object(self, tmp_path):
        path = self._write(tmp_path / "arch.dam", [32, 4])
        with pytest.raises(DamcapError, match=r"arch\.dam: damcap metadata 'architecture' must be an object"):
            load_dam(path)

    def test_model_constructor_checks_the_scale_in_float32(self):
        with pytest.raises(DamcapError, match="float32"):
            DeepAppearanceMap(DamArchitecture(), 1e39)


def _with_spatial(model: DeepAppearanceMap, keys=(3, 5), log_albedo=((0.1, -0.2, 0.3), (0.0, 0.5, -1.0))) -> DeepAppearanceMap:
    import numpy as np

    from damcap.appearance.spatial import SpatialAlbedo

    return model.with_spatial(SpatialAlbedo(np.array([0.5, -1.0, 2.0]), 0.01, np.array(keys, np.int64),
                                            np.array(log_albedo, np.float32)))


def test_round_trip_with_a_spatial_factor_is_format_2(tmp_path):
    import numpy as np

    m = _with_spatial(DeepAppearanceMap(DamArchitecture(width=8, depth=2), radiance_scale=1.5))
    save_dam(tmp_path / "s.dam", m, colorspace="lin_rec709", made_by="fit")
    back, meta = load_dam(tmp_path / "s.dam")
    assert meta["format_version"] == 2 and meta["spatial"]["kind"] == "albedo_voxels"
    sa, want = back.spatial, m.spatial
    assert sa is not None and sa.voxel_size == want.voxel_size
    np.testing.assert_array_equal(sa.keys, want.keys)
    np.testing.assert_array_equal(sa.log_albedo, want.log_albedo)
    np.testing.assert_array_equal(sa.origin_world, want.origin_world)
    torch.testing.assert_close(back.get_flat_weights(), m.get_flat_weights())
    save_dam(tmp_path / "plain.dam", back.with_spatial(None), colorspace="lin_rec709", made_by="fit")
    assert load_dam(tmp_path / "plain.dam")[1]["format_version"] == 1 and load_dam(tmp_path / "plain.dam")[0].spatial is None


def test_refuses_a_damaged_spatial_factor(tmp_path):
    base = DeepAppearanceMap(DamArchitecture(width=8, depth=2))
    cases = {
        "unsorted": (_with_spatial(base, keys=(5, 3)), "sorted"),
        "huge": (_with_spatial(base, log_albedo=((0, 0, 0), (80, 0, 0))), "outside"),
    }
    for name, (model, needle) in cases.items():
        save_dam(tmp_path / f"{name}.dam", model, colorspace="lin_rec709", made_by="fit")
        with pytest.raises(DamcapError, match=f"{name}.dam: spatial factor: .*{needle}"):
            load_dam(tmp_path / f"{name}.dam")
    # a file that names a spatial factor but lacks its tensors, and tensors without the metadata
    good = _with_spatial(base)
    meta = {"format_version": 2, "architecture": base.arch.to_json(), "radiance_scale": 1.0, "colorspace": "lin_rec709",
            "made_by": "fit", "spatial": {"kind": "albedo_voxels", "origin_world": [0, 0, 0], "voxel_size": 0.01}}
    (tmp_path / "missing.dam").write_bytes(st_save({"weights": base.get_flat_weights()}, metadata={"damcap": json.dumps(meta)}))
    with pytest.raises(DamcapError, match="missing.dam: expected the tensors"):
        load_dam(tmp_path / "missing.dam")
    del meta["spatial"]
    extra = {"weights": base.get_flat_weights(), "spatial_keys": torch.from_numpy(good.spatial.keys),
             "spatial_log_albedo": torch.from_numpy(good.spatial.log_albedo)}
    (tmp_path / "extra.dam").write_bytes(st_save(extra, metadata={"damcap": json.dumps(meta)}))
    with pytest.raises(DamcapError, match="extra.dam: expected the tensors \\['weights'\\]"):
        load_dam(tmp_path / "extra.dam")


def _with_normal_field(model, keys=(3, 5), offset=((0.1, 0.0, 0.0), (0.0, -0.2, 0.05))):
    import numpy as np

    from damcap.appearance.normal_field import NormalField

    return model.with_normal_field(NormalField(np.array([0.5, -1.0, 2.0]), 0.02, np.array(keys, np.int64), np.array(offset, np.float32)))


def test_round_trip_with_a_normal_field_is_format_3(tmp_path):
    import numpy as np

    m = _with_normal_field(_with_spatial(DeepAppearanceMap(DamArchitecture(width=8, depth=2), radiance_scale=1.5)))
    save_dam(tmp_path / "n.dam", m, colorspace="lin_rec709", made_by="fit")
    back, meta = load_dam(tmp_path / "n.dam")
    assert meta["format_version"] == 3 and meta["normal_field"]["kind"] == "normal_offset_voxels"
    nf, want = back.normal_field, m.normal_field
    assert nf is not None and nf.voxel_size == want.voxel_size and back.spatial is not None
    np.testing.assert_array_equal(nf.keys, want.keys)
    np.testing.assert_array_equal(nf.offset, want.offset)
    np.testing.assert_array_equal(nf.origin_world, want.origin_world)
    # the field alone is format 3 as well; dropping both factors gives format 1
    save_dam(tmp_path / "f.dam", back.with_spatial(None), colorspace="lin_rec709", made_by="fit")
    f_model, f_meta = load_dam(tmp_path / "f.dam")
    assert f_meta["format_version"] == 3 and f_model.spatial is None and f_model.normal_field is not None
    save_dam(tmp_path / "plain.dam", back.dam_alone(), colorspace="lin_rec709", made_by="fit")
    plain, p_meta = load_dam(tmp_path / "plain.dam")
    assert p_meta["format_version"] == 1 and not plain.has_surface_factors


def test_refuses_a_damaged_normal_field(tmp_path):
    base = DeepAppearanceMap(DamArchitecture(width=8, depth=2))
    cases = {
        "unsorted": (_with_normal_field(base, keys=(5, 3)), "sorted"),
        "huge": (_with_normal_field(base, offset=((0, 0, 0), (1e5, 0, 0))), "more than"),
        "nan": (_with_normal_field(base, offset=((0, 0, 0), (float("nan"), 0, 0))), "NaN"),
    }
    for name, (model, needle) in cases.items():
        save_dam(tmp_path / f"{name}.dam", model, colorspace="lin_rec709", made_by="fit")
        with pytest.raises(DamcapError, match=f"{name}.dam: normal field: .*{needle}"):
            load_dam(tmp_path / f"{name}.dam")
    meta = {"format_version": 3, "architecture": base.arch.to_json(), "radiance_scale": 1.0, "colorspace": "lin_rec709",
            "made_by": "fit", "normal_field": {"kind": "albedo_voxels", "origin_world": [0, 0, 0], "voxel_size": 0.01}}
    good = _with_normal_field(base).normal_field
    tensors = {"weights": base.get_flat_weights(), "normal_keys": torch.from_numpy(good.keys), "normal_offset": torch.from_numpy(good.offset)}
    (tmp_path / "kind.dam").write_bytes(st_save(tensors, metadata={"damcap": json.dumps(meta)}))
    with pytest.raises(DamcapError, match="kind.dam: metadata 'normal_field' must be an object of kind 'normal_offset_voxels'"):
        load_dam(tmp_path / "kind.dam")
    meta["normal_field"]["kind"] = "normal_offset_voxels"
    (tmp_path / "missing.dam").write_bytes(st_save({"weights": base.get_flat_weights()}, metadata={"damcap": json.dumps(meta)}))
    with pytest.raises(DamcapError, match="missing.dam: expected the tensors"):
        load_dam(tmp_path / "missing.dam")


def test_up_direction_is_recorded_and_checked(tmp_path):
    import numpy as np

    from damcap.appearance.dam_file import recorded_up

    m = DeepAppearanceMap(DamArchitecture(width=8, depth=2))
    save_dam(tmp_path / "z.dam", m, colorspace="lin_rec709", made_by="fit", up_world=np.array([0.0, 0.0, 3.0]))
    _, meta = load_dam(tmp_path / "z.dam")
    assert meta["up_world"] == [0.0, 0.0, 1.0] and recorded_up(meta).tolist() == [0.0, 0.0, 1.0] and meta["format_version"] == 1
    save_dam(tmp_path / "none.dam", m, colorspace="lin_rec709", made_by="fit")
    assert recorded_up(load_dam(tmp_path / "none.dam")[1]) is None
    for name, up in {"short": [0, 1], "zero": [0, 0, 0], "text": ["0", "1", "0"], "inf": [0, 1e400, 0]}.items():
        meta = {"format_version": 1, "architecture": m.arch.to_json(), "radiance_scale": 1.0, "up_world": up}
        (tmp_path / f"{name}.dam").write_bytes(st_save({"weights": m.get_flat_weights()}, metadata={"damcap": json.dumps(meta)}))
        with pytest.raises(DamcapError, match=f"{name}.dam: metadata 'up_world' must be 3 finite numbers"):
            load_dam(tmp_path / f"{name}.dam")


def test_the_training_normals_histogram_round_trips_and_a_bad_one_is_refused(tmp_path):
    """save_dam records normal_histogram as metadata (the format version unchanged: it does not
    change how the model renders); load_dam refuses one that is not a list of finite non-negative
    numbers, naming the file."""
    import numpy as np

    from damcap.appearance.coverage import normal_histogram
    from damcap.appearance.dam_file import recorded_normal_histogram

    m = DeepAppearanceMap(DamArchitecture(width=8, depth=2))
    hist = normal_histogram(np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]), np.array([2.0, 0.5]))
    save_dam(tmp_path / "h.dam", m, colorspace="lin_rec709", made_by="fit", normal_histogram=hist)
    _, meta = load_dam(tmp_path / "h.dam")
    np.testing.assert_array_equal(recorded_normal_histogram(meta), hist)
    assert meta["format_version"] == 1 and recorded_normal_histogram(meta).sum() == 2.5
    save_dam(tmp_path / "none.dam", m, colorspace="lin_rec709", made_by="fit")
    assert recorded_normal_histogram(load_dam(tmp_path / "none.dam")[1]) is None
    for name, h in {"negative": [1.0, -1.0], "empty": [], "text": ["1"], "inf": [1e400], "object": {"a": 1}}.items():
        meta = {"format_version": 1, "architecture": m.arch.to_json(), "radiance_scale": 1.0, "normal_histogram": h}
        (tmp_path / f"{name}.dam").write_bytes(st_save({"weights": m.get_flat_weights()}, metadata={"damcap": json.dumps(meta)}))
        with pytest.raises(DamcapError, match=f"{name}.dam: metadata 'normal_histogram' must be a list of finite non-negative numbers"):
            load_dam(tmp_path / f"{name}.dam")
