"""Error measures of radiance maps against references (capture.metrics)."""

from __future__ import annotations

import numpy as np

from damcap.capture.metrics import rgbe_step
from damcap.common.exr import read_exr, write_exr


def test_rgbe_step_matches_what_an_hdr_file_keeps(tmp_path):
    """Round trip through a Radiance .hdr written by OpenImageIO: every value comes back within one
    step below itself (the writer truncates), and the step is the same on the values read back."""
    rng = np.random.default_rng(0)
    radiance = np.exp(rng.normal(0.0, 3.0, (32, 48, 3))).astype(np.float32)  # about 8 decades
    write_exr(tmp_path / "r.hdr", radiance, "RGB", dtype="float")
    back = read_exr(tmp_path / "r.hdr")[0][..., :3].astype(np.float64)
    step = rgbe_step(radiance)
    assert np.all(back <= radiance + 1e-6 * step) and np.all(back > radiance - step)
    assert np.array_equal(rgbe_step(back), step)
    # a channel 100x below its pixel's largest is kept only to within more than a third of itself
    rel = (step / np.maximum(radiance, 1e-30))[radiance < radiance.max(axis=-1, keepdims=True) / 100]
    assert rel.min() > 0.39

