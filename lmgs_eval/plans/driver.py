"""The plan driver: expand, skip what the store holds, hand runs to an executor, write what comes back.

The driver alone writes into the store: a finished run's renders first, then its records
(each atomically, validated), so a record never names a render that is not there. A run that
failed on every try gets a failed record (``status.state = "failed"`` and the message) for
each record it did not make; a later start retries it, as it skips every finished one.
Stopping the driver loses only the runs in flight.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from lmgs.fileio import atomic_write
from lmgs_eval import results as store
from lmgs_eval.plans.execute import Outcome
from lmgs_eval.plans.identity import Identities
from lmgs_eval.plans.runs import Run, expand
from lmgs_eval.plans.schema import Plan


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


@dataclass
class Summary:
    """What a plan's execution did."""

    total: int = 0
    skipped: int = 0  # already in the store
    done: list[str] = field(default_factory=list)  # run ids
    failed: list[str] = field(default_factory=list)  # "label: message"
    messages: list[str] = field(default_factory=list)  # per-clip problems of runs that finished
    records: list[store.Record] = field(default_factory=list)  # the records written, in arrival order
    nodes: dict[str, str] = field(default_factory=dict)  # run id -> node it ran on
    seconds: float = 0.0


def run_plan(plan: Plan, executor, results: str | Path, *, progress=log) -> Summary:
    """Execute every run of ``plan`` not already in ``results`` with ``executor``; see the module doc."""
    t0 = time.perf_counter()
    results = Path(results)
    ids = Identities(results, plan.data_root)
    runs = expand(plan)
    s = Summary(total=len(runs))
    todo: dict[str, tuple[Run, list]] = {}
    for r in runs:
        keys = ids.keys(r)
        if keys and all(ids.finished(r, k) for k in keys):
            s.skipped += 1
        else:
            todo[r.id] = (r, keys)
    progress(f"[plan] {plan.name}: {len(runs)} runs, {s.skipped} already in {results}, {len(todo)} to do "
             f"({executor.name} executor, {executor.slots} at a time)")
    waiting = list(todo)
    running: dict[str, float] = {}
    durations: list[float] = []
    took: dict[str, list[float]] = {}  # protocol -> durations of its finished runs
    try:
        while waiting or running:
            for rid in list(waiting):
                if len(running) >= executor.slots:
                    break
                run, _ = todo[rid]
                if any(dep in todo and (dep in waiting or dep in running) for dep in run.after):
                    continue
                waiting.remove(rid)
                running[rid] = time.perf_counter()
                executor.submit(run, ids.known_records(run))
            run, outcome, error = executor.next()
            durations.append(time.perf_counter() - running.pop(run.id))
            took.setdefault(run.protocol, []).append(durations[-1])
            keys = todo[run.id][1]
            if outcome is not None and outcome.error is None:
                s.records += _write(results, outcome)
                s.nodes[run.id] = outcome.node
                s.messages += [f"{run.label}: {m}" for m in outcome.messages]
                s.done.append(run.id)
                state = "ok"
            else:
                reason = error if outcome is None else outcome.error
                for k in keys:
                    if not ids.finished(run, k):
                        s.records.append(ids.write_failed(run, k, reason))
                s.failed.append(f"{run.label}: {reason}")
                state = f"FAILED ({reason})"
            n_end = len(s.done) + len(s.failed)
            left = len(waiting) + len(running)
            eta = _eta([todo[r][0].protocol for r in (*waiting, *running)], took, executor.slots)
            progress(f"[plan] {n_end}/{len(todo)} finished ({len(s.done)} ok, {len(s.failed)} failed), {len(running)} in flight"
                     f"{f', about {_minutes(eta)} left' if left else ''}: {run.label} {state} in {durations[-1]:.0f} s")
    finally:
        executor.close()
    s.seconds = time.perf_counter() - t0
    return s


def _write(results: Path, outcome: Outcome) -> list[store.Record]:
    """A finished run's files into the store: everything else first, then the records (validated, atomic)."""
    records = []
    for rel, data in sorted(outcome.files.items(), key=lambda kv: kv[0].endswith(".json")):
        if rel.endswith(".json"):
            rec = store.to_record(json.loads(data.decode("utf-8")))
            store.write_record(results, rec)
            records.append(rec)
        else:
            atomic_write(results / rel, data)
    return records


def _eta(protocols: list[str], took: dict[str, list[float]], slots: int) -> float:
    """Seconds left: each run left at the mean time of finished runs of its protocol (of all runs when none), shared over the slots."""
    every = [d for ds in took.values() for d in ds]
    if not protocols or not every:
        return 0.0
    mean = {p: sum(ds) / len(ds) for p, ds in took.items()}
    fallback = sum(every) / len(every)
    return sum(mean.get(p, fallback) for p in protocols) / max(1, min(slots, len(protocols)))


def _minutes(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.0f} min"
