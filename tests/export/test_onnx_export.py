"""ONNX export, checked with onnxruntime to 1e-5."""

from __future__ import annotations

import numpy as np
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
from damcap.cli.main import main


def test_onnx_matches_onnxruntime(model_file, tmp_path, capsys):
    import onnxruntime as ort

    from damcap.appearance.dam_file import load_dam

    assert main(["export", str(model_file), "--format", "onnx", "-o", str(tmp_path / "m.onnx")]) == 0
    sess = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(3)
    v = rng.normal(size=(1000, 3)).astype(np.float32)
    n = rng.normal(size=(1000, 3)).astype(np.float32)
    got = sess.run(None, {"view_dir_world": v, "normal_world": n})[0]
    with torch.no_grad():
        want = load_dam(model_file)[0](torch.from_numpy(v), torch.from_numpy(n)).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(np.abs(want).max()))


def test_separable_dam_exports_to_onnx(tmp_path):
    import onnxruntime as ort

    from damcap.export.onnx_export import export_onnx

    m = DeepAppearanceMap(DamArchitecture(width=8, depth=3, separable=True), radiance_scale=3.0,
                          generator=torch.Generator().manual_seed(4))
    export_onnx(m, tmp_path / "s.onnx")
    sess = ort.InferenceSession(str(tmp_path / "s.onnx"), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(5)
    v, n = rng.normal(size=(2, 500, 3)).astype(np.float32)
    got = sess.run(None, {"view_dir_world": v, "normal_world": n})[0]
    with torch.no_grad():
        want = m(torch.from_numpy(v), torch.from_numpy(n)).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(np.abs(want).max()))
