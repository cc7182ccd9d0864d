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
95% CI over items and seeds (:func:`lmgs_eval.report.stats.bootstrap_ci_seeds`) goes to the CSV
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

import functools
from collections.abc import Sequence

import numpy as np

from lmgs_eval.report.cells import (COST_COLUMNS, by_subject, common_notes, fill_row, components_of, is_ok, is_variant,
                                    make_rows, metric_cell, metric_columns, rank_section, row_order, subject_title)
from lmgs_eval.report.table_model import METRICS, OURS, UNRANKED, Cell, Column, Record, Row, Section, Table
from lmgs_eval.results import se_fraction


# ----------------------------------------------------------------------------- the tables
def table_self(records: Sequence[Record], metrics: Sequence[str] = ("psnr", "lpips", "lmd", "lse_d", "lse_c"),
               cost: bool = True) -> Table:
    """Table I: self-driven reconstruction, Ground Truth row first, Ours last, cost columns.

    Args:
        records: the store (other protocols, variants, controls and failed runs are ignored).
        metrics: metric keys, in column order.
        cost: include FPS, training time, Gaussians and MB.
    """
    cols = metric_columns(metrics) + (COST_COLUMNS if cost else [])
    use = [r for r in records if r["protocol"]["name"] == "self" and is_ok(r) and not is_variant(r)
           and r["method"]["family"] != "control"]
    sections = []
    for subject, recs in by_subject(use).items():
        rows = sorted(make_rows(recs), key=row_order)
        for k, row in enumerate(rows):
            fill_row(row, cols)
            row.ranked = row.family not in UNRANKED
            row.rule_before = (row.method == OURS) or (row.ranked and k > 0 and rows[k - 1].family in UNRANKED)
            if row.family in UNRANKED:
                for c in COST_COLUMNS:
                    row.cells.pop(c.id, None)
        sec = Section(subject_title(recs), rows)
        rank_section(sec, cols)
        sections.append(sec)
    notes = common_notes(use, cols)
    return Table("table1_self", "Table I: self-driven reconstruction", cols, sections, notes)


def table_cross(records: Sequence[Record], metrics: Sequence[str] = ("lse_d", "lse_c")) -> Table:
    """Table II: cross-driven, one column group per driving clip (Audio A, Audio B, ...)."""
    use = [r for r in records if r["protocol"]["name"] == "cross" and is_ok(r) and not is_variant(r)]
    clips = sorted({r["protocol"]["clip"] for r in use})
    cols = [c for clip in clips for c in metric_columns(metrics, clip, f"Audio {clip}" if len(clip) == 1 else clip)]
    sections = []
    for subject, recs in by_subject(use).items():
        rows = sorted(make_rows(recs), key=row_order)
        for row in rows:
            fill_row(row, cols)
            row.rule_before = row.method == OURS
        sec = Section(subject_title(recs), rows)
        rank_section(sec, cols)
        sections.append(sec)
    return Table("table2_cross", "Table II: cross-driven lip sync", cols, sections, common_notes(use, cols))


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
            if r["protocol"]["name"] == "self" and is_ok(r) and _is_lmgs(r) and components_of(r) is not None]


def table_theta(records: Sequence[Record], metrics: Sequence[str] = ("lpips", "lmd", "lse_d", "lse_c")) -> Table:
    """Table III: the θ sweep (lmgs with SE, LC and GR on, differing in its declared ``theta``)."""
    use = []
    for r in _lmgs_self(records):
        c = components_of(r)
        variant = r["method"].get("variant") or ""
        if c["se"] and c["lc"] and c["gr"] and (not variant or variant.startswith("theta")):
            use.append(r)
    cols = [Column("se_points", "Points enhanced", "se_points", "text"), *metric_columns(metrics)]
    sections = []
    for subject, recs in by_subject(use).items():
        if len({components_of(r)["theta"] for r in recs}) < 2:
            continue
        rows = sorted(make_rows(recs, label=lambda r: f"{components_of(r)['theta']:g}"),
                      key=lambda row: (components_of(row.records[0])["theta"], row.label))
        for row in rows:
            fill_row(row, cols)
            # What θ does: the share of face points Spatial Enhancement selected (paper: about 20 % at 0.6).
            fr = [100 * f for f in (se_fraction(r) for r in row.records) if f is not None]
            text = f"{np.mean(fr):.1f}%" if fr else "–"
            if len(fr) > 1:
                text += f" ({min(fr):.1f}-{max(fr):.1f})"  # the range over seeds: how stable θ's selection is
            row.cells["se_points"] = Cell(text=text)
        sec = Section(subject_title(recs), rows)
        rank_section(sec, cols)
        sections.append(sec)
    used = [r for s in sections for row in s.rows for r in row.records]
    return Table("table3_theta", "Table III: effect of the threshold θ", cols, sections,
                 common_notes(used, cols, methods=False), label_header="θ")


def _gr_form(r: Record) -> tuple[str, float]:
    """How a record's Geometry Regularizer reduces and weighs its normal term: ``(reduce, lambda_normal)``."""
    c = components_of(r)
    return c["gr_reduce"], float(c["gr_weight"])


def _se_cap(r: Record) -> float:
    """The share of points a record's SE may select at most (0: θ alone)."""
    return float(components_of(r)["se_cap"])


def _ablation_label(r: Record, full_frontend: str | None = None, full_gr: tuple | None = None,
                    full_cap: float | None = None) -> str:
    """The row of Table IV: the audio rows of the paper, then what of SE / LC / GR is off."""
    c = components_of(r)
    parts = []
    frontend = c["audio_frontend"]
    if frontend == "ds" and full_frontend != "ds":
        parts.append("Replacing Audio Net with DS")
    elif frontend and full_frontend and frontend != full_frontend:
        parts.append(f"Audio front end {frontend}")
    if not c["audio_encoder"]:
        parts.append("w/o Audio Encoder")
    off = [n for n in ("SE", "LC", "GR") if not c[n.lower()]]
    if off:
        parts.append("w/o " + ", ".join(off))
    cap = _se_cap(r)
    if c["se"] and cap != (full_cap or 0.0):  # SE selects another share than the full model's
        parts.append(f"SE capped at {cap:.0%} of the points" if cap else "SE by θ alone (uncapped)")
    folds = c["landmark_folds"]
    if folds:
        parts.append(f"Training landmarks out of fold ({folds} folds)")
    form = _gr_form(r)
    if c["gr"] and form != (full_gr or ("sum", 1e-4)):  # GR in another form than the full model's
        parts.append("GR as the paper writes it (normal term summed, λ_N = {1:g})".format(*form) if form[0] == "sum"
                     else "GR, normal term per pixel ({0}, λ_N = {1:g})".format(*form))
    if parts:
        return ", ".join(parts)
    return "Full model" if not is_variant(r) else (r["method"]["display_name"] or r["method"]["name"])


def table_ablation(records: Sequence[Record], metrics: Sequence[str] = ("lmd", "lpips", "lse_d", "lse_c")) -> Table:
    """Table IV: component ablation (SE / LC / GR as ✓/✗) at the full model's θ; Full model last."""
    cols = [Column("se", "SE", "se", "text"), Column("lc", "LC", "lc", "text"), Column("gr", "GR", "gr", "text")]
    cols += metric_columns(metrics)
    sections = []
    for subject, recs in by_subject(_lmgs_self(records)).items():
        full = [r for r in recs if not is_variant(r)]
        theta = components_of(full[0])["theta"] if full else 0.6
        frontend = components_of(full[0])["audio_frontend"] if full else None
        recs = [r for r in recs if components_of(r)["theta"] == theta]
        label = functools.partial(_ablation_label, full_frontend=frontend, full_gr=_gr_form(full[0]) if full else None,
                                  full_cap=_se_cap(full[0]) if full else None)
        if len({label(r) for r in recs}) < 2:
            continue
        order = {"Replacing Audio Net with DS": 0, "w/o Audio Encoder": 1, "w/o SE": 2, "w/o LC": 3, "w/o GR": 4}
        rows = sorted(make_rows(recs, label=label),
                      key=lambda row: (row.label == "Full model", order.get(row.label, 5), row.label))
        for row in rows:
            fill_row(row, cols)
            c = components_of(row.records[0])
            for cid in ("se", "lc", "gr"):
                row.cells[cid] = Cell(text="✓" if c[cid] else "✗")
            row.rule_before = row.label == "Full model"
        sec = Section(f"{subject_title(recs)}, θ = {theta:g}", rows)
        rank_section(sec, cols)
        sections.append(sec)
    used = [r for s in sections for row in s.rows for r in row.records]
    return Table("table4_ablation", "Table IV: component ablation", cols, sections,
                 common_notes(used, cols, methods=False), label_header="Setting")


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
    cols = metric_columns(metrics)
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
        sections.append(Section(subject_title(recs), rows + [verdict], notes))
    return Table("calibration", "Calibration: ground truth against negative controls", cols, sections,
                 common_notes(use, cols) + ["A control separates when the ground truth is better and the bootstrap "
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
    for subject, recs in by_subject(use).items():
        rows = sorted(make_rows(recs), key=row_order)
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
    rows = sorted(make_rows(use), key=row_order)
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

