"""From records to a table's cells: means over seeds with CIs, ranking by paired tests, and the notes.

How a cell is made, how a column is ranked and when a figure is marked (busy host, mixed
backends, ties) is described in :mod:`lmgs_eval.report.tables`.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from lmgs_eval.report.stats import ALPHA, PairedTest, bootstrap_ci_seeds, mean_over_seeds, paired_test, seed_test
from lmgs_eval.report.table_model import (BUSY, BUSY_SHARE, CUSTOM_KEYS, FAMILY_ORDER, METRICS, MIXED, OURS, SLOW_HOST, TIE, UNTRUSTED,
                                          Cell, Column, Record, Row, Section, column_backends)
from lmgs_eval.results.notes import budget_note
from lmgs_eval.results.types import Cost


# ----------------------------------------------------------------------------- aggregation
def is_ok(rec: Record) -> bool:
    """A record whose run did not fail."""
    return not rec.failed


def is_variant(rec: Record) -> bool:
    """An ablation / sweep variant (goes to Tables III / IV, not Table I)."""
    return bool(rec.method.variant)


def components_of(rec: Record) -> dict[str, Any] | None:
    """The switchable parts a record's method declared (``method.components``), or None."""
    return rec.method.components


SYNC_KEYS = ("lse_d", "lse_c", "av_offset")  # the figures of one LSE, whose self-check is in lse_d's values


def metric_cell(records: Sequence[Record], key: str) -> Cell:
    """Aggregate metric ``key`` over the seeds of one row (see :class:`Cell`)."""
    vals, items, backends = [], [], set()
    untrusted = key in SYNC_KEYS and any(
        (getattr(r.metrics.get("lse_d"), "values", None) or {}).get("trusted") is False for r in records)
    for r in records:
        m = r.metrics.get(key)
        if m is None or m.value is None:
            continue
        vals.append(float(m.value))
        backends.add(f"{m.backend} v{m.backend_version}")
        if m.per_item:
            items.append(m.per_item)
    if not vals:
        return Cell(backends=backends)
    per_item_ok = len(items) == len(vals)
    return Cell(
        mean=float(np.mean(vals)),
        std=float(np.std(vals, ddof=1)) if len(vals) > 1 else None,
        n_seeds=len(vals),
        ci=bootstrap_ci_seeds(items) if per_item_ok else None,
        paired=mean_over_seeds(items) if per_item_ok else None,
        values=vals,
        backends=backends,
        untrusted=untrusted,
        flag=UNTRUSTED if untrusted else "",
    )


def cost_cell(records: Sequence[Record], key: str) -> Cell:
    """Aggregate a cost field over seeds (no CI: one number per run)."""
    vals = [float(getattr(r.cost, key)) for r in records if getattr(r.cost, key) is not None]
    if not vals:
        return Cell()
    return Cell(mean=float(np.mean(vals)), std=float(np.std(vals, ddof=1)) if len(vals) > 1 else None,
                n_seeds=len(vals))


def fill_row(row: Row, columns: Sequence[Column]) -> None:
    for c in columns:
        recs = [r for r in row.records if c.clip is None or r.protocol.clip == c.clip]
        if c.kind == "metric":
            row.cells[c.id] = metric_cell(recs, c.key)
        elif c.kind == "cost":
            row.cells[c.id] = cost_cell(recs, c.key)


def timed_busy(cost: Cost) -> bool:
    """True when a run's FPS was timed while other processes took more than :data:`BUSY_SHARE` of the host's
    CPU, or while the host ran the fixed probe more than :data:`SLOW_HOST` times slower than its best."""
    share, slow = cost.others_cpu_share, cost.host_slowdown
    return (share is not None and share > BUSY_SHARE) or (slow is not None and slow > SLOW_HOST)


def busy_text(cost: Cost) -> str:
    """What made a timing busy, e.g. ``others 23%`` or ``probe 2.1x slower``."""
    parts = []
    share, slow = cost.others_cpu_share, cost.host_slowdown
    if share is not None and share > BUSY_SHARE:
        parts.append(f"others {share:.0%}")
    if slow is not None and slow > SLOW_HOST:
        parts.append(f"probe {slow:.1f}x slower")
    return ", ".join(parts)


BUSY_NOTE = (f"{BUSY} FPS timed on a busy or slowed host: other processes took more than {BUSY_SHARE:.0%} of its CPU "
             f"(cost.others_cpu_share) or it ran a fixed probe workload more than {SLOW_HOST:g}x slower than its best on "
             "that machine (cost.host_slowdown)")


def _flag_column(sec: Section, columns: Sequence[Column], key: str, hit: Callable[[Cost], bool],
                 describe: Callable[[list[Cost], int], str]) -> list[str]:
    """Mark with :data:`BUSY` the ``key`` cost cell of every row with a run where ``hit(cost)``.

    Returns one ``"<row> <describe(hits, n_runs)>"`` per marked row, for the section's note.
    """
    col = next((c for c in columns if c.kind == "cost" and c.key == key), None)
    if col is None:
        return []
    busy = []
    for row in sec.rows:
        cell = row.cells.get(col.id)
        costs = [r.cost for r in row.records]
        hits = [c for c in costs if hit(c)]
        if cell is not None and cell.mean is not None and hits:
            cell.flag = BUSY
            busy.append(f"{row.label} {describe(hits, len(costs))}")
    return busy


def flag_busy_timings(sec: Section, columns: Sequence[Column]) -> None:
    """Mark FPS timed while other processes took more than :data:`BUSY_SHARE` of the host's CPU."""
    def worst(hits: list[Cost], n: int) -> str:
        w = max(hits, key=lambda c: (c.host_slowdown or 1.0) * (1 + (c.others_cpu_share or 0.0)))
        return f"{len(hits)}/{n} runs, worst {busy_text(w)}"

    busy = _flag_column(sec, columns, "fps", timed_busy, worst)
    if busy:
        sec.notes.append(f"{BUSY_NOTE}: {'; '.join(busy)}. On a quiet host these render faster.")
    flag_busy_training(sec, columns)


def trained_busy(cost: Cost) -> bool:
    """True when other processes took more than :data:`BUSY_SHARE` of the host's CPU while the model trained."""
    share = cost.train_others_cpu_share
    return share is not None and share > BUSY_SHARE


def flag_busy_training(sec: Section, columns: Sequence[Column]) -> None:
    """Mark training times measured while other processes took more than :data:`BUSY_SHARE` of the host's CPU."""
    def worst(hits: list[Cost], n: int) -> str:
        return f"{len(hits)}/{n} runs, worst others {max(c.train_others_cpu_share for c in hits):.0%}"

    busy = _flag_column(sec, columns, "train_seconds", trained_busy, worst)
    if busy:
        sec.notes.append(f"{BUSY} Train: trained while other processes took more than {BUSY_SHARE:.0%} of the host's CPU "
                         f"(cost.train_others_cpu_share): {'; '.join(busy)}. On a quiet host these train faster.")


def rank_section(sec: Section, columns: Sequence[Column], alpha: float = ALPHA) -> None:
    """Mark best / second / ties per column (see the module docstring); notes go to ``sec.notes``.

    FPS timed on a busy host are marked first (:func:`flag_busy_timings`).
    """
    flag_busy_timings(sec, columns)
    used: list[str] = []
    for col in columns:
        if col.kind != "metric" or not col.rank:
            continue
        rows = [r for r in sec.rows if r.ranked and r.cells.get(col.id) and r.cells[col.id].mean is not None]
        doubted = [r.label for r in rows if r.cells[col.id].untrusted]
        if doubted:
            rows = [r for r in rows if not r.cells[col.id].untrusted]
            sec.notes.append(f"{UNTRUSTED} {col.group + ' ' if col.group else ''}{col.label}: the sync scorer did not pass "
                             f"its self-check on {', '.join(doubted)} (the clip's own audio not separated from controls "
                             "of the same clip), so these figures are not ranked; import the official SyncNet weights "
                             "(lmgs-eval weights import-syncnet) to score this footage.")
        if len(column_backends(sec, col)) > 1:
            for r in sec.rows:
                cell = r.cells.get(col.id)
                if cell is not None and cell.mean is not None:
                    cell.flag = MIXED
            who = "; ".join(f"{r.label}: {', '.join(sorted(r.cells[col.id].backends))}" for r in rows)
            sec.notes.append(f"{MIXED} {col.group + ' ' if col.group else ''}{col.label} mixes metric backends "
                             f"({who}); these numbers are not comparable and the column is not ranked.")
            continue
        if len(rows) < 2:
            continue
        sign = -1.0 if col.higher_is_better else 1.0
        rows.sort(key=lambda r: sign * r.cells[col.id].mean)
        best = rows[0].cells[col.id]
        tests = [compare(best, other.cells[col.id]) for other in rows[1:]]
        name = f"{col.group + ' ' if col.group else ''}{col.label}"
        if tests[0] is None:
            best.mark, rows[1].cells[col.id].mark = "best", "second"
            sec.notes.append(f"{name}: best / second not tested for significance (no per-item values on the same "
                             f"items, nor two seeds on each side).")
            continue
        if tests[0].significant(alpha):
            best.mark, rows[1].cells[col.id].mark = "best", "second"
            used.append(f"{name} {rows[0].label} vs {rows[1].label}: {tests[0].how}, {p_text(tests[0].p)}")
            continue
        best.mark = "tie"
        tied = [rows[0].label]
        for other, t in zip(rows[1:], tests):
            if t is not None and not t.significant(alpha):
                other.cells[col.id].mark = "tie"
                tied.append(f"{other.label} ({t.how}, {p_text(t.p)})")
        sec.notes.append(f"{TIE} {name}: {', '.join(tied)} are not significantly different from the best "
                         f"(p ≥ {alpha:g}); no winner is bolded.")
    if used:
        sec.notes.append("Bold / underline made by: " + "; ".join(used) + ".")


def p_text(p: float) -> str:
    """A p-value as the notes print it."""
    return "p < 0.001" if p < 0.001 else f"p = {p:.2g}"


def compare(a: Cell, b: Cell) -> PairedTest | None:
    """The test behind a mark between two cells of one column.

    Two trained rows with at least two seeds each are compared at the seed level (Welch's t on
    the seed values): the seed is the unit of replication. Otherwise, when both have per-frame
    values on the same frames (averaged over seeds), a circular-block paired bootstrap over
    the frames; None when neither is possible.
    """
    t = seed_test(a.values, b.values) if len(a.values) >= 2 and len(b.values) >= 2 else None
    if t is None and a.paired is not None and b.paired is not None and len(a.paired) == len(b.paired):
        t = paired_test(a.paired, b.paired)
    return t


def subject_title(recs: Iterable[Record]) -> str:
    s = next(iter(recs)).subject
    return s.name + (" (bundled)" if s.bundled else "")


def by_subject(records: Iterable[Record]) -> dict[str, list[Record]]:
    out: dict[str, list[Record]] = defaultdict(list)
    for r in records:
        out[r.subject.name].append(r)
    return dict(sorted(out.items()))


def make_rows(records: Iterable[Record], label: Callable[[Record], str] | None = None) -> list[Row]:
    groups: dict[tuple[str, str], list[Record]] = defaultdict(list)
    for r in records:
        groups[(r.method.name, r.config_hash)].append(r)
    names = defaultdict(int)
    for name, _ in groups:
        names[name] += 1
    rows = []
    for (name, h), recs in groups.items():
        recs.sort(key=lambda r: (r.seed, r.protocol.clip))
        m = recs[0].method
        text = label(recs[0]) if label else m.display_name or name
        if names[name] > 1:
            text += f" [{h[:8]}]"  # same method, different configs: never merged silently
        rows.append(Row(text, name, m.family, recs))
    return rows


def row_order(row: Row) -> tuple:
    fam = FAMILY_ORDER.index(row.family) if row.family in FAMILY_ORDER else len(FAMILY_ORDER)
    return (row.method == OURS, fam, row.label)


def common_notes(records: Sequence[Record], columns: Sequence[Column], methods: bool = True) -> list[str]:
    notes = []
    for c in columns:
        if c.kind != "metric":
            continue
        made, standins = set(), set()
        for r in records:
            m = r.metrics.get(c.key)
            if m is not None and m.value is not None:
                made.add(f"{m.backend} v{m.backend_version}")
                if m.standin:
                    standins.add(m.standin)
        if not made:
            continue
        name = f"{c.group + ' ' if c.group else ''}{c.label}"
        note = f"{name} made by {', '.join(sorted(made))}"
        if standins:
            note += f"; STAND-IN: {'; '.join(x.rstrip('.') for x in sorted(standins))}"
        notes.append(note + ".")
    # a subject's own Gaussian budget (record.run.budget), and the rows that used it
    sized: dict[tuple[str, str], set[str]] = defaultdict(set)
    for r in records:
        b = r.run.budget if r.run is not None else None
        if b:
            sized[(r.subject.name, budget_note(b.density, b.preset_density))].add(
                r.method.display_name or r.method.name)
    seen = set()
    for r in records:
        s = r.subject
        if s.name in seen:
            continue
        seen.add(s.name)
        if s.bundled or s.standin:
            notes.append(f"Subject {s.name}: {'bundled, synthetic' if s.bundled else 'stand-in'}"
                         f"{': ' + s.standin if s.standin else ''} (not a real recording).")
        for (name, n), labels in sized.items():
            if name == s.name:
                notes.append(f"Subject {name}: {n} ({', '.join(sorted(labels))}).")
    if methods:
        done = set()
        for r in sorted(records, key=lambda r: r.method.name):
            m = r.method
            if m.name in done or m.family == "ground-truth":
                continue
            done.add(m.name)
            text = f"{m.display_name or m.name} ({m.family}): {m.description}"
            if m.standins:
                text += f" Stand-ins: {'; '.join(m.standins)}."
            notes.append(text)
    machines = {f"{r.machine.cpu}, {r.machine.threads} threads, "
                + (f"{r.machine.cpu_kernels} kernels, " if r.machine.cpu_kernels else "")
                + f"{r.machine.cuda_device or 'no GPU'}" for r in records}
    if any(c.kind == "cost" for c in columns) and machines:
        if len(machines) > 1:
            notes.append(f"{MIXED} cost measured on different machines: {' | '.join(sorted(machines))}.")
        else:
            notes.append(f"Cost measured on {machines.pop()}.")
    return notes


def with_custom_keys(keys: Iterable[str], records: Sequence[Record]) -> list[str]:
    """``keys`` with each custom-weights key (:data:`CUSTOM_KEYS`) after its metric's when a record has a value for it."""
    keys = list(keys)
    present = {k for r in records for k, m in r.metrics.items() if m.value is not None}
    out = []
    for k in keys:
        out.append(k)
        c = CUSTOM_KEYS.get(k)
        if c and c in present and c not in keys:
            out.append(c)
    return out


def metric_columns(keys: Iterable[str], clip: str | None = None, group: str = "") -> list[Column]:
    cols = []
    for k in keys:
        label, hib, digits = METRICS[k]
        cols.append(Column(f"{clip}.{k}" if clip else k, label, k, "metric", hib, digits, group, clip))
    return cols


COST_COLUMNS = [
    Column("cost.fps", "FPS", "fps", "cost", True, 1, rank=False),
    Column("cost.train", "Train (min)", "train_seconds", "cost", False, 1, rank=False, scale=1 / 60),
    Column("cost.gaussians", "Gaussians", "n_gaussians", "cost", None, 0, rank=False),
    Column("cost.mb", "MB", "model_mb", "cost", False, 2, rank=False),
]


