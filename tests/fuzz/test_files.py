"""Broken and hostile files, per reader: each refused in one line naming the file, inputs intact.

Readers: .dam, segmentation folder, predictor, transforms.json, EXR frames, photos (JPEG/PNG/RAW),
masks, meshes (OBJ/PLY/GLB), pose files, labels, corpus.json, hdr brackets. Random corruption of a
valid .dam / EXR / transforms.json (hypothesis) must be either read or refused cleanly.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import tempfile
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.fuzz.conftest import (accepted_or_refused, corrupt, dam_parts, deep_json, refused, safetensors_bytes,
                                 set_transforms, shipped_predictor, transforms, write_dam)

# ---------------------------------------------------------------- .dam ------------------------


def _meta_edit(**kv):
    def f(w, m):
        m.update(kv)
        return w, m
    return f


def _arch_edit(**kv):
    def f(w, m):
        m["architecture"].update(kv)
        return w, m
    return f


DAM_CASES = {
    "empty": lambda p, w, m: p.write_bytes(b""),
    "random-bytes": lambda p, w, m: p.write_bytes(os.urandom(4096)),
    "truncated": lambda p, w, m: p.write_bytes(p.read_bytes()[:200]),
    "truncated-weights": lambda p, w, m: p.write_bytes(p.read_bytes()[:-100]),
    "pickle": lambda p, w, m: p.write_bytes(pickle.dumps({"weights": w})),
    "json-text": lambda p, w, m: p.write_text(json.dumps(m)),
    "no-metadata": lambda p, w, m: p.write_bytes(safetensors_bytes({"weights": w}, None)),
    "metadata-not-json": lambda p, w, m: write_dam(p, w, "{not json"),
    "metadata-deeply-nested": lambda p, w, m: write_dam(p, w, deep_json(50_000)),
    "metadata-a-list": lambda p, w, m: write_dam(p, w, "[1, 2]"),
    "header-length-huge": lambda p, w, m: p.write_bytes((2**62).to_bytes(8, "little") + p.read_bytes()[8:]),
    "two-tensors": lambda p, w, m: p.write_bytes(safetensors_bytes({"weights": w, "extra": w}, {"damcap": json.dumps(m)})),
    "weights-float64": lambda p, w, m: p.write_bytes(safetensors_bytes({"weights": w.astype(np.float64) * 0}, {"damcap": json.dumps(m)}) if False else safetensors_bytes({"weights": w.reshape(-1, 1)}, {"damcap": json.dumps(m)})),
    "weights-short": lambda p, w, m: write_dam(p, w[:-1], m),
    "weights-nan": lambda p, w, m: write_dam(p, np.where(np.arange(w.size) == 7, np.nan, w).astype(np.float32), m),
    "weights-inf": lambda p, w, m: write_dam(p, np.where(np.arange(w.size) == 7, np.inf, w).astype(np.float32), m),
    "weights-huge-finite": lambda p, w, m: write_dam(p, (w * 0 + 3e38).astype(np.float32), m),
}
META_CASES = {
    "version-99": _meta_edit(format_version=99),
    "version-string": _meta_edit(format_version="1"),
    "version-missing": lambda w, m: (w, {k: v for k, v in m.items() if k != "format_version"}),
    "scale-nan": _meta_edit(radiance_scale=float("nan")),
    "scale-inf": _meta_edit(radiance_scale=float("inf")),
    "scale-negative": _meta_edit(radiance_scale=-1.0),
    "scale-zero": _meta_edit(radiance_scale=0.0),
    "scale-inf-in-float32": _meta_edit(radiance_scale=1e39),
    "scale-string": _meta_edit(radiance_scale="bright"),
    "scale-bool": _meta_edit(radiance_scale=True),
    "colorspace-unknown": _meta_edit(colorspace="prophoto"),
    "architecture-null": _meta_edit(architecture=None),
    "width-zero": _arch_edit(width=0),
    "width-negative": _arch_edit(width=-32),
    "width-float": _arch_edit(width=32.5),
    "width-string": _arch_edit(width="32"),
    "width-whole-float": lambda w, m: (w, {**m, "architecture": {**m["architecture"], "width": float(m["architecture"]["width"])}}),
    "depth-whole-float": lambda w, m: (w, {**m, "architecture": {**m["architecture"], "depth": float(m["architecture"]["depth"])}}),
    "width-bool": _arch_edit(width=True),
    "depth-zero": _arch_edit(depth=0),
    "activation-unknown": _arch_edit(activation="gelu9"),
    "encoding-unknown": _arch_edit(encoding="xyz"),
    "unknown-arch-field": _arch_edit(dropout=0.5),
    "separable-odd-width": _arch_edit(separable=True, width=33),
}


def _dam_readers(w: Path, dam: Path):
    return {
        "render": (["render", dam, w / "cap", "-o", w / "out"], w / "out"),
        "export-glsl": (["export", dam, "--format", "glsl", "-o", w / "out"], w / "out"),
        "view": (["view", dam, "-o", w / "out"], w / "out"),
        "evaluate": (["evaluate", w / "cap", "--model", dam, "--json", w / "out"], w / "out"),
    }


def _dam_case_refused(case, reader, work):
    """Damage a copy of the fitted model as ``case`` says and check ``reader`` refuses it."""
    dam = work / "bad.dam"
    shutil.copy(work / "m.dam", dam)
    w, m = dam_parts(dam)
    if case in DAM_CASES:
        DAM_CASES[case](dam, w, m)
    else:
        write_dam(dam, *META_CASES[case](w, m))
    args, out = _dam_readers(work, dam)[reader]
    refused(args, "bad.dam", inputs=[dam, work / "cap"], outputs=[out])


@pytest.mark.parametrize("reader", ["render", "export-glsl"])
@pytest.mark.parametrize("case", sorted(DAM_CASES) + sorted(META_CASES))
def test_dam(case, reader, work):
    _dam_case_refused(case, reader, work)


@pytest.mark.parametrize("reader", ["view", "evaluate"])
@pytest.mark.parametrize("case", ["random-bytes", "scale-inf-in-float32", "weights-nan"])
def test_dam_other_readers(case, reader, work):
    _dam_case_refused(case, reader, work)


def test_dam_is_a_directory(work):
    (work / "d.dam").mkdir()
    refused(["render", work / "d.dam", work / "cap", "-o", work / "out"], "d.dam", inputs=[work / "cap"], outputs=[work / "out"])


def test_dam_is_the_predictor(work):
    refused(["render", shipped_predictor(), work / "cap", "-o", work / "out"], "dam-predictor-v1.safetensors",
            inputs=[work / "cap"], outputs=[work / "out"])


FUZZ = settings(max_examples=8, deadline=timedelta(seconds=30), suppress_health_check=list(HealthCheck), derandomize=True)


@FUZZ
@given(pos=st.lists(st.integers(0, 10**6), min_size=1, max_size=6), val=st.lists(st.integers(0, 255), min_size=6, max_size=6))
def test_dam_random_corruption(base, pos, val):
    with tempfile.TemporaryDirectory() as td:
        dam = Path(td) / "c.dam"
        data = (base / "m.dam").read_bytes()
        n = int.from_bytes(data[:8], "little")
        dam.write_bytes(corrupt(data, [p % (n + 8) for p in pos], val))  # the header: the hostile part
        accepted_or_refused(["export", dam, "--format", "glsl", "-o", Path(td) / "o.glsl"], inputs=[dam], outputs=[Path(td) / "o.glsl"])


@FUZZ
@given(pos=st.lists(st.integers(0, 10**6), min_size=1, max_size=8), val=st.lists(st.integers(0, 255), min_size=8, max_size=8))
def test_exr_random_corruption(base, pos, val):
    with tempfile.TemporaryDirectory() as td:
        cap = Path(td) / "cap"
        shutil.copytree(base / "cap", cap)
        f = cap / transforms(cap)["train_filenames"][0]
        data = f.read_bytes()
        f.write_bytes(corrupt(data, [p % 400 for p in pos], val))  # the header region
        accepted_or_refused(["fit", cap, "-o", Path(td) / "m.dam", "--steps", 2, "--batch-size", 64, "--holdout-views", 0],
                            inputs=[cap], outputs=[Path(td) / "m.dam"])


@FUZZ
@given(cut=st.integers(0, 10**5), ch=st.sampled_from(list('{}[],:"0-eE.nN ')))
def test_transforms_random_corruption(base, cut, ch):
    with tempfile.TemporaryDirectory() as td:
        cap = Path(td) / "cap"
        shutil.copytree(base / "cap", cap)
        text = (cap / "transforms.json").read_text()
        i = cut % len(text)
        (cap / "transforms.json").write_text(text[:i] + ch + text[i + 1:])
        accepted_or_refused(["fit", cap, "-o", Path(td) / "m.dam", "--steps", 2, "--batch-size", 64, "--holdout-views", 0],
                            inputs=[cap], outputs=[Path(td) / "m.dam"])


# ---------------------------------------------------------------- transforms.json -------------


def _tr(fn):
    def edit(cap):
        doc = transforms(cap)
        r = fn(doc, cap)
        set_transforms(cap, doc if r is None else r)
    return edit


def _frame0(**kv):
    return _tr(lambda d, c: d["frames"][0].update(kv))


TRANSFORMS = {
    "empty-file": (lambda c: set_transforms(c, ""), []),
    "null": (lambda c: set_transforms(c, "null"), []),
    "a-list": (lambda c: set_transforms(c, "[]"), []),
    "deeply-nested": (lambda c: set_transforms(c, deep_json(200_000)), []),
    "utf8-bom": (lambda c: (c / "transforms.json").write_bytes(b"\xef\xbb\xbf" + (c / "transforms.json").read_bytes()), []),
    "not-utf8": (lambda c: (c / "transforms.json").write_bytes(b'{"frames": "\xff\xfe"}'), []),
    "frames-not-list": (_tr(lambda d, c: d.update(frames={"a": 1})), ["frames"]),
    "frames-empty": (_tr(lambda d, c: d.update(frames=[])), ["frames"]),
    "frame-no-file-path": (_tr(lambda d, c: d["frames"][0].pop("file_path") and None), ["file_path"]),
    "frame-file-path-number": (_frame0(file_path=7), ["file_path"]),
    "matrix-3x3": (_tr(lambda d, c: d["frames"][0].update(transform_matrix=[r[:3] for r in d["frames"][0]["transform_matrix"][:3]])), ["transform_matrix"]),
    "matrix-nan": (lambda c: set_transforms(c, json.dumps(_set00(transforms(c), float("nan")))), ["NaN"]),
    "matrix-1e400": (lambda c: (c / "transforms.json").write_text((c / "transforms.json").read_text().replace("1.0\n", "1e400\n", 1)), ["inf"]),
    "matrix-strings": (_tr(lambda d, c: d["frames"][0].update(transform_matrix=[["a"] * 4] * 4)), ["transform_matrix"]),
    "matrix-not-rigid": (lambda c: set_transforms(c, json.dumps(_set00(transforms(c), 5.0))), ["rigid"]),
    "w-negative": (_tr(lambda d, c: d.update(w=-16)), ["-16"]),
    "w-mismatch": (_tr(lambda d, c: d.update(w=17)), ["17"]),
    "w-float": (_tr(lambda d, c: d.update(w=16.5)), ["16.5"]),
    "fl-zero": (_tr(lambda d, c: d.update(fl_x=0.0)), ["fl_x"]),
    "fl-nan": (_tr(lambda d, c: d.update(fl_x=float("nan"))), ["fl_x"]),
    "fl-negative": (_tr(lambda d, c: d.update(fl_x=-27.5)), ["fl_x"]),
    "cx-inf": (_tr(lambda d, c: d.update(cx=float("inf"))), ["cx"]),
    "camera-model-unknown": (_tr(lambda d, c: d.update(camera_model="FISHEYE_9")), ["FISHEYE_9"]),
    "version-999": (_tr(lambda d, c: d.update(damcap_version=999)), ["999"]),
    "version-string": (_tr(lambda d, c: d.update(damcap_version="one")), ["one"]),
    "colorspace-unknown": (_tr(lambda d, c: d.update(colorspace="srgb-ish")), ["srgb-ish"]),
    "materials-zero": (_tr(lambda d, c: d.update(materials=0)), ["materials"]),
    "materials-string": (_tr(lambda d, c: d.update(materials="two")), ["materials"]),
    "file-path-absolute-outside": (_frame0(file_path="/etc/passwd"), ["/etc/passwd"]),
    "file-path-traversal": (_frame0(file_path="../../../../etc/hostname"), ["etc/hostname"]),
    "file-path-is-dir": (_frame0(file_path="images"), ["images"]),
    "file-path-missing": (_frame0(file_path="images/9999.exr"), ["9999.exr"]),
    "geometry-path-missing": (_frame0(geometry_path="geometry/9999.exr"), ["9999.exr"]),
    "duplicate-frame": (_tr(lambda d, c: d["frames"].append(dict(d["frames"][0]))), ["duplicate"]),
    "duplicate-train-entry": (_tr(lambda d, c: d.update(train_filenames=d["train_filenames"] + d["train_filenames"][:1])), ["duplicate"]),
    "train-test-overlap": (_tr(lambda d, c: d.update(test_filenames=d["test_filenames"] + d["train_filenames"][:1])), ["train"]),
    "train-unknown-frame": (_tr(lambda d, c: d.update(train_filenames=["images/nope.exr"])), ["nope.exr"]),
    "train-not-list": (_tr(lambda d, c: d.update(train_filenames="images/0000.exr")), ["train_filenames"]),
    "train-empty": (_tr(lambda d, c: d.update(train_filenames=[])), ["train"]),
}


def _set00(doc, v):
    doc["frames"][0]["transform_matrix"][0][0] = v
    return doc


@pytest.mark.parametrize("case", sorted(TRANSFORMS))
def test_transforms_json(case, work):
    cap = work / "cap"
    edit, needles = TRANSFORMS[case]
    edit(cap)
    refused(["fit", cap, "-o", work / "o.dam", "--steps", 2, "--batch-size", 64, "--holdout-views", 0],
            "transforms.json", *needles, inputs=[cap], outputs=[work / "o.dam"])


@pytest.mark.parametrize("case", ["deeply-nested", "matrix-nan", "duplicate-frame", "file-path-traversal"])
def test_transforms_json_inspect_render(case, work):
    cap = work / "cap"
    TRANSFORMS[case][0](cap)
    refused(["inspect", cap], "transforms.json", exit_code=None, inputs=[cap])
    refused(["render", work / "m.dam", cap, "-o", work / "r", "--split", "all"], "transforms.json", inputs=[cap], outputs=[work / "r"])


# ---------------------------------------------------------------- EXR frames ------------------


def _frame(cap, kind="images"):
    d = transforms(cap)
    name = Path(d["train_filenames"][0]).name
    return cap / kind / name


def _write_exr(p, arr, chans, dtype="float"):
    from damcap.common.exr import write_exr
    tmp = p.parent / ("tmp_" + p.name)
    write_exr(tmp, arr, chans, dtype=dtype)
    os.replace(tmp, p)


def _img_pixels(cap):
    from damcap.common.exr import read_exr
    px, ch = read_exr(_frame(cap))
    return px, ch


def _exr_values(v):
    def f(cap):
        px, ch = _img_pixels(cap)
        px = px.astype(np.float32).copy()
        px[8, 8, 0] = v
        _write_exr(_frame(cap), px, ch)
    return f


def _geom_edit(fn):
    def f(cap):
        from damcap.common.exr import read_exr
        g = _frame(cap, "geometry")
        px, ch = read_exr(g)
        px = px.astype(np.float32).copy()
        fn(px, ch)
        _write_exr(g, px, ch)
    return f


EXR = {
    "empty": lambda c: _frame(c).write_bytes(b""),
    "random-bytes": lambda c: _frame(c).write_bytes(os.urandom(2048)),
    "truncated-header": lambda c: _frame(c).write_bytes(_frame(c).read_bytes()[:100]),
    "truncated-pixels": lambda c: _frame(c).write_bytes(_frame(c).read_bytes()[:-64]),
    "a-png-named-exr": lambda c: _frame(c).write_bytes((c.parent / "photos" / "masks" / "IMG_0000.png").read_bytes()),
    "is-a-directory": lambda c: (_frame(c).unlink(), _frame(c).mkdir()),
    "dangling-symlink": lambda c: (_frame(c).unlink(), os.symlink(c / "nowhere.exr", _frame(c))),
    "wrong-channels": lambda c: _write_exr(_frame(c), np.ones((16, 16, 1), np.float32), ["Y"]),
    "wrong-size": lambda c: _write_exr(_frame(c), np.ones((32, 32, 3), np.float32), ["R", "G", "B"]),
    # a channel name byte damaged to 0x80 (not UTF-8): the error line names it escaped
    "channel-name-not-utf8": lambda c: _frame(c).write_bytes(_frame(c).read_bytes().replace(b"\x00B\x00", b"\x00\x80\x00", 1)),
    # an attribute's name run into its type by 0x80: OpenImageIO's error quotes the bytes
    "attribute-name-not-utf8": lambda c: _frame(c).write_bytes(_frame(c).read_bytes().replace(b"compression\x00compression",
                                                                                              b"compression\x80compression", 1)),
    "radiance-nan": _exr_values(float("nan")),
    "radiance-inf": _exr_values(float("inf")),
    "radiance-negative": _exr_values(-5.0),
    "geometry-normals-not-unit": _geom_edit(lambda px, ch: px.__setitem__((slice(None), slice(None), slice(0, 3)), px[..., :3] * 7)),
    "geometry-nan": _geom_edit(lambda px, ch: px.__setitem__((8, 8, 0), np.nan)),
    "geometry-coverage-2": _geom_edit(lambda px, ch: px.__setitem__((slice(None), slice(None), list(ch).index("A")), 2.0)),
    "geometry-random-bytes": lambda c: _frame(c, "geometry").write_bytes(os.urandom(1024)),
}


@pytest.mark.parametrize("case", sorted(EXR))
def test_exr_frame(case, work):
    cap = work / "cap"
    name = _frame(cap).name
    EXR[case](cap)
    refused(["fit", cap, "-o", work / "o.dam", "--steps", 2, "--batch-size", 64, "--holdout-views", 0], name,
            inputs=[cap], outputs=[work / "o.dam"])


# ---------------------------------------------------------------- photos, masks, poses --------

JPEG = "IMG_0001.jpg"


def _photo(w):
    return w / "photos" / "images" / JPEG


PHOTOS = {
    "truncated-jpeg": lambda w: _photo(w).write_bytes(_photo(w).read_bytes()[: len(_photo(w).read_bytes()) // 2]),
    "truncated-jpeg-no-eoi": lambda w: _photo(w).write_bytes(_photo(w).read_bytes()[:-2]),
    "empty-jpeg": lambda w: _photo(w).write_bytes(b""),
    "random-bytes-jpeg": lambda w: _photo(w).write_bytes(os.urandom(3000)),
    "text-as-jpeg": lambda w: _photo(w).write_text("hello"),
    "jpeg-is-directory": lambda w: (_photo(w).unlink(), _photo(w).mkdir()),
    "raw-random-bytes": lambda w: (_photo(w).unlink(), (w / "photos" / "images" / "IMG_0001.dng").write_bytes(os.urandom(5000))),
    "png-truncated": lambda w: (_photo(w).unlink(), (w / "photos" / "images" / "IMG_0001.png").write_bytes((w / "photos" / "masks" / "IMG_0001.png").read_bytes()[:60])),
    "different-size": lambda w: _resize_photo(w, 24),
}
PHOTO_NEEDLE = {"raw-random-bytes": "IMG_0001.dng", "png-truncated": "IMG_0001.png"}


def _resize_photo(w, n):
    from PIL import Image
    Image.open(_photo(w)).resize((n, n)).save(_photo(w), quality=90)


def _photo_readers(w):
    p = w / "photos"
    return {
        "linearize": ["linearize", p / "images", "-o", w / "out"],
        "reconstruct": ["reconstruct", p / "images", "-o", w / "out", "--poses", p / "transforms.json", "--geometry", "sphere",
                        "--masks", p / "masks", "--capture-size", 32, "--train-views", 2],
    }


@pytest.mark.parametrize("reader", ["linearize", "reconstruct"])
@pytest.mark.parametrize("case", sorted(PHOTOS))
def test_photo(case, reader, work):
    PHOTOS[case](work)
    if case == "different-size" and reader == "linearize":
        pytest.importorskip("PIL")
    needle = PHOTO_NEEDLE.get(case, JPEG)
    if case == "different-size" and reader == "linearize":  # one size per folder is not linearize's rule
        return
    refused(_photo_readers(work)[reader], needle, inputs=[work / "photos"], outputs=[work / "out"])


def test_photos_folder_empty(work):
    (work / "empty").mkdir()
    refused(["linearize", work / "empty", "-o", work / "out"], "empty", inputs=[work / "empty"], outputs=[work / "out"])


def test_photos_folder_only_non_images(work):
    (work / "txt").mkdir()
    (work / "txt" / "a.txt").write_text("x")
    refused(["reconstruct", work / "txt", "-o", work / "out"], "txt", inputs=[work / "txt"], outputs=[work / "out"])


def test_photo_without_exposure_metadata(work):
    from PIL import Image
    img = Image.open(_photo(work))
    img.save(_photo(work), quality=95)  # drops EXIF
    refused(["linearize", work / "photos" / "images", "-o", work / "out"], JPEG, inputs=[work / "photos"], outputs=[work / "out"])


MASKS = {
    "missing": lambda m: (m / "IMG_0001.png").unlink(),
    "random-bytes": lambda m: (m / "IMG_0001.png").write_bytes(os.urandom(500)),
    "truncated": lambda m: (m / "IMG_0001.png").write_bytes((m / "IMG_0001.png").read_bytes()[:50]),
    "wrong-size": lambda m: _resize_mask(m, 20),
    "all-black": lambda m: _fill_mask(m, 0),
}


def _resize_mask(m, n):
    from PIL import Image
    Image.open(m / "IMG_0001.png").resize((n, n)).save(m / "IMG_0001.png")


def _fill_mask(m, v):
    from PIL import Image
    im = Image.open(m / "IMG_0001.png")
    Image.new(im.mode, im.size, v).save(m / "IMG_0001.png")


@pytest.mark.parametrize("case", sorted(MASKS))
def test_mask(case, work):
    p = work / "photos"
    MASKS[case](p / "masks")
    refused(["reconstruct", p / "images", "-o", work / "out", "--poses", p / "transforms.json", "--geometry", "sphere",
             "--masks", p / "masks", "--capture-size", 32, "--train-views", 2], "IMG_0001", inputs=[p], outputs=[work / "out"])


def _poses_edit(fn):
    def f(p):
        d = json.loads((p / "transforms.json").read_text())
        r = fn(d)
        (p / "transforms.json").write_text(json.dumps(d if r is None else r))
        return p / "transforms.json"
    return f


def _pb(arr):
    def f(p):
        np.save(p / "poses_bounds.npy", arr)
        return p / "poses_bounds.npy"
    return f


POSES = {
    "transforms-duplicate-entry": (_poses_edit(lambda d: d["frames"].append(dict(d["frames"][1]))), "duplicate"),
    "transforms-photo-without-pose": (_poses_edit(lambda d: (d["frames"].pop(1), None)[1]), "IMG_0001"),
    "transforms-nan-matrix": (_poses_edit(lambda d: d["frames"][1]["transform_matrix"][0].__setitem__(0, float("nan"))), "transforms.json"),
    "transforms-deeply-nested": (lambda p: ((p / "transforms.json").write_text(deep_json(200_000)), p / "transforms.json")[1], "transforms.json"),
    "transforms-invalid-json": (lambda p: ((p / "transforms.json").write_text('{"frames": ['), p / "transforms.json")[1], "transforms.json"),
    "poses-bounds-wrong-shape": (_pb(np.zeros((4, 15))), "poses_bounds.npy"),
    "poses-bounds-count-mismatch": (_pb(np.tile(np.r_[np.eye(3, 5).ravel(), 1, 2], (3, 1))), "poses_bounds.npy"),
    "poses-bounds-nan": (_pb(np.full((4, 17), np.nan)), "poses_bounds.npy"),
    "poses-bounds-pickle": (lambda p: (np.save(p / "poses_bounds.npy", np.array([{"a": 1}] * 4, dtype=object), allow_pickle=True), p / "poses_bounds.npy")[1], "poses_bounds.npy"),
    "poses-bounds-random": (lambda p: ((p / "poses_bounds.npy").write_bytes(os.urandom(300)), p / "poses_bounds.npy")[1], "poses_bounds.npy"),
    "poses-missing-file": (lambda p: p / "nope.json", "nope.json"),
    "poses-unknown-kind": (lambda p: ((p / "poses.yaml").write_text("a: 1"), p / "poses.yaml")[1], "poses.yaml"),
}


@pytest.mark.parametrize("case", sorted(POSES))
def test_pose_file(case, work):
    p = work / "photos"
    make, needle = POSES[case]
    poses = make(p)
    # a photo without a pose is unregistered (partial pose files are allowed): every photo is needed here
    need_all = ["--min-registered", 4] if case == "transforms-photo-without-pose" else []
    refused(["reconstruct", p / "images", "-o", work / "out", "--poses", poses, "--geometry", "sphere", "--masks", p / "masks",
             "--capture-size", 32, "--train-views", 2, *need_all], needle, inputs=[p], outputs=[work / "out"])


@pytest.mark.parametrize("case", ["missing-dir", "empty-dir", "garbage-bin", "garbage-txt"])
def test_colmap_folder(case, work):
    p = work / "photos"
    d = work / "colmap"
    if case != "missing-dir":
        d.mkdir()
    if case == "garbage-bin":
        for n in ("cameras.bin", "images.bin", "points3D.bin"):
            (d / n).write_bytes(os.urandom(200))
    if case == "garbage-txt":
        for n in ("cameras.txt", "images.txt", "points3D.txt"):
            (d / n).write_text("1 PINHOLE nan nan x y\n")
    refused(["reconstruct", p / "images", "-o", work / "out", "--poses", f"colmap:{d}", "--geometry", "sphere",
             "--capture-size", 32, "--train-views", 2], "colmap", inputs=[p], outputs=[work / "out"])


def test_reconstruct_response_file_garbage(work):
    p = work / "photos"
    (work / "resp.json").write_text('{"response": [1, 2, "x"]}')
    refused(["reconstruct", p / "images", "-o", work / "out", "--poses", p / "transforms.json", "--geometry", "sphere",
             "--response", work / "resp.json"], "resp.json", inputs=[p], outputs=[work / "out"])


# ---------------------------------------------------------------- meshes ----------------------

MESHES = {
    "empty.obj": "",
    "no-faces.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\n",
    "index-out-of-range.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99\n",
    "index-zero.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n",
    "nan-vertex.obj": "v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "inf-vertex.obj": "v inf 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "degenerate.obj": "v 1 1 1\nv 1 1 1\nv 1 1 1\nf 1 2 3\n",
    "garbage.obj": "this is not\na mesh at all {}\n",
    "binary.obj": None,
    "truncated.ply": "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\x00\x00",
    "ascii-bad.ply": "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n1 x 0\n",
    "random.glb": None,
    "mesh.stl": "solid x\nendsolid x\n",
}


def _write_mesh(w, name):
    p = w / name
    text = MESHES[name]
    if text is None:
        p.write_bytes(os.urandom(700))
    else:
        p.write_bytes(text.encode("latin-1"))
    return p


def _mesh_readers(w, mesh):
    return {
        "export": ["export", w / "m.dam", "--mesh", mesh, "-o", w / "out", "--views", 1, "--resolution", 8],
        "view": ["view", w / "m.dam", "--mesh", mesh, "-o", w / "out"],
        "segment-labels": ["segment-labels", w / "seg", "--mesh", mesh, "-o", w / "out.npy"],  # labels need .npy/.txt
        "reconstruct": ["reconstruct", w / "photos" / "images", "-o", w / "out", "--poses", w / "photos" / "transforms.json",
                        "--geometry", f"mesh:{mesh}", "--mesh-align", "none", "--capture-size", 32, "--train-views", 2],
    }


@pytest.mark.parametrize("reader", ["export", "view", "segment-labels", "reconstruct"])
@pytest.mark.parametrize("case", sorted(MESHES))
def test_mesh(case, reader, work):
    if reader in ("view", "segment-labels", "reconstruct") and case not in ("empty.obj", "nan-vertex.obj", "degenerate.obj", "random.glb", "truncated.ply"):
        return  # one reader gets every case, the others the worst few
    mesh = _write_mesh(work, case)
    refused(_mesh_readers(work, mesh)[reader], case, inputs=[mesh, work / "photos", work / "seg"],
            outputs=[work / "out", work / "out.npy"])


# ---------------------------------------------------------------- labels ----------------------

LABELS = {
    "wrong-length.npy": lambda p: np.save(p, np.zeros(5, np.int64)),
    "negative.npy": lambda p: np.save(p, np.array([-1, 0, 0, 0, 0, 1])),
    "out-of-range.npy": lambda p: np.save(p, np.array([0, 1, 2, 0, 0, 1])),
    "float-nan.npy": lambda p: np.save(p, np.array([0, 1, np.nan, 0, 0, 1])),
    "two-d.npy": lambda p: np.save(p, np.zeros((6, 2), np.int64)),
    "pickle.npy": lambda p: np.save(p, np.array([{"x": 1}] * 6, dtype=object), allow_pickle=True),
    "random.npy": lambda p: p.write_bytes(os.urandom(300)),
    "empty.npy": lambda p: p.write_bytes(b""),
    "garbage.txt": lambda p: p.write_text("0\n1\nbanana\n0\n0\n1\n"),
    "labels.csv": lambda p: p.write_text("0,1,0,0,0,1"),
}


@pytest.mark.parametrize("case", sorted(LABELS))
def test_labels(case, work):
    lab = work / case
    LABELS[case](lab)
    refused(["export", work / "seg" / "material_0.dam", work / "seg" / "material_1.dam", "--mesh", work / "mesh.obj",
             "--labels", lab, "-o", work / "out", "--views", 1, "--resolution", 8], case,
            inputs=[lab, work / "seg", work / "mesh.obj"], outputs=[work / "out"])


# ---------------------------------------------------------------- segmentation folder ---------

SEG = {
    "no-segment-json": lambda s: (s / "segment.json").unlink(),
    "segment-json-invalid": lambda s: (s / "segment.json").write_text("{"),
    "segment-json-deep": lambda s: (s / "segment.json").write_text(deep_json(200_000)),
    "materials-huge": lambda s: _seg_json(s, materials=10**12),
    "materials-string": lambda s: _seg_json(s, materials="two"),
    "material-missing": lambda s: (s / "material_1.dam").unlink(),
    "material-random": lambda s: (s / "material_1.dam").write_bytes(os.urandom(400)),
    "segmenter-missing": lambda s: (s / "segmenter.safetensors").unlink(),
    "segmenter-random": lambda s: (s / "segmenter.safetensors").write_bytes(os.urandom(400)),
    "weights-missing": lambda s: shutil.rmtree(s / "weights"),
    "weights-random": lambda s: [p.write_bytes(os.urandom(300)) for p in (s / "weights").glob("*.exr")],
}
SEG_NEEDLE = {"material-missing": "material_1.dam", "material-random": "material_1.dam", "segmenter-missing": "segmenter",
              "segmenter-random": "segmenter", "weights-missing": "weights", "weights-random": ".exr"}


def _seg_json(s, **kv):
    d = json.loads((s / "segment.json").read_text())
    d.update(kv)
    (s / "segment.json").write_text(json.dumps(d))


@pytest.mark.parametrize("reader", ["segment-labels", "evaluate"])
@pytest.mark.parametrize("case", sorted(SEG))
def test_segmentation_folder(case, reader, work):
    SEG[case](work / "seg")
    args = {"segment-labels": ["segment-labels", work / "seg", "--mesh", work / "mesh.obj", "-o", work / "out.npy"],
            "evaluate": ["evaluate", work / "cap", "--segmentation", work / "seg", "--json", work / "out"]}[reader]
    refused(args, SEG_NEEDLE.get(case, "segment.json" if "json" in case or "materials" in case else "seg"),
            inputs=[work / "seg", work / "cap", work / "mesh.obj"], outputs=[work / "out", work / "out.npy"])


def test_segmentation_folder_is_a_capture(work):
    refused(["segment-labels", work / "cap", "--mesh", work / "mesh.obj", "-o", work / "out.npy"], "cap",
            inputs=[work / "cap"], outputs=[work / "out.npy"])


# ---------------------------------------------------------------- predictor -------------------

PRED = {
    "missing": lambda p: None,
    "random-bytes": lambda p: p.write_bytes(os.urandom(4096)),
    "truncated": lambda p: p.write_bytes(shipped_predictor().read_bytes()[:5000]),
    "a-dam-file": lambda p: p.write_bytes((p.parent / "m.dam").read_bytes()),
    "empty": lambda p: p.write_bytes(b""),
    "no-metadata": lambda p: p.write_bytes(safetensors_bytes({"w": np.zeros(3, np.float32)}, None)),
    "nan-weights": None,
}


@pytest.mark.parametrize("case", sorted(PRED))
def test_predictor(case, work):
    p = work / "pred.safetensors"
    if case == "nan-weights":
        from safetensors.numpy import load_file, save_file
        from damcap.appearance.dam_file import read_safetensors_metadata
        src = shipped_predictor()
        t = load_file(src)
        k = sorted(t)[0]
        t[k] = np.full_like(t[k], np.nan)
        save_file(t, p, metadata=read_safetensors_metadata(src.read_bytes()))
    else:
        PRED[case](p)
    refused(["predict", work / "cap", "-o", work / "out.dam", "--predictor", p], "pred.safetensors",
            inputs=[work / "cap", p], outputs=[work / "out.dam"])


# ---------------------------------------------------------------- corpus.json -----------------

CORPUS = {
    "missing": lambda c: (c / "corpus.json").unlink(),
    "invalid-json": lambda c: (c / "corpus.json").write_text("{"),
    "deeply-nested": lambda c: (c / "corpus.json").write_text(deep_json(200_000)),
    "captures-not-list": lambda c: (c / "corpus.json").write_text('{"captures": 5}'),
    "captures-empty": lambda c: (c / "corpus.json").write_text('{"captures": []}'),
    "path-traversal": lambda c: (c / "corpus.json").write_text('{"captures": [{"path": "../../../../etc", "split": "train"}]}'),
    "path-absolute": lambda c: (c / "corpus.json").write_text(json.dumps({"captures": [{"path": str(c.parent / "cap"), "split": "train"}]})),
    "split-unknown": lambda c: (c / "corpus.json").write_text('{"captures": [{"path": "captures/a", "split": "banana"}]}'),
    "capture-broken": lambda c: (c / "captures" / "a" / "transforms.json").write_text("{"),
    "duplicate-capture": lambda c: (c / "corpus.json").write_text('{"captures": [{"path": "captures/a", "split": "train"}, {"path": "captures/a", "split": "train"}]}'),
}


@pytest.mark.parametrize("case", sorted(CORPUS))
def test_corpus(case, work):
    c = work / "corpus"
    CORPUS[case](c)
    needle = "transforms.json" if case == "capture-broken" else "corpus"
    refused(["train-hyper", c, "-o", work / "p.safetensors", "--steps", 2, "--batch-size", 1, "--input-size", 16,
             "--channels", "4,8",  # a valid tiny predictor: the corpus, not the architecture, is what is refused
             "--pixels", 16, "--eval-every", 1, "--checkpoint-every", 0], needle, inputs=[c], outputs=[work / "p.safetensors"])


# ---------------------------------------------------------------- hdr brackets ----------------


def _bracket(w, *names):
    return [w / "photos" / "images" / n for n in names]


HDR = {
    "single-file": (lambda w: _bracket(w, "IMG_0000.jpg"), [], "IMG_0000.jpg"),
    "same-file-twice": (lambda w: _bracket(w, "IMG_0000.jpg", "IMG_0000.jpg"), [], "IMG_0000.jpg"),
    "exposures-count-mismatch": (lambda w: _bracket(w, "IMG_0000.jpg", "IMG_0001.jpg"), ["--exposures", "0.01"], "--exposures"),
    "exposures-not-numbers": (lambda w: _bracket(w, "IMG_0000.jpg", "IMG_0001.jpg"), ["--exposures", "a,b"], "a"),
    "exposures-zero": (lambda w: _bracket(w, "IMG_0000.jpg", "IMG_0001.jpg"), ["--exposures", "0,0.01"], "0"),
    "exposures-negative": (lambda w: _bracket(w, "IMG_0000.jpg", "IMG_0001.jpg"), ["--exposures", "-1,0.01"], "-1"),
    "exposures-nan": (lambda w: _bracket(w, "IMG_0000.jpg", "IMG_0001.jpg"), ["--exposures", "nan,0.01"], "nan"),
    "exposures-equal": (lambda w: _bracket(w, "IMG_0000.jpg", "IMG_0001.jpg"), ["--exposures", "0.01,0.01"], "0.01"),
    "different-sizes": (lambda w: [_resized(w), *_bracket(w, "IMG_0001.jpg")], ["--exposures", "0.01,0.02"], "small.jpg"),
    "truncated-member": (lambda w: [_trunc(w), *_bracket(w, "IMG_0001.jpg")], ["--exposures", "0.01,0.02"], "trunc.jpg"),
    "missing-member": (lambda w: [w / "nope.jpg", *_bracket(w, "IMG_0001.jpg")], ["--exposures", "0.01,0.02"], "nope.jpg"),
    "raw-and-jpeg-mixed": (lambda w: [_raw(w), *_bracket(w, "IMG_0001.jpg")], ["--exposures", "0.01,0.02"], "x.dng"),
}


def _resized(w):
    from PIL import Image
    Image.open(w / "photos" / "images" / "IMG_0000.jpg").resize((20, 20)).save(w / "small.jpg")
    return w / "small.jpg"


def _trunc(w):
    (w / "trunc.jpg").write_bytes((w / "photos" / "images" / "IMG_0000.jpg").read_bytes()[:700])
    return w / "trunc.jpg"


def _raw(w):
    (w / "x.dng").write_bytes(os.urandom(3000))
    return w / "x.dng"


@pytest.mark.parametrize("case", sorted(HDR))
def test_hdr_bracket(case, work):
    make, extra, needle = HDR[case]
    files = make(work)
    refused(["hdr", *files, "-o", work / "out.exr", *extra], needle, inputs=[work / "photos"] + [f for f in files if f.exists()],
            outputs=[work / "out.exr"])
