"""Outputs that collide with inputs or with each other, outputs that cannot be written, odd paths.

Each case: exit 2, one ``error:`` line naming the path, inputs byte-identical, nothing left behind.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.fuzz.conftest import damcap_fork, digest, refused, set_transforms, transforms

# (id, args (with W = the private work folder), paths that must be named, inputs, outputs)
# Paths are written relative to W; "{W}" is substituted.
COLLISIONS = [
    ("reconstruct-output-is-photo-set-with-poses", "reconstruct {W}/photos/images -o {W}/photos --poses {W}/photos/transforms.json --geometry sphere", ["photos"], ["photos"], []),
    ("reconstruct-output-is-photos", "reconstruct {W}/photos/images -o {W}/photos/images --poses {W}/photos/transforms.json --geometry sphere", ["images"], ["photos"], []),
    ("reconstruct-output-inside-photos", "reconstruct {W}/photos/images -o {W}/photos/images/cap --poses {W}/photos/transforms.json --geometry sphere", ["cap"], ["photos"], ["photos/images/cap"]),
    ("reconstruct-output-is-masks", "reconstruct {W}/photos/images -o {W}/photos/masks --masks {W}/photos/masks --poses {W}/photos/transforms.json --geometry sphere", ["masks"], ["photos"], []),
    ("reconstruct-output-is-poses-file", "reconstruct {W}/photos/images -o {W}/photos/transforms.json --poses {W}/photos/transforms.json --geometry sphere", ["transforms.json"], ["photos"], []),
    ("reconstruct-output-is-other-capture", "reconstruct {W}/photos/images -o {W}/cap --poses {W}/photos/transforms.json --geometry sphere", ["cap"], ["photos", "cap"], []),
    ("reconstruct-output-holds-mesh", "reconstruct {W}/photos/images -o {W}/rcap2 --poses {W}/photos/transforms.json --geometry mesh:{W}/rcap2", ["rcap2"], ["photos"], ["rcap2"]),
    ("fit-output-is-existing-dir", "fit {W}/cap -o {W}/frames --steps 2", ["frames"], ["cap", "frames"], []),
    ("fit-output-is-capture", "fit {W}/cap -o {W}/cap --steps 2", ["cap"], ["cap"], []),
    ("fit-output-is-transforms", "fit {W}/cap -o {W}/cap/transforms.json --steps 2", ["transforms.json"], ["cap"], []),
    ("fit-output-is-a-frame", "fit {W}/cap -o {W}/cap/images/0000.exr --steps 2", ["0000.exr"], ["cap"], []),
    ("fit-output-inside-capture", "fit {W}/cap -o {W}/cap/m.dam --steps 2", ["m.dam"], ["cap"], ["cap/m.dam"]),
    ("fit-output-under-a-file", "fit {W}/cap -o {W}/mesh.obj/m.dam --steps 2", ["mesh.obj"], ["cap", "mesh.obj"], []),
    ("fit-output-unwritable-sysfs", "fit {W}/cap -o /sys/damcap-fuzz.dam --steps 2", ["/sys/damcap-fuzz.dam"], ["cap"], []),
    ("fit-output-empty-string", "fit {W}/cap -o '' --steps 2", [], ["cap"], []),
    ("fit-capture-is-a-file", "fit {W}/m.dam -o {W}/x.dam --steps 2", ["m.dam"], ["m.dam"], ["x.dam"]),
    ("fit-capture-symlink-loop", "fit {W}/loop -o {W}/x.dam --steps 2", ["loop"], [], ["x.dam"]),
    ("render-output-is-capture-images", "render {W}/m.dam {W}/cap -o {W}/cap/images --split all", ["images"], ["cap", "m.dam"], []),
    ("render-output-is-capture", "render {W}/m.dam {W}/cap -o {W}/cap", ["cap"], ["cap", "m.dam"], []),
    ("render-output-is-geometry", "render {W}/m.dam {W}/cap -o {W}/cap/geometry --split all", ["geometry"], ["cap", "m.dam"], []),
    ("render-output-is-model", "render {W}/m.dam {W}/cap -o {W}/m.dam", ["m.dam"], ["cap", "m.dam"], []),
    ("render-output-is-existing-file", "render {W}/m.dam {W}/cap -o {W}/mesh.obj", ["mesh.obj"], ["cap", "mesh.obj"], []),
    ("render-args-swapped", "render {W}/cap {W}/m.dam -o {W}/r", ["cap"], ["cap", "m.dam"], ["r"]),
    ("segment-output-is-capture", "segment {W}/cap -o {W}/cap --materials 2 --steps 1 --init-steps 1", ["cap"], ["cap"], []),
    ("segment-output-is-capture-images", "segment {W}/cap -o {W}/cap/images --materials 2 --steps 1 --init-steps 1", ["images"], ["cap"], []),
    ("segment-output-is-file", "segment {W}/cap -o {W}/m.dam --materials 2 --steps 1 --init-steps 1", ["m.dam"], ["cap", "m.dam"], []),
    ("export-onnx-over-model", "export {W}/m.dam --format onnx -o {W}/m.dam", ["m.dam"], ["m.dam"], []),
    ("export-glsl-over-model", "export {W}/m.dam --format glsl -o {W}/m.dam", ["m.dam"], ["m.dam"], []),
    ("export-glsl-over-mesh", "export {W}/m.dam --format glsl -o {W}/mesh.obj", ["mesh.obj"], ["m.dam", "mesh.obj"], []),
    ("export-frames-over-labels", "export {W}/seg/material_0.dam {W}/seg/material_1.dam --mesh {W}/mesh.obj --labels {W}/labels.npy -o {W}/labels.npy --views 1 --resolution 8", ["labels.npy"], ["seg", "mesh.obj", "labels.npy"], []),
    ("export-frames-over-mesh", "export {W}/m.dam --mesh {W}/mesh.obj -o {W}/mesh.obj --views 1 --resolution 8", ["mesh.obj"], ["m.dam", "mesh.obj"], []),
    ("export-frames-into-seg", "export {W}/seg/material_0.dam {W}/seg/material_1.dam --mesh {W}/mesh.obj --labels {W}/labels.npy -o {W}/seg --views 1 --resolution 8", ["seg"], ["seg", "mesh.obj", "labels.npy"], []),
    ("view-over-model", "view {W}/m.dam -o {W}/m.dam", ["m.dam"], ["m.dam"], []),
    ("view-over-mesh", "view {W}/m.dam --mesh {W}/mesh.obj -o {W}/mesh.obj", ["mesh.obj"], ["m.dam", "mesh.obj"], []),
    ("view-output-is-dir", "view {W}/m.dam -o {W}/frames", ["frames"], ["m.dam", "frames"], []),
    ("segment-labels-over-mesh", "segment-labels {W}/seg --mesh {W}/mesh.obj -o {W}/mesh.obj", ["mesh.obj"], ["seg", "mesh.obj"], []),
    ("segment-labels-over-material", "segment-labels {W}/seg --mesh {W}/mesh.obj -o {W}/seg/material_0.dam", ["material_0.dam"], ["seg", "mesh.obj"], []),
    ("segment-labels-weights-equal-output", "segment-labels {W}/seg --mesh {W}/mesh.obj -o {W}/l2.npy --weights {W}/l2.npy", ["l2.npy"], ["seg", "mesh.obj"], ["l2.npy"]),
    ("hdr-output-is-input", "hdr {W}/photos/images/IMG_0000.jpg {W}/photos/images/IMG_0001.jpg -o {W}/photos/images/IMG_0000.jpg", ["IMG_0000.jpg"], ["photos"], []),
    ("hdr-output-is-dir", "hdr {W}/photos/images/IMG_0000.jpg {W}/photos/images/IMG_0001.jpg -o {W}/frames", ["frames"], ["photos", "frames"], []),
    ("linearize-output-is-photos", "linearize {W}/photos/images -o {W}/photos/images", ["images"], ["photos"], []),
    ("linearize-output-is-file", "linearize {W}/photos/images -o {W}/m.dam", ["m.dam"], ["photos", "m.dam"], []),
    ("predict-output-is-transforms", "predict {W}/cap -o {W}/cap/transforms.json", ["transforms.json"], ["cap"], []),
    ("predict-output-is-dir", "predict {W}/cap -o {W}/frames", ["frames"], ["cap", "frames"], []),
    ("predict-output-is-predictor", "predict {W}/cap -o {W}/p.safetensors --predictor {W}/p.safetensors", ["p.safetensors"], ["cap", "p.safetensors"], []),
    ("train-hyper-output-is-index", "train-hyper {W}/corpus -o {W}/corpus/corpus.json --steps 1", ["corpus.json"], ["corpus"], []),
    ("train-hyper-output-is-corpus", "train-hyper {W}/corpus -o {W}/corpus --steps 1", ["corpus"], ["corpus"], []),
    ("evaluate-json-over-transforms", "evaluate {W}/cap --model {W}/m.dam --json {W}/cap/transforms.json", ["transforms.json"], ["cap", "m.dam"], []),
    ("evaluate-plot-over-model", "evaluate {W}/cap --model {W}/m.dam --json {W}/e.json --plot {W}/m.dam", ["m.dam"], ["cap", "m.dam"], ["e.json"]),
    ("evaluate-json-equals-plot", "evaluate {W}/cap --model {W}/m.dam --json {W}/e.json --plot {W}/e.json", ["e.json"], ["cap", "m.dam"], ["e.json"]),
    ("closed-form-over-existing-file", "closed-form {W}/m.dam --views 4 --train-views 2 --res 16", ["m.dam"], ["m.dam"], []),
    ("closed-form-over-other-folder", "closed-form {W}/frames --views 4 --train-views 2 --res 16", ["frames"], ["frames"], []),
    ("synth-photos-over-photos", "synth-photos {W}/cap --views 4 --size 32", ["cap"], ["cap"], []),
    ("shape-over-existing-dir", "shape sphere {W}/frames", ["frames"], ["frames"], []),
    ("shape-unknown-extension", "shape sphere {W}/s.xyz", ["s.xyz"], [], ["s.xyz"]),
    ("shape-over-model", "shape torus {W}/m.dam", ["m.dam"], ["m.dam"], []),
]


def _expand(w: Path, s: str) -> list[str]:
    import shlex
    return [a.replace("{W}", str(w)) for a in shlex.split(s)]


@pytest.mark.parametrize("case", COLLISIONS, ids=[c[0] for c in COLLISIONS])
def test_output_collides_or_cannot_be_written(case, work):
    cid, args, needles, inputs, outputs = case
    os.symlink(work / "loop", work / "loop")
    if "p.safetensors" in args:
        from tests.fuzz.conftest import shipped_predictor
        (work / "p.safetensors").write_bytes(shipped_predictor().read_bytes())
    refused(_expand(work, args), *needles, inputs=[work / p for p in inputs] + [work / "cap", work / "m.dam"],
            outputs=[work / p for p in outputs])


def _frame_collision(cap: Path, what: str) -> Path:
    """Two frames of one base name in one split (``what``): images/0001.exr and images2/0001.exr.

    Returns the base name. The new frame is in ``what``'s split only (a frame in both splits is a
    different mistake, refused for itself)."""
    doc = transforms(cap)
    (cap / "images2").mkdir()
    key = "train_filenames" if what == "train" else "test_filenames"
    src = doc["frames"][0]["file_path"]
    other = [f for f in doc["frames"] if f["file_path"] != src and f["file_path"] in doc.get(key, [])][0]  # in the split
    name = Path(other["file_path"]).name
    (cap / "images2" / name).write_bytes((cap / src).read_bytes())
    other_dup = dict(doc["frames"][0], file_path=f"images2/{name}")
    doc["frames"].append(other_dup)
    doc[key] = doc.get(key, []) + [f"images2/{name}"]
    set_transforms(cap, doc)
    return Path(name)


def _kept_apart(args, inputs, *outputs: Path) -> None:
    """The issue's contract allows output names unique by construction (the relative path, not the
    base name) instead of a refusal: the command runs, both outputs exist and differ, inputs stay."""
    before = {p: digest(p) for p in inputs}
    run = damcap_fork(args)
    assert run.code == 0 and not run.timed_out, run.err[-2000:]
    assert all(digest(p) == d for p, d in before.items()), "an input changed"
    for o in outputs:
        assert o.is_file(), f"{o} was not written"
    assert len({o.read_bytes() for o in outputs}) == len(outputs), "the outputs are the same file"


def test_render_frames_with_the_same_name_collide(work):
    name = _frame_collision(work / "cap", "test")
    r = work / "r"
    _kept_apart(["render", work / "m.dam", work / "cap", "-o", r, "--split", "all"], [work / "cap", work / "m.dam"],
                r / "images" / name.with_suffix(".exr"), r / "images2" / name.with_suffix(".exr"))


def test_segment_frames_with_the_same_name_collide(work):
    name = _frame_collision(work / "cap", "train")
    w = work / "s" / "weights"
    _kept_apart(["segment", work / "cap", "-o", work / "s", "--materials", 2, "--steps", 1, "--init-steps", 1,
                 "--batch-pixels", 64, "--psi-resolution", 16], [work / "cap"],
                w / "images" / name.with_suffix(".exr"), w / "images2" / name.with_suffix(".exr"))


def test_linearize_photos_with_the_same_stem_collide(work):
    img = work / "photos" / "images"
    (img / "IMG_0000.png").write_bytes((work / "photos" / "masks" / "IMG_0000.png").read_bytes())
    refused(["linearize", img, "-o", work / "l"], "IMG_0000", inputs=[work / "photos"], outputs=[work / "l"])


def test_reconstruct_photos_with_the_same_stem_collide(work):
    img = work / "photos" / "images"
    (img / "IMG_0000.png").write_bytes((work / "photos" / "masks" / "IMG_0000.png").read_bytes())
    refused(["reconstruct", img, "-o", work / "c", "--poses", work / "photos" / "transforms.json", "--geometry", "sphere",
             "--masks", work / "photos" / "masks"], "IMG_0000", inputs=[work / "photos"], outputs=[work / "c"])


@pytest.mark.parametrize("cmd", ["fit", "render", "export-glsl", "linearize"])
def test_full_disk(cmd, work):
    """A write that fails half-way (RLIMIT_FSIZE: EFBIG, as ENOSPC) leaves nothing behind."""
    args = {
        "fit": ["fit", work / "cap", "-o", work / "o.dam", "--steps", 2, "--batch-size", 64, "--holdout-views", 0],
        "render": ["render", work / "m.dam", work / "cap", "-o", work / "o"],
        "export-glsl": ["export", work / "m.dam", "--format", "glsl", "-o", work / "o"],
        "linearize": ["linearize", work / "photos" / "images", "-o", work / "o"],
    }[cmd]
    refused(args, "o", inputs=[work / "cap", work / "m.dam", work / "photos"], outputs=[work / ("o.dam" if cmd == "fit" else "o")],
            fsize=1024)


def test_existing_output_folder_of_another_command_is_kept(work):
    """render -o FOLDER that holds someone's files: refused, not merged into."""
    (work / "mine").mkdir()
    (work / "mine" / "notes.txt").write_text("keep me")
    refused(["render", work / "m.dam", work / "cap", "-o", work / "mine"], "mine",
            inputs=[work / "cap", work / "m.dam", work / "mine"])


@pytest.mark.parametrize("cmd", ["render", "export", "segment"])
def test_own_earlier_output_folder_is_replaced_whole(cmd, work):
    """Rerunning a command onto its own earlier output replaces that folder as a whole: no file of
    the earlier run survives (a stale frame of another split would pass for a result); the
    inputs stay byte-identical. (Onto any other non-empty folder it is refused: above.)"""
    from tests.fuzz.conftest import damcap_fork, digest

    out = {"render": work / "rendered", "export": work / "frames", "segment": work / "seg"}[cmd]
    args = {
        "render": ["render", work / "m.dam", work / "cap", "-o", out],
        # the same model for both parts of the labels: a valid request (two parts, one material)
        "export": ["export", work / "m.dam", work / "m.dam", "--mesh", work / "mesh.obj", "--labels", work / "labels.npy", "-o", out,
                   "--views", 1, "--resolution", 8],
        "segment": ["segment", work / "cap", "-o", out, "--materials", 2, "--steps", 1, "--init-steps", 1, "--batch-pixels", 64,
                    "--psi-resolution", 16],
    }[cmd]
    (out / "stale-from-an-earlier-run.exr").write_bytes(b"old")
    inputs = [work / "m.dam", work / "mesh.obj", work / "labels.npy", work / "cap"]
    before = {p: digest(p) for p in inputs}
    run = damcap_fork(args, timeout=60)
    assert run.code == 0, run.err
    assert not (out / "stale-from-an-earlier-run.exr").exists()
    assert all(digest(p) == d for p, d in before.items())
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]  # no staging or replaced folder left
