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
  method x subject, in the manner of nerfbaselines): :mod:`lmgs_eval.report.diagnostics`.

How a cell is made: the mean over seeds (``± std`` when there are several); its bootstrap
95% CI over seeds and circular blocks of frames (:func:`lmgs_eval.report.stats.bootstrap_ci_seeds`)
goes to the CSV (and to Markdown/LaTeX with ``show_ci``). Ranking per column within a subject:
the best is **bold** only if a test says it differs from the runner-up at p < 0.05; then the
runner-up is underlined. The test (:func:`lmgs_eval.report.cells.compare`) is Welch's t on the
seed values when both rows have at least two seeds (the seed is the unit of replication of a
trained method), otherwise a circular-block paired bootstrap over the same frames (per-frame
values averaged over seeds, block length chosen from the differences). Otherwise the best
and every method not significantly different from it are marked † (a tie), and nothing is
bolded. Each section's notes name the test and p behind every mark. A column
whose rows were made by different metric backends is not ranked and is flagged ‡; the
backend of every column is named in the notes, with every stand-in (subjects, metric
scorers, method components) and each method's description.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np

from lmgs_eval.report.cells import (COST_COLUMNS, by_subject, common_notes, components_of, fill_row, is_ok, is_variant,
                                    make_rows, metric_columns, rank_section, row_order, subject_title, with_custom_keys)
from lmgs_eval.report.diagnostics import paper_order_agreement, table_calibration, table_stability, table_status
from lmgs_eval.report.table_model import METRICS, OURS, UNRANKED, Cell, Column, Record, Row, Section, Table
from lmgs_eval.results.store import se_fraction

__all__ = ["all_tables", "paper_order_agreement", "table_ablation", "table_calibration", "table_cross", "table_self",
           "table_stability", "table_status", "table_theta"]


# ----------------------------------------------------------------------------- the tables
def table_self(records: Sequence[Record], metrics: Sequence[str] = ("psnr", "lpips", "lmd", "lse_d", "lse_c"),
               cost: bool = True) -> Table:
    """Table I: self-driven reconstruction, Ground Truth row first, Ours last, cost columns.

    Args:
        records: the store (other protocols, variants, controls and failed runs are ignored).
        metrics: metric keys, in column order.
        cost: include FPS, training time, Gaussians and MB.
    """
    use = [r for r in records if r.protocol.name == "self" and is_ok(r) and not is_variant(r)
           and r.method.family != "control"]
    cols = metric_columns(with_custom_keys(metrics, use)) + (COST_COLUMNS if cost else [])
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
    use = [r for r in records if r.protocol.name == "cross" and is_ok(r) and not is_variant(r)]
    clips = sorted({r.protocol.clip for r in use})
    cols = [c for clip in clips
            for c in metric_columns(with_custom_keys(metrics, use), clip, f"Audio {clip}" if len(clip) == 1 else clip)]
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
    name = rec.method.name
    return name == "lmgs" or name.startswith("lmgs-")


def _lmgs_self(records: Sequence[Record]) -> list[Record]:
    return [r for r in records
            if r.protocol.name == "self" and is_ok(r) and _is_lmgs(r) and components_of(r) is not None]


def table_theta(records: Sequence[Record], metrics: Sequence[str] = ("lpips", "lmd", "lse_d", "lse_c")) -> Table:
    """Table III: the θ sweep (lmgs with SE, LC and GR on, differing in its declared ``theta``)."""
    use = []
    for r in _lmgs_self(records):
        c = components_of(r)
        variant = r.method.variant or ""
        if c["se"] and c["lc"] and c["gr"] and (not variant or variant.startswith("theta")):
            use.append(r)
    cols = [Column("se_points", "Points enhanced", "se_points", "text"), *metric_columns(with_custom_keys(metrics, use))]
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


def _landmark_source(r: Record) -> str:
    """Where a record's guiding landmarks came from (``train.landmark_source``): ``subject`` (the per-subject
    predictor, the default, which the config leaves out, as it does when nothing reads the landmarks),
    ``generic`` or ``generic-tuned`` (the generic lip model's mouth)."""
    return str((r.config.get("train") or {}).get("landmark_source", "subject"))


def _ablation_label(r: Record, full_frontend: str | None = None, full_gr: tuple | None = None,
                    full_cap: float | None = None) -> str:
    """The row of Table IV: the audio rows of the paper, then what of SE / LC / GR is off, then what else differs
    from the full model (SE's cap, the mouth state, where the guiding landmarks come from, their folds, GR's form)."""
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
    if c.get("mouth_state"):
        parts.append("Mouth state read by the deformations")
    source = _landmark_source(r)
    if source != "subject":
        parts.append("Mouth from the generic lip model" + (", fine-tuned on the subject" if source == "generic-tuned" else ""))
    folds = c["landmark_folds"]
    if folds:
        parts.append(f"Training landmarks out of fold ({folds} folds)")
    form = _gr_form(r)
    if c["gr"] and form != (full_gr or ("sum", 1e-4)):  # GR in another form than the full model's
        parts.append("GR as the paper writes it (normal term summed, λ_N = {1:g})".format(*form) if form[0] == "sum"
                     else "GR, normal term per pixel ({0}, λ_N = {1:g})".format(*form))
    if parts:
        return ", ".join(parts)
    return "Full model" if not is_variant(r) else (r.method.display_name or r.method.name)


def _full_model(row: Row) -> bool:
    """Is this Table IV's full-model row (its label carries the config hash where two configs share the name)?"""
    return row.label == "Full model" or row.label.startswith("Full model [")


def table_ablation(records: Sequence[Record], metrics: Sequence[str] = ("lmd", "lpips", "lse_d", "lse_c")) -> Table:
    """Table IV: component ablation (SE / LC / GR as ✓/✗) at the full model's θ; Full model last."""
    cols = [Column("se", "SE", "se", "text"), Column("lc", "LC", "lc", "text"), Column("gr", "GR", "gr", "text")]
    cols += metric_columns(with_custom_keys(metrics, _lmgs_self(records)))
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
        rows = sorted(make_rows(recs, label=label), key=lambda row: (_full_model(row), order.get(row.label, 5), row.label))
        for row in rows:
            fill_row(row, cols)
            c = components_of(row.records[0])
            for cid in ("se", "lc", "gr"):
                row.cells[cid] = Cell(text="✓" if c[cid] else "✗")
            row.rule_before = _full_model(row)
        sec = Section(f"{subject_title(recs)}, θ = {theta:g}", rows)
        rank_section(sec, cols)
        sections.append(sec)
    used = [r for s in sections for row in s.rows for r in row.records]
    return Table("table4_ablation", "Table IV: component ablation", cols, sections,
                 common_notes(used, cols, methods=False), label_header="Setting")


def all_tables(records: Sequence[Record]) -> list[Table]:
    """Every table that has rows in ``records`` (Table I first)."""
    tables = [table_self(records), table_cross(records), table_theta(records), table_ablation(records),
              table_calibration(records)]
    stress_metrics = sorted({k for r in records if r.protocol.name == "stress" for k in r.metrics if k in METRICS})
    tables += [table_stability(records, m) for m in stress_metrics]
    tables.append(table_status(records))
    return [t for t in tables if not t.is_empty()]

