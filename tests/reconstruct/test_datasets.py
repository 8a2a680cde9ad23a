"""reconstruct's dataset folders: plain photos, a nerfstudio / instant-ngp dataset, a COLMAP project."""

from __future__ import annotations

import json

import pytest

from damcap.common.errors import DamcapError
from damcap.reconstruct.datasets import dataset_inputs


def _touch(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"x")
    return path


def _transforms(root, frames):
    root.mkdir(parents=True, exist_ok=True)
    (root / "transforms.json").write_text(json.dumps({"frames": frames}))


def test_a_folder_of_photos_is_itself(tmp_path):
    _touch(tmp_path / "a.jpg")
    d = dataset_inputs(tmp_path)
    assert (d.kind, d.photos, d.poses, d.masks) == ("photos", tmp_path, None, None)


def test_a_nerfstudio_dataset_gives_its_photos_cameras_and_masks(tmp_path):
    for k in range(2):
        _touch(tmp_path / "images" / f"frame_{k}.png")
        _touch(tmp_path / "masks" / f"frame_{k}.png")
    _transforms(tmp_path, [{"file_path": f"images/frame_{k}.png", "mask_path": f"masks/frame_{k}.png"} for k in range(2)])
    d = dataset_inputs(tmp_path)
    assert d.kind == "nerfstudio" and d.photos == (tmp_path / "images").resolve() and d.masks == (tmp_path / "masks").resolve()
    assert d.poses == str(tmp_path / "transforms.json") and "masks in" in d.describe()


def test_instant_ngp_paths_without_masks(tmp_path):
    _touch(tmp_path / "images" / "0001.jpg")
    _transforms(tmp_path, [{"file_path": "./images/0001.jpg"}])
    d = dataset_inputs(tmp_path)
    assert d.kind == "nerfstudio" and d.photos == (tmp_path / "images").resolve() and d.masks is None


def test_a_colmap_project(tmp_path):
    _touch(tmp_path / "images" / "a.jpg")
    _touch(tmp_path / "sparse" / "0" / "cameras.bin")
    d = dataset_inputs(tmp_path)
    assert d.kind == "colmap" and d.photos == tmp_path / "images" and d.poses == f"colmap:{tmp_path / 'sparse' / '0'}"


@pytest.mark.parametrize("frames, needle", [
    ([{"file_path": "a/1.png"}, {"file_path": "b/2.png"}], "lie in 2 folders"),
    ([{"file_path": "a/1.png", "mask_path": "m/1.png"}, {"file_path": "a/2.png"}], "1 of 2 frames have a mask_path"),
    ([], "non-empty 'frames' list"),
])
def test_datasets_damcap_cannot_read_are_refused_naming_why(tmp_path, frames, needle):
    _transforms(tmp_path, frames)
    with pytest.raises(DamcapError, match=needle):
        dataset_inputs(tmp_path)


def test_a_folder_with_nothing_to_read(tmp_path):
    with pytest.raises(DamcapError, match="holds no photos, no transforms.json"):
        dataset_inputs(tmp_path)
    with pytest.raises(DamcapError, match="photo folder not found"):
        dataset_inputs(tmp_path / "missing")
    (tmp_path / "transforms.json").write_text("{not json")
    with pytest.raises(DamcapError, match="not JSON"):
        dataset_inputs(tmp_path)
