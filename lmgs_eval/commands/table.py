"""``lmgs-eval table``: the paper's tables and the charts, made from the results store alone."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "write Tables I-IV, calibration, stability, status (md/tex/csv) and the speed charts from results files"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--results", default="results", type=Path, help="results store (default: results/)")
    parser.add_argument("--format", choices=("md", "tex", "csv", "all"), default="all",
                        help="table formats to write (default: all)")
    parser.add_argument("--out", default="tables", type=Path, help="output folder (default: tables/)")
    parser.add_argument("--ci", action="store_true", help="show bootstrap 95%% CIs in Markdown/LaTeX cells too")
    parser.add_argument("--no-charts", action="store_true", help="tables only")
    parser.add_argument("--records", type=Path, default=None, metavar="DIR",
                        help="also write the records the tables were made from into DIR (JSON only; DIR is replaced), "
                             "so `lmgs-eval table --results DIR` makes the same tables anywhere (make bench: tables/records)")


def run(args: argparse.Namespace) -> int:
    """Load the store (warning about skipped files), write every table and chart, print Table I."""
    from lmgs.fileio import atomic_write
    from lmgs_eval.paths import check_out_dir
    from lmgs_eval.results import load_records
    from lmgs_eval.report.tables import all_tables

    records_dir = args.records
    check_out_dir(Path(args.out), "--out")
    if records_dir is not None:
        check_out_dir(Path(records_dir).parent, "--records")
        _check_records_dir(Path(records_dir), Path(args.results))
    records, warnings = load_records(args.results)
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    if not records:
        print(f"lmgs-eval table: no result records in {args.results}; run `lmgs-eval self` (or `cross`) first, "
              f"or pass --results DIR", file=sys.stderr)
        return 2
    formats = ("md", "tex", "csv") if args.format == "all" else (args.format,)
    out = Path(args.out)
    written: list[Path] = []
    tables = all_tables(records)
    for t in tables:
        for fmt in formats:
            text = {"md": lambda: t.markdown(show_ci=args.ci), "tex": lambda: t.latex(show_ci=args.ci),
                    "csv": t.csv}[fmt]()
            path = out / f"{t.name}.{fmt}"
            atomic_write(path, text)
            written.append(path)
    if not args.no_charts:
        from lmgs_eval.report.charts import all_charts

        written += all_charts(records, out)
        from lmgs_eval.report.charts import render_sheets

        written += render_sheets(records, args.results, out)
    if records_dir is not None:
        from lmgs_eval.results import snapshot_records

        snapshot_records(records, records_dir)
        print(f"{len(records)} records the tables were made from -> {records_dir}/")
    first = next((t for t in tables if t.name == "table1_self"), tables[0] if tables else None)
    if first is not None:
        print(first.markdown(show_ci=args.ci))
    print(f"{len(records)} records -> {len(written)} files in {out}/:")
    for p in written:
        print(f"  {p}")
    return 0


def _check_records_dir(records_dir: Path, results: Path) -> None:
    """The snapshot folder must be apart from the store: inside it, its records would be read twice."""
    from lmgs_eval.errors import UserError

    a, b = records_dir.resolve(), results.resolve()
    if a == b or b in a.parents or a in b.parents:
        raise UserError(f"--records {records_dir}: overlaps the results store {results} "
                        "(its records would be read twice); choose a folder outside it, e.g. tables/records")
