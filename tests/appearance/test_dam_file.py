"""`.dam` files: round trip, and refusal of anything else without executing it."""

from __future__ import annotations

import json
import os
import pickle

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
