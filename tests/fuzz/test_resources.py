"""Hostile sizes are refused quickly: each case runs under a 10 s limit and 3 GiB of memory
(``damcap_fork`` kills it past either), and must end in a one-line error naming the file/option."""

from __future__ import annotations

import os

import pytest

from tests.fuzz.conftest import (dam_parts, deep_json, exr_claiming, png_bomb, refused, set_transforms, transforms,
                                 write_dam)

LIMIT = 10


def _arch(**kv):
    def f(w):
        wts, m = dam_parts(w / "m.dam")
        m["architecture"].update(kv)
        write_dam(w / "bad.dam", wts, m)
        return w / "bad.dam"
    return f


def _frame0(w):
    cap = w / "cap"
    return cap / transforms(cap)["train_filenames"][0]


def _cap_edit(**kv):
    def f(w):
        d = transforms(w / "cap")
        d.update(kv)
        set_transforms(w / "cap", d)
        return w / "cap" / "transforms.json"
    return f


def _many_frames(w):
    d = transforms(w / "cap")
    d["frames"] = d["frames"] * 200_000
    set_transforms(w / "cap", d)
    return w / "cap" / "transforms.json"


def _ply_bomb(w):
    p = w / "bomb.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\nproperty float x\nproperty float y\n"
                  b"property float z\nelement face 1000000000000\nproperty list uchar int vertex_indices\nend_header\n" + b"\0" * 64)
    return p


def _obj_bomb(w):
    p = w / "bomb.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 1000000000000000\n")
    return p


def _npy_bomb(w):
    p = w / "bomb.npy"
    hdr = "{'descr': '<i8', 'fortran_order': False, 'shape': (1000000000000,), }"
    hdr = hdr + " " * (-(len(hdr) + 11) % 64) + "\n"
    p.write_bytes(b"\x93NUMPY\x01\x00" + len(hdr).to_bytes(2, "little") + hdr.encode() + b"\0" * 64)
    return p


def _exr_bomb(w):
    f = _frame0(w)
    f.write_bytes(exr_claiming(f, 200_000, 200_000))
    return f


def _png_bomb_photo(w):
    p = w / "photos" / "images" / "IMG_0001.jpg"
    p.unlink()
    q = p.with_suffix(".png")
    q.write_bytes(png_bomb(100_000, 100_000))
    return q


def _fifo_frame(w):
    f = _frame0(w)
    f.unlink()
    os.mkfifo(f)
    return f


def _dev_zero_frame(w):
    f = _frame0(w)
    f.unlink()
    os.symlink("/dev/zero", f)
    return f


def _seg_materials(w):
    import json
    s = w / "seg" / "segment.json"
    d = json.loads(s.read_text())
    d["materials"] = 10**9
    s.write_text(json.dumps(d))
    return s


# id -> (build(w) -> the hostile file, args(w, file), needle)
CASES = {
    "dam-width-1e9": (_arch(width=10**9), lambda w, f: ["export", f, "--format", "glsl", "-o", w / "out"], "bad.dam"),
    "dam-depth-1e9": (_arch(depth=10**9), lambda w, f: ["export", f, "--format", "glsl", "-o", w / "out"], "bad.dam"),
    "dam-width-1e5-depth-1e5": (_arch(width=10**5, depth=10**5), lambda w, f: ["render", f, w / "cap", "-o", w / "out"], "bad.dam"),
    "dam-header-claims-huge-tensor": (lambda w: _huge_tensor_dam(w), lambda w, f: ["render", f, w / "cap", "-o", w / "out"], "bad.dam"),
    "transforms-w-h-1e9": (_cap_edit(w=10**9, h=10**9), lambda w, f: ["fit", w / "cap", "-o", w / "out", "--steps", 2], "transforms.json"),
    "transforms-materials-1e12": (_cap_edit(materials=10**12), lambda w, f: ["fit", w / "cap", "-o", w / "out", "--steps", 2], "transforms.json"),
    "transforms-800k-frames": (_many_frames, lambda w, f: ["fit", w / "cap", "-o", w / "out", "--steps", 2], "transforms.json"),
    "transforms-nested-1e6": (lambda w: (set_transforms(w / "cap", deep_json(10**6)), w / "cap" / "transforms.json")[1],
                              lambda w, f: ["inspect", w / "cap"], "transforms.json"),
    "exr-claims-200k-square": (_exr_bomb, lambda w, f: ["fit", w / "cap", "-o", w / "out", "--steps", 2], "exr"),
    "frame-is-fifo": (_fifo_frame, lambda w, f: ["fit", w / "cap", "-o", w / "out", "--steps", 2], "exr"),
    "frame-is-dev-zero": (_dev_zero_frame, lambda w, f: ["fit", w / "cap", "-o", w / "out", "--steps", 2], "exr"),
    "png-bomb-photo-linearize": (_png_bomb_photo, lambda w, f: ["linearize", w / "photos" / "images", "-o", w / "out"], "IMG_0001.png"),
    "png-bomb-hdr": (lambda w: (w / "bomb.png").write_bytes(png_bomb(100_000, 100_000)) and w / "bomb.png",
                     lambda w, f: ["hdr", f, w / "photos" / "images" / "IMG_0000.jpg", "-o", w / "out.exr", "--exposures", "0.01,0.02"], "bomb.png"),
    "ply-claims-1e12-vertices": (_ply_bomb, lambda w, f: ["export", w / "m.dam", "--mesh", f, "-o", w / "out", "--views", 1, "--resolution", 8], "bomb.ply"),
    "obj-index-1e15": (_obj_bomb, lambda w, f: ["view", w / "m.dam", "--mesh", f, "-o", w / "out"], "bomb.obj"),
    "labels-npy-claims-1e12": (_npy_bomb, lambda w, f: ["export", w / "seg" / "material_0.dam", w / "seg" / "material_1.dam", "--mesh", w / "mesh.obj",
                                                         "--labels", f, "-o", w / "out", "--views", 1, "--resolution", 8], "bomb.npy"),
    "segment-json-materials-1e9": (_seg_materials, lambda w, f: ["segment-labels", w / "seg", "--mesh", w / "mesh.obj", "-o", w / "out.npy"], "segment.json"),
    # unbounded sizes through options
    "fit-width-1e6": (lambda w: None, lambda w, f: ["fit", w / "cap", "-o", w / "out", "--width", 10**6, "--steps", 2], "--width"),
    "fit-depth-1e5": (lambda w: None, lambda w, f: ["fit", w / "cap", "-o", w / "out", "--depth", 10**5, "--steps", 2], "--depth"),
    "fit-batch-1e12": (lambda w: None, lambda w, f: ["fit", w / "cap", "-o", w / "out", "--batch-size", 10**12, "--steps", 2], "--batch-size"),
    "closed-form-res-1e6": (lambda w: None, lambda w, f: ["closed-form", w / "out", "--res", 10**6, "--views", 2, "--train-views", 1], "--res"),
    "closed-form-views-1e9": (lambda w: None, lambda w, f: ["closed-form", w / "out", "--res", 8, "--views", 10**9, "--train-views", 1], "--views"),
    "export-resolution-1e6": (lambda w: None, lambda w, f: ["export", w / "m.dam", "--mesh", w / "mesh.obj", "-o", w / "out", "--views", 1, "--resolution", 10**6], "--resolution"),
    "export-views-1e9": (lambda w: None, lambda w, f: ["export", w / "m.dam", "--mesh", w / "mesh.obj", "-o", w / "out", "--views", 10**9, "--resolution", 8], "--views"),
    "segment-materials-1e6": (lambda w: None, lambda w, f: ["segment", w / "cap", "-o", w / "out", "--materials", 10**6], "--materials"),
    "segment-max-materials-1e6": (lambda w: None, lambda w, f: ["segment", w / "cap", "-o", w / "out", "--max-materials", 10**6], "--max-materials"),
    "reconstruct-voxels-1e6": (lambda w: None, lambda w, f: ["reconstruct", w / "photos" / "images", "-o", w / "out", "--poses", w / "photos" / "transforms.json",
                                                           "--geometry", "visual-hull", "--masks", w / "photos" / "masks", "--voxels", 10**6], "--voxels"),
    "reconstruct-capture-size-1e6": (lambda w: None, lambda w, f: ["reconstruct", w / "photos" / "images", "-o", w / "out", "--poses", w / "photos" / "transforms.json",
                                                                 "--geometry", "sphere", "--capture-size", 10**6], "--capture-size"),
    "train-hyper-channels-1e6": (lambda w: None, lambda w, f: ["train-hyper", w / "corpus", "-o", w / "out", "--channels", "1000000,1000000", "--steps", 1], "--channels"),
    "train-hyper-input-size-1e6": (lambda w: None, lambda w, f: ["train-hyper", w / "corpus", "-o", w / "out", "--input-size", 10**6, "--steps", 1], "--input-size"),
    "hdr-response-samples-1e10": (lambda w: None, lambda w, f: ["hdr", w / "photos" / "images" / "IMG_0000.jpg", w / "photos" / "images" / "IMG_0001.jpg",
                                                              "-o", w / "out", "--response-samples", 10**10], "--response-samples"),
    "synth-photos-size-1e6": (lambda w: None, lambda w, f: ["synth-photos", w / "out", "--size", 10**6, "--views", 2], "--size"),
    "predict-refine-1e12": (lambda w: None, lambda w, f: ["predict", w / "cap", "-o", w / "out", "--refine-steps", 10**12], "--refine-steps"),
}


def _huge_tensor_dam(w):
    import json
    import struct
    wts, m = dam_parts(w / "m.dam")
    header = {"weights": {"dtype": "F32", "shape": [10**12], "data_offsets": [0, 4 * 10**12]}, "__metadata__": {"damcap": json.dumps(m)}}
    h = json.dumps(header).encode()
    h += b" " * (-len(h) % 8)
    (w / "bad.dam").write_bytes(struct.pack("<Q", len(h)) + h + wts.tobytes())
    return w / "bad.dam"


@pytest.mark.parametrize("case", sorted(CASES))
def test_hostile_size_refused_quickly(case, work):
    build, args, needle = CASES[case]
    f = build(work)
    run = refused(args(work, f), needle, inputs=[work / "cap", work / "photos", work / "m.dam", work / "seg", work / "corpus"],
                  outputs=[work / "out"], timeout=LIMIT, memory=3 * 2**30)
    assert run.seconds < LIMIT


MEMORY_BOUND_300_VIEWS = 2 * 1024 ** 3
"""docs/model.md's stated bound for `damcap fit` on a capture of 300 views at 64 px (measured peak:
1.16 GB with the default path, 50 steps; 1.13 GB with 2000)"""


@pytest.mark.slow
def test_a_300_view_capture_fits_within_the_stated_memory_bound(tmp_path):
    """The fit of 300 views at 64 px (758,400 training pixels) in a child process, at its defaults
    but for few steps (memory follows the pixels, not the steps): its peak resident memory stays
    under the bound docs/model.md states."""
    import subprocess
    import sys

    cap = tmp_path / "c300"
    damcap = [sys.executable, "-c", "from damcap.cli.console import run; run()"]
    subprocess.run([*damcap, "closed-form", str(cap), "--views", "301", "--res", "64", "--train-views", "300", "--seed", "1"],
                   check=True, capture_output=True)
    # a fresh parent whose only child is the fit, so that its peak is the fit's alone (KiB on Linux)
    meter = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
             "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); sys.exit(r.returncode)")
    run = subprocess.run([sys.executable, "-c", meter, *damcap, "fit", str(cap), "-o", str(tmp_path / "m.dam"), "--steps", "50",
                          "--normal-refine-steps", "4"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    peak_bytes = int(run.stderr.strip().splitlines()[-1]) * 1024
    assert "758400 pixels" in run.stdout
    assert 0 < peak_bytes < MEMORY_BOUND_300_VIEWS, peak_bytes
