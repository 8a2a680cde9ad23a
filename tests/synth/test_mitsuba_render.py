"""Mitsuba render passes: which sample counts the multijitter sampler takes, how spp is split.

The check against Mitsuba's own sampler, and the renders, are in test_mitsuba_capture.py."""

from __future__ import annotations

import math

import pytest

from damcap.common.errors import DamcapError
from damcap.synth.mitsuba_render import MAX_LANES_PER_PASS, pass_sample_counts, sampler_count_ok


def test_sampler_counts_closed_form():
    ok = {k * k for k in range(1, 40)} | {k * (k + 1) for k in range(1, 40)} | {k * (k + 2) for k in range(1, 40)}
    assert [n for n in range(1, 1000) if sampler_count_ok(n)] == sorted(x for x in ok if x < 1000)
    assert not sampler_count_ok(0) and not sampler_count_ok(128) and sampler_count_ok(132)


@pytest.mark.parametrize("spp, res", [(1, 8), (7, 8), (128, 128), (512, 256), (1000, 256), (4096, 128), (99, 1024)])
def test_passes_add_up_are_taken_exactly_and_fit_the_lanes(spp, res):
    counts = pass_sample_counts(spp, res, res)
    assert sum(counts) == spp and all(sampler_count_ok(n) for n in counts)
    assert max(counts) * res * res <= max(MAX_LANES_PER_PASS, res * res)
    assert len(counts) >= math.ceil(spp * res * res / MAX_LANES_PER_PASS)


def test_pass_counts_closed_form():
    assert pass_sample_counts(1024, 128, 128) == [256, 256, 256, 256]  # 2^22 lanes = 256 spp at 128 px
    assert pass_sample_counts(16, 64, 64) == [16]
    assert pass_sample_counts(10, 8, 8, max_lanes=64) == [1] * 10  # one sample per pixel per pass
    with pytest.raises(ValueError, match="spp must be >= 1, got 0"):
        pass_sample_counts(0, 8, 8)


def test_the_cuda_variant_is_refused_clearly_without_a_gpu():
    import drjit as dr

    from damcap.synth.mitsuba_render import select_variant

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("a CUDA GPU is present: auto picks cuda_ad_rgb there")
    with pytest.raises(DamcapError, match="cuda_ad_rgb needs a CUDA GPU"):
        select_variant("cuda_ad_rgb")
    with pytest.raises(DamcapError, match="use auto, cuda_ad_rgb, llvm_ad_rgb, scalar_rgb"):
        select_variant("optix")
    assert select_variant("auto") in ("llvm_ad_rgb", "scalar_rgb")
