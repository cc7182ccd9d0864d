"""The paper's tables, made only from result records (never by re-running anything).

Every function here is a pure function of a list of records (:mod:`lmgs_eval.results`):
``table_*(records) -> Table``, and a :class:`Table` renders to Markdown, LaTeX (booktabs)
and CSV. The layouts follow the paper (``paper.tex``):

* Table I, self-driven: PSNR↑, LPIPS↓, LMD↓, LSE-D↓, LSE-C↑ with the Ground Truth row,
  plus the cost columns FPS↑, training time, Gaussians, model MB.
* Table II, cross-driven: Audio A / B x LSE-D / LSE-C.
* Table III, the θ sweep of Spatial Enhancement; Table IV, the component ablation (the audio
  front end and Audio Encoder rows, then SE / LC / GR).
* Calibration (does each metric separate the ground truth from its negative controls?),
  stability (change from the clean condition under stress), status (ok / failed per
  method x subject, in the manner of nerfbaselines).

How a cell is made: the mean over seeds (``± std`` when there are several); its bootstrap
95% CI over items and seeds (:func:`lmgs_eval.stats.bootstrap_ci_seeds`) goes to the CSV
(and to Markdown/LaTeX with ``show_ci``). Ranking per column within a subject: the best
is **bold** only if a paired test over the same items (per-item values averaged over
seeds; paired bootstrap and Wilcoxon, the larger p) says it differs from the runner-up at
p < 0.05; then the runner-up is underlined. Otherwise the best and every method not
significantly different from it are marked † (a tie), and nothing is bolded. A column
whose rows were made by different metric backends is not ranked and is flagged ‡; the
backend of every column is named in the notes, with every stand-in (subjects, metric
scorers, method components) and each method's description.
"""

from __future__ import annotations

import csv
import functools
import io
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lmgs_eval.results import BUDGET_NOTE, se_fraction
from lmgs_eval.stats import ALPHA, CI, bootstrap_ci_seeds, mean_over_seeds, paired_test

Record = dict[str, Any]

# metric key -> (label, higher_is_better, digits)
METRICS: dict[str, tuple[str, bool, int]] = {
    "psnr": ("PSNR", True, 2),
    "ssim": ("SSIM", True, 4),
    "lpips": ("LPIPS", False, 4),
    "lmd": ("LMD", False, 2),
    "lse_d": ("LSE-D", False, 3),
    "lse_c": ("LSE-C", True, 3),
    "av_offset": ("|AV offset|", False, 0),
    "jitter": ("Jitter (px)", False, 3),
    "silence_open": ("Open in silence (px)", False, 2),
}
FAMILY_ORDER = ("ground-truth", "reference", "2D", "NeRF", "3DGS", "external", "control")
OURS = "lmgs"
UNRANKED = ("ground-truth", "reference")
"""Table I's rows above the rule: the ground truth and the protocol's reference composite."""
TIE = "†"
MIXED = "‡"
BUSY = "§"
BUSY_SHARE = 0.10
"""FPS timed while other processes took more of the host's CPU than this (``cost.others_cpu_share``) are marked."""
SLOW_HOST = 1.5
"""... and FPS timed while the host ran a fixed probe this many times slower than its best (``cost.host_slowdown``)."""


# ----------------------------------------------------------------------------- data model
@dataclass(frozen=True)
class Column:
    """One column: a metric (``kind="metric"``), a cost field (``"cost"``) or row text (``"text"``).

    Attributes:
        id: unique id (``psnr``, ``cost.fps``, ``A.lse_d``, ``se``).
        label: header text.
        key: metric key, cost field or text key.
        higher_is_better: arrow direction (None: no arrow).
        digits: decimals shown.
        group: header group (Table II's "Audio A").
        clip: only records of this ``protocol.clip`` feed the column (None: all of the row's).
        rank: whether best / second are marked.
        scale: factor applied to the value before display (seconds -> minutes).
    """

    id: str
    label: str
    key: str
    kind: str = "metric"
    higher_is_better: bool | None = None
    digits: int = 3
    group: str = ""
    clip: str | None = None
    rank: bool = True
    scale: float = 1.0


@dataclass
class Cell:
    """The aggregate of one row's records for one column.

    Attributes:
        mean: mean over seeds (None: no value).
        std: sample std over seeds (None with one seed).
        n_seeds: seeds with a value.
        ci: bootstrap CI over items (and seeds), None without per-item values.
        paired: per-item values averaged over seeds (for the paired test), or None.
        backends: ``backend vVERSION`` strings of the values.
        mark: ``best``, ``second``, ``tie`` or ``""``.
        text: a text cell (✓ / ✗, failure notes) instead of a number.
        flag: an extra mark shown after the value (``‡``, ``✗``).
    """

    mean: float | None = None
    std: float | None = None
    n_seeds: int = 0
    ci: CI | None = None
    paired: list[float] | None = None
    backends: set[str] = field(default_factory=set)
    mark: str = ""
    text: str | None = None
    flag: str = ""


@dataclass
class Row:
    """One table row: a method (or variant / control) on one subject, all its seeds."""

    label: str
    method: str
    family: str
    records: list[Record]
    cells: dict[str, Cell] = field(default_factory=dict)
    ranked: bool = True
    rule_before: bool = False


@dataclass
class Section:
    """A per-subject block of rows, with notes that only concern it."""

    title: str
    rows: list[Row]
    notes: list[str] = field(default_factory=list)


@dataclass
class Table:
    """A finished table: render with :meth:`markdown`, :meth:`latex` or :meth:`csv`."""

    name: str
    title: str
    columns: list[Column]
    sections: list[Section]
    notes: list[str] = field(default_factory=list)
    label_header: str = "Method"

    # ------------------------------------------------------------------ markdown
    def markdown(self, show_ci: bool = False) -> str:
        """GitHub Markdown: bold best, ``<u>`` second, † ties, ‡ mixed backends, notes as a list."""
        out = [f"## {self.title}", ""]
        heads = [self.label_header] + [_md_head(c, self._mixed(c)) for c in self.columns]
        for sec in self.sections:
            out += [f"### {sec.title}", "", "| " + " | ".join(heads) + " |",
                    "|" + "|".join([":--"] + ["--:" if c.kind != "text" else ":-:" for c in self.columns]) + "|"]
            for row in sec.rows:
                cells = [_md_cell(row.cells.get(c.id), c, show_ci) for c in self.columns]
                out.append("| " + " | ".join([_md_escape(row.label)] + cells) + " |")
            out.append("")
            out += [f"- {n}" for n in sec.notes]
            if sec.notes:
                out.append("")
        if self.notes:
            out += ["Notes:", ""] + [f"- {n}" for n in self.notes] + [""]
        return "\n".join(out)

    # ------------------------------------------------------------------ latex
    def latex(self, show_ci: bool = False, label: str | None = None) -> str:
        """A booktabs ``table``: ``\\textbf`` best, ``\\underline`` second, ``$^\\dagger$`` ties."""
        n = len(self.columns) + 1
        groups = [c.group for c in self.columns]
        lines = ["\\begin{table}[htbp]", "\\centering",
                 f"\\caption{{{_tex_escape(self.title)}}}", f"\\label{{{label or 'tab:' + self.name}}}",
                 "\\begin{tabular}{l" + "".join("c" for _ in self.columns) + "}", "\\toprule"]
        if any(groups):
            head, rules, col = [""], [], 2
            i = 0
            while i < len(groups):
                j = i
                while j < len(groups) and groups[j] == groups[i]:
                    j += 1
                head.append(f"\\multicolumn{{{j - i}}}{{c}}{{{_tex_escape(groups[i])}}}" if groups[i] else "")
                if groups[i]:
                    rules.append(f"\\cmidrule(lr){{{col}-{col + j - i - 1}}}")
                col += j - i
                i = j
            lines.append(" & ".join(head) + " \\\\")
            lines.append(" ".join(rules))
        lines.append(" & ".join([f"\\textbf{{{_tex_escape(self.label_header)}}}"] + [_tex_head(c, self._mixed(c)) for c in self.columns])
                     + " \\\\")
        for sec in self.sections:
            lines += ["\\midrule", f"\\multicolumn{{{n}}}{{l}}{{\\textit{{{_tex_escape(sec.title)}}}}} \\\\",
                      "\\midrule"]
            for k, row in enumerate(sec.rows):
                if row.rule_before and k:
                    lines.append("\\midrule")
                cells = [_tex_cell(row.cells.get(c.id), c, show_ci) for c in self.columns]
                lines.append(" & ".join([_tex_escape(row.label)] + cells) + " \\\\")
        lines += ["\\bottomrule", "\\end{tabular}"]
        notes = [f"{sec.title}: {n}" for sec in self.sections for n in sec.notes] + self.notes
        if notes:
            lines.append("\\par\\smallskip\\footnotesize")
            lines += [_tex_escape(n) + "\\par" for n in notes]
        lines.append("\\end{table}")
        return "\n".join(lines) + "\n"

    # ------------------------------------------------------------------ csv
    def csv(self) -> str:
        """Machine-readable: one line per row; per column the mean, std, CI, seeds, backends, mark."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        head = ["table", "section", "row", "method", "family"]
        for c in self.columns:
            head += [c.id] if c.kind == "text" else [c.id, f"{c.id}_std", f"{c.id}_ci_lo", f"{c.id}_ci_hi",
                                                     f"{c.id}_n_seeds", f"{c.id}_backend", f"{c.id}_mark"]
        w.writerow(head)
        for sec in self.sections:
            for row in sec.rows:
                line = [self.name, sec.title, row.label, row.method, row.family]
                for c in self.columns:
                    cell = row.cells.get(c.id) or Cell()
                    if c.kind == "text":
                        line.append(cell.text or "")
                        continue
                    line += [_num(cell.mean), _num(cell.std), _num(cell.ci.lo if cell.ci else None),
                             _num(cell.ci.hi if cell.ci else None), cell.n_seeds, ";".join(sorted(cell.backends)),
                             (cell.mark + (" " + cell.text if cell.text else "") + cell.flag).strip()]
                w.writerow(line)
        return buf.getvalue()

    def _mixed(self, col: Column) -> bool:
        return any(len(_column_backends(sec, col)) > 1 for sec in self.sections)

    def is_empty(self) -> bool:
        return not any(sec.rows for sec in self.sections)


# ----------------------------------------------------------------------------- formatting
def _num(v: float | None) -> str:
    return "" if v is None else repr(float(v))


def _fmt(v: float, c: Column) -> str:
    return f"{v * c.scale:.{c.digits}f}"


def _arrow(c: Column, md: bool) -> str:
    if c.higher_is_better is None:
        return ""
    if md:
        return "↑" if c.higher_is_better else "↓"
    return "$\\uparrow$" if c.higher_is_better else "$\\downarrow$"


def _md_escape(s: str) -> str:
    return s.replace("|", "\\|")


def _md_head(c: Column, mixed: bool) -> str:
    return _md_escape(f"{c.group} {c.label}".strip()) + _arrow(c, True) + (f" {MIXED}" if mixed else "")


def _md_cell(cell: Cell | None, c: Column, show_ci: bool) -> str:
    if cell is None:
        return "–"
    if cell.text is not None and cell.mean is None:
        return _md_escape(cell.text)
    if cell.mean is None:
        return "N/A"
    s = _fmt(cell.mean, c)
    if cell.std is not None:
        s += f" ± {_fmt(cell.std, c)}"
    if show_ci and cell.ci is not None:
        s += f" [{_fmt(cell.ci.lo, c)}, {_fmt(cell.ci.hi, c)}]"
    s = {"best": f"**{s}**", "second": f"<u>{s}</u>", "tie": f"{s}{TIE}"}.get(cell.mark, s)
    if cell.text:
        s += f" ({cell.text})"
    return s + (f" {cell.flag}" if cell.flag else "")


_TEX = {"\\": "\\textbackslash{}", "&": "\\&", "%": "\\%", "$": "\\$", "#": "\\#", "_": "\\_", "{": "\\{",
        "}": "\\}", "~": "\\textasciitilde{}", "^": "\\textasciicircum{}", "θ": "$\\theta$", "†": "$^\\dagger$",
        "‡": "$^\\ddagger$", "✓": "\\checkmark", "✗": "$\\times$", "±": "$\\pm$", "↑": "$\\uparrow$",
        "↓": "$\\downarrow$", "Δ": "$\\Delta$", "–": "--", "→": "$\\to$", "≥": "$\\geq$"}


def _tex_escape(s: str) -> str:
    return "".join(_TEX.get(ch, ch) for ch in s)


def _tex_head(c: Column, mixed: bool) -> str:
    return f"\\textbf{{{_tex_escape(c.label)}}}" + _arrow(c, False) + ("$^\\ddagger$" if mixed else "")


def _tex_cell(cell: Cell | None, c: Column, show_ci: bool) -> str:
    if cell is None:
        return "--"
    if cell.text is not None and cell.mean is None:
        return _tex_escape(cell.text)
    if cell.mean is None:
        return "N/A"
    s = _fmt(cell.mean, c)
    if cell.std is not None:
        s += f"$\\pm${_fmt(cell.std, c)}"
    if show_ci and cell.ci is not None:
        s += f" [{_fmt(cell.ci.lo, c)}, {_fmt(cell.ci.hi, c)}]"
    s = {"best": f"\\textbf{{{s}}}", "second": f"\\underline{{{s}}}", "tie": f"{s}$^\\dagger$"}.get(cell.mark, s)
    if cell.text:
        s += f" ({_tex_escape(cell.text)})"
    return s + (_tex_escape(cell.flag) if cell.flag else "")


# ----------------------------------------------------------------------------- aggregation
def is_ok(rec: Record) -> bool:
    """A record whose run did not fail."""
    return (rec.get("status") or {}).get("state", "ok") == "ok"


def is_variant(rec: Record) -> bool:
    """An ablation / sweep variant (goes to Tables III / IV, not Table I)."""
    return bool(rec["method"].get("variant"))


def _guidance(rec: Record) -> dict[str, Any] | None:
    g = rec.get("config", {}).get("guidance")
    return g if isinstance(g, dict) and "theta" in g else None


def metric_cell(records: Sequence[Record], key: str) -> Cell:
    """Aggregate metric ``key`` over the seeds of one row (see :class:`Cell`)."""
    vals, items, backends = [], [], set()
    for r in records:
        m = r["metrics"].get(key)
        if m is None or m["value"] is None:
            continue
        vals.append(float(m["value"]))
        backends.add(f"{m['backend']} v{m['backend_version']}")
        if m.get("per_item"):
            items.append(m["per_item"])
    if not vals:
        return Cell(backends=backends)
    per_item_ok = len(items) == len(vals)
    return Cell(
        mean=float(np.mean(vals)),
        std=float(np.std(vals, ddof=1)) if len(vals) > 1 else None,
        n_seeds=len(vals),
        ci=bootstrap_ci_seeds(items) if per_item_ok else None,
        paired=mean_over_seeds(items) if per_item_ok else None,
        backends=backends,
    )


def cost_cell(records: Sequence[Record], key: str) -> Cell:
    """Aggregate a cost field over seeds (no CI: one number per run)."""
    vals = [float(r["cost"][key]) for r in records if r["cost"].get(key) is not None]
    if not vals:
        return Cell()
    return Cell(mean=float(np.mean(vals)), std=float(np.std(vals, ddof=1)) if len(vals) > 1 else None,
                n_seeds=len(vals))


def _fill(row: Row, columns: Sequence[Column]) -> None:
    for c in columns:
        recs = [r for r in row.records if c.clip is None or r["protocol"]["clip"] == c.clip]
        if c.kind == "metric":
            row.cells[c.id] = metric_cell(recs, c.key)
        elif c.kind == "cost":
            row.cells[c.id] = cost_cell(recs, c.key)


def _column_backends(sec: Section, col: Column) -> set[str]:
    out: set[str] = set()
    for row in sec.rows:
        cell = row.cells.get(col.id)
        if cell is not None and cell.mean is not None and col.kind == "metric":
            out |= {b.split(" v")[0] for b in cell.backends}
    return out


def timed_busy(cost: dict) -> bool:
    """True when a run's FPS was timed while other processes took more than :data:`BUSY_SHARE` of the host's
    CPU, or while the host ran the fixed probe more than :data:`SLOW_HOST` times slower than its best."""
    share, slow = cost.get("others_cpu_share"), cost.get("host_slowdown")
    return (share is not None and share > BUSY_SHARE) or (slow is not None and slow > SLOW_HOST)


def busy_text(cost: dict) -> str:
    """What made a timing busy, e.g. ``others 23%`` or ``probe 2.1x slower``."""
    parts = []
    share, slow = cost.get("others_cpu_share"), cost.get("host_slowdown")
    if share is not None and share > BUSY_SHARE:
        parts.append(f"others {share:.0%}")
    if slow is not None and slow > SLOW_HOST:
        parts.append(f"probe {slow:.1f}x slower")
    return ", ".join(parts)


BUSY_NOTE = (f"{BUSY} FPS timed on a busy or slowed host: other processes took more than {BUSY_SHARE:.0%} of its CPU "
             f"(cost.others_cpu_share) or it ran a fixed probe workload more than {SLOW_HOST:g}x slower than its best on "
             "that machine (cost.host_slowdown)")


def _flag_column(sec: Section, columns: Sequence[Column], key: str, hit: Callable[[dict], bool],
                 describe: Callable[[list[dict], int], str]) -> list[str]:
    """Mark with :data:`BUSY` the ``key`` cost cell of every row with a run where ``hit(cost)``.

    Returns one ``"<row> <describe(hits, n_runs)>"`` per marked row, for the section's note.
    """
    col = next((c for c in columns if c.kind == "cost" and c.key == key), None)
    if col is None:
        return []
    busy = []
    for row in sec.rows:
        cell = row.cells.get(col.id)
        costs = [r.get("cost") or {} for r in row.records]
        hits = [c for c in costs if hit(c)]
        if cell is not None and cell.mean is not None and hits:
            cell.flag = BUSY
            busy.append(f"{row.label} {describe(hits, len(costs))}")
    return busy


def flag_busy_timings(sec: Section, columns: Sequence[Column]) -> None:
    """Mark FPS timed while other processes took more than :data:`BUSY_SHARE` of the host's CPU."""
    def worst(hits: list[dict], n: int) -> str:
        w = max(hits, key=lambda c: (c.get("host_slowdown") or 1.0) * (1 + (c.get("others_cpu_share") or 0.0)))
        return f"{len(hits)}/{n} runs, worst {busy_text(w)}"

    busy = _flag_column(sec, columns, "fps", timed_busy, worst)
    if busy:
        sec.notes.append(f"{BUSY_NOTE}: {'; '.join(busy)}. On a quiet host these render faster.")
    flag_busy_training(sec, columns)


def trained_busy(cost: dict) -> bool:
    """True when other processes took more than :data:`BUSY_SHARE` of the host's CPU while the model trained."""
    share = cost.get("train_others_cpu_share")
    return share is not None and share > BUSY_SHARE


def flag_busy_training(sec: Section, columns: Sequence[Column]) -> None:
    """Mark training times measured while other processes took more than :data:`BUSY_SHARE` of the host's CPU."""
    def worst(hits: list[dict], n: int) -> str:
        return f"{len(hits)}/{n} runs, worst others {max(c['train_others_cpu_share'] for c in hits):.0%}"

    busy = _flag_column(sec, columns, "train_seconds", trained_busy, worst)
    if busy:
        sec.notes.append(f"{BUSY} Train: trained while other processes took more than {BUSY_SHARE:.0%} of the host's CPU "
                         f"(cost.train_others_cpu_share): {'; '.join(busy)}. On a quiet host these train faster.")


def rank_section(sec: Section, columns: Sequence[Column], alpha: float = ALPHA) -> None:
    """Mark best / second / ties per column (see the module docstring); notes go to ``sec.notes``.

    FPS timed on a busy host are marked first (:func:`flag_busy_timings`).
    """
    flag_busy_timings(sec, columns)
    for col in columns:
        if col.kind != "metric" or not col.rank:
            continue
        rows = [r for r in sec.rows if r.ranked and r.cells.get(col.id) and r.cells[col.id].mean is not None]
        if len(_column_backends(sec, col)) > 1:
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
        tests = []
        for other in rows[1:]:
            oc = other.cells[col.id]
            t = None
            if best.paired is not None and oc.paired is not None and len(best.paired) == len(oc.paired):
                t = paired_test(best.paired, oc.paired)
            tests.append(t)
        name = f"{col.group + ' ' if col.group else ''}{col.label}"
        if tests[0] is None:
            best.mark, rows[1].cells[col.id].mark = "best", "second"
            sec.notes.append(f"{name}: best / second not tested for significance (no per-item values on the same "
                             f"items).")
            continue
        if tests[0].significant(alpha):
            best.mark, rows[1].cells[col.id].mark = "best", "second"
            continue
        best.mark = "tie"
        tied = [rows[0].label]
        for other, t in zip(rows[1:], tests):
            if t is not None and not t.significant(alpha):
                other.cells[col.id].mark = "tie"
                tied.append(f"{other.label} (p={t.p:.2g})")
        sec.notes.append(f"{TIE} {name}: {', '.join(tied)} are not significantly different (paired bootstrap and "
                         f"Wilcoxon over the same items, p ≥ {alpha:g}); no winner is bolded.")


def _subject_title(recs: Iterable[Record]) -> str:
    s = next(iter(recs))["subject"]
    return s["name"] + (" (bundled)" if s["bundled"] else "")


def _by_subject(records: Iterable[Record]) -> dict[str, list[Record]]:
    out: dict[str, list[Record]] = defaultdict(list)
    for r in records:
        out[r["subject"]["name"]].append(r)
    return dict(sorted(out.items()))


def _rows(records: Iterable[Record], label: Callable[[Record], str] | None = None) -> list[Row]:
    groups: dict[tuple[str, str], list[Record]] = defaultdict(list)
    for r in records:
        groups[(r["method"]["name"], r["config_hash"])].append(r)
    names = defaultdict(int)
    for name, _ in groups:
        names[name] += 1
    rows = []
    for (name, h), recs in groups.items():
        recs.sort(key=lambda r: (r["seed"], r["protocol"]["clip"]))
        m = recs[0]["method"]
        text = label(recs[0]) if label else m["display_name"] or name
        if names[name] > 1:
            text += f" [{h[:8]}]"  # same method, different configs: never merged silently
        rows.append(Row(text, name, m["family"], recs))
    return rows


def _order(row: Row) -> tuple:
    fam = FAMILY_ORDER.index(row.family) if row.family in FAMILY_ORDER else len(FAMILY_ORDER)
    return (row.method == OURS, fam, row.label)


def _common_notes(records: Sequence[Record], columns: Sequence[Column], methods: bool = True) -> list[str]:
    notes = []
    for c in columns:
        if c.kind != "metric":
            continue
        made, standins = set(), set()
        for r in records:
            m = r["metrics"].get(c.key)
            if m is not None and m["value"] is not None:
                made.add(f"{m['backend']} v{m['backend_version']}")
                if m.get("standin"):
                    standins.add(m["standin"])
        if not made:
            continue
        name = f"{c.group + ' ' if c.group else ''}{c.label}"
        note = f"{name} made by {', '.join(sorted(made))}"
        if standins:
            note += f"; STAND-IN: {'; '.join(x.rstrip('.') for x in sorted(standins))}"
        notes.append(note + ".")
    # a subject's own Gaussian budget (a record note), and the rows that used it
    sized: dict[tuple[str, str], set[str]] = defaultdict(set)
    for r in records:
        for n in r.get("notes") or ():
            if n.startswith(BUDGET_NOTE):
                sized[(r["subject"]["name"], n)].add(r["method"]["display_name"] or r["method"]["name"])
    seen = set()
    for r in records:
        s = r["subject"]
        if s["name"] in seen:
            continue
        seen.add(s["name"])
        if s["bundled"] or s["standin"]:
            notes.append(f"Subject {s['name']}: {'bundled, synthetic' if s['bundled'] else 'stand-in'}"
                         f"{': ' + s['standin'] if s['standin'] else ''} (not a real recording).")
        for (name, n), labels in sized.items():
            if name == s["name"]:
                notes.append(f"Subject {name}: {n} ({', '.join(sorted(labels))}).")
    if methods:
        done = set()
        for r in sorted(records, key=lambda r: r["method"]["name"]):
            m = r["method"]
            if m["name"] in done or m["family"] == "ground-truth":
                continue
            done.add(m["name"])
            text = f"{m['display_name'] or m['name']} ({m['family']}): {m['description']}"
            if m["standins"]:
                text += f" Stand-ins: {'; '.join(m['standins'])}."
            notes.append(text)
    machines = {f"{r['machine']['cpu']}, {r['machine']['threads']} threads, "
                + (f"{r['machine']['cpu_kernels']} kernels, " if r["machine"].get("cpu_kernels") else "")
                + f"{r['machine']['cuda_device'] or 'no GPU'}" for r in records}
    if any(c.kind == "cost" for c in columns) and machines:
        if len(machines) > 1:
            notes.append(f"{MIXED} cost measured on different machines: {' | '.join(sorted(machines))}.")
        else:
            notes.append(f"Cost measured on {machines.pop()}.")
    return notes


def _metric_cols(keys: Iterable[str], clip: str | None = None, group: str = "") -> list[Column]:
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


# ----------------------------------------------------------------------------- the tables
def table_self(records: Sequence[Record], metrics: Sequence[str] = ("psnr", "lpips", "lmd", "lse_d", "lse_c"),
               cost: bool = True) -> Table:
    """Table I: self-driven reconstruction, Ground Truth row first, Ours last, cost columns.

    Args:
        records: the store (other protocols, variants, controls and failed runs are ignored).
        metrics: metric keys, in column order.
        cost: include FPS, training time, Gaussians and MB.
    """
    cols = _metric_cols(metrics) + (COST_COLUMNS if cost else [])
    use = [r for r in records if r["protocol"]["name"] == "self" and is_ok(r) and not is_variant(r)
           and r["method"]["family"] != "control"]
    sections = []
    for subject, recs in _by_subject(use).items():
        rows = sorted(_rows(recs), key=_order)
        for k, row in enumerate(rows):
            _fill(row, cols)
            row.ranked = row.family not in UNRANKED
            row.rule_before = (row.method == OURS) or (row.ranked and k > 0 and rows[k - 1].family in UNRANKED)
            if row.family in UNRANKED:
                for c in COST_COLUMNS:
                    row.cells.pop(c.id, None)
        sec = Section(_subject_title(recs), rows)
        rank_section(sec, cols)
        sections.append(sec)
    notes = _common_notes(use, cols)
    return Table("table1_self", "Table I: self-driven reconstruction", cols, sections, notes)


def table_cross(records: Sequence[Record], metrics: Sequence[str] = ("lse_d", "lse_c")) -> Table:
    """Table II: cross-driven, one column group per driving clip (Audio A, Audio B, ...)."""
    use = [r for r in records if r["protocol"]["name"] == "cross" and is_ok(r) and not is_variant(r)]
    clips = sorted({r["protocol"]["clip"] for r in use})
    cols = [c for clip in clips for c in _metric_cols(metrics, clip, f"Audio {clip}" if len(clip) == 1 else clip)]
    sections = []
    for subject, recs in _by_subject(use).items():
        rows = sorted(_rows(recs), key=_order)
        for row in rows:
            _fill(row, cols)
            row.rule_before = row.method == OURS
        sec = Section(_subject_title(recs), rows)
        rank_section(sec, cols)
        sections.append(sec)
    return Table("table2_cross", "Table II: cross-driven lip sync", cols, sections, _common_notes(use, cols))


def _is_lmgs(rec: Record) -> bool:
    """The reference model or one of its named variants (``lmgs``, ``lmgs-no-se``...).

    Baselines built on the same backbone (``talkinggaussian``, ``degstalk``) carry the same config
    keys, but they are other methods: they never stand in for an ablation row of Tables III-IV
    (``lmgs-base`` is the TalkingGaussian-like configuration of the ablation).
    """
    name = rec["method"]["name"]
    return name == "lmgs" or name.startswith("lmgs-")


def _lmgs_self(records: Sequence[Record]) -> list[Record]:
    return [r for r in records
            if r["protocol"]["name"] == "self" and is_ok(r) and _is_lmgs(r) and _guidance(r) is not None]


def table_theta(records: Sequence[Record], metrics: Sequence[str] = ("lpips", "lmd", "lse_d", "lse_c")) -> Table:
    """Table III: the θ sweep (lmgs configs with SE, LC and GR on, differing in ``config.guidance.theta``)."""
    use = []
    for r in _lmgs_self(records):
        g = _guidance(r)
        variant = r["method"].get("variant") or ""
        if g.get("se", True) and g.get("lc", True) and r["config"].get("gr", True) and \
                (not variant or variant.startswith("theta")):
            use.append(r)
    cols = [Column("se_points", "Points enhanced", "se_points", "text"), *_metric_cols(metrics)]
    sections = []
    for subject, recs in _by_subject(use).items():
        if len({_guidance(r)["theta"] for r in recs}) < 2:
            continue
        rows = sorted(_rows(recs, label=lambda r: f"{_guidance(r)['theta']:g}"),
                      key=lambda row: (_guidance(row.records[0])["theta"], row.label))
        for row in rows:
            _fill(row, cols)
            # What θ does: the share of face points Spatial Enhancement selected (paper: about 20 % at 0.6).
            fr = [100 * f for f in (se_fraction(r) for r in row.records) if f is not None]
            text = f"{np.mean(fr):.1f}%" if fr else "–"
            if len(fr) > 1:
                text += f" ({min(fr):.1f}-{max(fr):.1f})"  # the range over seeds: how stable θ's selection is
            row.cells["se_points"] = Cell(text=text)
        sec = Section(_subject_title(recs), rows)
        rank_section(sec, cols)
        sections.append(sec)
    used = [r for s in sections for row in s.rows for r in row.records]
    return Table("table3_theta", "Table III: effect of the threshold θ", cols, sections,
                 _common_notes(used, cols, methods=False), label_header="θ")


def _gr_form(r: Record) -> tuple[str, float]:
    """How a record's Geometry Regularizer reduces and weighs its normal term: ``(reduce, lambda_normal)``."""
    train = r["config"].get("train") or {}
    return train.get("normal_reduce", "sum"), float(train.get("lambda_normal", 1e-4))


def _se_cap(r: Record) -> float:
    """The share of points a record's SE may select at most (0: θ alone; records before the cap lack it)."""
    return float(_guidance(r).get("select_fraction", 0.0))


def _ablation_label(r: Record, full_frontend: str | None = None, full_gr: tuple | None = None,
                    full_cap: float | None = None) -> str:
    """The row of Table IV: the audio rows of the paper, then what of SE / LC / GR is off."""
    g, audio = _guidance(r), r["config"].get("audio") or {}
    parts = []
    frontend = audio.get("frontend")
    if frontend == "ds" and full_frontend != "ds":
        parts.append("Replacing Audio Net with DS")
    elif frontend and full_frontend and frontend != full_frontend:
        parts.append(f"Audio front end {frontend}")
    if audio.get("use_encoder", True) is False:
        parts.append("w/o Audio Encoder")
    off = [n for n, on in (("SE", g.get("se", True)), ("LC", g.get("lc", True)), ("GR", r["config"].get("gr", True)))
           if not on]
    if off:
        parts.append("w/o " + ", ".join(off))
    cap = _se_cap(r)
    if g.get("se", True) and cap != (full_cap or 0.0):  # SE selects another share than the full model's
        parts.append(f"SE capped at {cap:.0%} of the points" if cap else "SE by θ alone (uncapped)")
    folds = (r["config"].get("train") or {}).get("landmark_folds", 0)
    if folds and (g.get("se", True) or g.get("lc", True)):
        parts.append(f"Training landmarks out of fold ({folds} folds)")
    form = _gr_form(r)
    if r["config"].get("gr", True) and form != (full_gr or ("sum", 1e-4)):  # GR in another form than the full model's
        parts.append("GR as the paper writes it (normal term summed, λ_N = {1:g})".format(*form) if form[0] == "sum"
                     else "GR, normal term per pixel ({0}, λ_N = {1:g})".format(*form))
    if parts:
        return ", ".join(parts)
    return "Full model" if not is_variant(r) else (r["method"]["display_name"] or r["method"]["name"])


def table_ablation(records: Sequence[Record], metrics: Sequence[str] = ("lmd", "lpips", "lse_d", "lse_c")) -> Table:
    """Table IV: component ablation (SE / LC / GR as ✓/✗) at the full model's θ; Full model last."""
    cols = [Column("se", "SE", "se", "text"), Column("lc", "LC", "lc", "text"), Column("gr", "GR", "gr", "text")]
    cols += _metric_cols(metrics)
    sections = []
    for subject, recs in _by_subject(_lmgs_self(records)).items():
        full = [r for r in recs if not is_variant(r)]
        theta = _guidance(full[0])["theta"] if full else 0.6
        frontend = (full[0]["config"].get("audio") or {}).get("frontend") if full else None
        recs = [r for r in recs if _guidance(r)["theta"] == theta]
        label = functools.partial(_ablation_label, full_frontend=frontend, full_gr=_gr_form(full[0]) if full else None,
                                  full_cap=_se_cap(full[0]) if full else None)
        if len({label(r) for r in recs}) < 2:
            continue
        order = {"Replacing Audio Net with DS": 0, "w/o Audio Encoder": 1, "w/o SE": 2, "w/o LC": 3, "w/o GR": 4}
        rows = sorted(_rows(recs, label=label),
                      key=lambda row: (row.label == "Full model", order.get(row.label, 5), row.label))
        for row in rows:
            _fill(row, cols)
            g, gr = _guidance(row.records[0]), row.records[0]["config"].get("gr", True)
            for cid, on in (("se", g.get("se", True)), ("lc", g.get("lc", True)), ("gr", gr)):
                row.cells[cid] = Cell(text="✓" if on else "✗")
            row.rule_before = row.label == "Full model"
        sec = Section(f"{_subject_title(recs)}, θ = {theta:g}", rows)
        rank_section(sec, cols)
        sections.append(sec)
    used = [r for s in sections for row in s.rows for r in row.records]
    return Table("table4_ablation", "Table IV: component ablation", cols, sections,
                 _common_notes(used, cols, methods=False), label_header="Setting")


def _separates(gt: Cell, ctl: Cell, hib: bool) -> bool:
    if gt.mean is None or ctl.mean is None:
        return True  # nothing to compare: not evidence of failure
    better = gt.mean > ctl.mean if hib else gt.mean < ctl.mean
    if not better:
        return False
    if gt.ci is not None and ctl.ci is not None:  # intervals must not overlap
        return gt.ci.lo > ctl.ci.hi if hib else gt.ci.hi < ctl.ci.lo
    return True


def table_calibration(records: Sequence[Record],
                      metrics: Sequence[str] = ("psnr", "lpips", "lmd", "lse_d", "lse_c", "av_offset")) -> Table:
    """Calibration (issue 9): the ground truth against its negative controls, per subject.

    A metric *separates* when, for every control that targets it (``method.control.targets``;
    all metrics when absent), the ground truth is better and their bootstrap CIs do not
    overlap. A metric that does not is marked ✗ in the last row and on the control's cell.
    """
    use = [r for r in records if r["protocol"]["name"] in ("self", "calibration") and is_ok(r)
           and r["method"]["family"] in ("ground-truth", "control")]
    cols = _metric_cols(metrics)
    sections = []
    for subject, recs in _by_subject(use).items():
        rows = sorted(_rows(recs), key=_order)
        for k, row in enumerate(rows):
            _fill(row, cols)
            row.ranked = False
            row.rule_before = k > 0 and rows[k - 1].family == "ground-truth"
        gts = [r for r in rows if r.family == "ground-truth"]
        verdict = Row("GT separated from its controls", "", "", [], ranked=False, rule_before=True)
        notes = []
        for c in cols:
            if not gts:
                verdict.cells[c.id] = Cell(text="no GT row")
                continue
            gt = gts[0].cells[c.id]
            failed, tested = [], 0
            for row in rows:
                if row.family != "control":
                    continue
                targets = row.records[0]["method"].get("control", {}).get("targets")
                if targets is not None and c.key not in targets:
                    continue
                if gt.mean is None or row.cells[c.id].mean is None:
                    continue
                tested += 1
                if not _separates(gt, row.cells[c.id], bool(c.higher_is_better)):
                    row.cells[c.id].flag = "✗"
                    failed.append(row.label)
            verdict.cells[c.id] = Cell(text="–" if not tested else ("✗" if failed else "✓"))
            if failed:
                notes.append(f"✗ {c.label} does not separate the ground truth from: {', '.join(failed)}; "
                             f"do not trust {c.label} on this subject.")
        sections.append(Section(_subject_title(recs), rows + [verdict], notes))
    return Table("calibration", "Calibration: ground truth against negative controls", cols, sections,
                 _common_notes(use, cols) + ["A control separates when the ground truth is better and the bootstrap "
                                             "95% CIs do not overlap.",
                                             "The shifted-audio controls target the AV offset only: LSE-D and LSE-C "
                                             "take the best of the offsets within +-15 frames (syncnet_python), so a "
                                             "constant shift of up to 10 frames leaves them nearly unchanged by "
                                             "design."])


def table_stability(records: Sequence[Record], metric: str = "lse_c", clean: str = "clean") -> Table:
    """Stability (issue 8): per method x stress condition, the change of ``metric`` from the clean run.

    Cells show ``value - clean`` (mean over seeds); failed runs are counted per cell, and the
    last column is the suite's cost: the wall time of the row's stress runs (render, scoring and
    writing; training excluded: the suite reuses the trained model).
    """
    use = [r for r in records if r["protocol"]["name"] == "stress"]
    conds = sorted({r["protocol"]["clip"] for r in use} - {clean})
    label, hib, digits = METRICS[metric]
    cols = [Column(f"{c}.{metric}", c, metric, "metric", None, digits, rank=False) for c in conds]
    cols.append(Column("failures", "failed runs", "failures", "text"))
    cols.append(Column("suite_min", "suite wall (min)", "suite_min", "text"))
    sections, absolute = [], set()
    for subject, recs in _by_subject(use).items():
        rows = sorted(_rows(recs), key=_order)
        for row in rows:
            row.ranked = False
            clean_ok = [r for r in row.records if r["protocol"]["clip"] == clean and is_ok(r)]
            base = metric_cell(clean_ok, metric)
            n_fail = 0
            for c in conds:
                here = [r for r in row.records if r["protocol"]["clip"] == c]
                fails = [r for r in here if not is_ok(r)]
                n_fail += len(fails)
                cell = metric_cell([r for r in here if is_ok(r)], metric)
                if cell.mean is not None and base.mean is not None:
                    cell.mean -= base.mean
                    cell.ci = None
                elif cell.mean is not None and clean_ok:
                    absolute.add(c)  # not measured on the clean clip (mouth opening in silence): the value itself
                    cell.ci = None
                elif cell.mean is not None:
                    cell.mean = None
                    cell.text = "no clean run"
                if fails:
                    cell.text = f"{len(fails)} failed: {fails[0]['status'].get('reason')}"
                if cell.mean is None and cell.text is None:
                    cell.text = "–"
                row.cells[f"{c}.{metric}"] = cell
            row.cells["failures"] = Cell(text=str(n_fail))
            walls = [r.get("cost", {}).get("wall_seconds") for r in row.records]
            row.cells["suite_min"] = Cell(text=f"{sum(walls) / 60:.1f}" if all(w is not None for w in walls) else "–")
        sections.append(Section(_subject_title(recs), rows))
    arrow = "↑" if hib else "↓"
    notes = _common_notes(use, _metric_cols([metric]), methods=False)
    if absolute:
        notes.append(f"{', '.join(sorted(absolute))}: {label} itself, not a change: it is not measured on the clean clip.")
    return Table(f"stability_{metric}", f"Stability: change of {label}{arrow} from the clean condition", cols,
                 sections, notes)


# The paper's Table I (self-driven, mean over Obama, May and Lieu): PSNR, LPIPS, LMD, LSE-D, LSE-C.
PAPER_TABLE_I: dict[str, tuple[float, float, float, float, float]] = {
    "wav2lip": (17, 0.2954, 4.72, 6.609, 8.745),
    "ip_lap": (16, 0.3821, 5.16, 9.633, 4.603),
    "adnerf": (26, 0.2380, 3.15, 9.230, 5.586),
    "radnerf": (26, 0.1250, 2.92, 8.902, 5.322),
    "ernerf": (27, 0.0864, 2.86, 8.712, 6.088),
    "geneface": (26, 0.1053, 3.36, 9.103, 5.423),
    "talkinggaussian": (32, 0.0407, 2.81, 8.145, 6.673),
    "gaussiantalker": (32, 0.0520, 2.80, 8.335, 6.676),
    "degstalk": (37, 0.0164, 2.66, 7.660, 7.277),
    "lmgs": (38, 0.0128, 2.28, 7.150, 7.900),
}
PAPER_KEYS = ("psnr", "lpips", "lmd", "lse_d", "lse_c")


def paper_order_agreement(records: Sequence[Record], method: str, subject: str) -> tuple[int, int] | None:
    """Pairs (this method vs another, per metric) ordered as in the paper's Table I: ``(agree, total)``.

    Uses the self-driven means on ``subject`` of the methods the paper reports (variants and
    failed runs excluded); pairs the paper ties are skipped. None without a published ordering.
    """
    if method not in PAPER_TABLE_I:
        return None
    means: dict[str, dict[str, float]] = {}
    for r in records:
        name = r["method"]["name"]
        if (name in PAPER_TABLE_I and r["subject"]["name"] == subject and r["protocol"]["name"] == "self"
                and not r["method"].get("variant") and is_ok(r)):
            for k in PAPER_KEYS:
                v = r["metrics"].get(k, {}).get("value")
                if v is not None:
                    means.setdefault(name, {}).setdefault(k, []).append(v)
    if method not in means:
        return None
    agree = total = 0
    for other in means:
        if other == method:
            continue
        for j, k in enumerate(PAPER_KEYS):
            a, b = means[method].get(k), means[other].get(k)
            pa, pb = PAPER_TABLE_I[method][j], PAPER_TABLE_I[other][j]
            if not a or not b or pa == pb:
                continue
            ours = float(np.mean(a)) - float(np.mean(b))
            if ours == 0:
                continue
            total += 1
            agree += (ours > 0) == (pa > pb)
    return (agree, total) if total else None


def table_status(records: Sequence[Record]) -> Table:
    """Status per method x subject (nerfbaselines' badges): ``ok (n runs)`` or ``failed: reason``,
    and how many of its pairwise orderings agree with the paper's Table I."""
    use = [r for r in records if r["method"]["family"] != "control"]
    subjects = sorted({r["subject"]["name"] for r in use})
    cols = [Column(f"s.{s}", s, s, "text") for s in subjects]
    rows = sorted(_rows(use), key=_order)
    merged: dict[str, Row] = {}
    for row in rows:  # one line per method, all configs
        merged.setdefault(row.method, Row(row.label.split(" [")[0], row.method, row.family, [])).records += row.records
    out = []
    for row in merged.values():
        for s in subjects:
            recs = [r for r in row.records if r["subject"]["name"] == s]
            ok = [r for r in recs if is_ok(r)]
            bad = [r for r in recs if not is_ok(r)]
            if not recs:
                text = "–"
            elif not bad:
                text = f"ok ({len(ok)})"
            else:
                first = bad[0]
                text = (f"{len(ok)} ok, {len(bad)} failed: {first['status'].get('reason')} "
                        f"({first['protocol']['name']}:{first['protocol']['clip']})")
            po = paper_order_agreement(use, row.method, s) if recs else None
            if po is not None:
                text += f"; paper's order {po[0]}/{po[1]}"
            row.cells[f"s.{s}"] = Cell(text=text)
        out.append(row)
    return Table("status", "Status per method and subject", cols, [Section("all subjects", out)],
                 ["ok (n): n runs recorded without failure; failed: the first failure's reason and protocol:clip.",
                  "paper's order k/n: of the n (other method, metric) pairs of the self-driven table, k are ordered as "
                  "in the paper's Table I (mean over Obama, May and Lieu); on a bundled stand-in subject this is a "
                  "comparison, not an expectation."])


def all_tables(records: Sequence[Record]) -> list[Table]:
    """Every table that has rows in ``records`` (Table I first)."""
    tables = [table_self(records), table_cross(records), table_theta(records), table_ablation(records),
              table_calibration(records)]
    stress_metrics = sorted({k for r in records if r["protocol"]["name"] == "stress" for k in r["metrics"]
                             if k in METRICS})
    tables += [table_stability(records, m) for m in stress_metrics]
    tables.append(table_status(records))
    return [t for t in tables if not t.is_empty()]

