"""The one place that decides torch devices and dtypes."""

from __future__ import annotations

import contextlib
import functools
from typing import Any, Iterator

import torch

from damcap.common.errors import DamcapError


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` -> CUDA when available, else CPU; ``cpu``/``cuda``/``cuda:N`` as given.

    Raises:
        DamcapError: an unknown name, or CUDA asked for where none is available.
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise DamcapError(f"unknown device {name!r}: use auto, cpu or cuda") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise DamcapError(f"device {name!r} asked for, but this torch build sees no CUDA GPU; use --device cpu")
    return dev


@functools.lru_cache(maxsize=1)
def _thread_libraries() -> tuple[Any, Any]:
    """torch's OpenMP runtime and oneMKL (ctypes handles, None where this build has none)."""
    import ctypes
    import glob
    import os

    lib = os.path.join(os.path.dirname(torch.__file__), "lib")
    handles = []
    for pattern, symbols in (("libgomp*.so*", ("omp_get_dynamic", "omp_set_dynamic")),
                             ("libtorch_cpu.so", ("mkl_serv_get_dynamic", "MKL_Set_Dynamic"))):  # oneMKL linked into torch
        handle = None
        for path in sorted(glob.glob(os.path.join(lib, pattern))):
            try:
                candidate = ctypes.CDLL(path)
                for symbol in symbols:
                    getattr(candidate, symbol)
            except (OSError, AttributeError):
                continue
            handle = candidate
            break
        handles.append(handle)
    return handles[0], handles[1]


@contextlib.contextmanager
def fixed_threads(threads: int | None = None) -> Iterator[int]:
    """Hold torch's CPU thread count fixed for the block: the conditions of a bit-reproducible run.

    A parallel reduction (a loss's sum, a matrix product's accumulation) splits its terms by
    thread, so float results depend on the number of threads that run it; oneMKL's and OpenMP's
    documented conditions for reproducible results are a fixed thread count with their dynamic
    adjustment off (MKL_DYNAMIC, which oneMKL enables by default, lets it use fewer threads than
    asked at run time; OMP_DYNAMIC likewise for OpenMP). Inside the block the intra-op thread
    count is ``threads`` (default: the current ``torch.get_num_threads()``) and both adjustments
    are off; all three are restored after it.

    Yields:
        the thread count in force (record it: the same inputs and seed give the same bits with
        the same thread count).
    """
    before = torch.get_num_threads()
    n = int(threads) if threads else before
    omp, mkl = _thread_libraries()
    omp_dynamic = omp.omp_get_dynamic() if omp is not None else 0
    mkl_dynamic = mkl.mkl_serv_get_dynamic() if mkl is not None else 0
    try:
        if omp is not None and omp_dynamic:
            omp.omp_set_dynamic(0)
        if mkl is not None and mkl_dynamic:
            mkl.MKL_Set_Dynamic(0)
        torch.set_num_threads(n)
        yield n
    finally:
        torch.set_num_threads(before)
        if mkl is not None and mkl_dynamic:
            mkl.MKL_Set_Dynamic(mkl_dynamic)
        if omp is not None and omp_dynamic:
            omp.omp_set_dynamic(omp_dynamic)
