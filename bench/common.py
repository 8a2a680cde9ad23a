"""What every study shares: where the repository, the results and the shared data are, the
command line a report quotes, a timestamped log line, the machine description and CPU meters.

Every study runs as a module from the repository root, e.g. ``.venv/bin/python -m bench.synth``.
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import shlex
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from damcap.common import data_dir


BENCH = Path(__file__).resolve().parent
"""the bench/ folder: the committed reports (``*.md``), ``results/`` and the git-ignored ``.cache/``"""
REPO = BENCH.parent
RESULTS = BENCH / "results"
CACHE = BENCH / ".cache"
PYTHON = ".venv/bin/python"
"""the interpreter the reports' command lines name (the repository's virtual environment)"""


def shared_data_dir() -> Path:
    """The shared data folder (meshes/, envmaps/, brackets/, raw/, real/): ``$DAMCAP_SHARED_DATA``,
    else ``../shared/data`` beside the repository (:func:`damcap.common.data_dir.shared_data_dir`)."""
    return data_dir.shared_data_dir(fallback=REPO.parent / "shared" / "data")


def command_line(study: str, argv: list[str] | tuple[str, ...]) -> str:
    """The command line that reruns a study from the repository root, as its report quotes it.

    >>> command_line("synth", ["--stages", "noise,why"])
    '.venv/bin/python -m bench.synth --stages noise,why'
    """
    return " ".join([PYTHON, "-m", f"bench.{study}", *(shlex.quote(a) for a in argv)])


def rows_not_rerun(prev: dict | None, new_rows: list[dict], key: Callable[[dict], Any]) -> list[dict]:
    """The saved rows of a result (``prev``: its ``rows``, ``command`` and ``machine.date_utc``)
    whose ``key`` no new row has, each tagged with the command and date that measured it: what a
    rerun of some methods keeps of the others.

    >>> prev = {"command": "a", "machine": {"date_utc": "d0"}, "rows": [{"method": "x"}, {"method": "y"}]}
    >>> rows_not_rerun(prev, [{"method": "x"}], lambda r: r["method"]), rows_not_rerun(None, [], lambda r: r["method"])
    ([{'command': 'a', 'date_utc': 'd0', 'method': 'y'}], [])
    """
    if not prev:
        return []
    done = {key(r) for r in new_rows}
    return [{"command": prev.get("command"), "date_utc": prev["machine"]["date_utc"], **r} for r in prev.get("rows", []) if key(r) not in done]


def write_report_keeping(report: Path, lines: list[str], mark: str) -> None:
    """Write a study's generated report, keeping everything of the old one from its ``mark`` line
    on (hand-written notes survive a rerun)."""
    old = report.read_text() if report.is_file() else ""
    keep = old[old.index(mark):] if mark in old else ""
    report.write_text("\n".join(lines) + "\n" + (("\n" + keep) if keep else ""))


def study_paths(result: Path, report: Path, out: Path | None) -> tuple[Path, Path]:
    """Where a study writes its results JSON and its report: ``result`` and ``report`` (bench/'s
    own), or files of the same names in ``out`` (created)."""
    if out is None:
        result.parent.mkdir(parents=True, exist_ok=True)
        return result, report
    out.mkdir(parents=True, exist_ok=True)
    return out / result.name, out / report.name


def machine_line(machine: dict) -> str:
    """A report's machine line from :func:`machine_info`'s record: CPU model, cores, UTC date."""
    return f"Machine: {machine.get('cpu_model', '')}, {machine.get('nproc', '')} cores, {machine.get('date_utc', '')}"


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


NCPU = len(os.sched_getaffinity(0))


def system_busy_s() -> float:
    """CPU seconds all processes have been busy since boot (/proc/stat: user, nice, system,
    irq, softirq, steal; not idle or iowait)."""
    f = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    user, nice, system, _idle, _iowait, irq, softirq, steal = (int(x) for x in f[:8])
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def own_cpu_s() -> float:
    """CPU seconds of this process (all threads) and its finished children."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


class CpuMeter:
    """Wall time of a section, this process's CPU time, and the CPU time and share of all cores
    that OTHER processes used meanwhile (the machines are shared).

    ``idle`` estimates the section's time on an otherwise idle machine: the larger of own CPU
    time / cores (every core busy) and wall time x (1 - others' share).
    """

    def __enter__(self) -> "CpuMeter":
        self.busy0, self.own0, self.t0 = system_busy_s(), own_cpu_s(), time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        self.wall = time.perf_counter() - self.t0
        self.own_cpu = own_cpu_s() - self.own0
        self.foreign_cpu = max(0.0, (system_busy_s() - self.busy0) - self.own_cpu)
        self.foreign_frac = self.foreign_cpu / max(self.wall * NCPU, 1e-9)
        self.idle = max(self.own_cpu / NCPU, self.wall * (1 - min(self.foreign_frac, 1.0)))
