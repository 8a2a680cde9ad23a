"""Predictor files: one safetensors file, the network's tensors plus a JSON metadata block.

Like ``.dam`` files (:mod:`.dam_file`), opening a stranger's predictor executes nothing. Metadata
key ``damcap`` holds JSON with ``format_version``, ``kind`` = ``"dam-predictor"``,
``architecture`` (:class:`.hyper.HyperArchitecture`) and ``training`` (command, data, options,
validation curve, ...).

This module imports torch only when a predictor is read or written: the command line reads its
names of the shipped predictors (:data:`DEFAULT_SHIPPED`, :data:`PAPER_SHIPPED`) for its help.
"""

from __future__ import annotations

import json
import os
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

from damcap.common.atomic import atomic_path
from damcap.common.errors import DamcapError
from damcap.common.validate import loads_json

if TYPE_CHECKING:
    from damcap.appearance.hyper.model import HyperNet

PREDICTOR_FORMAT_VERSION = 1
KIND = "dam-predictor"
DEFAULT_SHIPPED = "v10"
"""the predictor ``damcap predict`` uses when none is named: up to 4 views, random closed-form
scenes, trained through predict's readout solve, in its light orientation"""
PAPER_SHIPPED = "v1"
"""the predictor the paper's reproductions use whatever the default (``damcap tables`` and
bench/hyper.py, bench/dam_core.py): the paper's method (Sec. 3.3: one input view, the network's own
output), so their published numbers stay the ones measured with it"""
SHIPPED = {
    PAPER_SHIPPED: "dam-predictor-v1.safetensors",
    DEFAULT_SHIPPED: "dam-predictor-v10.safetensors",
}
"""the trained predictors shipped in ``damcap.appearance.hyper/predictors/`` by name, one per
command that uses one (each one's recipe: the .json beside it; bench/hyper_ood.md compares
them): v1 reads one view and was trained on 202 Mitsuba captures (the paper's method); v10 reads
up to 4 views: v3 (random closed-form scenes rendered on a GPU, bench/train_predictor.sh) trained
further through predict's readout solve (``train-hyper --readout-iterations 3``, on the CPU: 400
steps to v4, 1600 to v6, 1600 on a mix with more distant lights to v8, ``--scene-lights-only 0.55
--scene-env-only 0.3``), then 2400 in its light orientation (``--orientation light``), for use with that solve"""
RETIRED = {"v2": "f25b5a5", "v3": "d796965", "v4": "db45094", "v6": "11dc441", "v8": "2d3e413"}
"""predictors shipped once and no longer, by name: the commit whose
``appearance/hyper/predictors/`` still holds them (v2 became v3, v3 v4, v4 v6, v6 v8, v8 v10 by
further training; bench/train_predictor.sh holds each one's recipe)"""


def shipped_predictor_path(name: str = DEFAULT_SHIPPED) -> Path:
    """Where a shipped predictor lives in the installed package.

    Raises:
        DamcapError: no shipped predictor has that name.
    """
    if name not in SHIPPED:
        raise DamcapError(f"no shipped predictor is called {name!r}; the shipped ones are {', '.join(SHIPPED)}")
    return Path(str(resources.files("damcap.appearance.hyper") / "predictors" / SHIPPED[name]))


def predictor_path(choice: str | os.PathLike | None) -> Path:
    """The predictor a ``--predictor`` value names: None = the default shipped one, a shipped
    name (``v1``, ``v10``), or a file path.

    >>> predictor_path("v10").name, predictor_path("my.safetensors").name
    ('dam-predictor-v10.safetensors', 'my.safetensors')

    Raises:
        DamcapError: a retired shipped name (:data:`RETIRED`) that is not also a file here.
    """
    if choice is None:
        return shipped_predictor_path()
    if str(choice) in SHIPPED:
        return shipped_predictor_path(str(choice))
    if str(choice) in RETIRED and not Path(choice).exists():
        raise DamcapError(f"{choice}: damcap no longer ships predictor {choice} (shipped: {', '.join(SHIPPED)}; "
                          f"default {DEFAULT_SHIPPED}); its file is in appearance/hyper/predictors/ at commit {RETIRED[str(choice)]}")
    return Path(choice)


def save_predictor(path: str | os.PathLike, net: HyperNet, training: dict[str, Any]) -> None:
    """Write a predictor atomically (float32 tensors + metadata)."""
    from safetensors.torch import save as st_save

    from damcap.appearance.dam_file import METADATA_KEY
    meta = {"format_version": PREDICTOR_FORMAT_VERSION, "kind": KIND, "architecture": net.arch.to_json(), "training": training}
    tensors = {k: v.detach().float().contiguous().cpu() for k, v in net.state_dict().items()}
    blob = st_save(tensors, metadata={METADATA_KEY: json.dumps(meta)})
    with atomic_path(path) as tmp:
        tmp.write_bytes(blob)


def load_predictor(path: str | os.PathLike) -> tuple[HyperNet, dict[str, Any]]:
    """Read a predictor file; refuses anything else with a clear error.

    Raises:
        DamcapError: missing file, not safetensors (random bytes, a pickle, truncated), not a
            predictor, a newer format version, an integer of the architecture given as 256.0 or
            true, tensors that do not match the stated architecture,
            non-finite tensors.
    """
    import torch

    from damcap.appearance.dam import DamArchitecture
    from damcap.appearance.dam_file import integer_fields, read_damcap_safetensors, require_integers
    from damcap.appearance.hyper.model import HyperArchitecture, HyperNet

    path = Path(path)
    retired = path.name.removeprefix("dam-predictor-").removesuffix(".safetensors")
    if not path.exists() and path.name.startswith("dam-predictor-") and retired in RETIRED:
        raise DamcapError(f"{path}: not found; damcap no longer ships predictor {retired}: git show {RETIRED[retired]}:"
                          f"appearance/hyper/predictors/{path.name} > {path.name} (bench/train_predictor.sh holds its recipe)")
    tensors, meta_text = read_damcap_safetensors(path, "predictor", "predictor")
    meta = loads_json(meta_text, path, "predictor metadata")
    if not isinstance(meta, dict) or meta.get("kind") != KIND:
        raise DamcapError(f"{path}: damcap file of kind {meta.get('kind') if isinstance(meta, dict) else None!r}, not a predictor "
                          f"(a .dam model? use it with render/evaluate instead)")
    version = meta.get("format_version")
    if not isinstance(version, int) or version > PREDICTOR_FORMAT_VERSION:
        raise DamcapError(f"{path}: predictor format version {version!r} is newer than this damcap reads ({PREDICTOR_FORMAT_VERSION}); upgrade damcap")
    arch_json = meta.get("architecture")
    if isinstance(arch_json, dict):  # integers stay integers: from_json's int() would take 256.7 or true
        require_integers(arch_json, integer_fields(HyperArchitecture), path, "architecture")
        channels = arch_json.get("channels")
        if isinstance(channels, list):
            require_integers(dict(enumerate(channels)), tuple(range(len(channels))), path, "architecture.channels")
        if isinstance(arch_json.get("dam"), dict):
            require_integers(arch_json["dam"], integer_fields(DamArchitecture), path, "architecture.dam")
    try:
        arch = HyperArchitecture.from_json(meta["architecture"])
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        raise DamcapError(f"{path}: predictor architecture metadata is invalid ({e!r})") from None
    except DamcapError as e:  # a bound of the architecture (checked before anything is allocated)
        raise DamcapError(f"{path}: invalid predictor architecture: {e}") from None
    net = HyperNet(arch)
    expected = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    found = {k: tuple(v.shape) for k, v in tensors.items()}
    if expected != found:
        diff = sorted(set(expected.items()) ^ set(found.items()))[:3]
        raise DamcapError(f"{path}: tensors do not match the stated architecture (first differences: {diff}); "
                          f"the file is damaged or was written by another damcap version")
    bad = [k for k, v in tensors.items() if not (v.dtype.is_floating_point and torch.isfinite(v.float()).all())]
    if bad:
        raise DamcapError(f"{path}: tensor(s) {bad[:3]} contain NaN or inf")
    net.load_state_dict(tensors)
    net.eval()
    return net, meta
