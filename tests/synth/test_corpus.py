"""The synthetic corpus: the plan, the held-out rule, resumable parallel rendering, corpus.json."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from damcap.common.errors import DamcapError
from damcap.synth import corpus as synth_set
from damcap.synth.mitsuba_capture import validate_synthetic_capture
from damcap.synth.corpus import (
    HELDOUT_OBJECTS, OBJECTS, CorpusOptions, CorpusPreset, env_illuminations, make_corpus, parse_shard, plan_corpus,
    point_illuminations, preset, shard_indices,
)


def test_illuminations_are_distinct_and_twenty_each():
    env, point = env_illuminations(), point_illuminations()
    assert len({l.spec for l in env}) == 20 and len({l.spec for l in point}) == 20
    assert {l.name.split("-r")[0] for l in env if l.heldout} == {"env-sunset"}
    assert sum(l.heldout for l in point) == 4
    elevations = [float(l.spec.split(":")[2]) for l in point]
    assert min(elevations) == pytest.approx(15) and max(elevations) == pytest.approx(65)


def test_paper_plan_and_heldout_rule(shared_data):
    entries, options = plan_corpus(preset("paper"), shared_data)
    assert len(entries) == len(OBJECTS) * 40 * 2 == 720
    assert len({e.name for e in entries}) == 720 and len({e.seed for e in entries}) == 720
    train = [e for e in entries if e.split == "train"]
    held = [e for e in entries if e.split == "heldout"]
    # no held-out object or illumination ever appears in training
    assert not any(e.heldout_object or e.heldout_light for e in train)
    assert all(e.heldout_object or e.heldout_light for e in held)
    assert {e.object for e in train}.isdisjoint(Path(o).stem for o in HELDOUT_OBJECTS)
    assert {e.light for e in train}.isdisjoint(e.light for e in held if e.heldout_light)
    assert sum(e.heldout_object and e.heldout_light for e in held) == 2 * 8 * 2
    assert {o.resolution for o in options} == {256} and {o.views for o in options} == {32}
    assert all(Path(o.object).is_file() or o.object == "sphere" for o in options)


def test_small_preset_is_part_of_the_paper_grid(shared_data):
    small, _ = plan_corpus(preset("small"), shared_data)
    paper = {e.name: e for e in plan_corpus(preset("paper"), shared_data)[0]}
    assert all(e.name in paper and paper[e.name].split == e.split and paper[e.name].seed == e.seed for e in small)
    held = [e for e in small if e.split == "heldout"]
    # the paper's Table 1 setting: single material, held-out objects and lights, both light kinds
    assert {(e.light_kind, e.materials) for e in held} == {("env", 1), ("point", 1)}
    assert all(e.heldout_object and e.heldout_light for e in held)
    assert {e.materials for e in small if e.split == "train"} == {1, 3}


def test_missing_data_is_named(tmp_path):
    with pytest.raises(DamcapError, match="mesh of the 'small' preset not found; pass --data"):
        plan_corpus(preset("small"), tmp_path)
    with pytest.raises(DamcapError, match="unknown preset 'big'"):
        preset("big")  # type: ignore[arg-type]
    with pytest.raises(DamcapError, match="--jobs must be >= 1"):
        make_corpus(tmp_path / "c", "small", tmp_path, jobs=0)


def test_corpus_renders_in_parallel_and_resumes(tmp_path, monkeypatch):
    tiny = CorpusPreset("small", ("sphere",), ("point-03", "point-17"), (1,), resolution=16, views=11, spp_env=1, spp_point=2,
                        combos=(("sphere", "point-03", 1), ("sphere", "point-17", 1)))
    monkeypatch.setattr(synth_set, "preset", lambda name: tiny)
    seen = []
    entries = make_corpus(tmp_path / "corpus", "small", tmp_path, jobs=2, on_capture=lambda e, k, n: seen.append((e.status, k, n)))
    assert sorted(seen) == [("done", 1, 2), ("done", 2, 2)]
    doc = json.loads((tmp_path / "corpus" / "corpus.json").read_text())
    assert [c["status"] for c in doc["captures"]] == ["done", "done"]
    assert [c["split"] for c in doc["captures"]] == ["train", "heldout"]
    assert doc["counts"] == {"train": 1, "heldout": 1}
    for e in entries:
        assert validate_synthetic_capture(tmp_path / "corpus" / e.path) == []
    again = make_corpus(tmp_path / "corpus", "small", tmp_path, jobs=2)
    assert [e.status for e in again] == ["skipped", "skipped"]
    # a finished capture the plan would render otherwise is not taken for the planned one
    tj = tmp_path / "corpus" / entries[1].path / "transforms.json"
    doc = json.loads(tj.read_text())
    doc["damcap_source"]["options"]["seed"] += 1
    tj.write_text(json.dumps(doc))
    with pytest.raises(DamcapError, match="holds a capture made with other options or input files than the 'small' preset"):
        make_corpus(tmp_path / "corpus", "small", tmp_path, jobs=2)


def test_shards_split_the_plan_deterministically_and_completely():
    for count in (0, 1, 7, 720):
        for n in (1, 2, 3, 7):
            parts = [shard_indices(count, (i, n)) for i in range(1, n + 1)]
            assert sorted(k for p in parts for k in p) == list(range(count))  # every capture once
            assert max(map(len, parts)) - min(map(len, parts)) <= 1  # balanced
            assert parts == [shard_indices(count, (i, n)) for i in range(1, n + 1)]  # same split every time
    assert shard_indices(7, (2, 3)) == [1, 4] and shard_indices(3, None) == [0, 1, 2]
    assert parse_shard(" 3/4 ") == (3, 4)
    for bad in ("0/2", "3/2", "x", "1/0", "1/2/3", "", "-1/2", "1.5/2", "1/100001"):
        with pytest.raises(DamcapError, match=r"--shard must be I/N with 1 <= I <= N"):
            parse_shard(bad)
    with pytest.raises(DamcapError, match="got '3/2'"):
        CorpusOptions(shard=(3, 2)).validate()


def _contents(root: Path) -> dict[str, object]:
    """Every file under a corpus but its index: EXRs as (pixels, channel names), since OpenEXR
    stamps each file with the time it was written; other files as bytes."""
    from damcap.common.exr import read_exr

    out: dict[str, object] = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and p.name != "corpus.json":
            out[str(p.relative_to(root))] = (read_exr(p)[0].tobytes(), read_exr(p)[1]) if p.suffix == ".exr" else p.read_bytes()
    return out


def test_shards_then_a_final_run_build_the_corpus_of_one_unsharded_run(tmp_path, monkeypatch):
    """Shards 1/2 and 2/2 one after the other, then the final run without --shard: the same
    capture files (pixels bit for bit) and the same index (but for when and how each capture was
    rendered) as one un-sharded run; the shards never write corpus.json."""
    tiny = CorpusPreset("small", ("sphere",), ("point-03", "point-17"), (1,), resolution=16, views=11, spp_env=1, spp_point=2,
                        combos=(("sphere", "point-03", 1), ("sphere", "point-17", 1)))
    monkeypatch.setattr(synth_set, "preset", lambda name: tiny)
    whole = make_corpus(tmp_path / "whole", "small", tmp_path)
    assert [e.status for e in whole] == ["done"] * 2
    sharded = tmp_path / "sharded"
    planned = make_corpus(sharded, "small", tmp_path, shard=(2, 2), dry_run=True)
    assert [e.name for e in planned] == [whole[1].name] and not sharded.exists()  # a shard's dry run writes nothing
    one = make_corpus(sharded, "small", tmp_path, shard=(1, 2))
    assert [(e.name, e.status) for e in one] == [(whole[0].name, "done")]
    assert not (sharded / "corpus.json").exists() and not (sharded / whole[1].path).exists()
    two = make_corpus(sharded, "small", tmp_path, shard=(2, 2))
    assert [(e.name, e.status) for e in two] == [(whole[1].name, "done")] and not (sharded / "corpus.json").exists()
    final = make_corpus(sharded, "small", tmp_path)
    assert [e.status for e in final] == ["skipped"] * 2  # the final run renders nothing the shards rendered
    assert _contents(sharded) == _contents(tmp_path / "whole")
    index = lambda root: json.loads((root / "corpus.json").read_text())  # noqa: E731
    a, b = index(sharded), index(tmp_path / "whole")
    for doc in (a, b):
        doc.pop("started_utc")
        for c in doc["captures"]:
            c.pop("status"), c.pop("seconds")
    assert a == b
    assert make_corpus(sharded, "small", tmp_path, shard=(2, 2))[0].status == "skipped"  # a rerun shard resumes
