"""Fixtures of the capture tests: the real brackets, a small simulated RAW bracket, an LDR helper."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from damcap.capture.exif import read_hdr_image_list


@pytest.fixture(scope="session")
def memorial(shared_data) -> tuple[list[Path], list[float], Path]:
    """Memorial Church: 16 PNG paths, their exposure times (s), the reference radiance map."""
    folder = shared_data / "brackets" / "memorial"
    times = read_hdr_image_list(folder / "memorial.hdr_image_list.txt")
    files = sorted(folder / name for name in times)
    return files, [times[f.name] for f in files], folder / "memorial_reference.hdr"


@pytest.fixture(scope="session")
def frobisher(shared_data) -> list[Path]:
    """Frobisher: 3 JPEGs with full EXIF (1/8, 1, 8 s at f/8, ISO 100)."""
    return sorted((shared_data / "brackets" / "frobisher").glob("*.jpg"))


@pytest.fixture(scope="session")
def sim_bracket(shared_data, tmp_path_factory):
    """A 5-frame simulated DNG bracket (2 stops apart) of a real HDR environment map, 256x128."""
    import cv2

    from damcap.synth.brackets import bracket_times, simulate_raw_bracket
    from damcap.common.exr import read_exr

    env, _ = read_exr(shared_data / "envmaps" / "sunset.hdr")
    small = cv2.resize(env[..., :3], (256, 128), interpolation=cv2.INTER_AREA)
    out = tmp_path_factory.mktemp("simdng")
    return simulate_raw_bracket(np.maximum(small, 0), out, bracket_times(5, 2.0, 1 / 15), seed=3)


def write_png_bracket(folder: Path, codes: np.ndarray, names: list[str] | None = None) -> list[Path]:
    """Write a (P, H, W, 3) uint8/uint16 stack as PNG files; returns their paths."""
    import OpenImageIO as oiio

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for j, img in enumerate(codes):
        p = folder / (names[j] if names else f"frame_{j}.png")
        fmt = "uint8" if img.dtype == np.uint8 else "uint16"
        out = oiio.ImageOutput.create(str(p))
        assert out.open(str(p), oiio.ImageSpec(img.shape[1], img.shape[0], img.shape[2], fmt))
        assert out.write_image(np.ascontiguousarray(img))
        out.close()
        paths.append(p)
    return paths
