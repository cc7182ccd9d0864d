"""``lmgs-eval verify [RESULTS]``: re-hash every artefact the results reference."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "re-hash the renders, ground truth, checkpoints and weights every result references; exit 1 if any changed"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("results", nargs="?", default="results", type=Path,
                        help="results store (default: results/)")


def run(args: argparse.Namespace) -> int:
    """Check each record's artefacts; print one line per changed or missing input.

    Returns:
        0 when every artefact of every valid record hashes as recorded, 1 otherwise (and when the
        folder holds no record at all: nothing was checked).
        A record file that cannot be read (not JSON, truncated, of an unknown schema version,
        invalid) is named on stderr and makes the exit code 1: its inputs cannot be checked.
        A JSON file that is not a record at all (no ``schema_version``) is only a warning.
    """
    from lmgs_eval.errors import UserError
    from lmgs_eval.results import check_artefacts, imported_records, iter_store

    root = Path(args.results)
    if not root.is_dir():
        raise UserError(f"{root}: no results store there")
    items, warnings = iter_store(root)
    unreadable = [w for w in warnings if "not a result record" not in w]
    for w in warnings:
        print(f"{'error' if w in unreadable else 'warning'}: {w}", file=sys.stderr)
    bad = 0
    n_art = 0
    imported = imported_records(root)
    n_imported = 0
    for path, rec in items:
        here = path.relative_to(root).as_posix() in imported
        n_imported += here
        problems, checked = check_artefacts(root, rec, imported=here)
        n_art += checked
        if problems:
            bad += 1
            print(f"{path}: inputs changed ({rec.method.name} / {rec.subject.name} / "
                  f"{rec.protocol.name}:{rec.protocol.clip} / seed {rec.seed})")
            for p in problems:
                print(f"  {p}")
    if n_imported:
        print(f"{n_imported} records were imported from another machine (make bench: tables/records); "
              "their renders and checkpoints stay there and are checked only where present")
    if bad:
        print(f"{bad} of {len(items)} records have inputs that changed or went missing")
    if unreadable:
        print(f"{len(unreadable)} record files could not be read, so their inputs were not checked")
    if bad or unreadable:
        return 1
    if not items:  # nothing was checked: no store, or the wrong folder
        print(f"lmgs-eval verify: error: {root}: no result records there, so nothing was checked "
              "(give the results store, e.g. `lmgs-eval verify results`)", file=sys.stderr)
        return 1
    print(f"{len(items)} records, {n_art} artefacts checked: all inputs unchanged")
    return 0
