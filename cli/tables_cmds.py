"""``damcap evaluate --table1 CORPUS`` and ``--table2 REAL_CAPTURE``: the paper's tables.

Outputs (in ``--out``): ``table1.md`` / ``table1.json`` / ``table1_<task>_<light>.png``, or
``table2.md`` / ``table2.json`` / ``table2_<view>.png`` / ``table2_materials.png``. Table 1 is
computed capture by capture and ``table1.json`` is rewritten after each one: an interrupted run
resumes where it stopped (rows of captures already done are reused when the options match).
"""

from __future__ import annotations

import json
import shlex
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Optional

import typer

from damcap.common.errors import DamcapError


def _command() -> str:
    return "damcap " + " ".join(shlex.quote(a) for a in sys.argv[1:])


def _predictor(path: Optional[Path]):
    from damcap.appearance.hyper.file import PAPER_SHIPPED, load_predictor, shipped_predictor_path

    return load_predictor(path or shipped_predictor_path(PAPER_SHIPPED))[0]


def _options_record(opts, predictor: Optional[Path]) -> dict:
    return {"fit": asdict(opts.fit), "refine_steps": list(opts.refine_steps), "segment": asdict(opts.segment),
            "kmeans_steps": opts.kmeans_steps, "predictor": str(predictor) if predictor else "shipped"}


def run_table1(corpora: list[Path], out: Path, predictor_path: Optional[Path], fresh: bool, opts) -> None:
    """``--table1``: ``opts`` is the TableOptions of the command line."""
    from damcap.cli.app import make_bar, stage_progress
    from damcap.paper.tables import heldout_entries, plot_table1, summarise, table1_markdown, table1_rows
    from damcap.common.atomic import write_json_atomic, write_text_atomic
    from damcap.common.version import damcap_version

    for c in corpora:
        if not (c / "corpus.json").is_file():
            raise DamcapError(f"{c}: no corpus.json; --table1 takes a folder written by damcap synth-set")
    opts.fit.validate()
    opts.segment.validate()
    record = _options_record(opts, predictor_path)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / "table1.json"
    done: dict[str, dict] = {}
    if json_path.is_file() and not fresh:
        try:
            old = json.loads(json_path.read_text())
        except ValueError:
            old = {}
        if old.get("options") == record:
            done = {r["name"]: r for r in old.get("captures", [])}
            if done:
                typer.echo(f"resuming: {len(done)} capture(s) already in {json_path}", err=True)
    rows: list = []
    header = {"damcap_version": damcap_version(), "command": _command(), "corpora": [str(c.resolve()) for c in corpora],
              "options": record, "metric": "DSSIM (capture-format.md)"}

    total = len(heldout_entries(corpora))
    captures = make_bar(total, "Table 1", "capture")
    captures.n = sum(1 for _, e in heldout_entries(corpora) if e["name"] in done)

    def save(row) -> None:
        rows.append(row)
        write_json_atomic(json_path, {**header, "captures": list(done.values()) + [r.as_json() for r in rows]})
        captures.update()

    all_rows = table1_rows(corpora, opts, _predictor(predictor_path), log=lambda m: typer.echo(m, err=True),
                           done=done, on_capture=save, progress=stage_progress())
    captures.close()
    write_json_atomic(json_path, {**header, "table": summarise(all_rows), "captures": [r.as_json() for r in all_rows]})
    md = table1_markdown(all_rows, header["command"])
    plots = plot_table1(all_rows, out)
    write_text_atomic(out / "table1.md", md + "\nPlots: " + ", ".join(p.name for p in plots) + "\n")
    typer.echo(md)
    typer.echo(f"wrote {out / 'table1.md'}, {json_path} and {len(plots)} plot(s) in {out}")


def run_table2(capture: Path, out: Path, predictor_path: Optional[Path], materials: str, opts) -> None:
    """``--table2``: ``opts`` is the TableOptions of the command line."""
    from damcap.appearance.evaluate import plot_sorted_dssim
    from damcap.cli.app import stage_progress
    from damcap.paper.tables import false_colour_figure, table2_markdown, table2_rows
    from damcap.appearance.views import load_views
    from damcap.common.atomic import write_json_atomic, write_text_atomic
    from damcap.common.capture_folder import read_capture
    from damcap.common.version import damcap_version

    if materials != "auto":
        try:
            if int(materials) < 1:
                raise ValueError
        except ValueError:
            raise DamcapError(f"--table-materials must be a positive number or 'auto', got {materials!r}") from None
    opts.fit.validate()
    opts.segment.validate()
    cap = read_capture(capture)
    train, test = load_views(cap, "train"), load_views(cap, "test")
    if not test:
        raise DamcapError(f"{capture}: the capture has no test split; Table 2 scores novel views")
    row, seg = table2_rows(train, test, opts, _predictor(predictor_path), capture.name, materials,
                           log=lambda m: typer.echo(m, err=True), progress=stage_progress())
    out.mkdir(parents=True, exist_ok=True)
    figure = out / "table2_materials.png"
    false_colour_figure(seg, train, figure)
    for view in ("same", "novel"):
        per_view = {f"{task}: {m}": v[view] for task, methods in row.scores.items() for m, v in methods.items() if view in v}
        plot_sorted_dssim({f"{view} view": per_view}, out / f"table2_{view}.png", title=capture.name)
    command = _command()
    write_json_atomic(out / "table2.json", {"damcap_version": damcap_version(), "command": command, "capture": str(capture.resolve()),
                                            "options": _options_record(opts, predictor_path), "metric": "DSSIM (capture-format.md)",
                                            **row.as_json()})
    md = table2_markdown(row, command, figure.name)
    write_text_atomic(out / "table2.md", md + "\nPlots: table2_same.png, table2_novel.png\n")
    typer.echo(md)
    typer.echo(f"wrote {out / 'table2.md'}, table2.json, the plots and {figure.name} in {out}")
