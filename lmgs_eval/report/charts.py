"""Speed-accuracy charts and the stability heat-map, pure functions of result records.

* rendering FPS (log x) against LPIPS, LMD and LSE-C, and training time against PSNR:
  one marker per method x subject (mean over seeds, from the self-driven records), colour
  by family, the Pareto front drawn (:func:`pareto_front`), each point labelled;
* a heat-map of the change of a metric under each stress condition (methods x conditions);
* a contact sheet of the self-driven renders per subject (methods x frames, from the videos
  the records point to, where they are on this machine), to look at what the numbers score.

Output is deterministic (Agg backend, fixed fonts, no dates or software tags in the
files, a fixed SVG hash salt), so regenerating from the same store gives the same bytes.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lmgs_eval.data.frames import FrameFile
from lmgs_eval.report.capacity import budget_means, failed_points, knee, points_from_records, tolerance_text
from lmgs_eval.report.cells import by_subject, cost_cell, is_ok, is_variant, make_rows, metric_cell
from lmgs_eval.report.table_model import METRICS
from lmgs_eval.report.tables import table_stability
from lmgs_eval.results.types import Record

FAMILY_COLOURS = {"2D": "#8c564b", "NeRF": "#1f77b4", "3DGS": "#2ca02c", "external": "#9467bd",
                  "ground-truth": "#7f7f7f", "control": "#d62728"}
_RC = {"svg.hashsalt": "lmgs-eval", "svg.fonttype": "path", "font.family": "DejaVu Sans", "font.size": 9,
       "figure.dpi": 100}

# (file stem, x cost key, x label, log x, x higher is better, y metric key)
SPEED_CHARTS = (
    ("speed_lpips", "fps", "rendering FPS (log)", True, True, "lpips"),
    ("speed_lmd", "fps", "rendering FPS (log)", True, True, "lmd"),
    ("speed_lse_c", "fps", "rendering FPS (log)", True, True, "lse_c"),
    ("train_psnr", "train_seconds", "training time (min, log)", True, False, "psnr"),
)


def pareto_front(xs: Sequence[float], ys: Sequence[float], x_higher: bool = True, y_higher: bool = True) -> list[int]:
    """Indices of the points no other point dominates, ordered by x.

    A point dominates another when it is at least as good on both axes and strictly better
    on one (``x_higher`` / ``y_higher`` give the good direction of each axis).

    Args:
        xs, ys: coordinates (same length).
        x_higher, y_higher: whether larger is better on each axis.

    Returns:
        Indices into ``xs`` of the non-dominated points, sorted by increasing x.
    """
    x = np.asarray(xs, np.float64) * (1 if x_higher else -1)
    y = np.asarray(ys, np.float64) * (1 if y_higher else -1)
    keep = []
    for i in range(x.size):
        dominated = np.any((x >= x[i]) & (y >= y[i]) & ((x > x[i]) | (y > y[i])))
        if not dominated:
            keep.append(i)
    return sorted(keep, key=lambda i: (float(xs[i]), float(ys[i])))


def _points(records: Sequence[Record], cost_key: str, metric: str) -> list[dict[str, Any]]:
    use = [r for r in records if r.protocol.name == "self" and is_ok(r) and not is_variant(r)
           and r.method.family not in ("control", "ground-truth", "reference")]
    pts = []
    for subject, recs in by_subject(use).items():
        for row in make_rows(recs):
            c = cost_cell(row.records, cost_key)
            m = metric_cell(row.records, metric)
            if c.mean is None or m.mean is None or c.mean <= 0:
                continue
            x = c.mean / 60 if cost_key == "train_seconds" else c.mean
            label = row.label if len({r.subject.name for r in records}) == 1 else f"{row.label} / {subject}"
            pts.append({"x": x, "y": m.mean, "family": row.family, "label": label,
                        "backends": {b.split(" v")[0] for b in m.backends}})
    return pts


def _save(fig, stem: Path) -> list[Path]:
    png, svg = stem.with_suffix(".png"), stem.with_suffix(".svg")
    fig.savefig(png, dpi=120, metadata={"Software": None})
    fig.savefig(svg, metadata={"Date": None, "Creator": None})
    return [png, svg]


def _declutter(fig, ax, labels) -> None:
    """Move point labels apart so that none overlaps another (deterministic: greedy, top to bottom).

    A label that had to move is redrawn with a thin leader line to its point.
    """
    if len(labels) < 2:
        return
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    px_per_pt = fig.dpi / 72.0
    placed = []
    order = sorted(range(len(labels)), key=lambda i: (-labels[i].get_window_extent(renderer).y0, i))
    for i in order:
        a = labels[i]
        start = a.xyann
        dx, dy = start
        for _ in range(40):
            box = a.get_window_extent(renderer)
            if not any(box.overlaps(b) for b in placed):
                break
            dy -= (box.height + 1.0) / px_per_pt
            a.xyann = (dx, dy)
        if a.xyann != start:
            text, xy = a.get_text(), a.xy
            a.remove()
            a = ax.annotate(text, xy, textcoords="offset points", xytext=(dx, dy), fontsize=7,
                            arrowprops={"arrowstyle": "-", "color": "0.6", "lw": 0.5, "shrinkA": 0, "shrinkB": 3})
        placed.append(a.get_window_extent(renderer))


def speed_charts(records: Sequence[Record], out_dir: str | Path) -> list[Path]:
    """Write the four speed / training-time versus accuracy charts (PNG and SVG); returns the files.

    A chart with no point (no record has both numbers) is not written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for stem, cost_key, xlabel, logx, x_higher, metric in SPEED_CHARTS:
        pts = _points(records, cost_key, metric)
        if not pts:
            continue
        label, y_higher, _ = METRICS[metric]
        with matplotlib.rc_context(_RC):
            fig, ax = plt.subplots(figsize=(5.2, 3.8))
            for fam in sorted({p["family"] for p in pts}):
                sub = [p for p in pts if p["family"] == fam]
                ax.scatter([p["x"] for p in sub], [p["y"] for p in sub], s=36, color=FAMILY_COLOURS.get(fam, "k"),
                           label=fam, zorder=3)
            labels = [ax.annotate(p["label"], (p["x"], p["y"]), textcoords="offset points", xytext=(4, 4), fontsize=7)
                      for p in pts]
            front = pareto_front([p["x"] for p in pts], [p["y"] for p in pts], x_higher, y_higher)
            if len(front) > 1:
                ax.plot([pts[i]["x"] for i in front], [pts[i]["y"] for i in front], "--", color="0.4", lw=1,
                        label="Pareto front", zorder=2)
            if logx:
                ax.set_xscale("log")
                fmt = matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}")
                ax.xaxis.set_major_formatter(fmt)
                xs = [p["x"] for p in pts]
                # Within about a decade there is no major tick to label: label the minor ones.
                few = max(xs) / min(xs) < 20
                # (only the 2x and 5x minor ticks, so labels never run into each other; on a
                # very short axis, e.g. 38-46 FPS, there may be none of those: then label all)
                narrow = max(xs) / min(xs) < 2.5
                minor = matplotlib.ticker.FuncFormatter(
                    lambda v, _: f"{v:g}" if narrow or round(v / 10 ** np.floor(np.log10(v)), 6) in (2.0, 5.0) else "")
                ax.xaxis.set_minor_formatter(minor if few else matplotlib.ticker.NullFormatter())
            ax.margins(0.15)
            backends = sorted({b for p in pts for b in p["backends"]})
            warn = " (MIXED backends!)" if len(backends) > 1 else ""
            ax.set_xlabel(xlabel)
            # short backend names on the axis (the tables' footnotes carry the full ones)
            short = sorted({b.split("|")[0].split("(")[0] for b in backends})
            ax.set_ylabel(f"{label} {'↑' if y_higher else '↓'} [{', '.join(short)}]{warn}")
            ax.set_title(f"{label} against {'speed' if cost_key == 'fps' else 'training time'} (self-driven)")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7, loc="best")
            fig.tight_layout()
            _declutter(fig, ax, labels)
            written += _save(fig, out_dir / stem)
            plt.close(fig)
    return written


def stability_heatmap(records: Sequence[Record], out_dir: str | Path, metric: str = "lse_c") -> list[Path]:
    """Write ``stability_<metric>.png``: methods x stress conditions, colour = change from clean.

    Cells with failed runs are hatched and marked with the failure count. Nothing is written
    without stress records carrying ``metric``.
    """
    table = table_stability(records, metric)
    cols = [c for c in table.columns if c.kind == "metric"]
    rows = [(sec.title, row) for sec in table.sections for row in sec.rows]
    if not rows or not cols:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    grid = np.full((len(rows), len(cols)), np.nan)
    for i, (_, row) in enumerate(rows):
        for j, c in enumerate(cols):
            cell = row.cells.get(c.id)
            if cell is not None and cell.mean is not None:
                grid[i, j] = cell.mean
    label, hib, digits = METRICS[metric]
    lim = float(np.nanmax(np.abs(grid))) if np.isfinite(grid).any() else 1.0
    multi = len(table.sections) > 1
    with matplotlib.rc_context(_RC):
        fig, ax = plt.subplots(figsize=(1.2 + 1.1 * len(cols), 1.0 + 0.45 * len(rows)))
        # Better is green whatever the metric's direction.
        im = ax.imshow(grid, cmap="RdYlGn" if hib else "RdYlGn_r", vmin=-lim, vmax=lim, aspect="auto")
        for i, (_, row) in enumerate(rows):
            for j, c in enumerate(cols):
                cell = row.cells.get(c.id)
                text = "" if np.isnan(grid[i, j]) else f"{grid[i, j]:+.{digits}f}"
                if cell is not None and cell.text and "failed" in cell.text:
                    text = (text + "\n" if text else "") + "✗ " + cell.text.split(":")[0]
                    ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, hatch="//", color="0.3"))
                ax.text(j, i, text, ha="center", va="center", fontsize=7)
        ax.set_xticks(range(len(cols)), [c.label for c in cols], rotation=30, ha="right")
        ax.set_yticks(range(len(rows)), [f"{row.label} / {t}" if multi else row.label for t, row in rows])
        fig.colorbar(im, ax=ax, label=f"Δ {label} from clean")
        ax.set_title(f"Stability: change of {label} {'↑' if hib else '↓'} under stress")
        fig.tight_layout()
        png = out_dir / f"stability_{metric}.png"
        fig.savefig(png, dpi=120, metadata={"Software": None})
        plt.close(fig)
    return [png]


def capacity_charts(records: Sequence[Record], out_dir: str | Path) -> list[Path]:
    """``capacity_<subject>.png/svg``: quality and cost against the Gaussian count, the knee marked.

    One column per quantity (PSNR, LPIPS, LMD, FPS, MB, training minutes), x = the final number
    of Gaussians (log); a dashed line at the knee (:func:`lmgs_eval.report.capacity.knee`) and a
    dotted one at the count of the ``lmgs`` self-driven run (the quick preset's default).
    """
    per_subject = points_from_records(records)
    failed = failed_points(records)
    if not per_subject:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    panels = (("psnr", "PSNR (dB) ↑", 1), ("lpips", "LPIPS ↓", 1), ("lmd", "LMD (px) ↓", 1),
              ("fps", "FPS ↑", 1), ("model_mb", "model MB ↓", 1), ("train_seconds", "training min ↓", 1 / 60))
    files = []
    for subject, pts in sorted(per_subject.items()):
        mean = budget_means(pts)
        k_pt = knee(mean)
        default = [r.cost.n_gaussians for r in records if r.protocol.name == "self"
                   and r.method.name == "lmgs" and r.subject.name == subject and r.cost.n_gaussians]
        with matplotlib.rc_context(_RC):
            fig, axes = plt.subplots(1, len(panels), figsize=(2.6 * len(panels), 2.8))
            sbs = all(q.get("fps_side_by_side") for q in pts)
            for ax, (key, label, scale) in zip(axes, panels):
                if key == "fps":
                    label = "FPS, side by side ↑" if sbs else "FPS, per run ↑"
                xs = [r["n_gaussians"] or r["budget"] for r in mean if r.get(key) is not None]
                ys = [r[key] * scale for r in mean if r.get(key) is not None]
                ax.plot(xs, ys, "o-", color=FAMILY_COLOURS["3DGS"])
                ax.set_xscale("log")
                # ticks at the measured counts only: a range under a decade otherwise gets
                # overlapping minor-tick labels
                ax.xaxis.set_major_locator(FixedLocator(xs))
                ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v / 1000:.1f}k" if v >= 1000 else f"{v:.0f}"))
                ax.xaxis.set_minor_formatter(NullFormatter())
                ax.set_title(label)
                ax.set_xlabel("Gaussians (log)")
                if k_pt is not None:
                    ax.axvline(k_pt["n_gaussians"] or k_pt["budget"], color="0.3", ls="--", lw=1)
                if default:
                    ax.axvline(float(np.mean(default)), color="#d62728", ls=":", lw=1)
            fails = sorted({f["budget"] for f in failed.get(subject, [])})
            extra = f"; training failed at budget {', '.join(map(str, fails))}" if fails else ""
            fig.suptitle(f"{subject}: capacity (dashed: knee, {tolerance_text()}; dotted: quick default{extra})", fontsize=8)
            fig.tight_layout()
            files += _save(fig, out_dir / f"capacity_{subject}")
            plt.close(fig)
    return files


def all_charts(records: Sequence[Record], out_dir: str | Path) -> list[Path]:
    """Every chart the records allow: speed charts, one heat-map per stressed metric, capacity."""
    files = speed_charts(records, out_dir) + capacity_charts(records, out_dir)
    stressed = sorted({k for r in records if r.protocol.name == "stress" for k in r.metrics if k in METRICS})
    for m in stressed:
        files += stability_heatmap(records, out_dir, m)
    return files


SHEET_FRAMES = 5
"""Test frames per method on a render contact sheet (evenly spaced over the clip)."""


def render_sheets(records: Sequence[Record], root: str | Path, out_dir: str | Path,
                  frames: int = SHEET_FRAMES) -> list[Path]:
    """``renders_<subject>.png``: per subject, ground truth then each method's self-driven render
    (its lowest seed), ``frames`` test frames each, labelled with the method and its PSNR.

    Renders are read from store ``root`` (``artefacts.render.path``); a record whose video is
    not on this machine (made elsewhere) is left out and the sheet says how many were. The
    ablation variants of Tables III / IV are left out too: the sheet is of the compared methods.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    root, out_dir = Path(root), Path(out_dir)
    by_subject: dict[str, dict[str, Record]] = {}
    for r in records:
        if r.protocol.name != "self" or not is_ok(r) or is_variant(r) or r.method.family == "reference":
            continue
        row = by_subject.setdefault(r.subject.name, {})
        name = r.method.name
        if name not in row or r.seed < row[name].seed:
            row[name] = r
    files = []
    for subject in sorted(by_subject):
        rows, missing = [], 0
        order = sorted(by_subject[subject].values(), key=lambda r: (r.method.family != "ground-truth",
                                                                   r.method.family, r.method.display_name))
        for r in order:
            art = r.artefacts.get("render")
            path = root / art.path if art else None
            if path is None or not path.is_file():
                missing += 1
                continue
            video = FrameFile(path).read()
            pick = np.unique(np.linspace(0, len(video) - 1, frames).round().astype(int))
            psnr = r.value("psnr")
            label = r.method.display_name + (f"\nseed {r.seed}" if r.method.family != "ground-truth" else "")
            if isinstance(psnr, (int, float)) and r.method.family != "ground-truth":
                label += f", {psnr:.2f} dB"
            rows.append((label, np.concatenate([video[i].astype(np.float32) / 255.0 for i in pick], 1)))
        if not rows:
            continue
        h, w = rows[0][1].shape[:2]
        fig_w, fig_h = w / 100 + 1.6, len(rows) * (h / 100 + 0.05) + 0.3
        with matplotlib.rc_context(_RC):
            fig, axes = plt.subplots(len(rows), 1, figsize=(fig_w, fig_h), squeeze=False)
            for ax, (label, strip) in zip(axes[:, 0], rows):
                ax.imshow(np.clip(strip, 0, 1), interpolation="nearest")
                ax.set_xticks([])
                ax.set_yticks([])
                ax.set_ylabel(label, rotation=0, ha="right", va="center", fontsize=8)
            title = f"{subject}: self-driven test renders, frames evenly spaced"
            if missing:
                title += f" ({missing} method(s) rendered on another machine: not shown)"
            fig.suptitle(title, fontsize=9, y=1 - 0.06 / fig_h, va="top")
            fig.subplots_adjust(left=1.5 / fig_w, right=0.99, top=1 - 0.3 / fig_h, bottom=0.005, hspace=0.04)
            stem = out_dir / f"renders_{subject}"
            out_dir.mkdir(parents=True, exist_ok=True)
            png = stem.with_suffix(".png")
            fig.savefig(png, dpi=100, metadata={"Software": None})
            plt.close(fig)
        files.append(png)
    return files
