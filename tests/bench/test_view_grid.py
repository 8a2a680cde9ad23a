"""bench.view_grid on a tiny closed-form capture: the picture is written, one row per asked view."""

from __future__ import annotations

import matplotlib.image
import pytest
import torch

from bench import view_grid
from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
from damcap.appearance.dam_file import save_dam
from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture


def test_grid_has_a_row_per_view_and_a_column_per_model(tmp_path):
    cap = tmp_path / "cap"
    make_closed_form_capture(cap, ClosedFormOptions(shape="sphere", light="directional", views=6, train_views=3, resolution=16, seed=1))
    dams = []
    for k in range(2):
        p = tmp_path / f"m{k}.dam"
        save_dam(p, DeepAppearanceMap(DamArchitecture(), generator=torch.Generator().manual_seed(k)), colorspace="lin_rec709", made_by="test")
        dams += ["--model", f"m{k}={p}"]
    out = tmp_path / "grid.png"
    view_grid.main([str(cap), *dams, "--rows", "2", "--out", str(out)])
    h, w = matplotlib.image.imread(out).shape[:2]
    assert h == 2 * 120 and w == 3 * 120  # 2.4 in per panel at 50 dpi


def test_a_model_without_a_name_is_refused(tmp_path):
    with pytest.raises(SystemExit) as e:
        view_grid.main([str(tmp_path), "--model", "x.dam", "--out", str(tmp_path / "g.png")])
    assert e.value.code == 2
