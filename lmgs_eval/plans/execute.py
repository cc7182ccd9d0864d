"""One run, wherever it executes: the protocol function on a store of its own, the new files handed back.

The worker (this process for the serial executor, a Ray worker on any node for the Ray one)
gets the run and the records of its subject the driver's store already holds. It lays those
into a temporary store, so the protocol skips what is done as it would in the real one, runs
the protocol there with the run's CPU threads, and returns every file that is new or changed
(records and renders, by path relative to the store). The driver writes them into its store.
The same function in both executors is what makes their records equal: nothing but where it
runs differs (cost and machine fields aside).
"""

from __future__ import annotations

import dataclasses
import importlib
import shutil
import socket
import tempfile
import time
from pathlib import Path

from lmgs_eval.plans.runs import Run


@dataclasses.dataclass
class Outcome:
    """What a run hands back: files by store-relative path, messages (the protocol's per-clip errors), its time."""

    files: dict[str, bytes]
    messages: list[str]
    seconds: float
    error: str | None = None  # bad input: not retried, recorded as failed with this message
    node: str = dataclasses.field(default_factory=socket.gethostname)  # where it ran (a Ray node id under Ray)


def execute_run(run: Run, known: dict[str, str]) -> Outcome:
    """Run ``run`` in a temporary store seeded with ``known`` (relative path -> record JSON text)."""
    import torch

    from lmgs.errors import InputError

    t0 = time.perf_counter()
    threads = torch.get_num_threads()
    tmp = Path(tempfile.mkdtemp(prefix="lmgs-run-"))
    try:
        for rel, text in known.items():
            p = tmp / rel
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text(text, encoding="utf-8")
        torch.set_num_threads(run.cpus)
        for mod in run.imports:
            importlib.import_module(mod)
        try:
            messages = _protocol(run, tmp)
        except InputError as exc:
            return Outcome({}, [], time.perf_counter() - t0, error=str(exc))
        files = {}
        for p in sorted(tmp.rglob("*")):
            rel = p.relative_to(tmp).as_posix()
            if not p.is_file() or any(part.startswith(".") for part in p.relative_to(tmp).parts):
                continue
            data = p.read_bytes()
            if rel in known and data == known[rel].encode("utf-8"):
                continue
            files[rel] = data
        return Outcome(files, messages, time.perf_counter() - t0)
    finally:
        torch.set_num_threads(threads)
        shutil.rmtree(tmp, ignore_errors=True)


def run_config(run: Run, results: Path):
    """The :class:`~lmgs_eval.runner.RunConfig` a command line with these options would make."""
    from lmgs_eval.runner import RunConfig

    return RunConfig(subject=run.subject, methods=(run.method,), preset=run.preset, seeds=(run.seed,), results=results,
                     data_root=run.data_root, device=run.device, progress=False,
                     method_options={"overrides": dict(run.overrides)} if run.overrides else {})


def _protocol(run: Run, results: Path) -> list[str]:
    cfg = run_config(run, results)
    if run.protocol == "self":
        from lmgs_eval.protocols.self_driven import run_self

        run_self(cfg)
        return []
    if run.protocol == "cross":
        from lmgs_eval.protocols.cross import run_cross

        _, errors = run_cross(cfg, list(run.clips) or None)
        return list(errors)
    if run.protocol == "stress":
        from lmgs_eval.protocols.stress import run_stress

        _, messages = run_stress(cfg, run.conditions, run.max_minutes, run.long_seconds)
        return list(messages)
    if run.protocol == "capacity":
        from lmgs_eval.protocols.capacity import DEFAULT_BUDGETS, run_capacity

        run_capacity(cfg, run.budgets or DEFAULT_BUDGETS)
        return []
    raise ValueError(f"unknown protocol {run.protocol!r}")
