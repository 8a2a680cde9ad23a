"""The README's picture, ``bench/demo_everywhere.png``, from a ``make demo`` output: a bundled photo,
then the demo's three materials on its pot rendered by damcap, by Blender's Cycles with the exported
OSL materials and by the viewer page in headless Chromium.

Run (from the repository root, after ``make demo`` and ``make blender``; Debian's ``chromium``):
``.venv/bin/python -m bench.demo_picture --demo DIR`` writes, into bench/ (``--out OUT``: into OUT),
``blender_mesh.png`` (damcap's frame | Cycles' frame of export's first orbit view, 512x512 each,
:func:`bench.blender.mesh_render`), ``demo_viewer.png`` (``DIR/viewer.html`` at 480 px with its
caption, 256 colours) and ``demo_everywhere.png`` (:func:`compose_strip` of the photo and the three
renders). It reads DIR and writes nothing there.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image

from bench.common import BENCH, REPO, log

PHOTO = REPO / "samples" / "photos_studio" / "images" / "IMG_0000.jpg"
"""the bundled photo the picture starts with (red plastic, gold and aluminium on the bunny)"""
MESH_PX = 512
"""damcap's and Cycles' frame size, px (bench/blender.md's mesh render)"""
VIEWER_PX = 480
"""the viewer page's window size, px"""
VIEWER_COLOURS = 256
"""demo_viewer.png's palette size"""


def quantised(image_srgb8: np.ndarray, colours: int) -> Image.Image:
    """An sRGB image as a palette image of at most ``colours`` colours (Pillow's median cut, no dither).

    Args:
        image_srgb8: (H, W, 3) uint8, display sRGB.
        colours: palette size, 1-256.
    Returns:
        a Pillow image of mode "P", H x W.
    """
    return Image.fromarray(np.ascontiguousarray(image_srgb8), "RGB").quantize(colours, dither=Image.Dither.NONE)


def compose_strip(panels_srgb8: Sequence[np.ndarray], panel_px: int = 240, gap_px: int = 8, colours: int = 192) -> Image.Image:
    """Square panels side by side, left to right in the given order, each resized to ``panel_px``
    (Lanczos), ``gap_px`` of white between them, quantised to ``colours`` colours: the README's
    picture (photo, damcap, Cycles, viewer; 4 x 240 px + 3 x 8 px = 984 x 240, 192 colours).

    Args:
        panels_srgb8: N >= 1 arrays, each (S, S, 3) or (S, S, 4) uint8 display sRGB (alpha dropped), any S.
        panel_px: the side of each panel in the picture, px.
        gap_px: white columns between two panels, px.
        colours: the palette's size, 1-256.
    Returns:
        a Pillow image of mode "P", panel_px high and N * panel_px + (N - 1) * gap_px wide;
        panel k starts at column k * (panel_px + gap_px).
    """
    if not panels_srgb8:
        raise ValueError("compose_strip: no panels")
    for k, p in enumerate(panels_srgb8):
        if p.ndim != 3 or p.shape[0] != p.shape[1] or p.shape[2] not in (3, 4) or p.dtype != np.uint8:
            raise ValueError(f"compose_strip: panel {k} must be (S, S, 3|4) uint8, got {p.shape} {p.dtype}")
    n = len(panels_srgb8)
    strip = np.full((panel_px, n * panel_px + (n - 1) * gap_px, 3), 255, np.uint8)
    for k, p in enumerate(panels_srgb8):
        small = Image.fromarray(np.ascontiguousarray(p[..., :3]), "RGB").resize((panel_px, panel_px), Image.Resampling.LANCZOS)
        x = k * (panel_px + gap_px)
        strip[:, x:x + panel_px] = np.asarray(small)
    return quantised(strip, colours)


def save_png(path: Path, image: Image.Image) -> None:
    """Write a Pillow image as PNG, atomically."""
    from damcap.common.atomic import atomic_path

    with atomic_path(path) as tmp:
        image.save(tmp, format="PNG", optimize=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--demo", type=Path, required=True, help="a make demo output folder (pot.obj, segmentation/, viewer.html)")
    ap.add_argument("--out", type=Path, default=BENCH, help="where the three PNGs go (default: bench/)")
    args = ap.parse_args(argv)
    from bench.blender import BLENDER_PYTHON, mesh_render
    from damcap.common.exr import read_image_u8
    from damcap.export.browser import screenshot

    needed = [args.demo / "pot.obj", args.demo / "viewer.html", *(args.demo / "segmentation" / f"material_{k}.dam" for k in range(3))]
    missing = [str(p) for p in needed if not p.is_file()]
    if missing:
        raise SystemExit(f"{args.demo}: not a make demo output with the pot, missing {missing}")
    if not BLENDER_PYTHON.exists():
        raise SystemExit(f"{BLENDER_PYTHON}: run make blender first")
    args.out.mkdir(parents=True, exist_ok=True)
    mesh_png = args.out / "blender_mesh.png"
    with tempfile.TemporaryDirectory(prefix="damcap-demo-picture-") as tmp:
        work = Path(tmp)
        mesh = mesh_render(work, args.demo, MESH_PX, [], mesh_png)  # the exact render only: no timed sample counts
        log(f"{mesh_png}: {mesh['what']}; against damcap's frame {mesh['against_damcap_frame']}")
        screenshot(args.demo / "viewer.html", work / "viewer.png", VIEWER_PX)
        viewer = read_image_u8(work / "viewer.png")[..., :3]
    save_png(args.out / "demo_viewer.png", quantised(viewer, VIEWER_COLOURS))
    both = read_image_u8(mesh_png)[..., :3]
    damcap_frame, cycles_frame = both[:, :MESH_PX], both[:, MESH_PX:]
    picture = compose_strip([read_image_u8(PHOTO)[..., :3], damcap_frame, cycles_frame, viewer])
    save_png(args.out / "demo_everywhere.png", picture)
    log(f"wrote {args.out / 'demo_viewer.png'} and {args.out / 'demo_everywhere.png'} ({picture.width}x{picture.height})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
