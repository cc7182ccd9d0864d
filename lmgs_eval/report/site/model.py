"""What the site's pages show, as plain values made from records: leaderboards, runs, watch lists.

Every number comes from the table code (:func:`lmgs_eval.report.tables.all_tables` and its
cells: means, CIs, significance marks, busy-host and mixed-backend flags); this module only
lays those cells out for HTML, names every run, and picks what the Watch page plays.
"""

from __future__ import annotations

import re
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lmgs_eval.report.cells import is_ok, is_variant
from lmgs_eval.report.table_model import BUSY, METRICS, MIXED, TIE, UNTRUSTED, Cell, Column, Table
from lmgs_eval.results.types import Record

CURVE_METRICS = ("psnr", "ssim", "lpips", "lmd", "lse_d")
"""Metrics whose ``per_item`` values are drawn under the Watch page's players (per frame or per window)."""
FILTER_FAMILIES = ("ground-truth", "reference", "2D", "NeRF", "3DGS", "external", "control")


@dataclass(frozen=True)
class Run:
    """One record with the names the site gives it.

    Attributes:
        id: file-name-safe id, unique in the store (from the record's path in it).
        record: the record.
        path: the record's JSON file.
    """

    id: str
    record: Record
    path: Path

    @property
    def label(self) -> str:
        m = self.record.method
        return m.display_name or m.name


def make_runs(items: Sequence[tuple[Path, Record]], root: Path) -> list[Run]:
    """Name each ``(path, record)`` of a store (``iter_store``) by its path under ``root``."""
    runs = []
    for path, rec in items:
        try:
            rel = path.resolve().relative_to(root.resolve()).with_suffix("").as_posix()
        except ValueError:
            rel = path.with_suffix("").name
        runs.append(Run(re.sub(r"[^A-Za-z0-9._+-]+", "_", rel.replace("/", "__")), rec, path))
    return runs


# ----------------------------------------------------------------------------- leaderboards
@dataclass
class HtmlCell:
    text: str = "–"
    sort: float | None = None
    ci: str = ""
    mark: str = ""
    flag: str = ""
    title: str = ""
    style: str = ""


@dataclass
class HtmlRow:
    label: str
    method: str
    family: str
    cells: list[HtmlCell]
    runs: list[str]
    standins: list[str] = field(default_factory=list)
    rule_before: bool = False
    failed: bool = False


@dataclass
class HtmlTable:
    """One section (one subject) of one report table, ready for the template."""

    id: str
    title: str
    section: str
    subject_standin: str | None
    label_header: str
    columns: list[dict[str, Any]]
    rows: list[HtmlRow]
    notes: list[str]
    collapsed: bool = False


def _fmt(v: float, c: Column) -> str:
    return f"{v * c.scale:.{c.digits}f}"


def html_cell(cell: Cell | None, col: Column) -> HtmlCell:
    """A table cell as text, sort key, CI and marks (best / second / tie; ‡ mixed backends, § busy host)."""
    if cell is None:
        return HtmlCell()
    if cell.mean is None:
        text = cell.text if cell.text is not None else "N/A"
        return HtmlCell(text=text, flag=cell.flag, title=", ".join(sorted(cell.backends)))
    text = _fmt(cell.mean, col)
    if cell.std is not None:
        text += f" ± {_fmt(cell.std, col)}"
    if cell.text:
        text += f" ({cell.text})"
    ci = f"[{_fmt(cell.ci.lo, col)}, {_fmt(cell.ci.hi, col)}]" if cell.ci is not None else ""
    title = [f"{cell.n_seeds} seed(s)"]
    if cell.backends:
        title.append("backend " + ", ".join(sorted(cell.backends)))
    if cell.ci is not None:
        title.append(f"bootstrap {cell.ci.level:.0%} CI over {cell.ci.n} items")
    if cell.flag == BUSY:
        title.append("timed on a busy or slowed host")
    if cell.flag == MIXED:
        title.append("made by different metric backends: not comparable")
    mark = {"best": "best", "second": "second", "tie": "tie"}.get(cell.mark, "")
    if mark == "tie":
        title.append("not significantly different from the best")
    return HtmlCell(text=text, sort=float(cell.mean * col.scale), ci=ci, mark=mark, flag=cell.flag,
                    title="; ".join(title))


def _column(c: Column, recs: Sequence[Record]) -> dict[str, Any]:
    """A column's header: label, arrow, and the stand-ins of the metric scorers that made its numbers."""
    arrow = "" if c.higher_is_better is None else ("↑" if c.higher_is_better else "↓")
    standins = sorted({m.standin for r in recs for m in [r.metrics.get(c.key)]
                       if c.kind == "metric" and m and m.value is not None and m.standin})
    return {"id": c.id, "label": f"{c.group} {c.label}".strip(), "arrow": arrow, "kind": c.kind,
            "higher": c.higher_is_better, "standin": "; ".join(standins)}


def _row_standins(recs: Sequence[Record]) -> list[str]:
    out: list[str] = []
    for r in recs:
        for s in r.method.standins:
            if s not in out:
                out.append(s)
    return out


def leaderboards(tables: Sequence[Table], run_ids: dict[int, str]) -> dict[str, list[HtmlTable]]:
    """Per subject, every table's section about it (Table I first), as :class:`HtmlTable`.

    The status table (one section over all subjects) is returned under the key ``""``.
    ``run_ids`` maps ``id(record)`` to its :class:`Run` id, so rows link to their runs.
    """
    out: dict[str, list[HtmlTable]] = defaultdict(list)
    for t in tables:
        for k, sec in enumerate(t.sections):
            recs = [r for row in sec.rows for r in row.records]
            subjects = sorted({r.subject.name for r in recs})
            key = subjects[0] if len(subjects) == 1 else ""
            cols = [_column(c, recs) for c in t.columns]
            rows = []
            for row in sec.rows:
                rows.append(HtmlRow(
                    label=row.label, method=row.method, family=row.family or "",
                    cells=[html_cell(row.cells.get(c.id), c) if c.kind != "text"
                           else HtmlCell(text=(row.cells.get(c.id) or Cell(text="–")).text or "–") for c in t.columns],
                    runs=[run_ids[id(r)] for r in row.records if id(r) in run_ids],
                    standins=_row_standins(row.records), rule_before=row.rule_before,
                    failed=any(not is_ok(r) for r in row.records)))
            standin = recs[0].subject.standin if key and recs else None
            stability = t.name.startswith("stability_")
            if stability:
                _heat(t, rows)
            out[key].append(HtmlTable(f"{t.name}-{k}", t.title, sec.title, standin, t.label_header, cols, rows,
                                      list(sec.notes) + list(t.notes), collapsed=stability))
    return dict(out)


def _heat(t: Table, rows: Sequence[HtmlRow]) -> None:
    """Colour a stability section's cells as a heat map: green where the change under stress is for the
    better (by the metric's direction), red where for the worse, stronger with the size of the change."""
    idx = [i for i, c in enumerate(t.columns) if c.kind == "metric" and c.key in METRICS]
    vals = [abs(r.cells[i].sort) for r in rows for i in idx if r.cells[i].sort is not None]
    lim = max(vals, default=0.0)
    if lim <= 0:
        return
    for r in rows:
        for i in idx:
            v = r.cells[i].sort
            if v is None or v == 0:
                continue
            better = (v > 0) == METRICS[t.columns[i].key][1]
            rgb = "44,160,44" if better else "214,39,40"
            r.cells[i].style = f"background: rgba({rgb},{0.12 + 0.5 * abs(v) / lim:.2f})"


MARKS_LEGEND = (f"bold: best, significantly better than the runner-up (p < 0.05: Welch's t over the seeds' means where both "
                f"rows have two seeds or more, else a circular block bootstrap over the same frames; each table's notes name "
                f"the test); underlined: runner-up; {TIE}: not significantly different from the best (no winner); "
                f"{MIXED}: the column mixes metric backends and is not ranked; {UNTRUSTED}: the sync scorer failed its "
                f"self-check on that clip, not ranked; {BUSY}: timed on a busy or slowed host; "
                "[lo, hi]: block-bootstrap 95% CI over frames and seeds; S on a column: its scorer is a stand-in, "
                "stand-in on a row: the method has parts that stand in for the paper's (hover either for what).")


# ----------------------------------------------------------------------------- watch
WATCHED = ("self", "cross")
"""Protocols with a Watch page, in page order."""


@dataclass
class WatchRun:
    """One player of the Watch page: a method's run (lowest seed) on one subject and clip."""

    run: Run
    curves: dict[str, list[float | None]]
    video: str | None = None
    error: str | None = None
    missing: str | None = None
    full: str | None = None  # the full render, relative to the site
    audio: bool = False  # its preview carries the clip's audio (the page's clock)
    note: str | None = None  # e.g. why it has no error map


def watch_groups(runs: Sequence[Run]) -> dict[tuple[str, str, str], dict[str, Run]]:
    """``(subject, protocol, clip) -> {method: run}``: what each Watch page can play.

    Self-driven runs (with the ground truth, a row of that protocol) and cross-driven ones (one page
    per driving clip; no ground truth exists for another clip's audio): one run per method, its
    lowest seed; ablation variants and calibration controls are left out (they have their own
    tables). The ground truth comes first.
    """
    out: dict[tuple[str, str, str], dict[str, Run]] = defaultdict(dict)
    for run in runs:
        r = run.record
        if r.protocol.name not in WATCHED or not is_ok(r) or is_variant(r) or r.method.family == "control":
            continue
        key = (r.subject.name, r.protocol.name, r.protocol.clip)
        name = r.method.name
        have = out[key].get(name)
        if have is None or (r.seed, run.id) < (have.record.seed, have.id):
            out[key][name] = run
    ordered = {}
    for key in sorted(out, key=lambda k: (k[0], WATCHED.index(k[1]), k[2])):
        group = out[key]
        names = sorted(group, key=lambda n: (group[n].record.method.family != "ground-truth",
                                             FILTER_FAMILIES.index(group[n].record.method.family)
                                             if group[n].record.method.family in FILTER_FAMILIES else 99,
                                             n != "lmgs", group[n].label))
        ordered[key] = {n: group[n] for n in names}
    return ordered


def curves(rec: Record) -> dict[str, list[float | None]]:
    """The per-frame (or per-window) values of the metrics the Watch page draws."""
    out = {}
    for key in CURVE_METRICS:
        m = rec.metrics.get(key)
        if m and m.per_item:
            out[key] = list(m.per_item)
    return out


def curve_meta() -> dict[str, dict[str, Any]]:
    return {k: {"label": METRICS[k][0], "higher": METRICS[k][1], "digits": METRICS[k][2]} for k in CURVE_METRICS}
