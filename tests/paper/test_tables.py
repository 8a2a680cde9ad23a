"""The paper's tables as one evaluation (damcap tables --table1 / --table2) on a tiny closed-form corpus."""

from __future__ import annotations

import json
import statistics

import pytest

from damcap.appearance.fit import FitOptions
from damcap.appearance.hyper.file import PAPER_SHIPPED, load_predictor, shipped_predictor_path
from damcap.appearance.segment.options import SegmentOptions
from damcap.paper.tables import (
    TableOptions, heldout_entries, rows_from_json, summarise, table1_markdown, table1_rows, table2_markdown, table2_rows,
)
from damcap.appearance.views import load_views
from damcap.common.capture_folder import read_capture
from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

from ..conftest import assert_one_line_error, run_cli

FAST = TableOptions(fit=FitOptions(steps=150, checkpoint_every=0), refine_steps=(20,),
                    segment=SegmentOptions(materials=2, steps=150, init_steps=100, batch_pixels=2048), kmeans_steps=100)

#: (name, split, light kind, closed-form options)
CAPTURES = [
    ("sphere_dir_m1", "heldout", "point", dict(shape="sphere", light="directional", materials=1, seed=1)),
    ("torus_env_m1", "heldout", "env", dict(shape="torus", light="env", env_grid=8, materials=1, seed=2)),
    ("torus_env_m2", "heldout", "env", dict(shape="torus", light="env", env_grid=8, materials=2, seed=3)),
    ("sphere_env_m1", "train", "env", dict(shape="sphere", light="env", env_grid=8, materials=1, seed=4)),
]


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    """A synth-set-shaped corpus of tiny closed-form captures (corpus.json + captures/)."""
    root = tmp_path_factory.mktemp("corpus")
    entries = []
    for name, split, kind, kw in CAPTURES:
        make_closed_form_capture(root / "captures" / name, ClosedFormOptions(views=8, resolution=24, train_views=4, dtype="float", **kw))
        entries.append({"name": name, "path": f"captures/{name}", "split": split, "light_kind": kind, "materials": kw["materials"]})
    (root / "corpus.json").write_text(json.dumps({"captures": entries}))
    return root


@pytest.fixture(scope="module")
def predictor():
    return load_predictor(shipped_predictor_path(PAPER_SHIPPED))[0]


PROGRESS: list[tuple[str, int, int]] = []


@pytest.fixture(scope="module")
def rows(corpus, predictor):
    return table1_rows([corpus], FAST, predictor, progress=lambda *a: PROGRESS.append(a))


def _finished_stages(calls: list[tuple[str, int, int]]) -> set[str]:
    return {stage for stage, done, total in calls if done == total and total > 0}


def test_table1_reports_each_captures_training_loops(rows):
    assert {"sphere_dir_m1: fit", "torus_env_m1: fit", "torus_env_m2: segment"} <= _finished_stages(PROGRESS)
    steps = [done for stage, done, _ in PROGRESS if stage == "torus_env_m1: fit"]
    assert steps == sorted(steps) and len(steps) > 2  # step by step, in order


def test_table1_has_every_row_of_the_heldout_captures(rows, predictor):
    assert [r.name for r in rows] == ["sphere_dir_m1", "torus_env_m1", "torus_env_m2"]  # the train capture is left out
    one, seg = rows[0], rows[2]
    assert set(one.scores) == {"representation", "learning-to-learn"}
    assert set(one.scores["representation"]) == {"DAM (SGD fit)", "RM++", "RM"}
    assert set(one.scores["learning-to-learn"]) == {"DAM (SGD fit)", "predicted", "predicted + 20 refine"}
    assert set(seg.scores) == {"segmentation"}
    assert {"ours (true weights)", "ours (estimated weights)", "k-means (true weights)", "k-means (estimated weights)"} == set(seg.scores["segmentation"])
    for r in rows:
        for methods in r.scores.values():
            for views in methods.values():
                assert 0 <= views["novel"].mean <= 1
                assert len(views["novel"].per_frame) == 4  # 8 views, 4 train
    e = seg.extra["segmentation"]
    assert 0 <= e["iou_train"]["ours"] <= 1 and 0 <= e["iou_test_carried"]["k-means"] <= 1
    # learning-to-learn compares with an SGD fit of the predictor's own DAM architecture (leaky ReLU);
    # the representation row is damcap fit's default (shifted softplus): two different fits here
    assert predictor.arch.dam.activation != FAST.fit.activation
    assert one.scores["representation"]["DAM (SGD fit)"]["novel"].per_frame != one.scores["learning-to-learn"]["DAM (SGD fit)"]["novel"].per_frame


def test_cells_are_means_over_captures_and_markdown_quotes_the_paper(rows):
    cells = summarise(rows)
    got = cells["representation"]["point"]["RM++"]["novel"]
    assert got == pytest.approx(rows[0].scores["representation"]["RM++"]["novel"].mean)
    assert cells["segmentation"]["env"]["ours (true weights)"]["same"] == pytest.approx(
        statistics.fmean(r.scores["segmentation"]["ours (true weights)"]["same"].mean for r in rows[2:]))
    md = table1_markdown(rows, "damcap tables --table1 X --out Y")
    for needle in ("## representation (1 point-light, 1 environment-map captures)", "## learning-to-learn", "## segmentation",
                   "(paper: 0.800)", "(paper: 0.850)", "0.154 vs 0.164", "damcap tables --table1 X --out Y"):
        assert needle in md, needle


def test_rows_round_trip_through_json_and_resume_skips_done_captures(corpus, rows, predictor, monkeypatch):
    again = [rows_from_json(json.loads(json.dumps(r.as_json()))) for r in rows]
    assert summarise(again) == summarise(rows)
    import damcap.paper.tables as tables

    def boom(*a, **k):
        raise AssertionError("a finished capture was recomputed")

    monkeypatch.setattr(tables, "representation_rows", boom)
    monkeypatch.setattr(tables, "segmentation_rows", boom)
    resumed = table1_rows([corpus], FAST, predictor, done={r.name: r.as_json() for r in rows})
    assert summarise(resumed) == summarise(rows)


def test_table2_covers_all_three_tasks(corpus, predictor):
    cap = read_capture(corpus / "captures" / "torus_env_m2")
    calls: list[tuple[str, int, int]] = []
    row, seg = table2_rows(load_views(cap, "train"), load_views(cap, "test"), FAST, predictor, "torus_env_m2", materials="2",
                           progress=lambda *a: calls.append(a))
    assert set(row.scores) == {"representation", "learning-to-learn", "segmentation"}
    assert {"fit", "segment"} <= _finished_stages(calls)
    assert seg.materials == 2 and row.materials == 2
    md = table2_markdown(row, "damcap tables --table2 C --out D", "table2_materials.png")
    assert "paper, on its own real spheres" in md and "| segmentation | ours (estimated weights) |" in md


def test_table_commands_refuse_bad_input(corpus, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = run_cli(["tables", "--table1", empty, "--out", tmp_path / "o"], capsys)
    assert_one_line_error(code, err, str(empty), "corpus.json")
    code, _, err = run_cli(["tables", "--table1", corpus], capsys)
    assert_one_line_error(code, err, "--out")
    code, _, err = run_cli(["tables", "--table1", corpus, "--table2", corpus / "captures" / "torus_env_m1", "--out", tmp_path / "o"], capsys)
    assert_one_line_error(code, err, "not both")
    code, _, err = run_cli(["tables", "--table1", corpus, "--out", corpus / "inside"], capsys)
    assert_one_line_error(code, err, "input")
    code, _, err = run_cli(["tables", "--table2", corpus / "captures" / "torus_env_m1", "--out", tmp_path / "o", "--table-materials", "x"], capsys)
    assert_one_line_error(code, err, "'x'")
    code, _, err = run_cli(["tables"], capsys)
    assert_one_line_error(code, err, "--table1")
    code, _, err = run_cli(["evaluate"], capsys)
    assert_one_line_error(code, err, "CAPTURE")


def test_evaluate_still_runs_the_tables_and_says_where_they_are_now(corpus, tmp_path, capsys):
    """``evaluate --table1 / --table2`` and their options (hidden from its help) forward to
    ``damcap tables``: the same checks, after one note line."""
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = run_cli(["evaluate", "--table1", empty, "--out", tmp_path / "o", "--fit-steps", "5", "--fresh"], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 2 and lines[0].startswith("note: the paper's tables are now 'damcap tables'")
    assert str(empty) in lines[1] and "corpus.json" in lines[1]
    code, _, err = run_cli(["evaluate", corpus / "captures" / "torus_env_m1", "--table1", corpus, "--out", tmp_path / "o"], capsys)
    assert_one_line_error(code, err, "CAPTURE")
    code, _, err = run_cli(["evaluate", corpus / "captures" / "torus_env_m1", "--fit-steps", "5"], capsys)
    assert_one_line_error(code, err, "--fit-steps", "damcap tables")
    code, out, _ = run_cli(["evaluate", "--help"], capsys)
    assert code == 0 and "--table1" not in out and "--fit-steps" not in out and "damcap tables" in " ".join(out.split()), out


    assert heldout_entries([corpus])[0][1]["name"] == "sphere_dir_m1"
