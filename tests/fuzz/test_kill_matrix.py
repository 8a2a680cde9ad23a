"""kill -9 at an early, a middle and a late moment of every command that writes: what is left is
nothing, the earlier complete output, or a state the same command resumes; and the rerun then
completes to exactly what an uninterrupted run writes.

The moments are chosen by the test hook of common/atomic.py (``DAMCAP_TEST_PAUSE_AT``), not by
sleeps: the child stops for good at a named point and says so on stderr, and only then is it
killed, so each case kills at the same point however loaded the machine is:

- early: the outputs are locked (``.OUT.lock``), nothing is written yet;
- middle: a part of the work is on disk: a staged frame, a first checkpoint, a first photo (a
  command that writes one file at the end has no such part: it is killed while its staged file
  is being written, that is as soon as the temporary file appears);
- late: everything is written and staged, the swap into place is next.

Outputs are compared by content, ignoring what legitimately differs between two runs of the same
command (:func:`normalised`): the ``DateTime`` attribute OpenImageIO stamps into EXRs, and JSON
keys that hold wall-clock timings (``seconds``, ``*_seconds``), also inside a .dam's metadata.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pytest

from damcap.common.atomic import PAUSE_ENV
from tests.fuzz.conftest import damcap_fork

LIMIT = 40
PAUSED = "damcap test hook: paused before"
#: names of what a run stages or sets aside (removed by the next run), never part of an output
STAGED = re.compile(r"^\..*(\.tmp|\.staging-|\.replaced-)|\.lock$|^frames\.(next|previous)$")


# ----------------------------------------------------------------------------------------------
# content, ignoring what differs between two runs


def _drop_timings(doc):
    if isinstance(doc, dict):
        return {k: _drop_timings(v) for k, v in doc.items() if not (k == "seconds" or k.endswith("_seconds"))}
    if isinstance(doc, list):
        return [_drop_timings(v) for v in doc]
    return doc


def normalised(path: Path) -> str:
    """A file's content hash, without the EXR ``DateTime`` stamp and JSON timings."""
    data = path.read_bytes()
    if path.suffix == ".exr":
        import OpenImageIO as oiio

        img = oiio.ImageInput.open(str(path))
        spec = img.spec()
        pixels = img.read_image(format="float")
        img.close()
        attrs = sorted((a.name, str(a.value)) for a in spec.extra_attribs if a.name != "DateTime")
        return hashlib.sha256(pixels.tobytes() + json.dumps(attrs).encode()).hexdigest()
    if path.suffix == ".json":
        return hashlib.sha256(json.dumps(_drop_timings(json.loads(data)), sort_keys=True).encode()).hexdigest()
    if path.suffix == ".dam":  # safetensors: the tensors as they are, the metadata without timings
        n = struct.unpack("<Q", data[:8])[0]
        header = json.loads(data[8:8 + n])
        meta = {k: _drop_timings(json.loads(v)) if k == "damcap" else v for k, v in header.pop("__metadata__", {}).items()}
        return hashlib.sha256(json.dumps([header, meta], sort_keys=True).encode() + data[8 + n:]).hexdigest()
    return hashlib.sha256(data).hexdigest()


def snapshot(case: Path, names: tuple[str, ...], normalise: bool = False) -> dict[str, str] | None:
    """``{relative path: hash}`` of the output ``names`` (a file or a folder, and its sidecars) in
    ``case``, staged leftovers left out (``normalise``: by :func:`normalised`, else the bytes);
    None when none of them exists."""
    found = {}
    for name in names:
        p = case / name
        files = [p] if p.is_file() else sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else []
        for q in files:
            rel = q.relative_to(case)
            if not any(STAGED.search(part) for part in rel.parts):
                found[str(rel)] = normalised(q) if normalise else hashlib.sha256(q.read_bytes()).hexdigest()
    return found if any((case / n).exists() for n in names) else None


# ----------------------------------------------------------------------------------------------
# the commands


@dataclass(frozen=True)
class Writer:
    args: Callable[[Path, Path], list]
    """(base, case folder) -> damcap's arguments, writing ``names[0]`` in the case folder"""
    names: tuple[str, ...]
    """the output, then the files written beside it"""
    moments: dict[str, str]
    """moment -> ``DAMCAP_TEST_PAUSE_AT`` (``"tmp"``: killed once the staged file appears)"""
    previous: Callable[[Path, Path], None] | None = None
    """puts an earlier complete output (other options) in the case folder"""
    resumable: Callable[[Path], bool] | None = None
    """a killed run's state (other than nothing or the earlier output) that a rerun resumes"""
    beside: tuple[str, ...] = field(default=())
    """what a killed run may keep beside the output for the rerun to resume (a checkpoint)"""


def _copy(src: str, dst: str = "o"):
    def put(base: Path, case: Path) -> None:
        (shutil.copytree if (base / src).is_dir() else shutil.copy2)(base / src, case / dst)
    return put


def _env() -> Path:
    from damcap.common.data_dir import shared_data_dir

    return shared_data_dir(fallback=Path(__file__).resolve().parents[2].parent / "shared" / "data") / "envmaps" / "studio.hdr"


def _hdr(base: Path, case: Path, exposures: str) -> list:
    return ["hdr", *(base / "photos" / "images" / f"IMG_000{k}.jpg" for k in (0, 1)), "-o", case / "o.exr", "--exposures", exposures,
            "--response", "srgb"]  # not the Debevec fit's time


_EARLIER: dict[str, Path] = {}


def _earlier_hdr(base: Path, case: Path) -> None:
    """An earlier hdr output (other exposures) in the case folder: made once per test process."""
    if "hdr" not in _EARLIER:
        made = case.parent / "earlier-hdr"
        made.mkdir()
        run = damcap_fork(_hdr(base, made, "0.02,0.05"), timeout=LIMIT)
        assert run.code == 0, f"the earlier run failed: {run.err[-300:]}"
        _EARLIER["hdr"] = made
    for name in ("o.exr", "o.exr.json"):
        shutil.copy2(_EARLIER["hdr"] / name, case / name)


def _reconstruct(base: Path, case: Path) -> list:
    p = base / "photos"
    return ["reconstruct", p / "images", "-o", case / "o", "--masks", p / "masks", "--poses", p / "transforms.json", "--geometry", "sphere",
            "--capture-size", 24, "--train-views", 2, "--self-check", "off"]  # the check's time, not the staging's


CF = ["--views", 4, "--train-views", 2, "--res", 16, "--env-grid", 4, "--supersample", 1]
EARLY = ".o.lock"
FILE_MOMENTS = {"early": ".o.dam.lock", "middle": "tmp", "late": "o.dam"}

WRITERS: dict[str, Writer] = {
    "closed-form": Writer(lambda b, c: ["closed-form", c / "o", *CF, "--seed", 2], ("o",),
                          {"early": EARLY, "middle": "*.exr#2", "late": "o"}, previous=_copy("cap")),
    "reconstruct": Writer(_reconstruct, ("o",), {"early": EARLY, "middle": "*.exr#2", "late": "o"}, previous=_copy("rcap")),
    # into a new folder: a killed run may leave the folder with only its work folder, which the rerun resumes from
    "reconstruct-new": Writer(_reconstruct, ("o",), {"early": EARLY, "middle": "*.exr#2", "late": "o"},
                              resumable=lambda out: (out / "reconstruction").is_dir() and not (out / "transforms.json").exists()),
    "fit": Writer(lambda b, c: ["fit", b / "cap", "-o", c / "o.dam", "--steps", 8, "--batch-size", 64, "--holdout-views", 0,
                                "--checkpoint-every", 2], ("o.dam",),
                  {"early": ".o.dam.lock", "middle": "o.dam.ckpt#2", "late": "o.dam"}, previous=_copy("m.dam", "o.dam"),
                  beside=("o.dam.ckpt",)),
    "segment": Writer(lambda b, c: ["segment", b / "cap", "-o", c / "o", "--materials", 2, "--steps", 3, "--init-steps", 2,
                                    "--batch-pixels", 64, "--psi-resolution", 16], ("o",),
                      {"early": EARLY, "middle": "*.exr#2", "late": "o"}, previous=_copy("seg")),
    "predict": Writer(lambda b, c: ["predict", b / "cap", "-o", c / "o.dam"], ("o.dam",), FILE_MOMENTS, previous=_copy("m.dam", "o.dam")),
    "render": Writer(lambda b, c: ["render", b / "m.dam", b / "cap", "-o", c / "o", "--split", "all"], ("o",),
                     {"early": EARLY, "middle": "*.exr#2", "late": "o"}, previous=_copy("rendered")),
    "export": Writer(lambda b, c: ["export", b / "m.dam", "--mesh", b / "mesh.obj", "-o", c / "o", "--views", 2, "--resolution", 8],
                     ("o",), {"early": EARLY, "middle": "0000.png", "late": "o"}, previous=_copy("frames")),
    "hdr": Writer(lambda b, c: _hdr(b, c, "0.01,0.04"), ("o.exr", "o.exr.json"), {"early": ".o.exr.lock", "middle": "tmp", "late": "o.exr"},
                  previous=_earlier_hdr),
    "linearize": Writer(lambda b, c: ["linearize", b / "photos" / "images", "-o", c / "o", "--reference-exposure", 2.0], ("o",),
                        {"early": EARLY, "middle": "*.exr#2", "late": "o"}, previous=_copy("lin")),
    "synth-studio": Writer(lambda b, c: ["synth-studio", c / "o", "--object", b / "mesh.obj", "--env", _env(), "--views", 3, "--size", 8,
                                         "--spp", 1], ("o",),
                           {"early": EARLY, "middle": "IMG_0001.jpg", "late": "transforms.json"},
                           resumable=lambda out: (out / ".studio_partial.json").is_file()),
}

CASES = [(name, moment) for name, w in WRITERS.items() for moment in w.moments]


def _trigger(case: Path, w: Writer, moment: str):
    """The kill's trigger and the pause it waits at (or behind)."""
    spec = w.moments[moment]
    if spec != "tmp":
        return PAUSED, spec
    out = Path(w.names[0])
    return (lambda: any(p.name.startswith(f".{out.stem}.") and p.name.endswith(f".tmp{out.suffix}") for p in case.iterdir())), w.names[0]


_REFERENCE: dict[str, dict[str, str]] = {}


def reference(name: str, base: Path, tmp_path_factory) -> dict[str, str]:
    """What an uninterrupted run writes (once per command and test process), by normalised content."""
    if name not in _REFERENCE:
        w = WRITERS[name]
        case = tmp_path_factory.mktemp(f"ref-{name}")
        run = damcap_fork(w.args(base, case), timeout=LIMIT)
        assert run.code == 0, f"uninterrupted run failed: {run.err[-400:]}"
        _REFERENCE[name] = snapshot(case, w.names, normalise=True)
    return _REFERENCE[name]


_BOARDS: dict[tuple, object] = {}


def _board_made_once(monkeypatch) -> None:
    """synth-studio spends seconds on its board's texture, the same for every run of the same
    options: made once here, in the test process, which every forked run inherits (the photos are
    byte for byte what they are without this)."""
    import damcap.synth.studio as studio

    original = studio.board_albedo

    def board(*args):
        if args not in _BOARDS:
            _BOARDS[args] = original(*args)
        return _BOARDS[args].copy()

    monkeypatch.setattr(studio, "board_albedo", board)
    opts = studio.StudioOptions()
    board(opts.board_size, opts.board_saturation, opts.seed)


@pytest.mark.parametrize("name,moment", CASES, ids=[f"{n}-{m}" for n, m in CASES])
def test_killed_leaves_nothing_the_earlier_output_or_a_resumable_state(name, moment, base, tmp_path, tmp_path_factory, monkeypatch):
    w = WRITERS[name]
    if name == "synth-studio":
        _board_made_once(monkeypatch)
    want = reference(name, base, tmp_path_factory)
    case = tmp_path / "case"
    case.mkdir()
    if w.previous is not None:
        w.previous(base, case)
    before = snapshot(case, w.names)
    trigger, pause = _trigger(case, w, moment)
    run = damcap_fork(w.args(base, case), timeout=LIMIT, env={PAUSE_ENV: pause}, signal_when=(trigger, signal.SIGKILL))
    assert run.code == -signal.SIGKILL, f"not killed at the {moment} moment ({pause}): exit {run.code}; {run.err[-400:]}"

    left = snapshot(case, w.names)
    out = case / w.names[0]
    if left == before:
        outcome = "nothing" if before is None else "earlier output"
    else:
        assert w.resumable is not None and w.resumable(out), (
            f"killed {moment}: neither nothing, nor the earlier output, nor a state {name} resumes; changed: "
            f"{sorted(k for k in set(left or {}) | set(before or {}) if (left or {}).get(k) != (before or {}).get(k))[:6]}")
        outcome = "resumable"
    stray = sorted(p.name for p in case.iterdir() if p.name not in w.names + w.beside and not STAGED.search(p.name))
    assert not stray, f"killed {moment} ({outcome}): stray files beside the output: {stray}"
    kept = [n for n in w.beside if (case / n).exists()]

    again = damcap_fork(w.args(base, case), timeout=LIMIT)
    assert again.code == 0, f"rerun after a kill {moment} ({outcome}) failed: {again.err[-400:]}"
    if kept:  # what was kept beside the output is what the rerun resumes from
        assert "resum" in (again.err + again.out).lower(), f"kept {kept} but the rerun did not resume: {again.err[-300:]}"
        outcome += f", {' '.join(kept)} kept and resumed"
    print(f"{name} killed {moment} ({w.moments[moment]}): {outcome}; the rerun is identical to an uninterrupted run")
    assert sorted(os.listdir(case)) == sorted(n for n in w.names), f"left beside the output after the rerun: {sorted(os.listdir(case))}"
    if out.is_dir():
        staged = [str(p.relative_to(out)) for p in out.rglob("*") if STAGED.search(p.name)]
        assert not staged, f"left inside the output after the rerun: {staged[:4]}"
    got = snapshot(case, w.names, normalise=True)
    differ = sorted(k for k in set(got) | set(want) if got.get(k) != want.get(k))
    assert not differ, f"the rerun after a kill {moment} ({outcome}) differs from an uninterrupted run: {differ[:6]}"
