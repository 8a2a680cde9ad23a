"""The fuzz suite's harness: tiny valid inputs, builders of hostile ones, and one runner.

Every case runs ``damcap ARGS`` in a forked child of the test process (``damcap_fork``): the
child inherits the already imported library (a run costs ~0.1 s, not an interpreter start), and
the parent can kill it, so a case that hangs or exhausts memory fails in its time and memory limit
instead of taking the suite down. ``refused`` then checks the contract of a user mistake: exit 2,
one stderr line ``error: ...`` naming the file / option and the value, no traceback, inputs
byte-identical, no output (or temp file) left behind.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import resource
import shutil
import signal
import struct
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

# The harness forks this process for each case. OpenEXR's worker pool (started by the first EXR
# this process writes) does not survive a fork: a child that writes an EXR then waits forever on
# threads it does not have. damcap itself never forks (synth-set spawns), so only the test process
# runs OpenEXR single-threaded, set before any EXR is written (collection imports this first).
oiio.attribute("exr_threads", -1)

#: the cases of issue 25 still open: listed by test id in open_cases.txt and not run by default
#: (they fail today, and some only at their time limit); ``DAMCAP_FUZZ_OPEN=1`` runs them too.
#: A fixed case's line is deleted; ``test_open_cases_are_real_test_ids`` keeps the list honest.
OPEN_CASES_FILE = Path(__file__).with_name("open_cases.txt")


def open_cases() -> set[str]:
    """The test ids listed in open_cases.txt (comments and blank lines ignored)."""
    lines = OPEN_CASES_FILE.read_text().splitlines() if OPEN_CASES_FILE.is_file() else []
    return {ln.strip() for ln in lines if ln.strip() and not ln.lstrip().startswith("#")}


def pytest_collection_modifyitems(config, items):
    if os.environ.get("DAMCAP_FUZZ_OPEN") == "1":
        return
    listed = open_cases()
    drop = [item for item in items if item.nodeid in listed]
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = [item for item in items if item.nodeid not in listed]
        config._damcap_open_fuzz_cases = len(drop)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    n = getattr(config, "_damcap_open_fuzz_cases", 0)
    if n:
        terminalreporter.write_line(f"fuzz: {n} cases of issue 25 are still open and were not run "
                                    f"(tests/fuzz/open_cases.txt; DAMCAP_FUZZ_OPEN=1 runs them)")


#: a case's wall-clock limit (hostile sizes must be refused well within it)
TIMEOUT_S = 20.0
#: memory a case may allocate beyond what the test process already maps
MEMORY_BYTES = 3 * 2**30
#: exit code of the child when ``main`` raised instead of returning (a traceback)
UNCAUGHT = 99


# ----------------------------------------------------------------------------------------------
# the runner


@dataclass
class Run:
    args: list[str]
    code: int | None          # None: killed (time limit or signal)
    out: str
    err: str
    seconds: float
    timed_out: bool = False

    @property
    def lines(self) -> list[str]:
        return [ln for ln in self.err.splitlines() if ln.strip()]


def _vm_bytes() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    return 0


def damcap_fork(args, *, timeout: float = TIMEOUT_S, memory: int | None = MEMORY_BYTES, fsize: int | None = None,
                cwd: Path | None = None, signal_when=None, env: dict | None = None) -> Run:
    """Run ``damcap ARGS`` (``damcap.cli.main.main``) in a forked child.

    Args:
        timeout: seconds before the child is killed (``Run.timed_out``).
        memory: address space the child may add (RLIMIT_AS); MemoryError beyond it.
        fsize: largest file the child may write (RLIMIT_FSIZE, SIGXFSZ ignored: a full disk).
        signal_when: ``(predicate, signum[, signum...])``: once ``predicate()`` is true, the parent
            sends the signals (Ctrl-C / SIGTERM in the middle of a run); a string as the predicate:
            once the child's stderr holds it (``PAUSED``: the test hook of common/atomic.py).
    """
    args = [str(a) for a in args]
    with tempfile.TemporaryDirectory(prefix="damcap-fuzz-") as td:
        out_p, err_p = Path(td) / "out", Path(td) / "err"
        sys.stdout.flush(); sys.stderr.flush()
        t0 = time.monotonic()
        pid = os.fork()
        if pid == 0:  # child
            code = UNCAUGHT
            try:
                os.setpgid(0, 0)
                fo = os.open(out_p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
                fe = os.open(err_p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
                os.dup2(fo, 1); os.dup2(fe, 2)
                sys.stdout = io.TextIOWrapper(os.fdopen(1, "wb", buffering=0), write_through=True)
                sys.stderr = io.TextIOWrapper(os.fdopen(2, "wb", buffering=0), write_through=True)
                signal.signal(signal.SIGINT, signal.default_int_handler)
                signal.signal(signal.SIGTERM, signal.SIG_DFL)
                if memory is not None:
                    lim = _vm_bytes() + memory
                    resource.setrlimit(resource.RLIMIT_AS, (lim, resource.getrlimit(resource.RLIMIT_AS)[1]))
                if fsize is not None:
                    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
                    resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
                if cwd is not None:
                    os.chdir(cwd)
                if env:
                    os.environ.update(env)
                import torch
                torch.set_num_threads(1)
                from damcap.cli.main import main
                code = main(args)
            except BaseException:  # noqa: BLE001 - the point: report what escaped ``main``
                try:
                    sys.stderr.write("Traceback (escaped damcap main):\n" + traceback.format_exc())
                except BaseException:  # noqa: BLE001
                    pass
                code = UNCAUGHT
            finally:
                try:
                    sys.stdout.flush(); sys.stderr.flush()
                finally:
                    os._exit(code if isinstance(code, int) else UNCAUGHT)
        # parent
        timed_out, status = False, None
        sent = False
        while True:
            done, st = os.waitpid(pid, os.WNOHANG)
            if done:
                status = st
                break
            if signal_when is not None and not sent:
                pred, *sigs = signal_when
                try:
                    ready = pred in err_p.read_text(errors="replace") if isinstance(pred, str) else pred()
                except Exception:  # noqa: BLE001
                    ready = False
                if ready:
                    for s in sigs:
                        os.kill(pid, s)
                        time.sleep(0.05)
                    sent = True
            if time.monotonic() - t0 > timeout:
                timed_out = True
                try:
                    os.killpg(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                _, status = os.waitpid(pid, 0)
                break
            time.sleep(0.01)
        secs = time.monotonic() - t0
        code = os.waitstatus_to_exitcode(status) if not timed_out else None
        return Run(args, code, out_p.read_text(errors="replace"), err_p.read_text(errors="replace"), secs, timed_out)


# ----------------------------------------------------------------------------------------------
# the contract


def digest(path: Path) -> str | None:
    """Bytes of a file or of every file under a folder (None: absent)."""
    path = Path(path)
    if path.is_symlink() and not path.exists():
        return "dangling-link"
    if path.is_file():
        return hashlib.sha256(path.read_bytes()).hexdigest()
    if path.is_dir():
        h = hashlib.sha256()
        for p in sorted(path.rglob("*")):
            if p.is_file() and not p.is_symlink():
                h.update(str(p.relative_to(path)).encode())
                h.update(p.read_bytes())
            elif p.is_dir():
                h.update(b"dir:" + str(p.relative_to(path)).encode())
        return h.hexdigest()
    if path.exists():  # fifo, device
        return "special"
    return None


def _listing(folder: Path) -> set[str] | None:
    try:
        return set(os.listdir(folder))
    except OSError:
        return None


def problems_of(run: Run, needles, *, exit_code: int | None, before_in, before_out, timeout) -> list[str]:
    bad: list[str] = []
    last = run.lines[-1] if run.lines else ""
    if run.timed_out:
        bad.append(f"still running after {timeout:.0f} s (killed)")
    elif run.code == UNCAUGHT or "Traceback" in run.err:
        exc = [ln for ln in run.lines if not ln.startswith(" ")]
        bad.append(f"traceback: {exc[-1][:160] if exc else '?'}")
    elif run.code == 0:
        bad.append("accepted (exit 0)" + (f"; stdout: {run.out.strip().splitlines()[-1][:120]!r}" if run.out.strip() else ""))
    elif run.code is not None and run.code < 0:
        bad.append(f"killed by signal {-run.code}")
    elif exit_code is not None and run.code != exit_code:
        bad.append(f"exit {run.code}, want {exit_code}")
    if not run.timed_out and run.code not in (0, UNCAUGHT):
        if not last.startswith("error:"):
            bad.append(f"last stderr line is not 'error: ...': {last[:160]!r}")
        else:
            for n in needles:
                if str(n) not in last:
                    bad.append(f"error line does not name {str(n)!r}: {last[:200]!r}")
        if len(run.lines) > 1 and "Traceback" not in run.err:
            bad.append(f"{len(run.lines)} stderr lines, want 1 (first: {run.lines[0][:120]!r})")
    for p, d in before_in.items():
        if digest(p) != d:
            bad.append(f"input changed: {p.name}")
    for p, (d, listing) in before_out.items():
        if digest(p) != d:
            bad.append(f"output left behind: {p.name}" if d is None else f"existing output changed: {p.name}")
        now = _listing(p.parent)
        if listing is not None and now is not None and now - listing - {p.name}:
            bad.append(f"stray files beside the output: {sorted(now - listing - {p.name})[:3]}")
    return bad


def refused(args, *needles, inputs=(), outputs=(), exit_code: int | None = 2, timeout: float = TIMEOUT_S, **kw) -> Run:
    """Assert ``damcap ARGS`` is refused as a user mistake (see the module docstring).

    Args:
        needles: strings the last stderr line must contain (the file's name, the option, the value).
        inputs: files/folders that must stay byte-identical.
        outputs: paths that must be as before (absent stays absent), with no stray files beside them.
        exit_code: the code wanted (2 for user mistakes; None = any non-zero).
    """
    before_in = {Path(p): digest(Path(p)) for p in inputs}
    before_out = {Path(p): (digest(Path(p)), _listing(Path(p).parent)) for p in outputs}
    run = damcap_fork(args, timeout=timeout, **kw)
    bad = problems_of(run, needles, exit_code=exit_code, before_in=before_in, before_out=before_out, timeout=timeout)
    assert not bad, "; ".join(bad)
    return run


def accepted_or_refused(args, *, inputs=(), outputs=(), timeout: float = TIMEOUT_S, **kw) -> Run:
    """For random corruption: either it runs (exit 0) or it is a clean user-mistake refusal."""
    before_in = {Path(p): digest(Path(p)) for p in inputs}
    before_out = {Path(p): (digest(Path(p)), _listing(Path(p).parent)) for p in outputs}
    run = damcap_fork(args, timeout=timeout, **kw)
    if run.code == 0 and not run.timed_out:
        bad = [f"input changed: {p.name}" for p, d in before_in.items() if digest(p) != d]
    else:
        bad = problems_of(run, (), exit_code=2, before_in=before_in, before_out=before_out, timeout=timeout)
    assert not bad, "; ".join(bad)
    return run


# ----------------------------------------------------------------------------------------------
# tiny valid inputs (built once, in the test process: it also imports what the children need)


def _main_ok(args):
    from damcap.cli.main import main
    code = main([str(a) for a in args])
    assert code == 0, f"fixture command failed: damcap {' '.join(map(str, args))}"


def _warm_imports():
    import importlib
    import pkgutil
    for room in ("common", "capture", "reconstruct", "appearance", "export", "cli", "synth"):
        try:
            pkg = importlib.import_module(f"damcap.{room}")
        except Exception:  # noqa: BLE001
            continue
        for m in pkgutil.walk_packages(pkg.__path__, f"damcap.{room}."):
            try:
                importlib.import_module(m.name)
            except BaseException:  # noqa: BLE001 - optional extras may be absent
                pass


@pytest.fixture(scope="session")
def base(tmp_path_factory) -> Path:
    """Folder of tiny valid inputs, shared read-only by all cases (copy before damaging).

    Under pytest-xdist the first worker to get here builds it in the run's common temporary folder
    and the others wait for it (a file lock) and share it; each still imports the library for its
    forked children."""
    from filelock import FileLock

    _warm_imports()
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        root = tmp_path_factory.mktemp("fuzzbase")
        _build_base(root)
        return root
    shared = tmp_path_factory.getbasetemp().parent
    root, complete = shared / "fuzzbase", shared / "fuzzbase.complete"
    with FileLock(str(shared / "fuzzbase.lock")):
        if not complete.is_file():
            shutil.rmtree(root, ignore_errors=True)
            root.mkdir()
            _build_base(root)
            complete.touch()
    return root


def _build_base(root: Path) -> None:
    _main_ok(["closed-form", root / "cap", "--views", 4, "--train-views", 2, "--res", 16, "--env-grid", 4, "--supersample", 1, "--seed", 1])
    _main_ok(["fit", root / "cap", "-o", root / "m.dam", "--steps", 3, "--batch-size", 64, "--holdout-views", 0])
    _main_ok(["synth-photos", root / "photos", "--views", 4, "--size", 32])
    (root / "mesh.obj").write_text(OCTAHEDRON_OBJ)
    _main_ok(["export", root / "m.dam", "--mesh", root / "mesh.obj", "-o", root / "frames", "--views", 1, "--resolution", 8])
    _main_ok(["segment", root / "cap", "-o", root / "seg", "--materials", 2, "--steps", 2, "--init-steps", 2,
              "--batch-pixels", 64, "--psi-resolution", 16])
    _main_ok(["segment-labels", root / "seg", "--mesh", root / "mesh.obj", "-o", root / "labels.npy"])
    _main_ok(["reconstruct", root / "photos" / "images", "-o", root / "rcap", "--masks", root / "photos" / "masks",
              "--poses", root / "photos" / "transforms.json", "--geometry", "sphere", "--capture-size", 32, "--train-views", 2])
    _main_ok(["linearize", root / "photos" / "images", "-o", root / "lin"])
    corpus = root / "corpus"
    (corpus / "captures").mkdir(parents=True)
    shutil.copytree(root / "cap", corpus / "captures" / "a")
    shutil.copytree(root / "cap", corpus / "captures" / "b")
    (corpus / "corpus.json").write_text(json.dumps({"captures": [
        {"path": "captures/a", "split": "train"}, {"path": "captures/b", "split": "train"}]}))
    _main_ok(["render", root / "m.dam", root / "cap", "-o", root / "rendered"])


@pytest.fixture()
def work(base, tmp_path) -> Path:
    """A private copy of every tiny input, for one case to damage."""
    dst = tmp_path / "w"
    shutil.copytree(base, dst, symlinks=True)
    return dst


def shipped_predictor() -> Path:
    import damcap.appearance.hyper as hyper
    return Path(hyper.__path__[0]) / "predictors" / "dam-predictor-v1.safetensors"


# ----------------------------------------------------------------------------------------------
# builders of hostile inputs

OCTAHEDRON_OBJ = """o octa
v 1 0 0
v -1 0 0
v 0 1 0
v 0 -1 0
v 0 0 1
v 0 0 -1
f 1 3 5
f 3 2 5
f 2 4 5
f 4 1 5
f 3 1 6
f 2 3 6
f 4 2 6
f 1 4 6
"""


def transforms(cap: Path) -> dict:
    return json.loads((cap / "transforms.json").read_text())


def set_transforms(cap: Path, doc) -> None:
    (cap / "transforms.json").write_text(doc if isinstance(doc, str) else json.dumps(doc))


def deep_json(depth: int = 100_000) -> str:
    return "[" * depth + "]" * depth


def safetensors_bytes(tensors: dict[str, np.ndarray], metadata: dict[str, str] | None) -> bytes:
    """A safetensors blob written by hand (so headers can lie)."""
    header, blobs, off = {}, [], 0
    dt = {np.dtype("float32"): "F32", np.dtype("float16"): "F16", np.dtype("float64"): "F64", np.dtype("int64"): "I64"}
    for name, a in tensors.items():
        b = np.ascontiguousarray(a).tobytes()
        header[name] = {"dtype": dt[a.dtype], "shape": list(a.shape), "data_offsets": [off, off + len(b)]}
        blobs.append(b); off += len(b)
    if metadata is not None:
        header["__metadata__"] = metadata
    h = json.dumps(header).encode()
    h += b" " * (-len(h) % 8)
    return struct.pack("<Q", len(h)) + h + b"".join(blobs)


def dam_parts(dam: Path) -> tuple[np.ndarray, dict]:
    """The weights and the damcap metadata of a .dam file."""
    data = dam.read_bytes()
    n = struct.unpack("<Q", data[:8])[0]
    header = json.loads(data[8:8 + n])
    meta = json.loads(header["__metadata__"]["damcap"])
    s, e = header["weights"]["data_offsets"]
    w = np.frombuffer(data[8 + n + s:8 + n + e], dtype=np.float32).copy()
    return w, meta


def write_dam(path: Path, weights: np.ndarray, meta: dict | str) -> Path:
    path.write_bytes(safetensors_bytes({"weights": weights}, {"damcap": meta if isinstance(meta, str) else json.dumps(meta)}))
    return path


def png_bomb(width: int, height: int) -> bytes:
    """A valid-looking PNG whose header claims width x height (tiny file, huge decode)."""
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    idat = zlib.compress(b"\0" * 4096)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def exr_claiming(src: Path, width: int, height: int) -> bytes:
    """A copy of an EXR whose dataWindow/displayWindow claim width x height."""
    data = bytearray(src.read_bytes())
    for name in (b"dataWindow\0box2i\0", b"displayWindow\0box2i\0"):
        i = data.find(name)
        if i >= 0:
            j = i + len(name) + 4
            data[j:j + 16] = struct.pack("<iiii", 0, 0, width - 1, height - 1)
    return bytes(data)


def corrupt(data: bytes, positions, values) -> bytes:
    b = bytearray(data)
    for p, v in zip(positions, values):
        if b:
            b[p % len(b)] = v
    return bytes(b)
