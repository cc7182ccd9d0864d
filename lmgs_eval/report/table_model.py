"""A table of the report: columns, cells, rows, sections; rendered to Markdown, LaTeX and CSV."""

from __future__ import annotations

import csv
import io
from collections.abc import Callable
from dataclasses import dataclass, field

from lmgs_eval.report.stats import CI
from lmgs_eval.results.types import Record

# metric key -> (label, higher_is_better, digits)
METRICS: dict[str, tuple[str, bool, int]] = {
    "psnr": ("PSNR", True, 2),
    "ssim": ("SSIM", True, 4),
    "lpips": ("LPIPS", False, 4),
    "lpips_custom": ("LPIPS (custom trunk)", False, 4),
    "lmd": ("LMD", False, 2),
    "lse_d": ("LSE-D", False, 3),
    "lse_c": ("LSE-C", True, 3),
    "av_offset": ("|AV offset|", False, 0),
    "jitter": ("Jitter (px)", False, 3),
    "silence_open": ("Open in silence (px)", False, 2),
}
CUSTOM_KEYS = {"lpips": "lpips_custom"}
"""A metric key and the key of the same network on weights other than the published ones (an AlexNet
trunk that is not torchvision's): a column of its own, shown beside it when records carry it, never merged."""
FAMILY_ORDER = ("ground-truth", "reference", "2D", "NeRF", "3DGS", "external", "control")
OURS = "lmgs"
UNRANKED = ("ground-truth", "reference")
"""Table I's rows above the rule: the ground truth and the protocol's reference composite."""
TIE = "†"
MIXED = "‡"
UNTRUSTED = "¶"
"""An LSE whose scorer failed its self-check on that clip: shown, never ranked."""
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
        paired: per-item values averaged over seeds (for the frame-level test), or None.
        values: the value of each seed (for the seed-level test).
        backends: ``backend vVERSION`` strings of the values.
        mark: ``best``, ``second``, ``tie`` or ``""``.
        text: a text cell (✓ / ✗, failure notes) instead of a number.
        flag: an extra mark shown after the value (``‡``, ``✗``, ``¶``).
        untrusted: an LSE figure whose sync scorer did not separate the clip's own audio from
            controls of the same clip (its self-check): kept out of the ranking.
    """

    mean: float | None = None
    std: float | None = None
    n_seeds: int = 0
    ci: CI | None = None
    paired: list[float] | None = None
    values: list[float] = field(default_factory=list)
    backends: set[str] = field(default_factory=set)
    mark: str = ""
    text: str | None = None
    flag: str = ""
    untrusted: bool = False


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
        return any(len(column_backends(sec, col)) > 1 for sec in self.sections)

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


@dataclass(frozen=True)
class _Markup:
    """How a cell is written in one output format."""

    missing: str  # a column the row has no cell in
    escape: Callable[[str], str]  # a text-only cell
    pm: str  # between mean and std
    marks: dict[str, str]  # best / second / tie around the number ("{}")
    note: Callable[[str], str]  # the text after a number, in parentheses
    flag: Callable[[str], str]  # a flag after the cell


def _cell_text(cell: Cell | None, c: Column, show_ci: bool, fmt: _Markup) -> str:
    if cell is None:
        return fmt.missing
    if cell.text is not None and cell.mean is None:
        return fmt.escape(cell.text)
    if cell.mean is None:
        return "N/A"
    s = _fmt(cell.mean, c)
    if cell.std is not None:
        s += f"{fmt.pm}{_fmt(cell.std, c)}"
    if show_ci and cell.ci is not None:
        s += f" [{_fmt(cell.ci.lo, c)}, {_fmt(cell.ci.hi, c)}]"
    s = fmt.marks.get(cell.mark, "{}").format(s)
    if cell.text:
        s += f" ({fmt.note(cell.text)})"
    return s + (fmt.flag(cell.flag) if cell.flag else "")


def _md_cell(cell: Cell | None, c: Column, show_ci: bool) -> str:
    return _cell_text(cell, c, show_ci, _MD)


_TEX = {"\\": "\\textbackslash{}", "&": "\\&", "%": "\\%", "$": "\\$", "#": "\\#", "_": "\\_", "{": "\\{",
        "}": "\\}", "~": "\\textasciitilde{}", "^": "\\textasciicircum{}", "θ": "$\\theta$", "†": "$^\\dagger$",
        "‡": "$^\\ddagger$", "✓": "\\checkmark", "✗": "$\\times$", "±": "$\\pm$", "↑": "$\\uparrow$",
        "↓": "$\\downarrow$", "Δ": "$\\Delta$", "–": "--", "→": "$\\to$", "≥": "$\\geq$"}


def _tex_escape(s: str) -> str:
    return "".join(_TEX.get(ch, ch) for ch in s)


def _tex_head(c: Column, mixed: bool) -> str:
    return f"\\textbf{{{_tex_escape(c.label)}}}" + _arrow(c, False) + ("$^\\ddagger$" if mixed else "")


def _tex_cell(cell: Cell | None, c: Column, show_ci: bool) -> str:
    return _cell_text(cell, c, show_ci, _TEX_CELL)


_MD = _Markup("–", _md_escape, " ± ", {"best": "**{}**", "second": "<u>{}</u>", "tie": "{}" + TIE}, str,
              lambda f: f" {f}")
_TEX_CELL = _Markup("--", _tex_escape, "$\\pm$", {"best": "\\textbf{{{}}}", "second": "\\underline{{{}}}",
                                                   "tie": "{}$^\\dagger$"}, _tex_escape, _tex_escape)


def column_backends(sec: Section, col: Column) -> set[str]:
    """The metric backends (without versions) that made a column's numbers in a section."""
    out: set[str] = set()
    for row in sec.rows:
        cell = row.cells.get(col.id)
        if cell is not None and cell.mean is not None and col.kind == "metric":
            out |= {b.split(" v")[0] for b in cell.backends}
    return out
