"""The segmentation folder as the segment command writes it (DAMs, weights, previews, segment.json)."""

from __future__ import annotations

import json

import numpy as np

from damcap.cli.main import main
from damcap.common.exr import read_exr, read_image_u8


def test_segment_command_writes_everything(two_materials, tmp_path, capsys):
    path, train, _ = two_materials
    out = tmp_path / "seg"
    assert main(["segment", str(path), "-o", str(out), "--materials", "2", "--steps", "50", "--init-steps", "50"]) == 0
    for k in range(2):
        assert (out / f"material_{k}.dam").is_file()
    w, names = read_exr(out / "weights" / f"{train[0].name}.exr")
    assert names == ("W.0", "W.1")
    fg = train[0].data.coverage > 0.5
    np.testing.assert_allclose(w[fg].sum(-1), 1.0, atol=2e-3)
    assert (out / "preview" / f"{train[0].name}.png").is_file()
    legend = json.loads((out / "preview" / "legend.json").read_text())
    assert legend == {"0": {"rgb": [230, 76, 64], "dam": "material_0.dam"}, "1": {"rgb": [64, 153, 242], "dam": "material_1.dam"}}
    assert read_image_u8(out / "preview" / "legend.png").shape == (68, 300, 3)
    assert "preview/*.png and their legend preview/legend.png and .json" in capsys.readouterr().out
    meta = json.loads((out / "segment.json").read_text())
    assert meta["materials"] == 2 and meta["options"]["seed"] == 0
    # each DAM records the normals of the training pixels assigned to it: together, every foreground pixel once
    from damcap.appearance.coverage import normal_histogram
    from damcap.appearance.dam_file import load_dam, recorded_normal_histogram

    hists = [recorded_normal_histogram(load_dam(out / f"material_{k}.dam")[1]) for k in range(2)]
    every = normal_histogram(np.concatenate([v.data.normal_world[v.data.coverage > 0.5] for v in train]))
    np.testing.assert_array_equal(hists[0] + hists[1], every)
    assert min(h.sum() for h in hists) > 0.1 * every.sum()  # both materials hold pixels
    capsys.readouterr()
    assert main(["evaluate", str(path), "--segmentation", str(out), "--json", str(tmp_path / "e.json")]) == 0
    res = json.loads((tmp_path / "e.json").read_text())["results"]["test"]
    assert {"segment (estimated weights)", "segment (true weights)"} <= set(res)
    assert main(["segment", str(path), "-o", str(tmp_path / "x"), "--materials", "two"]) == 2
    capsys.readouterr()
    assert main(["segment", str(path), "-o", str(tmp_path / "x"), "--materials", "2", "--prior-weight", "-1"]) == 2
    assert "--prior-weight" in capsys.readouterr().err
    assert main(["segment", str(path), "-o", str(tmp_path / "x"), "--materials", "2", "--illumination-degree", "3"]) == 2
    assert "--illumination-degree must be an integer in [0, 2], got 3" in capsys.readouterr().err
    assert main(["segment", str(path), "-o", str(tmp_path / "x"), "--materials", "2", "--init-colour", "brightest"]) == 2
    assert "--init-colour must be one of pixel, darkest-view, got 'brightest'" in capsys.readouterr().err
    assert main(["segment", str(path), "-o", str(tmp_path / "x"), "--materials", "2", "--colour-floor", "0.5"]) == 2
    assert "--colour-floor must be a finite number in (0, 0.02], got 0.5" in capsys.readouterr().err
    assert main(["evaluate", str(path), "--segmentation", str(tmp_path / "nothing")]) == 2
