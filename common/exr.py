"""OpenEXR reading and writing through OpenImageIO (the only image I/O for linear data)."""

from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import Any, Literal, Mapping, Sequence

import numpy as np

from damcap.common.atomic import atomic_path, cut_short_error
from damcap.common.errors import DamcapError
from damcap.common.validate import check_format
from damcap.common.native_stderr import native_stderr_caught


def _oiio():
    """OpenImageIO, imported on first use (commands that read or write no image, such as
    ``train-hyper --procedural 1``, then run where it is not installed, e.g. a bare GPU machine)."""
    import OpenImageIO

    return OpenImageIO


def oiio_error(source) -> str:
    """The error OpenImageIO has pending (and clears) on ``source`` (the module, an ImageInput or
    an ImageOutput), as text. Its message may quote a damaged file's bytes, which its binding
    fails to decode as UTF-8: those are returned escaped (``\\x80``) instead of raising."""
    try:
        return source.geterror()
    except UnicodeDecodeError as e:
        return bytes(e.object).decode("utf-8", "backslashreplace")


def _one_line(message: str, path: Path) -> str:
    """OpenImageIO's error text as one short line (it repeats the path on every line)."""
    lines = [ln.replace(f'("{path}")', "").replace(f"({path})", "").replace(str(path), "").strip(" :")
             for ln in message.strip().splitlines()]
    lines = [ln for ln in lines if ln]
    return lines[-1] if lines else "unknown error"


#: the channel that flags pixels whose radiance is only a lower bound (saturated; 1 there, else 0):
#: damcap hdr and linearize write it, reconstruct reads it from such a photo
CLIPPED_CHANNEL = "clipped"

#: most channels damcap reads from one image
MAX_IMAGE_CHANNELS = 1024


def check_header_size(path: str | os.PathLike, width: int, height: int, channels: int, bytes_per_value: int,
                      working_bytes_per_pixel: int = 0) -> None:
    """Refuse an image whose header states a size that could not be held, before reading pixels.

    Args:
        bytes_per_value: of the decoded pixels (1 for uint8, 4 for float32); the decoder's buffer
            and its copy are counted.
        working_bytes_per_pixel: what the caller makes of each pixel once decoded (a mask's float32
            copy: 4), counted too, so that a picture that decodes but cannot be used is refused
            before it is decoded.

    Raises:
        DamcapError: a side outside [1, MAX_IMAGE_SIDE], a channel count outside [1, 1024], or
            pixels that would need more memory than the machine allows (the GiB are named).
    """
    from damcap.common.validate import MAX_IMAGE_SIDE, bounded_int, require_memory

    w = bounded_int(width, 1, MAX_IMAGE_SIDE, "image width (header)", path)
    h = bounded_int(height, 1, MAX_IMAGE_SIDE, "image height (header)", path)
    c = bounded_int(channels, 1, MAX_IMAGE_CHANNELS, "image channel count (header)", path)
    require_memory(float(w) * h * (c * bytes_per_value * 2 + working_bytes_per_pixel), f"an image of {w}x{h} pixels, {c} channels", path)


#: EXIF Orientation (tag 0x0112) -> how the stored (H, W) pixels are shown upright: 1 as stored,
#: 2 mirrored left-right, 3 turned 180 degrees, 4 mirrored top-bottom, 5 transposed, 6 turned 90
#: degrees clockwise (a phone's portrait photo), 7 transposed across the other diagonal, 8 turned
#: 90 degrees counter-clockwise. 5 to 8 swap width and height.
EXIF_ORIENTATIONS = (1, 2, 3, 4, 5, 6, 7, 8)


def exif_orientation(value: Any) -> int:
    """An EXIF Orientation value as one of 1..8; anything else (absent, 0, 9, text) is 1, as viewers read it.

    >>> exif_orientation(6), exif_orientation(None), exif_orientation(42)
    (6, 1, 1)
    """
    try:
        o = int(value)
    except (TypeError, ValueError):
        return 1
    return o if o in EXIF_ORIENTATIONS else 1


def upright(pixels: np.ndarray, orientation: int) -> np.ndarray:
    """Stored pixels turned upright, as a viewer shows them (OpenImageIO's ``ImageBufAlgo.reorient``).

    Args:
        pixels: (H, W) or (H, W, C) array, as stored in the file.
        orientation: its EXIF Orientation, 1..8 (:data:`EXIF_ORIENTATIONS`; others count as 1).

    Returns:
        (H', W'[, C]) contiguous array, (W, H) swapped for 5 to 8; the input itself for 1.

    >>> upright(np.array([[1, 2, 3], [4, 5, 6]]), 6).tolist()
    [[4, 1], [5, 2], [6, 3]]
    >>> upright(np.array([[1, 2, 3], [4, 5, 6]]), 2).tolist()
    [[3, 2, 1], [6, 5, 4]]
    """
    o = exif_orientation(orientation)
    if o == 1:
        return pixels
    a = np.asarray(pixels)
    a = {2: lambda: a[:, ::-1], 3: lambda: a[::-1, ::-1], 4: lambda: a[::-1],
         5: lambda: a.swapaxes(0, 1), 6: lambda: np.rot90(a, -1), 7: lambda: np.rot90(a, 2).swapaxes(0, 1),
         8: lambda: np.rot90(a, 1)}[o]()
    return np.ascontiguousarray(a)


def upright_size(width: int, height: int, orientation: int) -> tuple[int, int]:
    """(width, height) of an image stored ``width`` x ``height`` once turned upright by its EXIF Orientation.

    >>> upright_size(4032, 3024, 6), upright_size(4032, 3024, 3)
    ((3024, 4032), (4032, 3024))
    """
    return (height, width) if exif_orientation(orientation) >= 5 else (width, height)


def image_header(path: str | os.PathLike) -> tuple[int, int, int, int]:
    """(width, height, channels, EXIF orientation) of an image as stored, from its header only (no
    pixel is decoded); orientation 1 when the file has none (5 to 8: stored turned by 90 degrees,
    :func:`upright_size` gives the size a viewer shows).

    Raises:
        DamcapError: missing, or not an image OpenImageIO reads.
    """
    path = Path(path)
    if not path.is_file():
        raise DamcapError(f"{path}: {'is a folder, not an image' if path.is_dir() else 'file not found'}")
    with native_stderr_caught() as printed:
        inp = _oiio().ImageInput.open(str(path))
        if inp is not None:
            try:
                spec = inp.spec()
                orientation = spec.get_int_attribute("Orientation", 1)
            finally:
                inp.close()
    if inp is None:
        raise DamcapError(f"{path}: cannot read image ({_one_line(oiio_error(_oiio()) or chr(10).join(printed), path)})")
    return spec.width, spec.height, spec.nchannels, exif_orientation(orientation)


def read_exr(path: str | os.PathLike) -> tuple[np.ndarray, tuple[str, ...]]:
    """Read every channel of an image file.

    Args:
        path: an EXR (or any OpenImageIO-readable) file.

    Returns:
        pixels: (H, W, C) float32, as stored (linear for EXR).
        channel_names: C names, e.g. ``("R", "G", "B")`` or ``("N.X", ...)``.

    Raises:
        DamcapError: the file is missing, unreadable or truncated.
    """
    path = Path(path)
    if not path.is_file():
        raise DamcapError(f"{path}: file not found")
    check_format(path)  # OpenImageIO reads any format by content: a PNG named .exr is not an EXR
    inp = _oiio().ImageInput.open(str(path))
    if inp is None:
        raise DamcapError(f"{path}: cannot read image ({_one_line(oiio_error(_oiio()), path)})")
    try:
        spec = inp.spec()
        check_header_size(path, spec.width, spec.height, spec.nchannels, 4)
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        err = oiio_error(inp)
    finally:
        inp.close()
    if pixels is None or err:
        raise DamcapError(f"{path}: cannot read pixels, the file is damaged or truncated ({_one_line(err or '', path)})")
    pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    return pixels, tuple(spec.channelnames)


def read_exr_channels(path: str | os.PathLike, names: Sequence[str]) -> np.ndarray:
    """Read the named channels, in the order asked, as (H, W, len(names)) float32.

    Raises:
        DamcapError: a channel is missing (the message lists what the file has).
    """
    pixels, have = read_exr(path)
    missing = [n for n in names if n not in have]
    if missing:
        raise DamcapError(
            f"{path}: missing channel(s) {', '.join(missing)}; the file has {', '.join(have)}"
        )
    return np.stack([pixels[..., have.index(n)] for n in names], axis=-1)


def write_exr(
    path: str | os.PathLike,
    pixels: np.ndarray,
    channel_names: Sequence[str],
    *,
    dtype: Literal["half", "float"] = "half",
    attributes: Mapping[str, str | int | float] | None = None,
) -> None:
    """Write (H, W, C) pixels as a ZIP-compressed OpenEXR file, atomically.

    Args:
        path: destination ``.exr``.
        pixels: (H, W, C) or (H, W) array, finite; half storage keeps values up to 65504.
        channel_names: C names.
        dtype: ``"half"`` (float16) or ``"float"`` (float32) storage.
        attributes: extra header attributes (strings or numbers).
    """
    pixels = np.asarray(pixels, dtype=np.float32)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.ndim != 3 or pixels.shape[2] != len(channel_names):
        raise ValueError(f"pixels shape {pixels.shape} does not match channels {list(channel_names)}")
    h, w, c = pixels.shape
    spec = _oiio().ImageSpec(w, h, c, dtype)
    spec.channelnames = tuple(channel_names)
    spec.attribute("compression", "zip")
    for key, value in (attributes or {}).items():
        spec.attribute(key, value)
    _write_atomic(path, spec, np.ascontiguousarray(pixels))


def _write_atomic(path: str | os.PathLike, spec: Any, pixels: np.ndarray) -> None:
    """Write pixels with an OpenImageIO spec to a temporary file renamed onto ``path``; the
    format follows ``path``'s extension."""
    with atomic_path(path) as tmp:
        out = _oiio().ImageOutput.create(str(tmp))
        if out is None:
            raise DamcapError(f"{path}: cannot create image writer ({oiio_error(_oiio()).strip()})")
        try:
            if not (out.open(str(tmp), spec) and out.write_image(pixels)):
                _raise_full_disk(tmp, path, pixels.nbytes)
                # the line names the file the user asked for, not the hidden temporary one
                raise DamcapError(f"{path}: cannot write image ({oiio_error(out).strip().replace(str(tmp), str(path))})")
        finally:
            out.close()
        _verify_written(tmp, path, pixels.nbytes)


def _raise_full_disk(tmp: Path, path: str | os.PathLike, nbytes: int) -> None:
    """Raise ENOSPC (the disk has less room than ``nbytes``, the pixels before compression) or
    EFBIG (the file size limit) naming ``path`` after a failed write (:func:`cut_short_error`):
    OpenImageIO's own message says only that the output failed, naming the temporary file."""
    error = cut_short_error(tmp, path, nbytes)
    if error is not None:
        raise error


def _verify_written(tmp: Path, path: str | os.PathLike, nbytes: int = 0) -> None:
    """Read a just-written image back: OpenImageIO reports success for a write that the disk cut
    short (full disk, file-size limit), and the file is then a truncated image.

    Raises:
        OSError: ENOSPC naming ``path`` (the caller's one line for a full disk).
    """
    with native_stderr_caught():
        inp = _oiio().ImageInput.open(str(tmp))
        ok = inp is not None and inp.read_image() is not None and not oiio_error(inp)
        if inp is not None:
            inp.close()
    if not ok:
        _raise_full_disk(tmp, path, nbytes)
        raise OSError(errno.ENOSPC, "the image was written incompletely (disk full or file too large)", str(path))


def write_image_u8(path: str | os.PathLike, pixels_u8: np.ndarray, attributes: Mapping[str, str | int | float] | None = None) -> None:
    """Write (H, W), (H, W, 3) or (H, W, 4) uint8 display pixels (PNG, JPEG, ... by extension)
    with optional header attributes (e.g. ``Compression``, EXIF tags), atomically.

    A 4th channel is written as unassociated (straight) alpha, as PNG defines it: the colour
    channels are stored as given, not divided by alpha.
    """
    px = np.ascontiguousarray(pixels_u8, dtype=np.uint8)
    if px.ndim == 2:  # OpenImageIO reads a 2-D array's second axis as channels
        px = px[..., None]
    h, w, c = px.shape
    spec = _oiio().ImageSpec(w, h, c, "uint8")
    spec.attribute("oiio:UnassociatedAlpha", 1)
    for key, value in (attributes or {}).items():
        spec.attribute(key, value)
    _write_atomic(path, spec, px)


def write_png(path: str | os.PathLike, pixels_u8: np.ndarray) -> None:
    """Write (H, W, 3) or (H, W, 4) uint8 display pixels as PNG (OpenImageIO), atomically."""
    write_image_u8(path, pixels_u8)


def read_image_u8(path: str | os.PathLike, working_bytes_per_pixel: int = 0) -> np.ndarray:
    """Read an 8-bit display image (PNG/JPEG/TIFF) as (H, W, C) uint8, alpha unassociated (as
    stored), turned upright by its EXIF Orientation (:func:`upright`), as a viewer shows it.

    ``working_bytes_per_pixel``: what the caller makes of each pixel (:func:`check_header_size`),
    refused with the decode, before it."""
    path = Path(path)
    if not path.is_file():
        raise DamcapError(f"{path}: {'is a folder, not an image' if path.is_dir() else 'file not found'}")
    config = _oiio().ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    with native_stderr_caught() as printed:  # libpng prints its own lines on a damaged PNG
        inp = _oiio().ImageInput.open(str(path), config)
        if inp is not None:
            try:
                spec = inp.spec()
                check_header_size(path, spec.width, spec.height, spec.nchannels, 1, working_bytes_per_pixel)
                px = inp.read_image(0, 0, 0, spec.nchannels, "uint8")
                err = oiio_error(inp)  # a truncated JPEG/PNG reads with gray filler and an error here
                orientation = spec.get_int_attribute("Orientation", 1)
            finally:
                inp.close()
    if inp is None:
        raise DamcapError(f"{path}: cannot read image ({_one_line(oiio_error(_oiio()) or chr(10).join(printed), path)})")
    if px is None or err:
        raise DamcapError(f"{path}: cannot read pixels, the file is damaged or truncated "
                          f"({_one_line(err or chr(10).join(printed) or 'no data', path)})")
    return upright(np.asarray(px, np.uint8).reshape(spec.height, spec.width, spec.nchannels), orientation)
