"""Inputs that parse but cannot be right, and runs that are killed, fill the disk or run out of
memory: each refused in one line naming the file and the value, before any output exists, and
what a run leaves is nothing, the earlier complete output, or leftovers the next run removes."""

from __future__ import annotations

import json
import os
import signal
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from tests.fuzz.conftest import damcap_fork, digest, refused, set_transforms, transforms

LIMIT = 30


# ----------------------------------------------------------------------------------------------
# numbers, formats and signals that cannot be right


def _camera(value):
    def f(w):
        d = transforms(w / "cap")
        d["frames"][1]["transform_matrix"][0][3] = value
        set_transforms(w / "cap", d)
        return w / "cap" / "transforms.json"
    return f


def _named_exr(content, geometry=False):
    def f(w):
        d = transforms(w / "cap")
        frame = next(fr for fr in d["frames"] if fr["file_path"] == d["train_filenames"][0])
        path = w / "cap" / frame["geometry_path" if geometry else "file_path"]
        path.write_bytes(content(w))
        return path
    return f


def _png(w) -> bytes:
    from damcap.common.exr import write_png

    write_png(w / "x.png", np.zeros((16, 16, 3), np.uint8))
    return (w / "x.png").read_bytes()


def _jpeg(w) -> bytes:
    return (w / "photos" / "images" / "IMG_0000.jpg").read_bytes()


def _no_foreground(w):
    from damcap.common.capture_folder import read_capture, read_frame, write_frame

    cap = read_capture(w / "cap")
    for f in cap.frames:
        d = read_frame(cap, f)
        d.coverage[:] = d.coverage * 0.4  # covered, never foreground (> 0.5)
        write_frame(cap, f, d)
    return w / "cap"


def _bracket(codes):
    def f(w):
        from damcap.common.exr import write_png

        for k in range(2):
            write_png(w / f"b{k}.png", codes)
        return w / "b0.png"
    return f


def _photos_of(value):
    def f(w):
        from damcap.common.exr import write_image_u8

        folder = w / "photos" / "images"
        for p in folder.iterdir():
            write_image_u8(p, np.full((32, 32, 3), value, np.uint8), {"Exif:ExposureTime": 0.01, "Exif:PhotographicSensitivity": 100,
                                                                        "Exif:FNumber": 4.0})
        return folder / "IMG_0000.jpg"
    return f


def _huge_mask(w):
    """A grey PNG whose header claims 60000x60000 (a 1 MiB private chunk keeps OpenImageIO's own
    header-to-file-size check quiet, as a real, well-compressed one does)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    mask = w / "photos" / "masks" / "IMG_0001.png"
    mask.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 60000, 60000, 8, 0, 0, 0, 0))
                     + chunk(b"prVt", bytes(2 ** 20)) + chunk(b"IDAT", zlib.compress(bytes(4096))) + chunk(b"IEND", b""))
    return mask


def _reconstruct(w, masks=False):
    p = w / "photos"
    return (["reconstruct", p / "images", "-o", w / "out", "--poses", p / "transforms.json", "--geometry", "sphere", "--capture-size", 32,
             "--train-views", 2] + (["--masks", p / "masks"] if masks else []))


# id -> (build(w) -> the file named, args(w), needles of the error line)
CASES = {
    "camera-centre-1e300": (_camera(1e300), lambda w: ["inspect", w / "cap"], ["transforms.json", "1e+300", "float32"]),
    "camera-centre-float32-max": (_camera(-3.5e38), lambda w: ["fit", w / "cap", "-o", w / "out", "--steps", 2], ["transforms.json", "float32"]),
    "camera-centre-1e12": (_camera(1e12), lambda w: ["render", w / "m.dam", w / "cap", "-o", w / "out"], ["transforms.json", "1000000000000.0", "times farther"]),
    "png-named-exr": (_named_exr(_png), lambda w: ["fit", w / "cap", "-o", w / "out", "--steps", 2], [".exr", "content is PNG, not OpenEXR"]),
    "jpeg-named-exr": (_named_exr(_jpeg, geometry=True), lambda w: ["fit", w / "cap", "-o", w / "out", "--steps", 2],
                       ["geometry/", ".exr", "content is JPEG"]),
    "text-named-exr": (_named_exr(lambda w: b'{"not": "pixels"}'), lambda w: ["segment", w / "cap", "-o", w / "out", "--materials", 2],
                       [".exr", "content is JSON text"]),
    "evaluate-no-foreground": (_no_foreground, lambda w: ["evaluate", w / "cap", "--model", w / "m.dam", "--json", w / "out"],
                               ["no frame has a foreground pixel", "largest coverage 0.4"]),
    "hdr-all-black": (_bracket(np.zeros((16, 16, 3), np.uint8)),
                      lambda w: ["hdr", w / "b0.png", w / "b1.png", "-o", w / "out.exr", "--exposures", "0.01,0.04"],
                      ["b0.png", "no pixel of the bracket is exposed", "largest merged radiance 0"]),
    "reconstruct-all-white": (_photos_of(255), lambda w: _reconstruct(w), ["IMG_0000.jpg", "saturated everywhere", "255"]),
    "reconstruct-all-black": (_photos_of(0), lambda w: _reconstruct(w), ["IMG_0000.jpg", "black everywhere", "largest value 0"]),
    "mask-60000-square-header": (_huge_mask, lambda w: _reconstruct(w, masks=True), ["IMG_0001.png", "60000x60000"]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_cannot_be_right_is_refused_before_any_output(case, work):
    build, args, needles = CASES[case]
    build(work)
    refused(args(work), *needles, outputs=[work / "out", work / "out.exr"], timeout=LIMIT)


# ----------------------------------------------------------------------------------------------
# killed, full disk, out of memory


CLOSED_FORM = ["--views", 6, "--train-views", 3, "--res", 48, "--env-grid", 4, "--supersample", 1]


def _staging(folder: Path, name: str):
    return lambda: any(p.name.startswith(f".{name}.staging-") and any(p.rglob("*.exr")) for p in folder.iterdir())


@pytest.mark.parametrize("earlier", [False, True])
def test_closed_form_killed_mid_write_leaves_nothing_or_the_earlier_capture(earlier, work):
    """kill -9 while the frames are written: OUT is absent (or the earlier capture, byte for byte);
    the next run removes the staging folder, saying so in one line, and completes."""
    out = work / "newcap"
    if earlier:
        assert damcap_fork(["closed-form", out, *CLOSED_FORM, "--seed", 1], timeout=LIMIT).code == 0
    before = digest(out)
    run = damcap_fork(["closed-form", out, *CLOSED_FORM, "--seed", 2], timeout=LIMIT, signal_when=(_staging(work, "newcap"), signal.SIGKILL))
    assert run.code == -signal.SIGKILL, (run.code, run.err[-300:])
    assert digest(out) == before, "the earlier capture changed (or a partial one appeared)"
    assert any(p.name.startswith(".newcap.staging-") for p in work.iterdir())
    again = damcap_fork(["closed-form", out, *CLOSED_FORM, "--seed", 2], timeout=LIMIT)
    assert again.code == 0, again.err[-300:]
    assert [ln for ln in again.lines if "removed what an interrupted earlier run left" in ln] == again.lines, again.lines
    assert sorted(p.name for p in work.iterdir() if p.name.startswith(".newcap")) == []
    assert json.loads((out / "transforms.json").read_text())["damcap_source"]["options"]["seed"] == 2


def test_linearize_killed_during_a_rerun_keeps_the_earlier_output(work):
    out = work / "lin"  # the base's earlier linearize output of the same photos
    before = digest(out)
    run = damcap_fork(["linearize", work / "photos" / "images", "-o", out, "--reference-exposure", 2.0], timeout=LIMIT,
                      signal_when=(_staging(work, "lin"), signal.SIGKILL))
    assert run.code == -signal.SIGKILL and digest(out) == before
    again = damcap_fork(["linearize", work / "photos" / "images", "-o", out, "--reference-exposure", 2.0], timeout=LIMIT)
    assert again.code == 0 and digest(out) != before and sorted(p.name for p in work.iterdir() if p.name.startswith(".lin")) == []


@pytest.mark.parametrize("command", ["closed-form", "reconstruct-rerun", "linearize-rerun"])
def test_a_full_disk_names_the_file_and_keeps_the_earlier_output(command, work):
    """The file-size limit cuts every write past 4 kB (SIGXFSZ ignored: a full disk): one line
    naming the file that filled, exit 2, the earlier output byte for byte, nothing staged left."""
    p = work / "photos"
    out = {"closed-form": work / "newcap", "reconstruct-rerun": work / "rcap", "linearize-rerun": work / "lin"}[command]
    args = {"closed-form": ["closed-form", out, *CLOSED_FORM],
            "reconstruct-rerun": ["reconstruct", p / "images", "-o", out, "--poses", p / "transforms.json", "--geometry", "sphere",
                                  "--capture-size", 48, "--train-views", 2, "--masks", p / "masks"],
            "linearize-rerun": ["linearize", p / "images", "-o", out, "--reference-exposure", 2.0]}[command]
    before, listing = digest(out), sorted(os.listdir(work))
    run = damcap_fork(args, timeout=LIMIT, fsize=4000)
    assert run.code == 2 and len(run.lines) == 1 and run.lines[0].startswith("error: "), run.err[-500:]
    assert "File too large (the file size limit, ulimit -f, is 4000 bytes)" in run.lines[0], run.lines
    assert ".tmp" not in run.lines[0] and "staging" not in run.lines[0], run.lines
    assert digest(out) == before and sorted(os.listdir(work)) == listing


def test_memory_running_out_is_one_line(work):
    run = damcap_fork(["closed-form", work / "newcap", "--views", 3, "--train-views", 2, "--res", 4000, "--supersample", 1],
                      timeout=LIMIT, memory=600 * 2 ** 20)
    assert run.code == 2 and len(run.lines) == 1 and run.lines[0].startswith("error: out of memory ("), run.err[-500:]
    assert not (work / "newcap").exists() and not [p for p in work.iterdir() if p.name.startswith(".newcap.")]


def test_reconstruct_killed_mid_rerun_keeps_the_earlier_capture(work):
    """kill -9 while a rerun writes its frames: the earlier capture is byte for byte as it was
    (its frames, transforms.json); the next run removes the staged frames and says so."""
    from damcap.common.capture_folder import inspect_capture

    p, out = work / "photos", work / "rcap"
    args = ["reconstruct", p / "images", "-o", out, "--poses", p / "transforms.json", "--geometry", "sphere", "--capture-size", 48,
            "--train-views", 2, "--masks", p / "masks", "--supersample", 3]
    capture_files = lambda: {q: digest(out / q) for q in ("transforms.json", "images", "geometry")}  # noqa: E731
    before = capture_files()
    staged = out / "reconstruction" / "frames.next"
    run = damcap_fork(args, timeout=LIMIT, signal_when=(lambda: staged.is_dir() and any(staged.rglob("*.exr")), signal.SIGKILL))
    assert run.code == -signal.SIGKILL, (run.code, run.err[-300:])
    assert capture_files() == before and inspect_capture(out).problems == []
    again = damcap_fork(args, timeout=LIMIT)
    assert again.code == 0 and f"removed: the frames an interrupted run left in {staged}" in again.out, again.out[-500:] + again.err[-300:]
    assert capture_files() != before and not staged.exists() and inspect_capture(out).problems == []
