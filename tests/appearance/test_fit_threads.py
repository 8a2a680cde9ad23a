"""A fit's result depends on its seed, inputs and CPU thread count, not on the machine's load."""

from __future__ import annotations

import subprocess
import sys

import torch

from damcap.appearance.fit import FitOptions, fit_dam
from damcap.appearance.views import load_views, samples_of
from damcap.common.capture_folder import read_capture
from damcap.common.device import _thread_libraries, fixed_threads

#: batches and held-out views large enough for torch to split their work between threads, a
#: held-out evaluation every 5 steps: the stopping rule's choice is compared too
OPTS = FitOptions(steps=60, batch_size=16384, eval_every=5, holdout_views=2, seed=3, checkpoint_every=0)


def _fit_on_two_threads(samples):
    before = torch.get_num_threads()
    torch.set_num_threads(2)  # the parallel reductions split their terms between two threads
    try:
        return fit_dam(samples, OPTS)
    finally:
        torch.set_num_threads(before)


def test_the_same_fit_with_the_other_core_busy_gives_the_same_bits(sample_capture):
    samples = samples_of(load_views(read_capture(sample_capture), "train"))
    quiet = _fit_on_two_threads(samples)
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])  # loads a core for the second fit
    try:
        loaded = _fit_on_two_threads(samples)
    finally:
        busy.kill()
        busy.wait()
    assert quiet.threads == loaded.threads == 2
    assert torch.equal(quiet.model.get_flat_weights(), loaded.model.get_flat_weights())
    assert quiet.best_step == loaded.best_step
    assert [h["holdout_l1"] for h in quiet.history] == [h["holdout_l1"] for h in loaded.history]


def test_fixed_threads_holds_the_count_with_dynamic_adjustment_off_and_restores_both():
    omp, mkl = _thread_libraries()
    before = torch.get_num_threads()
    dynamic = (omp.omp_get_dynamic() if omp else None, mkl.mkl_serv_get_dynamic() if mkl else None)
    with fixed_threads(1) as n:
        assert n == 1 and torch.get_num_threads() == 1
        assert (omp is None or omp.omp_get_dynamic() == 0) and (mkl is None or mkl.mkl_serv_get_dynamic() == 0)
    assert torch.get_num_threads() == before
    assert (omp.omp_get_dynamic() if omp else None, mkl.mkl_serv_get_dynamic() if mkl else None) == dynamic
    with fixed_threads() as n:
        assert n == before
