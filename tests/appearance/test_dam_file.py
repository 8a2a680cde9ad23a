"""`.dam` files: round trip, and refusal of anything else without executing it."""

from __future__ import annotations

import json
import os
import pickle
import time

import pytest
import torch
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
                                                      ("width", 0, r"\[1, 4096\]"), ("depth", -3, r"\[1, 64\]"),
                                                      ("width", 2.5, r"\[1, 4096\]"), ("depth", "4", r"\[1, 64\]")])
    def test_huge_or_bad_architecture_is_refused_quickly_naming_the_bound(self, tmp_path, field, value, bound):
        path = self._write(tmp_path / "hostile.dam", {**DamArchitecture().to_json(), field: value})
        assert path.stat().st_size < 20_000
        t0 = time.perf_counter()
        with pytest.raises(DamcapError, match=rf"hostile\.dam: invalid architecture: DAM {field} must be an integer in {bound}"):
            load_dam(path)
        assert time.perf_counter() - t0 < 2.0

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
