"""Interactive speed-accuracy charts as inline SVG: one point per method x subject, the Pareto front,
labels moved apart so none overlaps another, and a hover card naming the runs and config hashes.

The points are the tables' cells (:func:`lmgs_eval.report.cells.metric_cell` / ``cost_cell``:
the mean over seeds of the self-driven records), the front is
:func:`lmgs_eval.report.charts.pareto_front`; the static PNG / SVG of the same chart is written
by :mod:`lmgs_eval.report.charts` beside it for papers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from html import escape
from typing import Any

from lmgs_eval.report.capacity import budget_means, knee, points_from_records, tolerance_text
from lmgs_eval.report.cells import by_subject, cost_cell, is_ok, is_variant, make_rows, metric_cell
from lmgs_eval.report.charts import FAMILY_COLOURS, SPEED_CHARTS, pareto_front
from lmgs_eval.report.table_model import METRICS
from lmgs_eval.results.types import Record

W, H = 720, 420
LEFT, RIGHT, TOP, BOTTOM = 64, 120, 20, 46
CHAR_W, LINE_H = 7.5, 13.5  # label box estimate at font-size 12.5px (DejaVu Sans)


def chart_points(records: Sequence[Record], cost_key: str, metric: str,
                 run_ids: dict[int, str]) -> list[dict[str, Any]]:
    """One point per (subject, method, config): x the cost, y the metric, with the runs behind it."""
    use = [r for r in records if r.protocol.name == "self" and is_ok(r) and not is_variant(r)
           and r.method.family not in ("control", "ground-truth", "reference")]
    pts = []
    multi = len({r.subject.name for r in use}) > 1
    for subject, recs in by_subject(use).items():
        for row in make_rows(recs):
            c, m = cost_cell(row.records, cost_key), metric_cell(row.records, metric)
            if c.mean is None or m.mean is None or c.mean <= 0:
                continue
            x = c.mean / 60 if cost_key == "train_seconds" else c.mean
            pts.append({"x": x, "y": m.mean, "family": row.family, "subject": subject,
                        "label": f"{row.label} / {subject}" if multi else row.label,
                        "runs": [run_ids.get(id(r), "") for r in row.records],
                        "config_hash": row.records[0].config_hash, "seeds": len(row.records),
                        "backends": sorted(m.backends)})
    return pts


def _ticks_log(lo: float, hi: float) -> list[float]:
    out = []
    for e in range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1):
        for k in (1, 2, 5):
            v = k * 10 ** e
            if lo <= v <= hi:
                out.append(v)
    return out or [lo, hi]


def _ticks_lin(lo: float, hi: float, n: int = 5) -> list[float]:
    span = hi - lo or abs(hi) or 1.0
    step = 10 ** math.floor(math.log10(span / n))
    for k in (1, 2, 5, 10):
        if span / (k * step) <= n:
            step *= k
            break
    start = math.ceil(lo / step) * step
    return [start + i * step for i in range(int((hi - start) / step + 1e-9) + 1)]


def _place_labels(anchors: list[tuple[float, float]], texts: list[str]) -> list[tuple[float, float]]:
    """Greedy, deterministic: each label right of its point, moved down (then up) until it overlaps no other."""
    # the points themselves are obstacles too: a label never covers another method's marker
    boxes: list[tuple[float, float, float, float]] = [(x - 6, y - 6, x + 6, y + 6) for x, y in anchors]
    right = W - RIGHT - 2
    out = [(0.0, 0.0)] * len(texts)
    order = sorted(range(len(texts)), key=lambda i: (anchors[i][1], anchors[i][0]))
    for i in order:
        ax, ay = anchors[i]
        w = CHAR_W * len(texts[i])
        x = ax + 8
        if x + w > right:  # no room on the right: put it on the left of the point
            x = max(LEFT + 2, ax - 8 - w)
        for k in range(60):
            dy = (k // 2 + 1) * (LINE_H + 1) * (1 if k % 2 == 0 else -1) if k else 0.0
            y = ay - 3 + dy
            box = (x, y - LINE_H + 2, x + w, y + 2)
            others = boxes[:i] + boxes[i + 1:]  # all but its own point
            if not any(box[0] < b[2] and b[0] < box[2] and box[1] < b[3] and b[1] < box[3] for b in others) \
                    and TOP <= box[1] and box[3] <= H - BOTTOM:
                break
        boxes.append(box)
        out[i] = (x, y)
    return out


def speed_svg(points: list[dict[str, Any]], xlabel: str, ylabel: str, logx: bool, x_higher: bool,
              y_higher: bool, chart_id: str) -> str:
    """An inline ``<svg>`` scatter: axes with ticks, points coloured by family, Pareto front dashed,
    labels placed apart (a thin leader line when moved), ``data-*`` attributes for the hover card."""
    xs, ys = [p["x"] for p in points], [p["y"] for p in points]
    x0, x1 = min(xs), max(xs)
    y0, y1 = min(ys), max(ys)
    if logx:
        lx0, lx1 = math.log10(x0), math.log10(x1)
        pad = max(0.08 * (lx1 - lx0), 0.05)
        lx0, lx1 = lx0 - pad, lx1 + pad
        sx = lambda v: LEFT + (math.log10(v) - lx0) / (lx1 - lx0) * (W - LEFT - RIGHT)  # noqa: E731
        xt = _ticks_log(10 ** lx0, 10 ** lx1)
    else:
        pad = max(0.08 * (x1 - x0), 1e-9)
        x0, x1 = x0 - pad, x1 + pad
        sx = lambda v: LEFT + (v - x0) / (x1 - x0) * (W - LEFT - RIGHT)  # noqa: E731
        xt = _ticks_lin(x0, x1)
    ypad = max(0.1 * (y1 - y0), 1e-6 * max(abs(y1), 1.0))
    y0, y1 = y0 - ypad, y1 + ypad
    sy = lambda v: TOP + (y1 - v) / (y1 - y0) * (H - TOP - BOTTOM)  # noqa: E731
    yt = _ticks_lin(y0, y1)
    digits = max(0, -math.floor(math.log10(max(yt[1] - yt[0], 1e-12)))) if len(yt) > 1 else 3
    out = [f'<svg class="chart" id="{chart_id}" viewBox="0 0 {W} {H}" width="{W}" height="{H}" role="img" '
           f'aria-label="{escape(ylabel)} against {escape(xlabel)}">',
           f'<rect x="{LEFT}" y="{TOP}" width="{W - LEFT - RIGHT}" height="{H - TOP - BOTTOM}" class="plot"/>']
    for v in xt:
        x = sx(v)
        out.append(f'<line x1="{x:.1f}" y1="{TOP}" x2="{x:.1f}" y2="{H - BOTTOM}" class="grid"/>'
                   f'<text x="{x:.1f}" y="{H - BOTTOM + 14}" class="tick" text-anchor="middle">{v:g}</text>')
    for v in yt:
        y = sy(v)
        out.append(f'<line x1="{LEFT}" y1="{y:.1f}" x2="{W - RIGHT}" y2="{y:.1f}" class="grid"/>'
                   f'<text x="{LEFT - 5}" y="{y + 4:.1f}" class="tick" text-anchor="end">{v:.{digits}f}</text>')
    out.append(f'<text x="{(LEFT + W - RIGHT) / 2:.0f}" y="{H - 8}" class="axis" text-anchor="middle">{escape(xlabel)}</text>')
    out.append(f'<text transform="translate(14 {(TOP + H - BOTTOM) / 2:.0f}) rotate(-90)" class="axis" '
               f'text-anchor="middle">{escape(ylabel)}</text>')
    front = pareto_front(xs, ys, x_higher, y_higher)
    if len(front) > 1:
        path = " ".join(f"{sx(xs[i]):.1f},{sy(ys[i]):.1f}" for i in front)
        out.append(f'<polyline points="{path}" class="front"><title>Pareto front: no other point is better on '
                   f'both axes</title></polyline>')
    anchors = [(sx(p["x"]), sy(p["y"])) for p in points]
    places = _place_labels(anchors, [p["label"] for p in points])
    for i, p in enumerate(points):
        ax, ay = anchors[i]
        lx, ly = places[i]
        on_front = i in front
        info = (f"{p['label']} ({p['subject']}): {ylabel.split(' [')[0]} {p['y']:.4g}, {xlabel.split(' (')[0]} {p['x']:.4g}; "
                f"{p['seeds']} run(s); config {p['config_hash']}; runs: {', '.join(p['runs'])}")
        colour = FAMILY_COLOURS.get(p["family"], "#333")
        if abs(ly + 3 - ay) > 1.0 or lx < ax:
            edge = lx + CHAR_W * len(p["label"]) if lx < ax else lx
            out.append(f'<line x1="{ax:.1f}" y1="{ay:.1f}" x2="{edge:.1f}" y2="{ly - 4:.1f}" class="leader"/>')
        out.append(f'<g class="pt{" on-front" if on_front else ""}" data-family="{escape(p["family"])}" '
                   f'data-info="{escape(info)}" data-run="{escape(p["runs"][0] if p["runs"] else "")}" tabindex="0">'
                   f'<circle cx="{ax:.1f}" cy="{ay:.1f}" r="5" fill="{colour}"/>'
                   f'<text x="{lx:.1f}" y="{ly:.1f}" class="lbl">{escape(p["label"])}</text>'
                   f'<title>{escape(info)}</title></g>')
    fams = sorted({p["family"] for p in points})
    for k, fam in enumerate(fams + (["Pareto front"] if len(front) > 1 else [])):
        y = TOP + 10 + 16 * k
        x = W - RIGHT + 12
        if fam == "Pareto front":
            out.append(f'<line x1="{x - 4}" y1="{y}" x2="{x + 8}" y2="{y}" class="front"/>')
        else:
            out.append(f'<circle cx="{x + 2}" cy="{y}" r="5" fill="{FAMILY_COLOURS.get(fam, "#333")}"/>')
        out.append(f'<text x="{x + 14}" y="{y + 4}" class="legend">{escape(fam)}</text>')
    out.append("</svg>")
    return "".join(out)


def speed_charts_svg(records: Sequence[Record], run_ids: dict[int, str]) -> list[dict[str, str]]:
    """Every speed / training-time chart the records allow: ``{id, title, svg, static}`` (static: the PNG's stem)."""
    out = []
    for stem, cost_key, xlabel, logx, x_higher, metric in SPEED_CHARTS:
        for subject, recs in by_subject(records).items():  # one chart per subject: its labels stay readable
            pts = chart_points(recs, cost_key, metric, run_ids)
            if not pts:
                continue
            label, y_higher, _ = METRICS[metric]
            backends = sorted({b.split(" v")[0].split("|")[0].split("(")[0] for p in pts for b in p["backends"]})
            ylabel = f"{label} {'↑' if y_higher else '↓'} [{', '.join(backends)}]"
            title = (f"{subject}: {label} against {'rendering speed' if cost_key == 'fps' else 'training time'} "
                     "(self-driven)")
            out.append({"id": f"{stem}-{subject}", "title": title, "static": stem, "subject": subject,
                        "svg": speed_svg(pts, xlabel, ylabel, logx, x_higher, y_higher, f"chart-{stem}-{subject}")})
    return out


CAPACITY_PANELS = (("psnr", "PSNR (dB) ↑"), ("lpips", "LPIPS ↓"), ("lmd", "LMD (px) ↓"), ("fps", "FPS ↑"))
PW, PH, PL, PB, PT = 300, 210, 52, 36, 22  # a capacity panel: size and margins


def _capacity_panel(mean: list[dict[str, Any]], key: str, label: str, knee_x: float | None,
                    info: dict[int, tuple[str, str]]) -> str:
    pts = [(p["n_gaussians"] or p["budget"], p[key], p["budget"]) for p in mean if p.get(key) is not None]
    if not pts:
        return ""
    xs, ys = [p[0] for p in pts], [p[1] for p in pts]
    lx0, lx1 = math.log10(min(xs)), math.log10(max(xs))
    pad = max(0.08 * (lx1 - lx0), 0.05)
    lx0, lx1 = lx0 - pad, lx1 + pad
    y0, y1 = min(ys), max(ys)
    ypad = max(0.12 * (y1 - y0), 1e-6 * max(abs(y1), 1.0))
    y0, y1 = y0 - ypad, y1 + ypad
    sx = lambda v: PL + (math.log10(v) - lx0) / (lx1 - lx0) * (PW - PL - 8)  # noqa: E731
    sy = lambda v: PT + (y1 - v) / (y1 - y0) * (PH - PT - PB)  # noqa: E731
    yt = _ticks_lin(y0, y1, 4)
    digits = max(0, -math.floor(math.log10(max(yt[1] - yt[0], 1e-12)))) if len(yt) > 1 else 3
    out = [f'<svg class="chart cap" viewBox="0 0 {PW} {PH}" width="{PW}" height="{PH}" role="img" aria-label="{escape(label)}">',
           f'<text x="{PW / 2:.0f}" y="14" class="axis" text-anchor="middle">{escape(label)}</text>',
           f'<rect x="{PL}" y="{PT}" width="{PW - PL - 8}" height="{PH - PT - PB}" class="plot"/>']
    for v in yt:
        out.append(f'<text x="{PL - 4}" y="{sy(v) + 4:.1f}" class="tick" text-anchor="end">{v:.{digits}f}</text>'
                   f'<line x1="{PL}" y1="{sy(v):.1f}" x2="{PW - 8}" y2="{sy(v):.1f}" class="grid"/>')
    for x in xs:
        out.append(f'<text x="{sx(x):.1f}" y="{PH - PB + 14}" class="tick" text-anchor="middle">'
                   f'{x / 1000:.1f}k</text>' if x >= 1000 else
                   f'<text x="{sx(x):.1f}" y="{PH - PB + 14}" class="tick" text-anchor="middle">{x:.0f}</text>')
    out.append(f'<text x="{(PL + PW) / 2:.0f}" y="{PH - 4}" class="tick" text-anchor="middle">Gaussians (log)</text>')
    if knee_x is not None:
        out.append(f'<line x1="{sx(knee_x):.1f}" y1="{PT}" x2="{sx(knee_x):.1f}" y2="{PH - PB}" class="front">'
                   f'<title>knee: {escape(tolerance_text())}</title></line>')
    out.append(f'<polyline points="{" ".join(f"{sx(x):.1f},{sy(y):.1f}" for x, y, _ in pts)}" class="capline"/>')
    for x, y, b in pts:
        about, first = info.get(b, ("", ""))
        text = f"{label.split(' ')[0]} {y:.4g} at {x:.0f} Gaussians; {about}"
        out.append(f'<g class="pt" data-info="{escape(text)}" data-run="{escape(first)}" '
                   f'tabindex="0"><circle cx="{sx(x):.1f}" cy="{sy(y):.1f}" r="4.5" fill="{FAMILY_COLOURS["3DGS"]}"/>'
                   f'<title>{escape(text)}</title></g>')
    out.append("</svg>")
    return "".join(out)


def capacity_svgs(records: Sequence[Record], run_ids: dict[int, str]) -> list[dict[str, str]]:
    """Per subject of the capacity protocol, small panels of quality and speed against the Gaussian count
    (mean over seeds per budget, :func:`lmgs_eval.report.capacity.budget_means`), the knee dashed,
    a hover card per budget with its runs and config hashes."""
    out = []
    for subject, pts in sorted(points_from_records(records).items()):
        mean = budget_means(pts)
        k = knee(mean)
        info: dict[int, tuple[str, str]] = {}
        for b in {p["budget"] for p in pts}:
            recs = [r for r in records if r.protocol.name == "capacity" and r.subject.name == subject
                    and r.protocol.clip == f"budget-{b}" and is_ok(r)]
            ids = [run_ids.get(id(r), "") for r in recs]
            info[b] = (f"budget {b}, {len(recs)} seed(s), config {', '.join(sorted({r.config_hash for r in recs}))}; "
                       f"runs: {', '.join(ids)}", ids[0] if ids else "")
        kx = (k["n_gaussians"] or k["budget"]) if k is not None else None
        panels = [_capacity_panel(mean, key, label, kx, info) for key, label in CAPACITY_PANELS]
        out.append({"subject": subject, "svg": "".join(p for p in panels if p),
                    "knee": None if k is None else f"{kx:.0f} Gaussians (budget {k['budget']})"})
    return out
