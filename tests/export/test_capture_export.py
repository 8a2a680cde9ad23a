"""export-capture: a capture as a nerfstudio dataset and as a COLMAP model, read back as those tools read them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from damcap.common.capture_folder import read_capture, read_frame
from damcap.common.exr import read_image_u8
from damcap.export.capture_export import CaptureExportOptions, cam_from_world_opencv, export_capture, mask_u8


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

    root = tmp_path_factory.mktemp("cap") / "blob"
    make_closed_form_capture(root, ClosedFormOptions(shape="blob", views=6, train_views=4, resolution=48, seed=3))
    return read_capture(root)


def inside_mask(mask: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Whether pixel coordinates (x right, y down, pixel centres at +0.5) land on the mask or
    within one pixel of it (silhouette pixels are sampled at 48 px)."""
    from scipy.ndimage import binary_dilation

    mask = binary_dilation(mask > 0, iterations=1)
    i, j = np.floor(v).astype(int), np.floor(u).astype(int)
    ok = (i >= 0) & (i < mask.shape[0]) & (j >= 0) & (j < mask.shape[1])
    out = np.zeros(len(u), bool)
    out[ok] = mask[i[ok], j[ok]] > 0
    return out


def test_nerfstudio_dataset_is_what_its_dataparser_reads(capture, tmp_path):
    """Every key nerfstudio's dataparser needs, all three split lists naming frames, 8-bit frames
    and masks of the camera's size, and a coloured point cloud in the frames' world: each point
    projects (OpenGL pose, pinhole intrinsics) onto the object's mask in every frame."""
    import open3d as o3d

    out = tmp_path / "ns"
    summary = export_capture(capture, out, CaptureExportOptions(points=500))
    doc = json.loads((out / "transforms.json").read_text())
    assert summary["frames"] == 6 and summary["points"] == 500
    assert doc["camera_model"] == "PINHOLE" and {"fl_x", "fl_y", "cx", "cy", "w", "h"} <= set(doc)
    names = {f["file_path"] for f in doc["frames"]}
    for split in ("train", "val", "test"):
        assert doc[f"{split}_filenames"] and set(doc[f"{split}_filenames"]) <= names
    assert len(doc["train_filenames"]) == 4 and doc["val_filenames"] == doc["test_filenames"]
    pcd = o3d.io.read_point_cloud(str(out / doc["ply_file_path"]))
    pts = np.asarray(pcd.points)
    assert len(pts) == 500 and pcd.has_colors()
    for f in doc["frames"]:
        img, mask = read_image_u8(out / f["file_path"]), read_image_u8(out / f["mask_path"])
        assert img.dtype == np.uint8 and img.shape == (doc["h"], doc["w"], 3) and mask.shape[:2] == (doc["h"], doc["w"])
        assert set(np.unique(mask)) <= {0, 255}
        cam = np.linalg.inv(np.array(f["transform_matrix"]))  # OpenGL: the camera looks down -z
        p = pts @ cam[:3, :3].T + cam[:3, 3]
        u = doc["cx"] + doc["fl_x"] * p[:, 0] / -p[:, 2]
        v = doc["cy"] - doc["fl_y"] * p[:, 1] / -p[:, 2]
        assert inside_mask(mask[..., 0] if mask.ndim == 3 else mask, u, v).mean() > 0.995


NERFSTUDIO_LOAD = """
import json, sys
from pathlib import Path
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from PIL import Image
# nerfstudio's own normalisation off: its cameras are then the file's
parser = NerfstudioDataParserConfig(data=Path(sys.argv[1]), orientation_method="none", center_method="none",
                                    auto_scale_poses=False, scale_factor=1.0, load_3D_points=True).setup()
out = {}
for split in ("train", "val", "test"):
    o = parser.get_dataparser_outputs(split)
    c = o.cameras
    out[split] = {"images": [p.name for p in o.image_filenames], "masks": [p.name for p in (o.mask_filenames or [])],
                  "camera_to_worlds": c.camera_to_worlds.tolist(), "fx": c.fx.ravel().tolist(), "fy": c.fy.ravel().tolist(),
                  "cx": c.cx.ravel().tolist(), "cy": c.cy.ravel().tolist(), "points": len(o.metadata["points3D_xyz"]),
                  "pil_modes": sorted({Image.open(p).mode for p in o.image_filenames})}
print("NERFSTUDIO " + json.dumps(out))
"""


def test_nerfstudios_own_dataparser_loads_the_export(capture, tmp_path):
    """nerfstudio 1.1.5's NerfstudioDataParser (installed by make test beside the venv, see
    tests/nerfstudio-reader.txt) reads the export: every split, its masks, 8-bit RGB frames through
    PIL, the point cloud, and the capture's cameras to 1e-6."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    reader = Path(sys.prefix) / "nerfstudio-reader"
    if not (reader / ".installed").is_file():
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"{reader}: nerfstudio's dataparser is required under CI (make test installs it)")
        pytest.skip("nerfstudio's dataparser not installed (make test installs it)")
    export_capture(capture, tmp_path / "ns", CaptureExportOptions(points=500))
    p = subprocess.run([sys.executable, "-c", NERFSTUDIO_LOAD, str(tmp_path / "ns")], capture_output=True, text=True, timeout=300,
                       env={**os.environ, "PYTHONPATH": str(reader)})
    assert p.returncode == 0, p.stderr[-2000:]
    got = json.loads(p.stdout.split("NERFSTUDIO ", 1)[1])
    by_name = {f.file_path.split("/")[-1].rsplit(".", 1)[0] + ".png": f for f in capture.frames}
    split_of = {"train": "train", "val": "test", "test": "test"}
    for split, o in got.items():
        want = {f.file_path.split("/")[-1].rsplit(".", 1)[0] + ".png" for f in capture.split(split_of[split])}
        assert sorted(o["images"]) == sorted(want), split
        assert o["masks"] == o["images"] and o["pil_modes"] == ["RGB"] and o["points"] == 500
        for name, c2w, fx, fy, cx, cy in zip(o["images"], o["camera_to_worlds"], o["fx"], o["fy"], o["cx"], o["cy"]):
            f = by_name[name]
            np.testing.assert_allclose(np.array(c2w), f.world_from_cam[:3, :4], atol=1e-6)
            np.testing.assert_allclose([fx, fy, cx, cy], [f.intrinsics.fl_x, f.intrinsics.fl_y, f.intrinsics.cx, f.intrinsics.cy], atol=1e-4)


def test_colmap_model_reads_back_with_pycolmap_and_projects_onto_the_masks(capture, tmp_path):
    """pycolmap reads the model of a closed-form capture (no registration): one PINHOLE camera per
    intrinsics, the capture's camera centres, and every surface point projects onto the object's
    mask through COLMAP's own camera model."""
    import pycolmap

    out = tmp_path / "colmap"
    summary = export_capture(capture, out, CaptureExportOptions(format="colmap", points=300))
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert len(rec.images) == 6 and len(rec.points3D) == 300 and len(rec.cameras) == 1
    # a closed-form capture has no registration: surface samples without tracks, and the record says so
    assert summary["points_source"] == "surface samples" and all(p.track.length() == 0 for p in rec.points3D.values())
    assert json.loads((out / "damcap_export.json").read_text())["points_source"] == "surface samples"
    cam = next(iter(rec.cameras.values()))
    assert cam.model.name == "PINHOLE"
    pts = np.array([p.xyz for p in rec.points3D.values()])
    frames = {f.file_path.split("/")[-1].rsplit(".", 1)[0] + ".png": f for f in capture.frames}
    for img in rec.images.values():
        f = frames[img.name]
        np.testing.assert_allclose(img.projection_center(), f.world_from_cam[:3, 3], atol=1e-9)
        assert (out / "images" / img.name).is_file()
        uv = np.array([cam.img_from_cam(img.cam_from_world() * p) for p in pts])
        mask = mask_u8(read_frame(capture, f, with_weights=False).coverage)
        assert inside_mask(mask, uv[:, 0], uv[:, 1]).mean() > 0.995


def test_opencv_pose_of_an_opengl_camera():
    """A camera at (0, 0, 2) looking at the origin down -z (OpenGL) sees the origin 2 ahead on
    its +z (OpenCV), and a point up (+y) in the world lies up in the image (-y in OpenCV)."""
    m = np.eye(4)
    m[:3, 3] = [0, 0, 2]
    pose = cam_from_world_opencv(m)
    assert np.allclose(pose[:3, :3] @ [0, 1, 0], [0, -1, 0])
    assert np.allclose(pose[:3, :3] @ [0, 0, 0] + pose[:3, 3], [0, 0, 2])


def test_an_exported_nerfstudio_dataset_reconstructs_with_its_own_cameras_and_masks(capture, tmp_path, capsys):
    """damcap reconstruct DATASET reads what export-capture wrote (a nerfstudio dataset): its
    cameras (no registration) and its masks, and writes the same cameras again."""
    from damcap.cli.main import main

    ns = tmp_path / "ns"
    export_capture(capture, ns, CaptureExportOptions(points=0))
    assert main(["reconstruct", str(ns), "-o", str(tmp_path / "again"), "--geometry", "visual-hull"]) == 0
    assert "input: nerfstudio dataset" in capsys.readouterr().out
    again = read_capture(tmp_path / "again")
    source = json.loads((tmp_path / "again" / "transforms.json").read_text())["damcap_source"]
    assert source["poses"].endswith("transforms.json") and source["masks"].endswith("masks") and len(again.frames) == 6
    # the same cameras, up to the similarity reconstruct normalises every capture by
    from damcap.reconstruct.normalize import umeyama_similarity

    before = np.stack([f.world_from_cam for f in capture.frames])
    after = np.stack([f.world_from_cam for f in again.frames])
    t = umeyama_similarity(before[:, :3, 3], after[:, :3, 3])
    s = np.cbrt(np.linalg.det(t[:3, :3]))
    moved = before[:, :3, 3] @ t[:3, :3].T + t[:3, 3]
    assert np.abs(moved - after[:, :3, 3]).max() < 1e-4 * s
    np.testing.assert_allclose(np.einsum("ij,njk->nik", t[:3, :3] / s, before[:, :3, :3]), after[:, :3, :3], atol=1e-5)


def test_an_exported_colmap_model_reconstructs_with_its_cameras(capture, tmp_path, capsys):
    """damcap reconstruct PROJECT reads a COLMAP project (images/ + sparse/0) as known cameras (a
    --masks on the command line joins them)."""
    from damcap.cli.main import main

    export_capture(capture, tmp_path / "colmap", CaptureExportOptions(format="colmap", points=0))
    export_capture(capture, tmp_path / "ns", CaptureExportOptions(points=0))  # for its masks
    assert main(["reconstruct", str(tmp_path / "colmap"), "-o", str(tmp_path / "again"), "--masks", str(tmp_path / "ns" / "masks"),
                 "--geometry", "visual-hull"]) == 0
    assert "input: colmap dataset" in capsys.readouterr().out
    again = read_capture(tmp_path / "again")
    d_before = np.linalg.norm(capture.frames[0].world_from_cam[:3, 3] - capture.frames[1].world_from_cam[:3, 3])
    d_after = np.linalg.norm(again.frames[0].world_from_cam[:3, 3] - again.frames[1].world_from_cam[:3, 3])
    d2_before = np.linalg.norm(capture.frames[0].world_from_cam[:3, 3] - capture.frames[2].world_from_cam[:3, 3])
    d2_after = np.linalg.norm(again.frames[0].world_from_cam[:3, 3] - again.frames[2].world_from_cam[:3, 3])
    assert d_after / d_before == pytest.approx(d2_after / d2_before, rel=1e-5)  # the same cameras up to a similarity


def _fisheye_photo(image: np.ndarray, k_pin: tuple[float, float, float, float], k_fish: tuple[float, ...], size: int,
                   coeffs: tuple[float, ...]) -> np.ndarray:
    """The photo an OPENCV_FISHEYE camera (fx, fy, cx, cy = ``k_fish``, k1..k4 = ``coeffs``, ``size``
    px) takes of what a pinhole (``k_pin``) saw in ``image``: each fisheye pixel's ray found by
    OpenCV's inverse of the model (cv2.fisheye.undistortPoints), the pinhole image sampled there."""
    import cv2

    fx, fy, cx, cy = k_fish
    j, i = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    pts = np.stack([(j - cx) / fx, (i - cy) / fy], -1).reshape(-1, 1, 2)
    ray = cv2.fisheye.undistortPoints(pts, np.eye(3), np.array(coeffs)).reshape(size, size, 2)
    px, py, pcx, pcy = k_pin
    mx = (px * ray[..., 0] + pcx - 0.5).astype(np.float32)
    my = (py * ray[..., 1] + pcy - 0.5).astype(np.float32)
    return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def test_a_fisheye_dataset_reconstructs_to_the_pinhole_frames(capture, tmp_path):
    """The dataset's photos retaken by a fisheye (COLMAP's OPENCV_FISHEYE, 2x the pixels) and
    undistorted by reconstruct through pycolmap's model give the frames the pinhole photos give;
    read as pinholes instead, they do not."""
    from damcap.cli.main import main
    from damcap.common.exr import write_png

    ns = tmp_path / "ns"
    export_capture(capture, ns, CaptureExportOptions(points=0))
    doc = json.loads((ns / "transforms.json").read_text())
    k_pin = (doc["fl_x"], doc["fl_y"], doc["cx"], doc["cy"])
    k_fish, size, coeffs = tuple(2 * v for v in k_pin), 2 * doc["w"], (-1.0, 0.5, 0.0, 0.0)  # 10% barrel at the edge
    for kind, model in (("fish", "OPENCV_FISHEYE"), ("fish-read-as-pinhole", "PINHOLE")):
        for sub in ("images", "masks"):
            (tmp_path / kind / sub).mkdir(parents=True)
            for f in (ns / sub).iterdir():
                img = read_image_u8(f).astype(np.float32)
                write_png(tmp_path / kind / sub / f.name, np.round(_fisheye_photo(img, k_pin, k_fish, size, coeffs)).astype(np.uint8))
        fish = {**doc, "camera_model": model, "fl_x": k_fish[0], "fl_y": k_fish[1], "cx": k_fish[2], "cy": k_fish[3], "w": size, "h": size}
        if model == "OPENCV_FISHEYE":
            fish.update(dict(zip(("k1", "k2", "k3", "k4"), coeffs)))
        (tmp_path / kind / "transforms.json").write_text(json.dumps(fish))
    caps = {}
    for kind in ("ns", "fish", "fish-read-as-pinhole"):
        src = ns if kind == "ns" else tmp_path / kind
        assert main(["reconstruct", str(src), "-o", str(tmp_path / f"cap-{kind}"), "--geometry", "visual-hull", "--capture-size", "48"]) == 0
        caps[kind] = read_capture(tmp_path / f"cap-{kind}")

    def error(kind: str) -> tuple[float, float]:
        """(relative radiance error inside both silhouettes, silhouette disagreement), frame mean."""
        rad, sil = [], []
        for a, b in zip(caps["ns"].frames, caps[kind].frames):
            assert a.intrinsics == b.intrinsics  # the same pinhole targets
            ra, rb = read_frame(caps["ns"], a), read_frame(caps[kind], b)
            inner = (ra.coverage > 0.99) & (rb.coverage > 0.99)
            rad.append(np.abs(ra.radiance_lin - rb.radiance_lin)[inner].mean() / ra.radiance_lin[inner].mean())
            sil.append(np.abs((ra.coverage > 0.5).astype(float) - (rb.coverage > 0.5)).sum() / (ra.coverage > 0.5).sum())
        return float(np.mean(rad)), float(np.mean(sil))

    right, wrong = error("fish"), error("fish-read-as-pinhole")
    assert right[0] < 0.05 and right[1] < 0.01, right  # measured 0.031 (two resamplings), 0.0006
    assert right[0] < 0.5 * wrong[0] and right[1] < 0.1 * wrong[1], (right, wrong)  # measured 0.086, 0.088


@pytest.mark.parametrize("fmt", ["nerfstudio", "colmap"])
def test_the_datasets_point_cloud_seeds_the_geometry(capture, tmp_path, capsys, fmt):
    """The points an exported dataset carries (nerfstudio's ply_file_path, COLMAP points without
    tracks) are reconstruct's sparse points: Poisson meshes them, no features are matched, and
    the surface covers the capture's silhouettes."""
    from damcap.cli.main import main

    export_capture(capture, tmp_path / "ds", CaptureExportOptions(format=fmt, points=3000))
    assert main(["reconstruct", str(tmp_path / "ds"), "-o", str(tmp_path / "again"), "--geometry", "poisson",
                 "--capture-size", "48"]) == 0
    out = capsys.readouterr().out
    assert "are the sparse points: no feature matching" in out and "triangulating" not in out, out
    again = read_capture(tmp_path / "again")
    ious = []
    for a, b in zip(capture.frames, again.frames):
        ca, cb = read_frame(capture, a).coverage > 0.5, read_frame(again, b).coverage > 0.5
        ious.append((ca & cb).sum() / (ca | cb).sum())
    assert min(ious) > 0.85, ious


@pytest.fixture(scope="module")
def registered_capture(tmp_path_factory):
    """A capture ``damcap reconstruct`` made through COLMAP registration of 20 rendered 256 px
    photos (a SIMPLE_RADIAL registration camera, frames resampled to 96 px pinhole cameras; ~6 s)."""
    from damcap.cli.main import main
    from damcap.common.shapes import bumpy_blob
    from damcap.synth.photos import default_intrinsics, exposure_series, orbit_cameras, write_photo_set

    root = tmp_path_factory.mktemp("registered")
    light = np.array([0.4, 0.8, 0.45]) / np.linalg.norm([0.4, 0.8, 0.45])
    write_photo_set(root / "photos", bumpy_blob(subdivisions=5), orbit_cameras(20, 3.2, (25.0,), jitter_deg=4, seed=0),
                    default_intrinsics(256), exposure_series(20, 0), light_dir_world=light, seed=0)
    assert main(["reconstruct", str(root / "photos" / "images"), "-o", str(root / "capture"), "--masks", str(root / "photos" / "masks"),
                 "--capture-size", "96", "--geometry", "visual-hull", "--voxels", "64", "--train-views", "5"]) == 0
    return read_capture(root / "capture")


def _tracks_are_consistent(rec) -> None:
    """Every track element names an image whose 2D point refers back to the track's point, and
    every 2D point with a 3D point is in that point's track."""
    for pid, p in rec.points3D.items():
        for el in p.track.elements:
            assert rec.image(el.image_id).points2D[el.point2D_idx].point3D_id == pid
    for img in rec.images.values():
        for idx, p2 in enumerate(img.points2D):
            if p2.has_point3D():
                assert any(e.image_id == img.image_id and e.point2D_idx == idx for e in rec.points3D[p2.point3D_id].track.elements)


def test_colmap_export_of_a_registered_capture_keeps_the_registrations_points_and_tracks(registered_capture, tmp_path, capsys):
    """The registration's own points with their tracks, observations moved into the 96 px pinhole
    frames: tracks of 2 or more, errors (observation to projection through the exported camera) of
    a fraction of a pixel, the same points as the registration's model (none lost: every photo
    became a frame), read back by pycolmap; the output line and damcap_export.json say so."""
    import pycolmap

    from damcap.cli.main import main

    out = tmp_path / "colmap"
    assert main(["export-capture", str(registered_capture.root), "--format", "colmap", "-o", str(out)]) == 0
    line = capsys.readouterr().out
    assert "sparse points with their tracks (from reconstruction/sfm/model" in line
    registration = pycolmap.Reconstruction(str(registered_capture.root / "reconstruction" / "sfm" / "model"))
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert len(rec.images) == 20 and rec.num_points3D() >= 0.98 * registration.num_points3D() > 100
    lengths = np.array([p.track.length() for p in rec.points3D.values()])
    errors = np.array([p.error for p in rec.points3D.values()])
    assert lengths.min() >= 2 and lengths.mean() > 3
    assert np.isfinite(errors).all() and errors.min() >= 0 and errors.mean() < 0.3 and errors.max() < 2.0
    _tracks_are_consistent(rec)
    record = json.loads((out / "damcap_export.json").read_text())
    assert record["points_source"] == "registration" and record["model"] == "reconstruction/sfm/model"
    assert record["points"] == rec.num_points3D() and record["options"]["format"] == "colmap"
    # the registration camera's scale: the mean error in the 256 px photos is the export's / (96 / 256), within a factor 2
    ratio = registration.compute_mean_reprojection_error() * 96 / 256 / rec.compute_mean_reprojection_error()
    assert 0.5 < ratio < 2.0


def test_undistortion_is_what_makes_the_observations_agree(registered_capture, monkeypatch):
    """The registration camera's radial distortion is undone: mapping its observations as if it
    were a pinhole leaves errors clearly larger than the export's."""
    import pycolmap

    from damcap.export import capture_export

    rec = pycolmap.Reconstruction(str(registered_capture.root / "reconstruction" / "sfm" / "model"))
    assert next(iter(rec.cameras.values())).params[-1] != 0  # SIMPLE_RADIAL's k
    norm = np.asarray(registered_capture.extra["damcap_source"]["norm_from_input_world"])

    def mean_error(tracked) -> float:
        errs = []
        for x, ks, xy in zip(tracked.xyz_world, tracked.frame_index, tracked.xy_px):
            for k, uv in zip(ks, xy):
                f = registered_capture.frames[k]
                cam = cam_from_world_opencv(f.world_from_cam)
                errs.append(np.linalg.norm(capture_export.pinhole_px((cam[:3, :3] @ x + cam[:3, 3])[None], f.intrinsics)[0] - uv))
        return float(np.nanmean(errs))

    good = mean_error(capture_export.tracked_points(rec, registered_capture, norm, "m"))
    for cam in rec.cameras.values():
        p = np.array(cam.params)
        p[-1] = 0.0
        cam.params = p
    bad = mean_error(capture_export.tracked_points(rec, registered_capture, norm, "m"))
    assert bad > 1.5 * good  # 0.19 px against 0.10 px: the object fills the middle of the photos, where k matters least


def test_observations_of_photos_the_capture_dropped_are_dropped(registered_capture, tmp_path):
    """A capture without 3 of the registration's photos: no track names them, points seen only
    by them (fewer than 2 observations left) are gone, the rest still read back consistently."""
    import dataclasses

    import pycolmap

    kept = registered_capture.frames[3:]
    names = {f.file_path for f in kept}
    capture = dataclasses.replace(registered_capture, frames=kept, train_filenames=[n for n in registered_capture.train_filenames if n in names],
                                  test_filenames=[n for n in registered_capture.test_filenames if n in names])
    full = export_capture(registered_capture, tmp_path / "full", CaptureExportOptions(format="colmap"))
    summary = export_capture(capture, tmp_path / "part", CaptureExportOptions(format="colmap"))
    rec = pycolmap.Reconstruction(str(tmp_path / "part" / "sparse" / "0"))
    assert summary["points_source"] == "registration" and len(rec.images) == 17
    assert {img.name for img in rec.images.values()} == {f.file_path.split("/")[-1].rsplit(".", 1)[0] + ".png" for f in kept}
    assert min(p.track.length() for p in rec.points3D.values()) >= 2
    observations = sum(p.track.length() for p in rec.points3D.values())
    full_rec = pycolmap.Reconstruction(str(tmp_path / "full" / "sparse" / "0"))
    assert observations < sum(p.track.length() for p in full_rec.points3D.values())
    assert summary["points"] <= full["points"]
    _tracks_are_consistent(rec)


def test_a_capture_whose_model_is_another_registration_falls_back_to_surface_samples(registered_capture, tmp_path):
    """A model whose cameras are not the capture's (here: the capture's similarity moved by 0.01)
    is not used: the export writes surface samples without tracks and says so."""
    import dataclasses

    import pycolmap

    source = dict(registered_capture.extra["damcap_source"])
    norm = np.array(source["norm_from_input_world"])
    norm[:3, 3] += 0.01
    source["norm_from_input_world"] = norm.tolist()
    capture = dataclasses.replace(registered_capture, extra={**registered_capture.extra, "damcap_source": source})
    summary = export_capture(capture, tmp_path / "c", CaptureExportOptions(format="colmap", points=200))
    rec = pycolmap.Reconstruction(str(tmp_path / "c" / "sparse" / "0"))
    assert summary["points_source"] == "surface samples" and rec.num_points3D() == 200
    assert all(p.track.length() == 0 for p in rec.points3D.values())


def test_points_triangulated_at_known_poses_are_exported_with_their_tracks(registered_capture, tmp_path, capsys):
    """A capture reconstructed at known poses (the registered capture as a nerfstudio dataset
    without masks, so its sphere is fitted to triangulated points) exports the points COLMAP
    triangulated there, with tracks and sub-pixel errors."""
    import pycolmap

    from damcap.cli.main import main

    ns = tmp_path / "ns"
    export_capture(registered_capture, ns, CaptureExportOptions(points=0))
    doc = json.loads((ns / "transforms.json").read_text())
    for f in doc["frames"]:
        del f["mask_path"]
    (ns / "transforms.json").write_text(json.dumps(doc))
    assert main(["reconstruct", str(ns), "-o", str(tmp_path / "known"), "--geometry", "sphere", "--capture-size", "64"]) == 0
    capsys.readouterr()
    assert main(["export-capture", str(tmp_path / "known"), "--format", "colmap", "-o", str(tmp_path / "colmap")]) == 0
    assert "sparse points with their tracks (from reconstruction/sfm/triangulated" in capsys.readouterr().out
    rec = pycolmap.Reconstruction(str(tmp_path / "colmap" / "sparse" / "0"))
    errors = np.array([p.error for p in rec.points3D.values()])
    assert rec.num_points3D() > 50 and min(p.track.length() for p in rec.points3D.values()) >= 2
    assert np.isfinite(errors).all() and errors.mean() < 0.3 and errors.max() < 2.0
    _tracks_are_consistent(rec)
