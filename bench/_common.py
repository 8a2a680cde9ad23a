"""What every benchmark script shares: a timestamped log line and the machine description."""

from __future__ import annotations

import datetime as _dt
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo ('unknown' elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"


def machine_info() -> dict:
    """CPU model, core count, library versions and the date (UTC)."""
    cpu = cpu_model()
    return {
        "date_utc": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC"),
        "nproc": len(os.sched_getaffinity(0)),
        "cpu_model": cpu,
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
    }


def busy_fraction_since(start: tuple[float, float, float]) -> float:
    """Share of all cores that OTHER processes used since ``start = cpu_snapshot()``."""
    busy0, own0, t0 = start
    busy1, own1, t1 = cpu_snapshot()
    ncpu = len(os.sched_getaffinity(0))
    return max(0.0, (busy1 - busy0) - (own1 - own0)) / max((t1 - t0) * ncpu, 1e-9)


def cpu_snapshot() -> tuple[float, float, float]:
    """(all processes' busy CPU seconds, this process's CPU seconds, wall clock)."""
    ticks = os.sysconf("SC_CLK_TCK")
    fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    vals = [int(x) for x in fields]
    busy = (sum(vals) - vals[3] - vals[4]) / ticks  # minus idle and iowait
    t = os.times()
    return busy, t.user + t.system + t.children_user + t.children_system, time.monotonic()
