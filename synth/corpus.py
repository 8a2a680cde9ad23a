"""The synthetic corpus (``damcap synth-set``): many captures, resumable, in parallel processes.

The paper's data set (Maximov et al. 2019, Sec. 4): objects x 20 illuminations x {environment
map, point light} x {1, 3 materials}. Here the objects are every mesh in ``shared/data/meshes``
plus the analytic sphere; the 20 environment illuminations are the 9 maps of
``shared/data/envmaps`` at rotations about +y; the 20 point lights lie on a golden-angle spiral
over the upper hemisphere.

A held-out part is fixed once for every preset: two objects (:data:`HELDOUT_OBJECTS`), one
environment map with all its rotations and four point-light positions
(:data:`HELDOUT_ENV_MAPS`, :data:`HELDOUT_POINT_LIGHTS`). A capture is ``train`` when neither
its object nor its light is held out and ``heldout`` otherwise, so no held-out object or
illumination is ever seen in training; ``heldout_object`` / ``heldout_light`` in ``corpus.json``
pick the strictest subset (both novel).

``OUT/corpus.json`` lists every capture (split, object, light, materials, seed, status) and is
rewritten atomically after each capture; finished captures (``transforms.json`` present) are
skipped on a rerun, and an interrupted capture resumes at its next unfinished frame.

Sharding (``--shard I/N``, :func:`shard_indices`): shard I of N renders only the captures at
positions I-1, I-1+N, I-1+2N, ... of the plan (a deterministic split: the plan's order is fixed by
the preset), so N processes, machines or the tasks of a job array build one corpus together, each
into the same folder. A shard writes only its own capture folders, never ``corpus.json``: the
index is written by one final run without ``--shard`` after every shard has finished. That run
finds the shards' captures finished (``skipped``), renders whatever a failed or missing shard
left, and writes the index once, so no two processes ever write it. The corpus is the same as one
un-sharded run's: every capture is rendered from its own seed whichever process renders it.
"""

from __future__ import annotations

import concurrent.futures as cf
import datetime as _dt
import multiprocessing
import os
import time
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal

from damcap.common.atomic import write_json_atomic
from damcap.common.errors import DamcapError
from damcap.common.validate import check_ranges, in_range

from damcap.synth.mitsuba_capture import SynthOptions, finished_with, make_synthetic_capture

Preset = Literal["small", "paper", "hyper", "segment", "segment-dev"]
PRESETS = ("small", "paper", "hyper", "segment", "segment-dev")

#: every object of the paper preset: mesh files in shared/data/meshes, and the analytic sphere
OBJECTS = ("stanford-bunny.obj", "spot.obj", "igea.ply", "cow.obj", "beetle.obj", "armadillo.obj",
           "dragon_10k.obj", "blub_triangulated.obj", "sphere")
HELDOUT_OBJECTS = ("spot.obj", "dragon_10k.obj")
ENV_MAPS = ("apartment.hdr", "city.hdr", "forest.hdr", "night.hdr", "studio.hdr", "warehouse.hdr",
            "mitsuba_envmap.hdr", "museum.exr", "sunset.hdr")
HELDOUT_ENV_MAPS = ("sunset.hdr",)
#: rotations about +y (degrees) of training maps and of the held-out map: 8 x 2 + 1 x 4 = 20
TRAIN_ENV_ROTATIONS = (0.0, 180.0)
HELDOUT_ENV_ROTATIONS = (0.0, 90.0, 180.0, 270.0)
N_POINT_LIGHTS = 20
HELDOUT_POINT_LIGHTS = (16, 17, 18, 19)


MAX_SHARDS = 100_000
"""most shards a corpus may be split into"""


def parse_shard(text: str) -> tuple[int, int]:
    """``--shard I/N`` -> (I, N), with 1 <= I <= N <= :data:`MAX_SHARDS`.

    >>> parse_shard("2/3")
    (2, 3)

    Raises:
        DamcapError: anything else, in one line naming the option and the value as typed.
    """
    parts = text.strip().split("/")
    try:
        i, n = (int(p) for p in parts) if len(parts) == 2 else (0, 0)
    except ValueError:
        i, n = 0, 0
    if not 1 <= i <= n <= MAX_SHARDS:
        raise DamcapError(f"--shard must be I/N with 1 <= I <= N <= {MAX_SHARDS} (shard I of N), got {text!r}")
    return i, n


def shard_indices(count: int, shard: tuple[int, int] | None) -> list[int]:
    """Positions in a plan of ``count`` captures that shard (I, N) renders: I-1, I-1+N, ...
    (round robin, so shards differ by at most one capture; None = all of them).

    >>> shard_indices(5, (1, 2)), shard_indices(5, (2, 2)), shard_indices(2, (3, 3)), shard_indices(3, None)
    ([0, 2, 4], [1, 3], [], [0, 1, 2])
    """
    if shard is None:
        return list(range(count))
    i, n = shard
    return list(range(i - 1, count, n))


@dataclass(frozen=True)
class CorpusOptions:
    """Options of ``damcap synth-set`` (the corpus folder and the shared data folder are arguments)."""

    preset: Preset = "small"
    """which corpus to render (:func:`preset`). 'small' (8 captures, 128 px), 'paper' (720 captures,
    256 px), 'hyper' (224 predictor-training captures, 128 px), 'segment' (the held-out part with 3
    materials, 4 captures, 128 px), 'segment-dev' (6 training-part 3-material captures, 128 px:
    where segmentation defaults are chosen)"""
    jobs: int = field(default=1, metadata=in_range(1, 256))
    """parallel processes (each gets cores / jobs render threads)"""
    dry_run: bool = False
    """write corpus.json (the plan) and render nothing (with --shard: only list the shard's share)"""
    shard: tuple[int, int] | None = field(default=None, metadata=in_range(1, MAX_SHARDS, cli_parse=parse_shard))
    """'I/N': render only shard I of N of the plan (captures I, I+N, I+2N, ... in plan order), for
    N processes or a job array sharing one corpus folder; a shard never writes corpus.json, so
    after all shards have finished run the same command once without --shard: it renders what
    is missing and writes the index"""

    def validate(self) -> None:
        """Raise DamcapError naming the first bad value."""
        check_ranges(self)
        if self.shard is not None:
            parse_shard("/".join(map(str, self.shard)))  # I <= N


@dataclass(frozen=True)
class LightEntry:
    """One of the corpus's 40 illuminations."""

    name: str
    """stable name, e.g. 'env-studio-r180' or 'point-07'"""
    spec: str
    """relative spec: 'env:studio.hdr:180' or 'point:AZ:EL'"""
    kind: Literal["env", "point"]
    heldout: bool


def env_illuminations() -> list[LightEntry]:
    """The 20 environment illuminations (maps x rotations).

    >>> lights = env_illuminations()
    >>> len(lights), sum(l.heldout for l in lights)
    (20, 4)
    """
    out = []
    for m in ENV_MAPS:
        held = m in HELDOUT_ENV_MAPS
        for r in (HELDOUT_ENV_ROTATIONS if held else TRAIN_ENV_ROTATIONS):
            out.append(LightEntry(f"env-{Path(m).stem}-r{int(r):03d}", f"env:{m}:{r:g}", "env", held))
    return out


def point_illuminations(n: int = N_POINT_LIGHTS) -> list[LightEntry]:
    """n point-light positions on a golden-angle spiral, elevation 15..65 degrees.

    >>> point_illuminations()[1].spec
    'point:137.508:17.6316'
    """
    golden = 180.0 * (3 - 5**0.5)
    return [LightEntry(f"point-{k:02d}", f"point:{(k * golden) % 360:.6g}:{15 + 50 * k / (n - 1):.6g}", "point",
                       k in HELDOUT_POINT_LIGHTS) for k in range(n)]


@dataclass(frozen=True)
class CorpusPreset:
    """What a preset renders and how."""

    name: str
    objects: tuple[str, ...]
    """object names (files in the meshes folder, or 'sphere')"""
    lights: tuple[str, ...]
    """light names (:func:`env_illuminations`, :func:`point_illuminations`)"""
    materials: tuple[int, ...]
    """material counts"""
    resolution: int
    """image size, pixels"""
    views: int
    """views per capture"""
    spp_env: int
    """samples per pixel under environment maps"""
    spp_point: int
    """samples per pixel under the point light"""
    combos: tuple[tuple[str, str, int], ...] | None = None
    """explicit (object, light, materials) triples instead of the full product"""


def _combo_preset(name: str, combos: tuple[tuple[str, str, int], ...]) -> CorpusPreset:
    """A preset of explicit (object, light, materials) captures at 128 px, 32 views, 512 / 256 spp."""
    return CorpusPreset(name, tuple(sorted({c[0] for c in combos})), tuple(sorted({c[1] for c in combos})),
                        tuple(sorted({c[2] for c in combos})), 128, 32, spp_env=512, spp_point=256, combos=combos)


def preset(name: Preset) -> CorpusPreset:
    """A corpus preset (``small``, ``paper``, ``hyper``, ``segment`` or ``segment-dev``).

    Samples per pixel keep the path-tracing noise floor (bench/synth.md) under 0.02 DSSIM:
    at 128 px, 512 under environment maps and 256 under the point light; twice that at 256 px.

    ``paper``: every object x 40 illuminations x {1, 3} materials at 256 px (720 captures).
    ``small``: 8 captures at 128 px, about 8 minutes on an idle 2-core machine: the held-out
    part has both held-out objects under the held-out environment map and held-out point lights,
    one material (the paper's Table 1 setting); the train part has the bunny and the sphere with
    1 and 3 materials under both light kinds.
    ``segment``: the held-out part of ``small`` with three materials (4 captures, 128 px): the
    test set of the segmentation rows of Table 1 (both held-out objects, the held-out environment
    map and held-out point lights).
    ``segment-dev``: the development set of the segmentation's defaults: six three-material
    captures of training objects under training illuminations (four environment maps, two point
    lights), 128 px, so a default is never chosen on the test set.
    ``hyper``: the training data of the predictor (``damcap train-hyper``): every training object
    x every training illumination, one material, 128 px, 12 views, 128 / 64 spp (224 captures,
    nothing held out is in it). Captures are in a hashed order, so an interrupted corpus is
    still a mix of objects and lights.

    >>> p = preset("hyper"); len(p.combos), len({c[0] for c in p.combos[:20]}) > 3
    (224, True)
    """
    lights = [l.name for l in env_illuminations() + point_illuminations()]
    if name == "paper":
        return CorpusPreset("paper", OBJECTS, tuple(lights), (1, 3), 256, 32, spp_env=1024, spp_point=512)
    if name == "small":
        combos = (
            ("spot.obj", "env-sunset-r090", 1), ("spot.obj", "point-16", 1),
            ("dragon_10k.obj", "env-sunset-r270", 1), ("dragon_10k.obj", "point-18", 1),
            ("stanford-bunny.obj", "env-studio-r000", 3), ("stanford-bunny.obj", "point-03", 1),
            ("sphere", "env-forest-r180", 1), ("sphere", "point-08", 3),
        )
        return _combo_preset("small", combos)
    if name == "segment":
        combos = (("spot.obj", "env-sunset-r090", 3), ("spot.obj", "point-16", 3),
                  ("dragon_10k.obj", "env-sunset-r270", 3), ("dragon_10k.obj", "point-18", 3))
        return _combo_preset("segment", combos)
    if name == "segment-dev":
        combos = (("cow.obj", "env-apartment-r000", 3), ("igea.ply", "env-city-r180", 3),
                  ("armadillo.obj", "env-forest-r000", 3), ("beetle.obj", "env-museum-r180", 3),
                  ("blub_triangulated.obj", "point-05", 3), ("cow.obj", "point-11", 3))
        return _combo_preset("segment-dev", combos)
    if name == "hyper":
        train_objects = tuple(o for o in OBJECTS if o not in HELDOUT_OBJECTS)
        train_lights = [l.name for l in env_illuminations() + point_illuminations() if not l.heldout]
        combos = sorted(((o, l, 1) for o in train_objects for l in train_lights),
                        key=lambda c: capture_seed(f"{Path(c[0]).stem}__{c[1]}__m1"))
        return CorpusPreset("hyper", train_objects, tuple(train_lights), (1,), 128, 12, spp_env=128, spp_point=64,
                            combos=tuple(combos))
    raise DamcapError(f"unknown preset {name!r}: use one of {', '.join(PRESETS)}")


@dataclass
class CorpusEntry:
    """One capture of the corpus."""

    name: str
    path: str
    """relative to the corpus folder"""
    split: Literal["train", "heldout"]
    object: str
    light: str
    light_kind: str
    materials: int
    seed: int
    heldout_object: bool
    heldout_light: bool
    options: dict[str, Any] = field(default_factory=dict)
    status: str = "pending"
    seconds: float | None = None
    message: str | None = None


def capture_seed(name: str) -> int:
    """A stable seed from a capture's name (same name, same capture on every machine).

    >>> capture_seed("bunny")
    3765765
    """
    return zlib.crc32(name.encode()) % 10_000_000


def plan_corpus(p: CorpusPreset, data_dir: Path) -> tuple[list[CorpusEntry], list[SynthOptions]]:
    """The captures of a preset, with the options that render each.

    Raises:
        DamcapError: a mesh or environment map of the preset is missing from ``data_dir``.
    """
    lights = {l.name: l for l in env_illuminations() + point_illuminations()}
    combos = p.combos or tuple((o, l, m) for o in p.objects for l in p.lights for m in p.materials)
    entries, options = [], []
    for obj, light_name, n in combos:
        light = lights[light_name]
        obj_path = "sphere" if obj == "sphere" else str(data_dir / "meshes" / obj)
        if obj != "sphere" and not Path(obj_path).is_file():
            raise DamcapError(f"{obj_path}: mesh of the {p.name!r} preset not found; pass --data with the shared data folder")
        spec = light.spec
        if light.kind == "env":
            _, file, rot = spec.split(":")
            env_path = data_dir / "envmaps" / file
            if not env_path.is_file():
                raise DamcapError(f"{env_path}: environment map of the {p.name!r} preset not found; pass --data with the shared data folder")
            spec = f"env:{env_path}:{rot}"
        name = f"{Path(obj).stem}__{light_name}__m{n}"
        seed = capture_seed(name)
        opts = SynthOptions(object=obj_path, light=spec, materials=n, views=p.views, resolution=p.resolution,
                            spp=p.spp_env if light.kind == "env" else p.spp_point, seed=seed)
        held_obj = obj in HELDOUT_OBJECTS
        entries.append(CorpusEntry(name=name, path=f"captures/{name}", split="heldout" if held_obj or light.heldout else "train",
                                   object=Path(obj).stem, light=light.spec, light_kind=light.kind, materials=n, seed=seed,
                                   heldout_object=held_obj, heldout_light=light.heldout, options=asdict(opts)))
        options.append(opts)
    return entries, options


def _render_one(out: str, opts: SynthOptions, threads: int) -> tuple[str, float, str | None]:
    """Worker: render one capture. Returns (status, seconds, message)."""
    t0 = time.perf_counter()
    try:
        make_synthetic_capture(out, opts, threads=threads)
    except DamcapError as e:
        return "failed", time.perf_counter() - t0, str(e)
    except (RuntimeError, OSError, ValueError) as e:  # renderer or file-system failures of this one capture
        return "failed", time.perf_counter() - t0, f"{e.__class__.__name__}: {e}"
    return "done", time.perf_counter() - t0, None


def _write_corpus(out: Path, p: CorpusPreset, entries: list[CorpusEntry], data_dir: Path, started: str) -> None:
    from damcap.common.version import package_version

    write_json_atomic(out / "corpus.json", {
        "damcap_package_version": package_version(), "preset": asdict(p), "data_dir": str(data_dir.resolve()), "started_utc": started,
        "heldout": {"objects": [Path(o).stem for o in HELDOUT_OBJECTS], "env_maps": list(HELDOUT_ENV_MAPS),
                    "point_lights": [f"point-{k:02d}" for k in HELDOUT_POINT_LIGHTS],
                    "rule": "split = heldout when the object or the light is held out; both flags give the strictest subset"},
        "counts": {s: sum(e.split == s for e in entries) for s in ("train", "heldout")},
        "captures": [asdict(e) for e in entries],
    })


def make_corpus(out: str | os.PathLike, preset_name: Preset, data_dir: str | os.PathLike, *, jobs: int = 1,
                dry_run: bool = False, on_capture: Callable[[CorpusEntry, int, int], None] | None = None,
                shard: tuple[int, int] | None = None) -> list[CorpusEntry]:
    """Render (or resume) every capture of a preset into ``out/captures/``, ``jobs`` at a time.

    Args:
        out: corpus folder.
        preset_name: a preset (:func:`preset`).
        data_dir: the shared data folder (``meshes/``, ``envmaps/``).
        jobs: parallel worker processes; each renders with ``cpu_count // jobs`` threads.
        dry_run: only write ``corpus.json`` (the plan), render nothing; with ``shard``, write nothing.
        on_capture: called as on_capture(entry, finished, total) as captures finish (or are skipped).
        shard: (I, N): render only shard I of N of the plan (:func:`shard_indices`) and write no
            ``corpus.json`` (see the module docstring: the index is written by a final run with
            ``shard=None`` once every shard has finished, so shards running at the same time never
            write the same file); None = the whole plan, index included.

    Returns:
        the entries (of the shard only, with ``shard``) with their status ('done', 'skipped' =
        finished before, 'failed', 'pending').

    Raises:
        DamcapError: bad preset, jobs or shard, missing data, or captures that failed (after all
            others ran).
    """
    if jobs < 1:
        raise DamcapError(f"--jobs must be >= 1, got {jobs}")
    if shard is not None:
        shard = parse_shard("/".join(map(str, shard)))
    out, data_dir = Path(out), Path(data_dir)
    p = preset(preset_name)
    entries, options = plan_corpus(p, data_dir)
    mine = shard_indices(len(entries), shard)
    entries, options = [entries[k] for k in mine], [options[k] for k in mine]
    if shard is not None and dry_run:
        return entries
    out.mkdir(parents=True, exist_ok=True)
    started = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    todo = []
    for e, o in zip(entries, options):
        if (out / e.path / "transforms.json").is_file():
            if not finished_with(out / e.path, o):
                raise DamcapError(f"{out / e.path}: holds a capture made with other options or input files than the "
                                  f"'{preset_name}' preset plans (--data {data_dir}); remove it or choose another corpus folder")
            e.status = "skipped"
        else:
            todo.append((e, o))
    write_index = shard is None  # a shard writes only its captures: the final un-sharded run writes the index
    if write_index:
        _write_corpus(out, p, entries, data_dir, started)
    finished = len(entries) - len(todo)
    if on_capture:
        for e in entries:
            if e.status == "skipped":
                on_capture(e, finished, len(entries))
    if dry_run or not todo:
        return entries
    from damcap.common.optional import require

    require("mitsuba", "damcap synth-set")  # one line here, not one failure per capture
    threads = max(1, (os.cpu_count() or 1) // jobs)
    ctx = multiprocessing.get_context("spawn")  # never fork a process that may hold LLVM/Dr.Jit threads
    with cf.ProcessPoolExecutor(max_workers=jobs, mp_context=ctx) as pool:
        futures = {pool.submit(_render_one, str(out / e.path), o, threads): e for e, o in todo}
        for fut in cf.as_completed(futures):
            e = futures[fut]
            e.status, e.seconds, e.message = fut.result()
            finished += 1
            if write_index:
                _write_corpus(out, p, entries, data_dir, started)
            if on_capture:
                on_capture(e, finished, len(entries))
    failed = [e for e in entries if e.status == "failed"]
    if failed:
        where = f"shard {shard[0]}/{shard[1]}" if shard else "see corpus.json"
        raise DamcapError(f"{out}: {len(failed)} capture(s) failed ({where}): "
                          + "; ".join(f"{e.name}: {e.message}" for e in failed[:3]))
    return entries
