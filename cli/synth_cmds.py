"""Commands of the synthetic data: closed-form (a capture known in closed form), synth (one
Mitsuba capture), synth-set (the corpus)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import typer

from damcap.common.errors import DamcapError

from damcap.cli.app import app, progress_bar


def default_data_dir() -> Path:
    """``$DAMCAP_SHARED_DATA`` or ``../shared/data`` next to the repository."""
    env = os.environ.get("DAMCAP_SHARED_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"


@app.command("closed-form")
def closed_form(
    out: Path = typer.Argument(..., help="new capture folder"),
    shape: str = typer.Option("sphere", help="sphere | torus"),
    light: str = typer.Option("directional", help="directional | env"),
    materials: int = typer.Option(1, help="1 or 2"),
    views: int = typer.Option(32, min=3),
    resolution: int = typer.Option(128, "--res", min=8),
    elevation: float = typer.Option(25.0, help="camera elevation, degrees"),
    train_views: int = typer.Option(10, help="consecutive training views"),
    seed: int = typer.Option(0),
    dtype: str = typer.Option("half", help="radiance storage: half | float"),
) -> None:
    """Write a capture whose appearance is known in closed form (Lambert + GGX, distant light)."""
    from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

    if shape not in ("sphere", "torus") or light not in ("directional", "env") or dtype not in ("half", "float"):
        raise DamcapError(f"--shape sphere|torus, --light directional|env, --dtype half|float; got {shape}, {light}, {dtype}")
    opts = ClosedFormOptions(shape=shape, light=light, materials=materials, views=views, resolution=resolution,  # type: ignore[arg-type]
                             elevation_deg=elevation, train_views=train_views, seed=seed, dtype=dtype)  # type: ignore[arg-type]
    cap = make_closed_form_capture(out, opts)
    typer.echo(f"wrote {len(cap.frames)} frames to {out}")


@app.command()
def synth(
    out: Path = typer.Argument(..., help="new capture folder (or a partial one to resume, same options)"),
    object_: str = typer.Option("sphere", "--object", help="mesh file (.obj, .ply) or 'sphere'"),
    light: str = typer.Option("point", help="'point[:AZIMUTH[:ELEVATION]]' or 'env:FILE[:ROTATION]' (degrees)"),
    materials: int = typer.Option(1, help="1 or 3 materials (noise regions)"),
    views: int = typer.Option(32, help="cameras on a circle"),
    resolution: int = typer.Option(256, "--res", help="image width and height, pixels"),
    spp: int = typer.Option(64, help="path-tracing samples per pixel (at 128 px: 512 under env maps, 256 under the point light keep the noise floor < 0.02)"),
    seed: int = typer.Option(0, help="elevation, colours, layout, split, light position, sampling"),
    train_views: int = typer.Option(10, help="consecutive training views"),
    elevation: Optional[float] = typer.Option(None, help="camera elevation, degrees (default: from the seed, 5..45)"),
    max_depth: int = typer.Option(6, help="longest path (2 = direct light only)"),
    supersample: int = typer.Option(4, help="k x k sub-pixel rays for coverage and weights"),
    variant: str = typer.Option("auto", help="Mitsuba variant: auto | llvm_ad_rgb | scalar_rgb"),
    dtype: str = typer.Option("half", help="radiance storage: half | float"),
) -> None:
    """Render one synthetic capture with Mitsuba 3 (the paper's data set), validated."""
    from damcap.synth.mitsuba_capture import SynthOptions, make_synthetic_capture

    opts = SynthOptions(object=object_, light=light, materials=materials, views=views, resolution=resolution, spp=spp,
                        seed=seed, train_views=train_views, elevation_deg=elevation, max_depth=max_depth,
                        supersample=supersample, variant=variant, dtype=dtype)  # type: ignore[arg-type]
    bar = progress_bar(views, "synth")
    cap = make_synthetic_capture(out, opts, progress=lambda done, total, stats: bar(done, total, stats))
    typer.echo(f"wrote {len(cap.frames)} frames to {out} (train {len(cap.train_filenames)}, test {len(cap.test_filenames)}, "
               f"{cap.materials} material(s)); validated")


@app.command("synth-set")
def synth_set(
    out: Path = typer.Argument(..., help="corpus folder (rerun to resume)"),
    preset: str = typer.Option("small", help="small (8 captures, 128 px) | paper (720 captures, 256 px) | hyper (224 predictor-training captures, 128 px) | segment (the held-out part with 3 materials, 4 captures, 128 px) | segment-dev (6 training-part 3-material captures, 128 px: where segmentation defaults are chosen)"),
    jobs: int = typer.Option(1, help="parallel processes (each gets cores / jobs render threads)"),
    data: Optional[Path] = typer.Option(None, help="shared data folder with meshes/ and envmaps/ (default: ../shared/data)"),
    dry_run: bool = typer.Option(False, "--dry-run", help="write corpus.json (the plan) and render nothing"),
) -> None:
    """Render the synthetic corpus: resumable, parallel, with a held-out part listed in corpus.json."""
    from tqdm import tqdm

    from damcap.synth.corpus import PRESETS, make_corpus

    if preset not in PRESETS:
        raise DamcapError(f"--preset must be one of {', '.join(PRESETS)}, got {preset!r}")
    data_dir = data or default_data_dir()
    if not (data_dir / "meshes").is_dir() or not (data_dir / "envmaps").is_dir():
        raise DamcapError(f"{data_dir}: no meshes/ and envmaps/ here; pass --data with the shared data folder")
    bar = None

    def on_capture(entry, finished: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=total, desc=f"synth-set {preset}", unit="capture", dynamic_ncols=True, disable=None)
        bar.n = finished
        bar.set_postfix_str(f"{entry.name}: {entry.status}", refresh=True)

    try:
        entries = make_corpus(out, preset, data_dir, jobs=jobs, dry_run=dry_run, on_capture=on_capture)  # type: ignore[arg-type]
    finally:
        if bar is not None:
            bar.close()
    counts = {s: sum(e.status == s for e in entries) for s in ("done", "skipped", "pending")}
    typer.echo(f"{out}/corpus.json: {len(entries)} captures ({sum(e.split == 'train' for e in entries)} train, "
               f"{sum(e.split == 'heldout' for e in entries)} held out); rendered {counts['done']}, "
               f"already there {counts['skipped']}, not rendered {counts['pending']}")
