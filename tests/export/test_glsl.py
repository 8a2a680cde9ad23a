"""GLSL source of a DAM: self-contained, every weight carried."""

from __future__ import annotations

import numpy as np
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, split_weights
from damcap.export.glsl import glsl_source


def test_glsl_of_a_separable_dam_writes_its_block_diagonal_matrices():
    m = DeepAppearanceMap(DamArchitecture(width=6, depth=2, separable=True), generator=torch.Generator().manual_seed(2))
    src = glsl_source(m)
    arrays = [line for line in src.splitlines() if line.startswith("const float")]
    values = np.array([float(x) for line in arrays for x in line.split("(", 1)[1].rstrip(");").split(",")])
    dense = torch.cat([w[0].flatten() for w, _ in split_weights(m.get_flat_weights()[None], m.arch)]).numpy()
    np.testing.assert_allclose(values, dense, rtol=1e-7)
    assert np.count_nonzero(values) == m.arch.num_weights == 6 * 3 + 6 * 6 // 2 + 3 * 6
    first = values[:36].reshape(6, 6)  # units 0-2 see N only, units 3-5 R only
    assert not first[:3, 3:].any() and not first[3:, :3].any()
    assert "separable" in src


def test_glsl_is_self_contained_and_carries_every_weight():
    m = DeepAppearanceMap(DamArchitecture(width=4, depth=2, encoding="vnr", bias=True), radiance_scale=2.0)
    src = glsl_source(m)
    assert "vec3 dam_eval(vec3 view_dir_world, vec3 normal_world)" in src
    arrays = [line for line in src.splitlines() if line.startswith("const float")]
    values = [float(x) for line in arrays for x in line.split("(", 1)[1].rstrip(");").split(",")]
    np.testing.assert_allclose(values, m.get_flat_weights().numpy(), rtol=1e-7)
    assert "* 2.0;" in src
