"""The ``lmgs-eval`` command line: parse, build a config, call the library, write files.

Each subcommand lives in its own module under :mod:`lmgs_eval.commands` with three names:
``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``. Modules keep heavy
imports (torch, onnxruntime, dlib) inside ``run`` so ``lmgs-eval --help`` stays instant.
User errors (:class:`lmgs.errors.InputError`) become one line on stderr and exit code 2; a
training run that diverged (:class:`lmgs.errors.TrainingDiverged`) one line and exit code 1.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

# name -> module; order is the order of `lmgs-eval --help`. Every module must import: a missing
# or broken command module is an error of the installation, never a command silently dropped.
COMMANDS: dict[str, str] = {
    "subjects": "lmgs_eval.commands.subjects",
    "ingest": "lmgs_eval.commands.ingest",
    "prepare": "lmgs_eval.commands.prepare",
    "metrics": "lmgs_eval.commands.metrics",
    "score": "lmgs_eval.commands.score",
    "methods": "lmgs_eval.commands.methods",
    "weights": "lmgs_eval.commands.weights",
    "sync-check": "lmgs_eval.commands.sync_check",
    "self": "lmgs_eval.commands.self_driven",
    "cross": "lmgs_eval.commands.cross",
    "run": "lmgs_eval.commands.run_plan",
    "table": "lmgs_eval.commands.table",
    "report": "lmgs_eval.commands.report",
    "stress": "lmgs_eval.commands.stress",
    "capacity": "lmgs_eval.commands.capacity",
    "verify": "lmgs_eval.commands.verify",
    "bench": "lmgs_eval.commands.bench",
    "demo": "lmgs_eval.commands.demo",
}


def _available_commands() -> dict[str, object]:
    return {name: importlib.import_module(path) for name, path in COMMANDS.items()}


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line, as every other error of the command line:
    ``lmgs-eval CMD: error: MSG`` on stderr, exit code 2 (``--help`` still prints the usage).
    Subparsers are made of the same class."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="lmgs-eval",
        description="Evaluate audio-driven talking heads; every number says how it was made.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, mod in _available_commands().items():
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from lmgs.errors import InputError, TrainingDiverged

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except InputError as exc:
        print(f"lmgs-eval {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except TrainingDiverged as exc:
        print(f"lmgs-eval {args.command}: training failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"lmgs-eval {args.command}: interrupted; finished work is kept and the run can be resumed", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
