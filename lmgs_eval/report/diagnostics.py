"""The report's diagnostic tables: calibration (does each metric separate the ground truth from its
negative controls on this subject?), stability under stress (change from the clean condition), the
status of each method x subject, and how far a method's ranking agrees with the paper's Table I."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lmgs_eval.report.cells import (by_subject, common_notes, fill_row, is_ok, make_rows, metric_cell, metric_columns,
                                    row_order, subject_title, with_custom_keys)
from lmgs_eval.report.table_model import CUSTOM_KEYS, METRICS, Cell, Column, Record, Row, Section, Table


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
    """Calibration: the ground truth against its negative controls, per subject.

    A metric *separates* when, for every control that targets it (``method.control.targets``;
    all metrics when absent), the ground truth is better and their bootstrap CIs do not
    overlap. A metric that does not is marked ✗ in the last row and on the control's cell.
    """
    use = [r for r in records if r.protocol.name in ("self", "calibration") and is_ok(r)
           and r.method.family in ("ground-truth", "control")]
    cols = metric_columns(with_custom_keys(metrics, use))
    sections = []
    for subject, recs in by_subject(use).items():
        rows = sorted(make_rows(recs), key=row_order)
        for k, row in enumerate(rows):
            fill_row(row, cols)
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
                control = row.records[0].method.control
                base = next((k for k, v in CUSTOM_KEYS.items() if v == c.key), c.key)  # lpips_custom: as lpips
                targets = control.targets if control is not None else ()  # none named: every metric
                if targets and c.key not in targets and base not in targets:
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
        sections.append(Section(subject_title(recs), rows + [verdict], notes))
    return Table("calibration", "Calibration: ground truth against negative controls", cols, sections,
                 common_notes(use, cols) + ["A control separates when the ground truth is better and the bootstrap "
                                             "95% CIs do not overlap.",
                                             "The shifted-audio controls target the AV offset only: LSE-D and LSE-C "
                                             "take the best of the offsets within +-15 frames (syncnet_python), so a "
                                             "constant shift of up to 10 frames leaves them nearly unchanged by "
                                             "design."])


def table_stability(records: Sequence[Record], metric: str = "lse_c", clean: str = "clean") -> Table:
    """Stability: per method x stress condition, the change of ``metric`` from the clean run.

    Cells show ``value - clean`` (mean over seeds); failed runs are counted per cell, and the
    last column is the suite's cost: the wall time of the row's stress runs (render, scoring and
    writing; training excluded: the suite reuses the trained model).
    """
    use = [r for r in records if r.protocol.name == "stress"]
    conds = sorted({r.protocol.clip for r in use} - {clean})
    label, hib, digits = METRICS[metric]
    cols = [Column(f"{c}.{metric}", c, metric, "metric", None, digits, rank=False) for c in conds]
    cols.append(Column("failures", "failed runs", "failures", "text"))
    cols.append(Column("suite_min", "suite wall (min)", "suite_min", "text"))
    sections, absolute = [], set()
    for subject, recs in by_subject(use).items():
        rows = sorted(make_rows(recs), key=row_order)
        for row in rows:
            row.ranked = False
            clean_ok = [r for r in row.records if r.protocol.clip == clean and is_ok(r)]
            base = metric_cell(clean_ok, metric)
            n_fail = 0
            for c in conds:
                here = [r for r in row.records if r.protocol.clip == c]
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
                    cell.text = f"{len(fails)} failed: {fails[0].status.reason}"
                if cell.mean is None and cell.text is None:
                    cell.text = "–"
                row.cells[f"{c}.{metric}"] = cell
            row.cells["failures"] = Cell(text=str(n_fail))
            walls = [r.cost.wall_seconds for r in row.records]
            row.cells["suite_min"] = Cell(text=f"{sum(walls) / 60:.1f}" if all(w is not None for w in walls) else "–")
        sections.append(Section(subject_title(recs), rows))
    arrow = "↑" if hib else "↓"
    notes = common_notes(use, metric_columns([metric]), methods=False)
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
        name = r.method.name
        if (name in PAPER_TABLE_I and r.subject.name == subject and r.protocol.name == "self"
                and not r.method.variant and is_ok(r)):
            for k in PAPER_KEYS:
                v = r.value(k)
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
    use = [r for r in records if r.method.family != "control"]
    subjects = sorted({r.subject.name for r in use})
    cols = [Column(f"s.{s}", s, s, "text") for s in subjects]
    rows = sorted(make_rows(use), key=row_order)
    merged: dict[str, Row] = {}
    for row in rows:  # one line per method, all configs
        merged.setdefault(row.method, Row(row.label.split(" [")[0], row.method, row.family, [])).records += row.records
    out = []
    for row in merged.values():
        for s in subjects:
            recs = [r for r in row.records if r.subject.name == s]
            ok = [r for r in recs if is_ok(r)]
            bad = [r for r in recs if not is_ok(r)]
            if not recs:
                text = "–"
            elif not bad:
                text = f"ok ({len(ok)})"
            else:
                first = bad[0]
                text = (f"{len(ok)} ok, {len(bad)} failed: {first.status.reason} "
                        f"({first.protocol.name}:{first.protocol.clip})")
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
