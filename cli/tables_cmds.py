"""``damcap tables --table1 CORPUS`` and ``damcap tables --table2 REAL_CAPTURE``: the paper's tables.

Outputs (in ``--out``): ``table1.md`` / ``table1.json`` / ``table1_<task>_<light>.png``, or
``table2.md`` / ``table2.json`` / ``table2_<view>.png`` / ``table2_materials.png``. Table 1 is
computed capture by capture and ``table1.json`` is rewritten after each one: an interrupted run
resumes where it stopped (rows of captures already done are reused when the options match).
``damcap evaluate --table1 / --table2`` (the tables' first home) still runs them, through
:func:`run_tables`, and says where they are now.
"""

from __future__ import annotations

import json
import shlex
import sys
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from damcap.appearance.hyper.file import PAPER_SHIPPED
from damcap.cli.app import command
from damcap.cli.paths import check_paths, folder_out
from damcap.common.errors import DamcapError

if TYPE_CHECKING:
    from damcap.paper.tables import TableOptions

TABLE1_HELP = "the paper's Table 1 on the held-out captures of this synth-set corpus (repeatable: corpora are pooled)"
TABLE2_HELP = "the paper's Table 2 (all three tasks) on this real capture"
OUT_HELP = "folder for the tables' markdown, JSON and plots"
PREDICTOR_HELP = (f"predictor file of the learning-to-learn rows (default: the shipped {PAPER_SHIPPED}, the paper's one-view "
                  "predictor, whatever predict's default)")
MATERIALS_HELP = "--table2: materials of the segmentation, a number or 'auto'"
FRESH_HELP = "--table1: recompute every capture instead of resuming"


@command(table="damcap.paper.tables:TableOptions")
def tables(
    table1: Optional[list[Path]] = typer.Option(None, "--table1", help=TABLE1_HELP),
    table2: Optional[Path] = typer.Option(None, "--table2", help=TABLE2_HELP),
    out: Optional[Path] = typer.Option(None, "--out", help=OUT_HELP),
    predictor: Optional[Path] = typer.Option(None, "--predictor", help=PREDICTOR_HELP),
    table_materials: str = typer.Option("auto", "--table-materials", help=MATERIALS_HELP),
    fresh: bool = typer.Option(False, "--fresh", help=FRESH_HELP),
    *,
    table: TableOptions,
) -> None:
    """The paper's Table 1 or Table 2: markdown, JSON and plots.

    The paper's tables: Table 1 (--table1 CORPUS: representation, learning to learn and segmentation
    on the held-out captures of synth-set corpora) or Table 2 (--table2 CAPTURE: the three tasks on
    a real capture), as markdown, JSON and plots in --out.
    """
    run_tables(table1, table2, out, predictor, table_materials, fresh, table)


def run_tables(table1: Optional[list[Path]], table2: Optional[Path], out: Optional[Path], predictor: Optional[Path],
               table_materials: str, fresh: bool, opts: "TableOptions") -> None:
    """``damcap tables`` (and ``evaluate --table1 / --table2``): check the arguments, then one table."""
    if not table1 and table2 is None:
        raise DamcapError("give --table1 CORPUS (Table 1) or --table2 CAPTURE (Table 2)")
    if table1 and table2 is not None:
        raise DamcapError("give --table1 or --table2, not both (they write different tables)")
    if out is None:
        raise DamcapError("--table1 / --table2 need --out FOLDER for the markdown, JSON and plots")
    check_paths([*(table1 or [table2]), predictor], [folder_out(out)])
    if table1:
        run_table1(list(table1), out, predictor, fresh, opts)
    else:
        run_table2(table2, out, predictor, table_materials, opts)


def _command() -> str:
    return "damcap " + " ".join(shlex.quote(a) for a in sys.argv[1:])


def _predictor(path: Optional[Path]):
    from damcap.appearance.hyper.file import PAPER_SHIPPED, load_predictor, shipped_predictor_path

    return load_predictor(path or shipped_predictor_path(PAPER_SHIPPED))[0]


def _options_record(opts, predictor: Optional[Path]) -> dict:
    return {"fit": asdict(opts.fit), "refine_steps": list(opts.refine_steps), "segment": asdict(opts.segment),
            "kmeans_steps": opts.kmeans_steps, "predictor": str(predictor) if predictor else "shipped"}


def run_table1(corpora: list[Path], out: Path, predictor_path: Optional[Path], fresh: bool, opts) -> None:
    """Table 1: ``opts`` is the TableOptions of the command line."""
    from damcap.cli.app import make_bar, stage_progress
    from damcap.paper.tables import heldout_entries, plot_table1, summarise, table1_markdown, table1_rows
    from damcap.common.atomic import write_json_atomic, write_text_atomic
    from damcap.common.version import package_version

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
    header = {"damcap_package_version": package_version(), "command": _command(), "corpora": [str(c.resolve()) for c in corpora],
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
    """Table 2: ``opts`` is the TableOptions of the command line."""
    from damcap.appearance.evaluate import plot_sorted_dssim
    from damcap.cli.app import stage_progress
    from damcap.paper.tables import false_colour_figure, table2_markdown, table2_rows
    from damcap.appearance.views import load_views
    from damcap.common.atomic import write_json_atomic, write_text_atomic
    from damcap.common.capture_folder import read_capture
    from damcap.common.version import package_version

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
    write_json_atomic(out / "table2.json", {"damcap_package_version": package_version(), "command": command, "capture": str(capture.resolve()),
                                            "options": _options_record(opts, predictor_path), "metric": "DSSIM (capture-format.md)",
                                            **row.as_json()})
    md = table2_markdown(row, command, figure.name)
    write_text_atomic(out / "table2.md", md + "\nPlots: table2_same.png, table2_novel.png\n")
    typer.echo(md)
    typer.echo(f"wrote {out / 'table2.md'}, table2.json, the plots and {figure.name} in {out}")
