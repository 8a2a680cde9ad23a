"""reconstruct/photos.py: photos of every kind the capture stage writes, through ``damcap reconstruct``.

One small scene with a known answer (:mod:`damcap.synth.photos`: a textured blob, 6 views of
128 px, cameras known, JPEGs with auto-exposure-like EXIF) is written several ways: as the
JPEGs themselves, as linear EXRs made by ``damcap linearize``'s library function, as LDR
brackets merged by ``damcap hdr`` (with its response curve saved beside each EXR), and as RAW
(DNG) files. Each set goes through ``reconstruct_capture`` with the known poses and the true mesh,
at the photos' own size, so every frame pixel is its photo pixel (no resampling) and the routes
compare pixel for pixel.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from damcap.capture.hdr import HdrOptions, merge_bracket_files, read_ldr_codes, read_response, write_hdr
from damcap.capture.linearize import LinearizeOptions, linearize_files
from damcap.capture.linearize import list_photos as linearize_list
from damcap.common.capture_folder import FrameData, inspect_capture, read_frame
from damcap.common.colour import srgb_to_linear
from damcap.common.errors import DamcapError
from damcap.common.exr import read_exr, write_exr, write_image_u8
from damcap.common.raycast import MeshRaycaster
from damcap.reconstruct.photos import (
    exposure_factors,
    list_photos,
    match_masks,
    photo_kind,
    proxy_srgb_u8,
    read_photo_radiance,
)
from damcap.reconstruct.dense import DenseOptions
from damcap.reconstruct.geometry import GeometryOptions
from damcap.reconstruct.pipeline import ReconstructOptions, ReconstructReport, reconstruct_capture
from damcap.synth.photos import (
    PhotoExposure,
    bumpy_blob,
    default_intrinsics,
    exposure_series,
    orbit_cameras,
    render_textured,
    write_photo_set,
)

N_VIEWS = 6
SIZE = 128
LIGHT = np.array([0.4, 0.8, 0.45]) / np.linalg.norm([0.4, 0.8, 0.45])
#: half-float storage (linearize's default): relative rounding 2^-11, two roundings at most
HALF_RTOL = 1e-3
#: float32 arithmetic on the same codes
FLOAT_RTOL = 1e-5


@dataclass
class Scene:
    root: Path
    cams: np.ndarray
    exposures: list[PhotoExposure]
    truth: dict[str, np.ndarray]
    """photo stem -> (H, W, 3) scene radiance"""

    @property
    def images(self) -> Path:
        return self.root / "images"


def _digests(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Scene:
    import open3d as o3d

    root = tmp_path_factory.mktemp("scene")
    mesh = bumpy_blob(subdivisions=4)
    cams = orbit_cameras(N_VIEWS, 3.2, (25.0,), jitter_deg=4, seed=0)
    exposures = exposure_series(N_VIEWS, 0)
    names = write_photo_set(root, mesh, cams, default_intrinsics(SIZE), exposures, light_dir_world=LIGHT)
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices.astype(np.float64)),
                                  o3d.utility.Vector3iVector(mesh.triangles))
    o3d.io.write_triangle_mesh(str(root / "blob.ply"), m)
    rc = MeshRaycaster(mesh)
    truth = {Path(n).stem: render_textured(rc, c, default_intrinsics(SIZE), LIGHT, e)[2] for n, c, e in zip(names, cams, exposures)}
    return Scene(root, cams, exposures, truth)


def _options(scene: Scene, **kw) -> ReconstructOptions:
    """Known poses, the true mesh, the photos' own size: frame pixel (i, j) is photo pixel (i, j)."""
    return ReconstructOptions(geometry=GeometryOptions(mode=f"mesh:{scene.root / 'blob.ply'}", mesh_align="none"), capture_size=SIZE,  # type: ignore[arg-type]
                              dtype="float", supersample=1, train_views=3, **kw)


def _reconstruct(scene: Scene, photos: Path, out: Path, **kw) -> tuple[dict[str, FrameData], ReconstructReport]:
    cap, report = reconstruct_capture(photos, out, _options(scene, **kw), masks_dir=scene.root / "masks",
                                      poses=str(scene.root / "transforms.json"))
    assert inspect_capture(out).problems == []
    return {Path(f.extra["photo"]).stem: read_frame(cap, f) for f in cap.frames}, report


@pytest.fixture(scope="module")
def jpeg_frames(scene, tmp_path_factory) -> dict[str, FrameData]:
    """The reference route: the JPEGs themselves (sRGB curve undone, EXIF exposure divided out)."""
    frames, report = _reconstruct(scene, scene.images, tmp_path_factory.mktemp("jpeg") / "capture")
    assert "tone curve (sRGB) undone" in report.linearisation and len(frames) == N_VIEWS
    return frames


@pytest.fixture(scope="module")
def linearized(scene, tmp_path_factory) -> Path:
    """``damcap linearize``'s EXRs of the JPEGs (half floats, relative to the median exposure)."""
    out = tmp_path_factory.mktemp("lin") / "linear"
    linearize_files(linearize_list(scene.images), out, LinearizeOptions())
    return out


def read_photo_header_reference(path: Path) -> float:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    try:
        return float(inp.spec().getattribute("damcap:reference_exposure"))
    finally:
        inp.close()


def _ratio_medians(frames: dict[str, FrameData], reference: dict[str, np.ndarray], min_reference: float) -> np.ndarray:
    """(views, 3) median over each frame's fully covered pixels of frame / reference radiance."""
    out = []
    for stem, d in sorted(frames.items()):
        ref = reference[stem]
        on = (d.coverage > 0.99) & (ref.min(axis=-1) > min_reference)
        out.append(np.median(d.radiance_lin[on] / ref[on], axis=0))
    return np.array(out)


def _stored_turned(upright_px: np.ndarray, orientation: int) -> np.ndarray:
    """What a camera stores for upright pixels and this EXIF Orientation (6: the picture shown turned
    90 degrees clockwise is stored turned counter-clockwise; 8: the other way; 7: transposed across
    the other diagonal, its own inverse). Written from the EXIF definitions, not from the reader's code."""
    return np.ascontiguousarray({6: np.rot90(upright_px, 1), 8: np.rot90(upright_px, -1),
                                 7: upright_px[::-1, ::-1].swapaxes(0, 1)}[orientation])


# ---- listing and pure functions ----------------------------------------------------------------

def test_photo_kinds_listing_and_masks(tmp_path):
    assert [photo_kind(n) for n in ("a.JPG", "a.tiff", "a.EXR", "a.hdr", "a.dng", "a.CR2", "a.nef")] == \
        ["display", "display", "linear", "linear", "raw", "raw", "raw"]
    linear = tmp_path / "linear"
    linear.mkdir()
    for n in ("IMG_1.exr", "IMG_2.hdr", "IMG_1.exr.json", "linearize.json"):
        (linear / n).write_bytes(b"")
    assert list_photos(linear) == ["IMG_1.exr", "IMG_2.hdr"]  # damcap hdr / linearize records are not photos
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for n in ("IMG_1.jpg", "IMG_2.exr"):
        (mixed / n).write_bytes(b"")
    with pytest.raises(DamcapError, match=r"mixes 8-bit photos \(e\.g\. IMG_1\.jpg\) and linear EXR/HDR files \(e\.g\. IMG_2\.exr\); "
                                          "their radiance scales are not comparable"):
        list_photos(mixed)
    (mixed / "IMG_1.jpg").unlink()
    (mixed / "IMG_3.dng").write_bytes(b"")
    with pytest.raises(DamcapError, match=r"mixes linear EXR/HDR files .* and RAW files \(e\.g\. IMG_3\.dng\)"):
        list_photos(mixed)
    masks = tmp_path / "masks"
    masks.mkdir()
    (masks / "IMG_1.exr").write_bytes(b"")  # not a mask image
    (masks / "IMG_1.png").write_bytes(b"")
    assert match_masks(["IMG_1.exr"], masks) == {"IMG_1.exr": masks / "IMG_1.png"}


def test_registration_proxy_is_an_exposure_normalised_srgb_encoding():
    rad = np.ones((10, 20, 3))
    rad[0, 0] = 0.18
    proxy = proxy_srgb_u8(rad)
    assert proxy.dtype == np.uint8 and proxy[5, 5].tolist() == [255, 255, 255]
    assert proxy[0, 0].tolist() == [118, 118, 118]  # 0.18 of white: sRGB 0.4613561 -> 118
    assert np.array_equal(proxy_srgb_u8(rad * 37.0), proxy)  # the exposure does not matter
    assert proxy_srgb_u8(np.zeros((2, 2, 3))).max() == 0


def test_exposure_of_linear_exrs_comes_from_their_headers(tmp_path):
    px = np.full((4, 4, 3), 0.5, np.float32)
    paths = []
    for name, ref in (("a.exr", 0.01), ("b.exr", 0.04), ("c.exr", 0.02)):
        write_exr(tmp_path / name, px, ("R", "G", "B"), attributes={"damcap:reference_exposure": ref})
        paths.append(tmp_path / name)
    factors, _, reference, note = exposure_factors(paths)
    assert factors.tolist() == [0.01, 0.04, 0.02] and reference == 0.02 and "rescaled to the median 0.02" in note
    assert read_photo_radiance(paths[1], factors[1], reference).radiance_lin[0, 0, 0] == pytest.approx(0.25)
    ones, _, reference, note = exposure_factors(paths, ignore_exposure=True)
    assert ones.tolist() == [1, 1, 1] and reference == 1.0 and "--ignore-exposure" in note
    write_exr(tmp_path / "plain.exr", px, ("R", "G", "B"))
    write_exr(tmp_path / "plain2.exr", px, ("R", "G", "B"))
    ones, _, reference, note = exposure_factors([tmp_path / "plain.exr", tmp_path / "plain2.exr"])
    assert ones.tolist() == [1, 1] and reference == 1.0
    assert "values used as stored, exposure factor 1 for every photo (no file's header has damcap:reference_exposure" in note
    with pytest.raises(DamcapError, match=r"plain\.exr: its header has no damcap:reference_exposure while other photos' do"):
        exposure_factors(paths + [tmp_path / "plain.exr"])


def test_linear_files_grey_acescg_and_bad_values(tmp_path):
    from damcap.capture.working_space import rec709_to_working

    rgb = np.array([[[0.2, 0.5, 0.1], [1.0, 0.25, 0.05]]], np.float32)
    write_exr(tmp_path / "aces.exr", rec709_to_working(rgb, "acescg"), ("R", "G", "B"), dtype="float",
              attributes={"damcap:colorspace": "acescg"})
    assert np.allclose(read_photo_radiance(tmp_path / "aces.exr", 1.0, 1.0).radiance_lin, rgb, rtol=1e-5, atol=1e-6)
    write_exr(tmp_path / "grey.exr", np.full((2, 3), 0.3, np.float32), ("Y",), dtype="float")
    grey = read_photo_radiance(tmp_path / "grey.exr", 2.0, 1.0).radiance_lin
    assert grey.shape == (2, 3, 3) and np.allclose(grey, 0.15)
    write_exr(tmp_path / "cam.exr", rgb, ("R", "G", "B"), attributes={"damcap:colorspace": "camera_rgb"})
    with pytest.raises(DamcapError, match=r"cam\.exr: radiance is in 'camera_rgb'"):
        read_photo_radiance(tmp_path / "cam.exr", 1.0, 1.0)
    bad = rgb.copy()
    bad[0, 0, 1] = np.nan
    write_exr(tmp_path / "nan.exr", bad, ("R", "G", "B"), dtype="float")
    with pytest.raises(DamcapError, match=r"nan\.exr: 1 pixel value\(s\) are NaN or infinite"):
        read_photo_radiance(tmp_path / "nan.exr", 1.0, 1.0)


# ---- linear EXRs from damcap linearize ----------------------------------------------------------

def test_linearize_output_reconstructs_like_the_jpegs(scene, jpeg_frames, linearized, tmp_path):
    """Same codes, same sRGB curve, same EXIF exposure, same median reference: the EXR route
    equals the JPEG route to half precision (linearize stores half floats; measured 4.7e-4 at
    most, relative)."""
    before = _digests(linearized)
    frames, report = _reconstruct(scene, linearized, tmp_path / "capture")
    assert "linear EXR/HDR radiance, no tone curve undone" in report.linearisation
    reference = exposure_factors(sorted(scene.images.iterdir()))[2]  # the JPEGs' median EXIF exposure
    assert f"rescaled to the median {reference:.6g}" in report.linearisation
    assert sorted(frames) == sorted(jpeg_frames)
    for stem, d in frames.items():
        ref = jpeg_frames[stem]
        assert np.array_equal(d.coverage, ref.coverage)  # nothing clipped in these photos
        on = ref.coverage > 0
        assert np.allclose(d.radiance_lin[on], ref.radiance_lin[on], rtol=HALF_RTOL, atol=1e-6)
    assert _digests(linearized) == before  # inputs are only read


def test_exrs_of_several_linearize_runs_are_made_comparable_by_their_headers(scene, jpeg_frames, linearized, tmp_path):
    """Half the photos linearised again relative to 4x the median exposure: their values are 4x
    larger, their headers say so, and reconstruct brings every photo to the set's median
    reference, (1 + 4) / 2 of the JPEG route's: one constant for all frames, as predicted."""
    photos = tmp_path / "photos"
    shutil.copytree(linearized, photos)
    reference = exposure_factors(sorted(scene.images.iterdir()))[2]  # the JPEGs' median EXIF exposure
    first = sorted(scene.images.iterdir())[: N_VIEWS // 2]
    linearize_files(first, photos, LinearizeOptions(reference_exposure=4 * reference))
    assert read_exr(photos / first[0].with_suffix(".exr").name)[0][..., :3].max() > 3 * read_exr(linearized / first[0].with_suffix(".exr").name)[0][..., :3].max()
    frames, _ = _reconstruct(scene, photos, tmp_path / "capture")
    for stem, d in frames.items():
        on = jpeg_frames[stem].coverage > 0
        assert np.allclose(d.radiance_lin[on], 2.5 * jpeg_frames[stem].radiance_lin[on], rtol=HALF_RTOL, atol=1e-6)


def test_clipped_pixels_leave_the_coverage(scene, jpeg_frames, linearized, tmp_path):
    photos = tmp_path / "photos"
    shutil.copytree(linearized, photos)
    path = photos / "IMG_0002.exr"
    pixels, names = read_exr(path)
    pixels[60:70, 60:70, names.index("clipped")] = 1.0  # on the object in every view
    write_exr(path, pixels, names, attributes={"damcap:reference_exposure": read_photo_header_reference(path)})
    frames, _ = _reconstruct(scene, photos, tmp_path / "excluded")
    cov, ref_cov = frames["IMG_0002"].coverage, jpeg_frames["IMG_0002"].coverage
    assert (ref_cov[60:70, 60:70] > 0.99).all() and (cov[60:70, 60:70] == 0).all()
    outside = np.ones_like(cov, bool)
    outside[60:70, 60:70] = False
    assert np.array_equal(cov[outside], ref_cov[outside])
    assert (frames["IMG_0002"].radiance_lin[60:70, 60:70] == 0).all()
    doc = json.loads((tmp_path / "excluded" / "transforms.json").read_text())
    assert [f.get("clipped_pixels") for f in doc["frames"] if f["photo"] == "IMG_0002.exr"] == [100]
    kept, _ = _reconstruct(scene, photos, tmp_path / "kept", clipped="keep")
    assert np.array_equal(kept["IMG_0002"].coverage, ref_cov)


def test_a_display_photo_flags_its_top_codes_clipped(tmp_path):
    """An 8-bit code at or above 99 % of full scale in any channel (what damcap linearize flags)
    is a lower bound of the radiance: read_photo_radiance flags it (a lossless PNG, so the codes
    are exact; a JPEG's decoded codes go through the same test)."""
    codes = np.full((4, 5, 3), 120, np.uint8)
    codes[1, 2] = (255, 40, 40)  # one channel saturated
    codes[3, 4] = (253, 253, 253)  # 253 / 255 = 0.992
    codes[0, 0] = (252, 252, 252)  # 0.988: measured
    write_image_u8(tmp_path / "a.png", codes)
    clipped = read_photo_radiance(tmp_path / "a.png", 1.0, 1.0).clipped
    assert clipped.tolist() == (np.isin(np.arange(20).reshape(4, 5), [7, 19])).tolist()


def test_saturated_jpeg_pixels_are_reported_kept_by_default_and_dropped_when_asked(scene, jpeg_frames, tmp_path):
    """A white patch burnt into one JPEG on the object. By default (--clipped auto) a display
    photo's saturated pixels stay in the coverage, one log line says how many of the object's
    pixels are clipped and the frame records the count; with --clipped drop they leave the
    coverage, as a clipped EXR's do."""
    from damcap.synth.photos import write_jpeg

    photos = tmp_path / "photos"
    shutil.copytree(scene.images, photos)
    codes, _ = read_ldr_codes(photos / "IMG_0002.jpg")
    codes = codes.copy()
    codes[60:70, 60:70] = 255
    write_jpeg(photos / "IMG_0002.jpg", codes, scene.exposures[2], quality=100)
    ref_cov = jpeg_frames["IMG_0002"].coverage
    object_px = sum(int((f.coverage > 0.5).sum()) for f in jpeg_frames.values())
    runs = {}
    for policy in ("auto", "drop"):
        lines: list[str] = []
        cap, _ = reconstruct_capture(photos, tmp_path / policy, _options(scene, clipped=policy), masks_dir=scene.root / "masks",
                                     poses=str(scene.root / "transforms.json"), log=lines.append)
        frame = cap.frame("IMG_0002")
        n = frame.extra["clipped_object_pixels"]
        assert 100 <= n <= 144  # the patch, and at most a ring of JPEG ringing
        (line,) = [ln for ln in lines if ln.startswith("clipped: ")]
        assert line.startswith(f"clipped: {n} of the object's {object_px} pixels") and f"in 1 of {N_VIEWS} photos" in line
        runs[policy] = (read_frame(cap, frame).coverage, n, line)
    cov, _, line = runs["auto"]
    assert np.array_equal(cov, ref_cov) and "kept in the coverage" in line
    cov, n, line = runs["drop"]
    assert (ref_cov[60:70, 60:70] > 0.99).all() and (cov[60:70, 60:70] == 0).all() and "left out of the coverage" in line
    assert (cov == 0).sum() - (ref_cov == 0).sum() == n


# ---- LDR brackets merged by damcap hdr, and its response curve ----------------------------------

@pytest.fixture(scope="module")
def hdr_photos(scene, tmp_path_factory) -> Path:
    """One 3-frame bracket per view (PNG with EXIF, 2 stops apart around the view's exposure)
    merged by damcap hdr (Debevec response) into ``IMG_000k.exr`` + ``IMG_000k.exr.json``.
    The sample pixels come from the whole image (flat_fraction 1): the flattest 10% would all be
    the black background, which says nothing about the response."""
    mesh = bumpy_blob(subdivisions=4)
    rc = MeshRaycaster(mesh)
    root = tmp_path_factory.mktemp("hdr")
    out = root / "merged"
    out.mkdir()
    opts = HdrOptions(flat_fraction=1.0)
    for k, (cam, ex) in enumerate(zip(scene.cams, scene.exposures)):
        files = []
        for j, stops in enumerate((-2, 0, 2)):
            e = PhotoExposure(ex.time_s * 2.0 ** stops, ex.iso, ex.f_number)
            photo, _, _ = render_textured(rc, cam, default_intrinsics(SIZE), LIGHT, e)
            files.append(root / f"IMG_{k:04d}_{j}.png")
            write_image_u8(files[-1], photo, {"ExposureTime": e.time_s, "FNumber": e.f_number,
                                              "Exif:PhotographicSensitivity": int(e.iso)})
        write_hdr(out / f"IMG_{k:04d}.exr", merge_bracket_files(files, opts), opts)
    return out


def test_hdr_output_reconstructs_in_proportion_to_the_scene(scene, jpeg_frames, hdr_photos, tmp_path):
    """Merged brackets: each view's frame is proportional to the scene radiance, as the JPEG
    route's is. Per view and channel, the median of frame / scene radiance stays within 1.3% of
    its mean over the views (measured; each merge recovers and normalises its own curve), the
    JPEG route's within 0.9%; the channels agree within 0.15%; and the hdr route's frames are
    one constant times the JPEG route's within 1.3% per view."""
    frames, report = _reconstruct(scene, hdr_photos, tmp_path / "capture")
    assert "relative to its damcap:reference_exposure" in report.linearisation
    hdr = _ratio_medians(frames, scene.truth, 0.05)
    jpeg = _ratio_medians(jpeg_frames, scene.truth, 0.05)
    assert np.abs(jpeg / jpeg.mean(axis=0) - 1).max() < 0.02
    assert np.abs(hdr / hdr.mean(axis=0) - 1).max() < 0.03
    assert np.abs(hdr.mean(axis=0) / hdr.mean() - 1).max() < 0.02  # a curve per channel, no colour cast
    vs_jpeg = _ratio_medians(frames, {k: d.radiance_lin for k, d in jpeg_frames.items()}, 0.02)
    assert np.abs(vs_jpeg / vs_jpeg.mean(axis=0) - 1).max() < 0.03


def test_the_response_curve_hdr_saved_is_undone_for_8bit_photos(scene, jpeg_frames, hdr_photos, tmp_path):
    """--response: each JPEG pixel becomes exp(g(code)) instead of the sRGB curve's value, with the
    same exposure division, so frame / sRGB-route frame = exp(g(code)) / srgb_to_linear(code) at
    every pixel; a curve scaled by (2, 1, 0.5) scales the frames by exactly that."""
    record = hdr_photos / "IMG_0000.exr.json"
    g = read_response(record).log_response
    frames, report = _reconstruct(scene, scene.images, tmp_path / "recovered", response=str(record))
    assert "tone curve (response curve of IMG_0000.exr.json (debevec, 256 levels" in report.linearisation
    for stem, d in frames.items():
        codes, _ = read_ldr_codes(scene.images / f"{stem}.jpg")
        on = (d.coverage > 0) & (codes.min(axis=-1) > 0)
        srgb_lin = srgb_to_linear(np.maximum(codes, 1) / 255.0)
        predicted = np.stack([np.exp(g[c][codes[..., c]]) for c in range(3)], axis=-1) / srgb_lin
        assert np.allclose(d.radiance_lin[on] / jpeg_frames[stem].radiance_lin[on], predicted[on], rtol=FLOAT_RTOL)
    # the recovered curve is the camera's sRGB curve up to one scale in the mid-tones (measured 0.01)
    mid = np.arange(60, 200)
    assert np.ptp(g[:, mid] - np.log(srgb_to_linear(mid / 255.0)), axis=1).max() < 0.05

    doctored = tmp_path / "doctored.exr"
    doc = json.loads(record.read_text())
    doc["response"]["log_response"] = (np.asarray(doc["response"]["log_response"]) + np.log([[2.0], [1.0], [0.5]])).tolist()
    (tmp_path / "doctored.exr.json").write_text(json.dumps(doc))
    scaled, _ = _reconstruct(scene, scene.images, tmp_path / "doctored", response=str(doctored))  # the EXR's name finds its record
    for stem, d in scaled.items():
        on = d.coverage > 0
        assert np.allclose(d.radiance_lin[on], frames[stem].radiance_lin[on] * np.float32([2.0, 1.0, 0.5]), rtol=FLOAT_RTOL)


def test_a_response_curve_for_linear_photos_or_a_missing_one_is_refused(scene, linearized, hdr_photos, tmp_path):
    with pytest.raises(DamcapError, match=r"a response curve undoes the tone curve of 8-bit photos, but .* holds linear EXR/HDR files"):
        reconstruct_capture(linearized, tmp_path / "a", _options(scene, response=str(hdr_photos / "IMG_0000.exr.json")),
                            poses=str(scene.root / "transforms.json"))
    with pytest.raises(DamcapError, match=r"nothing\.exr\.json: response file not found"):
        reconstruct_capture(scene.images, tmp_path / "b", _options(scene, response=str(tmp_path / "nothing.exr")),
                            poses=str(scene.root / "transforms.json"))
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()  # refused before any work


# ---- RAW files ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def raw_photos(scene, tmp_path_factory) -> Path:
    """One DNG per view: the scene radiance through a Bayer sensor (shot and read noise, 14 bits,
    a real camera's colour matrix) at the view's EXIF exposure."""
    from damcap.synth.brackets import CameraModel, camera_rgb_from_rec709, expose, mosaic, write_dng

    out = tmp_path_factory.mktemp("raw") / "dng"
    out.mkdir()
    model = CameraModel()
    rng = np.random.default_rng(0)
    for stem, ex in zip(sorted(scene.truth), scene.exposures):
        site = mosaic(camera_rgb_from_rec709(scene.truth[stem], np.asarray(model.camera_from_xyz)), model.cfa)
        h = ex.time_s * ex.iso / 100 / ex.f_number ** 2
        raw = expose(site * (50.0 * model.full_well_e), h, model, rng)  # brightest photosites at about 15% of the full well
        write_dng(out / f"{stem}.dng", raw, model, ex.time_s, int(ex.iso), ex.f_number)
    return out


def test_raw_photos_reconstruct_in_proportion_to_the_scene(scene, jpeg_frames, raw_photos, tmp_path):
    """Decoded linearly with the EXIF exposure divided out: one scale for every view (medians of
    frame / scene radiance within 0.5% of their mean, measured: shot noise and demosaicing of a
    sharp texture), and the colour matrix brings camera RGB to Rec.709 (channels within 1.2%)."""
    frames, report = _reconstruct(scene, raw_photos, tmp_path / "capture")
    assert "RAW sensor values decoded linearly" in report.linearisation and "EXIF exposure" in report.linearisation
    raw = _ratio_medians(frames, scene.truth, 0.05)
    assert np.abs(raw / raw.mean(axis=0) - 1).max() < 0.015
    assert np.abs(raw.mean(axis=0) / raw.mean() - 1).max() < 0.03
    # against the JPEG route: one scale for all views and channels (the JPEGs' chroma subsampling
    # makes single pixels noisy, so medians per view; measured 1.7%)
    vs_jpeg = _ratio_medians(frames, {k: d.radiance_lin for k, d in jpeg_frames.items()}, 0.02)
    assert np.abs(vs_jpeg / vs_jpeg.mean() - 1).max() < 0.03
    doc = json.loads((tmp_path / "capture" / "transforms.json").read_text())
    ex = {f["photo"]: f["exposure"] for f in doc["frames"]}
    assert ex["IMG_0000.dng"]["time_s"] == pytest.approx(scene.exposures[0].time_s, rel=1e-5)


# ---- files that cannot be read ------------------------------------------------------------------

def test_truncated_exr_and_raw_files_are_named(scene, linearized, raw_photos, tmp_path):
    from damcap.cli.main import main

    for source, name in ((linearized, "IMG_0003.exr"), (raw_photos, "IMG_0003.dng")):
        photos = tmp_path / source.name
        shutil.copytree(source, photos)
        data = (photos / name).read_bytes()
        (photos / name).write_bytes(data[: len(data) // 2])
        with pytest.raises(DamcapError, match=rf"{name}: cannot read"):
            reconstruct_capture(photos, tmp_path / f"out_{name}", _options(scene), poses=str(scene.root / "transforms.json"))
        (photos / name).write_bytes(data[:64])  # not even a header
        with pytest.raises(DamcapError, match=rf"{name}: cannot read"):
            reconstruct_capture(photos, tmp_path / f"out2_{name}", _options(scene), poses=str(scene.root / "transforms.json"))
    assert main(["reconstruct", str(tmp_path / linearized.name), "-o", str(tmp_path / "cli"),
                 "--poses", str(scene.root / "transforms.json")]) == 2


# ---- through the commands, and through COLMAP ----------------------------------------------------

def test_damcap_linearize_output_goes_straight_into_damcap_reconstruct(scene, jpeg_frames, tmp_path):
    from damcap.cli.main import main

    assert main(["linearize", str(scene.images), "-o", str(tmp_path / "linear")]) == 0
    out = tmp_path / "capture"
    assert main(["reconstruct", str(tmp_path / "linear"), "-o", str(out), "--poses", str(scene.root / "transforms.json"),
                 "--masks", str(scene.root / "masks"), "--geometry", f"mesh:{scene.root / 'blob.ply'}", "--mesh-align", "none",
                 "--capture-size", str(SIZE), "--supersample", "1", "--train-views", "3"]) == 0
    from damcap.common.capture_folder import read_capture

    cap = read_capture(out)
    assert inspect_capture(out).problems == [] and len(cap.frames) == N_VIEWS
    for f in cap.frames:
        d, ref = read_frame(cap, f), jpeg_frames[Path(f.extra["photo"]).stem]
        on = ref.coverage > 0
        assert np.allclose(d.radiance_lin[on], ref.radiance_lin[on], rtol=2 * HALF_RTOL, atol=1e-5)  # half in, half out


def test_sfm_registers_linear_exrs_through_8bit_proxies(tmp_path):
    """No poses: COLMAP registers the EXRs through sRGB proxies in the work folder (same base
    names), the cameras agree with the truth, and a rerun reuses every stage, also after the
    proxies were written again (they are deterministic). Two of the photos linearized were stored
    turned (EXIF Orientation 6 and 8, lossless PNGs), one mask too (7): they are read upright and
    register as well as the others."""
    from damcap.reconstruct.normalize import rotation_agreement_deg
    from damcap.common.capture_folder import read_capture

    n = 16
    cams = orbit_cameras(n, 3.2, (25.0,), jitter_deg=4, seed=0)
    exposures = exposure_series(n, 0)
    names = write_photo_set(tmp_path, bumpy_blob(subdivisions=5), cams, default_intrinsics(256), exposures)
    for k, tag in ((3, 6), (10, 8)):
        jpeg, e = tmp_path / "images" / names[k], exposures[k]
        write_image_u8(jpeg.with_suffix(".png"), _stored_turned(read_ldr_codes(jpeg)[0], tag),
                       {"ExposureTime": float(e.time_s), "FNumber": float(e.f_number),
                        "Exif:PhotographicSensitivity": int(round(e.iso)), "Orientation": tag})
        jpeg.unlink()
    mask = tmp_path / "masks" / Path(names[5]).with_suffix(".png").name
    write_image_u8(mask, _stored_turned(read_ldr_codes(mask)[0], 7), {"Orientation": 7})
    linearize_files(linearize_list(tmp_path / "images"), tmp_path / "linear", LinearizeOptions())
    opts = ReconstructOptions(capture_size=64, geometry=GeometryOptions(voxels=48), dense=DenseOptions(image_size=64, depth_planes=32),
                              train_views=3, supersample=1)
    out = tmp_path / "capture"
    _, report = reconstruct_capture(tmp_path / "linear", out, opts, masks_dir=tmp_path / "masks")
    assert report.registered == n and report.registration["source"] == "sfm"
    proxies = out / "reconstruction" / "proxies"
    assert sorted(p.name for p in proxies.glob("*.png")) == sorted(Path(nm).stem + ".png" for nm in names)
    cap = read_capture(out)
    est = np.stack([f.world_from_cam for f in cap.frames])
    gt = np.stack([cams[names.index(Path(f.extra["photo"]).stem + ".jpg")] for f in cap.frames])
    assert rotation_agreement_deg(est, gt)[0].max() < 1.5  # degrees, as for the JPEGs themselves
    (proxies / "manifest.json").unlink()  # every proxy is written again
    _, again = reconstruct_capture(tmp_path / "linear", out, opts, masks_dir=tmp_path / "masks")
    assert again.registration["resumed"] == ["features", "matches", "mapping"]


def _truncated_jpeg(folder: Path, name: str = "cut.jpg") -> Path:
    rng = np.random.default_rng(0)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    write_image_u8(path, (rng.random((64, 64, 3)) * 255).astype(np.uint8))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


class TestTruncatedJpeg:
    """A JPEG cut in half is refused by every reader reconstruct uses, as hdr and linearize refuse it."""

    def test_every_reader_refuses_it_naming_the_file(self, tmp_path):
        from damcap.reconstruct.photos import read_mask, read_photo_radiance, read_photo_u8

        path = _truncated_jpeg(tmp_path)
        for read in (read_photo_u8, read_mask, lambda p: read_photo_radiance(p, 1.0, 1.0), read_ldr_codes):
            with pytest.raises(DamcapError, match=r"cut\.jpg: cannot read pixels, the file is damaged or truncated") as e:
                read(path)
            assert "\n" not in str(e.value)

    def test_reconstruct_refuses_it_before_any_work(self, tmp_path):
        photos = tmp_path / "photos"
        rng = np.random.default_rng(1)
        photos.mkdir()
        for k in range(3):
            write_image_u8(photos / f"ok{k}.jpg", (rng.random((64, 64, 3)) * 255).astype(np.uint8))
        _truncated_jpeg(photos)
        with pytest.raises(DamcapError, match=r"cut\.jpg: cannot read pixels, the file is damaged or truncated"):
            reconstruct_capture(photos, tmp_path / "out", ReconstructOptions())
        assert not (tmp_path / "out" / "transforms.json").exists()


def test_a_photo_set_that_shows_nothing_is_refused_before_any_work(tmp_path):
    """Every photo saturated (or black) everywhere: refused naming a photo and its value; one such
    photo among others passes (registration leaves it out)."""
    from damcap.reconstruct.photos import verify_photos

    for k in range(4):
        write_image_u8(tmp_path / f"w{k}.png", np.full((16, 16, 3), 255, np.uint8))
    names = [f"w{k}.png" for k in range(4)]
    with pytest.raises(DamcapError, match=r"w0.png: saturated everywhere \(smallest value 255, saturation at 249.9\), as is every photo .* \(4\)"):
        verify_photos(tmp_path, names)
    for k in range(4):
        write_image_u8(tmp_path / f"w{k}.png", np.full((16, 16, 3), 3, np.uint8))
    with pytest.raises(DamcapError, match=r"w0.png: black everywhere \(largest value 3\)"):
        verify_photos(tmp_path, names)
    write_image_u8(tmp_path / "w2.png", np.random.default_rng(0).integers(0, 256, (16, 16, 3), dtype=np.uint8))
    verify_photos(tmp_path, names)


def _png_claiming(width: int, height: int) -> bytes:
    """A PNG whose header (IHDR) claims width x height, grey 8-bit: a few bytes, a huge decode."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    # a 1 MiB private chunk: OpenImageIO refuses a header that claims 1000x its file's size itself (a real
    # 60000x60000 grey PNG of one colour is about 3.5 MB, and it decodes)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"prVt", bytes(2 ** 20)) + chunk(b"IDAT", zlib.compress(b"\0" * 4096)) + chunk(b"IEND", b""))


def test_a_huge_mask_is_refused_from_its_header_before_decoding(tmp_path, monkeypatch):
    """A 60000x60000 grey PNG given as a mask: refused from its header, by its size against the
    photo's and, without a photo size, by memory (the decoder is never reached)."""
    import damcap.common.exr as exr
    from damcap.common import validate
    from damcap.reconstruct.photos import read_mask

    (tmp_path / "m.png").write_bytes(_png_claiming(60000, 60000))
    monkeypatch.setattr(exr._oiio().ImageInput, "read_image", lambda *a, **k: pytest.fail("decoded"), raising=False)
    with pytest.raises(DamcapError, match=r"m.png: mask is 60000x60000 but its photo IMG_1.jpg is 32x48; masks must match"):
        read_mask(tmp_path / "m.png", (32, 48), "IMG_1.jpg")
    monkeypatch.setattr(validate, "machine_memory_bytes", lambda: 16 * 2 ** 30)
    # 3.6 GB of pixels, decoded and copied (7.2 GB: 6.7 GiB, within 8 GiB) plus what a mask makes of them (28.8 GB)
    with pytest.raises(DamcapError, match=r"m.png: an image of 60000x60000 pixels, 1 channels would need 33.5 GiB of memory"):
        read_mask(tmp_path / "m.png")




def test_a_photo_stored_sideways_is_read_upright_with_its_upright_mask(tmp_path):
    """A phone's portrait photo stored sideways (EXIF Orientation 6): its size, pixels and radiance
    are upright, a mask drawn on it as a viewer shows it is accepted and aligned (also one stored
    turned with its own tag, 7: mirrored), the photo check warns of nothing; a mask drawn on the
    sideways pixels is refused in one line."""
    import warnings

    from damcap.reconstruct.photos import image_size, read_mask, read_photo_u8, verify_photos

    rng = np.random.default_rng(0)
    photo = rng.integers(0, 256, (48, 32, 3), dtype=np.uint8)  # upright: 32 wide, 48 high
    write_image_u8(tmp_path / "IMG_1.png", _stored_turned(photo, 6), {"Orientation": 6})
    mask = np.zeros((48, 32), np.uint8)
    mask[5:20, 3:10] = 255  # the object, top left as a viewer shows the photo
    write_image_u8(tmp_path / "upright.png", mask)
    write_image_u8(tmp_path / "tagged.png", _stored_turned(mask, 7), {"Orientation": 7})
    assert image_size(tmp_path / "IMG_1.png") == (32, 48)
    np.testing.assert_array_equal(read_photo_u8(tmp_path / "IMG_1.png"), photo)
    np.testing.assert_array_equal(read_ldr_codes(tmp_path / "IMG_1.png")[0], photo)
    for m in ("upright.png", "tagged.png"):
        np.testing.assert_array_equal(read_mask(tmp_path / m, (32, 48), "IMG_1.png"), mask / 255.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        verify_photos(tmp_path, ["IMG_1.png"])
    write_image_u8(tmp_path / "sideways.png", _stored_turned(mask, 6))  # drawn on the stored pixels, no tag
    with pytest.raises(DamcapError, match=r"sideways.png: mask is 48x32 but its photo IMG_1.png is 32x48, both upright as a "
                                          r"viewer shows them \(EXIF Orientation applied\): the mask is turned by 90 degrees") as e:
        read_mask(tmp_path / "sideways.png", (32, 48), "IMG_1.png")
    assert "\n" not in str(e.value)


def test_photos_stored_turned_reach_colmap_as_upright_proxies(tmp_path):
    """COLMAP reads pixels as stored: a set where some 8-bit photos are stored turned is registered
    through proxies: the turned photos written upright (with the EXIF focal length, so COLMAP's
    camera prior is the photo's: 26 mm in 35 mm terms, on the image's diagonal), the others linked; a
    rerun writes nothing again. A set stored upright is read by COLMAP as it is."""
    from damcap.reconstruct.colmap.database import import_pycolmap
    from damcap.reconstruct.photos import needs_registration_proxies, read_photo_u8, write_registration_proxies

    photos = tmp_path / "photos"
    rng = np.random.default_rng(1)
    upright_px = {n: rng.integers(0, 256, (48, 32, 3), dtype=np.uint8) for n in ("a.jpg", "b.jpg", "c.png")}
    exif = {"Make": "Phone", "Model": "P1", "Exif:FocalLength": 4.2, "Exif:FocalLengthIn35mmFilm": 26}
    for n, tag in (("a.jpg", 1), ("b.jpg", 6), ("c.png", 7)):
        write_image_u8(photos / n, _stored_turned(upright_px[n], tag) if tag != 1 else upright_px[n], {**exif, "Orientation": tag})
    names = ["a.jpg", "b.jpg", "c.png"]
    assert not needs_registration_proxies(photos, ["a.jpg"]) and needs_registration_proxies(photos, names)
    proxies = tmp_path / "proxies"
    by_photo = write_registration_proxies(photos, names, proxies)
    assert by_photo == {"a.jpg": "a.jpg", "b.jpg": "b.png", "c.png": "c.png"}
    assert (proxies / "a.jpg").read_bytes() == (photos / "a.jpg").read_bytes()
    np.testing.assert_array_equal(read_photo_u8(proxies / "c.png"), upright_px["c.png"])  # lossless
    np.testing.assert_array_equal(read_photo_u8(proxies / "b.png"), read_photo_u8(photos / "b.jpg"))
    pycolmap = import_pycolmap()

    def colmap_cameras(folder: Path, images: list[str]) -> dict[str, Any]:
        db_path = tmp_path / f"{folder.name}.db"
        pycolmap.Database.open(str(db_path)).close()
        pycolmap.import_images(str(db_path), str(folder), camera_mode=pycolmap.CameraMode.PER_IMAGE, image_names=images,
                               options=pycolmap.ImageReaderOptions())
        db = pycolmap.Database.open(str(db_path))
        try:
            return {im.name: db.read_camera(im.camera_id) for im in db.read_all_images()}
        finally:
            db.close()

    as_stored = colmap_cameras(photos, ["b.jpg"])["b.jpg"]  # COLMAP on the photo itself: sideways
    assert (as_stored.width, as_stored.height) == (48, 32) and as_stored.has_prior_focal_length
    assert as_stored.params[0] == pytest.approx(48 * 26 / 36, rel=1e-3)  # 26 mm in 35 mm terms
    for name, cam in colmap_cameras(proxies, list(by_photo.values())).items():
        assert (cam.width, cam.height) == (32, 48) and cam.has_prior_focal_length, name
        assert cam.params[0] == as_stored.params[0], name
    stamps = {p.name: p.lstat().st_mtime_ns for p in proxies.iterdir()}
    assert write_registration_proxies(photos, names, proxies) == by_photo
    assert {p.name: p.lstat().st_mtime_ns for p in proxies.iterdir()} == stamps


def test_a_set_with_photos_stored_turned_gives_the_frames_of_the_upright_photos(scene, jpeg_frames, tmp_path):
    """Two of the JPEGs stored turned, as lossless PNGs with their EXIF exposure (Orientation 6, and 7:
    mirrored), one mask stored turned with its own tag: reconstruct makes the same upright frames,
    pixel for pixel, as from the photos stored upright."""
    photos, masks = tmp_path / "images", tmp_path / "masks"
    shutil.copytree(scene.images, photos)
    shutil.copytree(scene.root / "masks", masks)
    for k, tag in ((1, 6), (4, 7)):
        stem, e = f"IMG_{k:04d}", scene.exposures[k]
        jpeg = photos / f"{stem}.jpg"
        exif = {"ExposureTime": float(e.time_s), "FNumber": float(e.f_number), "Exif:PhotographicSensitivity": int(round(e.iso))}
        write_image_u8(photos / f"{stem}.png", _stored_turned(read_ldr_codes(jpeg)[0], tag), {**exif, "Orientation": tag})
        jpeg.unlink()
    mask = read_ldr_codes(masks / "IMG_0004.png")[0][..., 0]
    write_image_u8(masks / "IMG_0004.png", _stored_turned(mask, 6), {"Orientation": 6})
    cap, _ = reconstruct_capture(photos, tmp_path / "capture", _options(scene), masks_dir=masks,
                                 poses=str(scene.root / "transforms.json"))
    frames = {Path(f.extra["photo"]).stem: read_frame(cap, f) for f in cap.frames}
    assert sorted(frames) == sorted(jpeg_frames) and {Path(f.extra["photo"]).name for f in cap.frames} >= {"IMG_0001.png", "IMG_0004.png"}
    for stem, ref in jpeg_frames.items():
        np.testing.assert_array_equal(frames[stem].coverage, ref.coverage)
        np.testing.assert_allclose(frames[stem].radiance_lin, ref.radiance_lin, rtol=FLOAT_RTOL, atol=1e-7)
