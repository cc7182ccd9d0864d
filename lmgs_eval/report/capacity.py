"""Capacity curves from records: quality and cost against the Gaussian budget, and the knee.

The *knee* is the smallest budget whose quality is within :data:`TOLERANCE` of the best
budget on every quality metric, taken on the mean over seeds per budget (:func:`budget_means`).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from lmgs_eval.results.types import Record

# (metric, higher is better, kind, amount): within `amount` of the best, absolute or relative.
TOLERANCE = (("psnr", True, "abs", 0.3), ("lpips", False, "rel", 0.05), ("lmd", False, "rel", 0.05))


def tolerance_text() -> str:
    parts = []
    for m, hib, kind, amt in TOLERANCE:
        parts.append(f"{m.upper()} {'>= best - ' if hib else '<= best + '}{amt:g}{' dB' if m == 'psnr' else ''}"
                     if kind == "abs" else f"{m.upper()} {'>=' if hib else '<='} best x {1 - amt if hib else 1 + amt:g}")
    return "; ".join(parts)


def knee(points: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """The smallest-budget point within :data:`TOLERANCE` of the best on every metric it has.

    ``points``: dicts with ``budget`` and metric values (None where missing).
    """
    pts = sorted(points, key=lambda p: p["budget"])
    if not pts:
        return None
    best = {}
    for m, hib, _, _ in TOLERANCE:
        vals = [p[m] for p in pts if p.get(m) is not None]
        if vals:
            best[m] = max(vals) if hib else min(vals)
    for p in pts:
        ok = True
        for m, hib, kind, amt in TOLERANCE:
            if m not in best or p.get(m) is None:
                continue
            b = best[m]
            lim = (b - amt if hib else b + amt) if kind == "abs" else (b * (1 - amt) if hib else b * (1 + amt))
            ok &= p[m] >= lim if hib else p[m] <= lim
        if ok:
            return p
    return pts[-1]


def budget_means(points: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One point per budget: each value the mean over that budget's seeds, with ``n_seeds``.

    The knee is taken on these (:func:`knee`), never on single seeds: on hopper the seed moves
    PSNR by 0.8 dB at a fixed budget, more than the tolerance.
    """
    by_budget: dict[int, list[dict[str, Any]]] = {}
    for p in points:
        by_budget.setdefault(p["budget"], []).append(p)
    out = []
    for b, ps in sorted(by_budget.items()):
        row: dict[str, Any] = {"budget": b, "n_seeds": len(ps)}
        for k in ("n_gaussians", "psnr", "lpips", "lmd", "fps", "model_mb", "train_seconds"):
            vals = [q[k] for q in ps if q.get(k) is not None]
            row[k] = float(np.mean(vals)) if vals else None
        out.append(row)
    return out


def _budget(rec: Record) -> int:
    """The Gaussian budget of a capacity record (its clip is ``budget-<N>``)."""
    return int(rec.protocol.clip.split("-", 1)[1])


def points_from_records(records: Sequence[Record]) -> dict[str, list[dict[str, Any]]]:
    """Per subject, one point per capacity record: budget, count, quality and cost.

    ``fps`` is the side-by-side figure only when every point of the subject was timed in one
    and the same side-by-side run (a later ``capacity --budget N`` re-times only the budgets
    it was given); otherwise every point uses its own run's FPS, so an axis never mixes them.
    """
    raw: dict[str, list[tuple[dict[str, Any], Any, Any, Any]]] = {}
    for r in records:
        if r.protocol.name != "capacity" or r.failed:
            continue
        c = r.cost
        point = {"budget": _budget(r), "n_gaussians": c.n_gaussians, "psnr": r.value("psnr"), "lpips": r.value("lpips"),
                 "lmd": r.value("lmd"), "model_mb": c.model_mb, "train_seconds": c.train_seconds, "seed": r.seed}
        raw.setdefault(r.subject.name, []).append((point, c.fps, c.fps_side_by_side, c.fps_side_by_side_run))
    out: dict[str, list[dict[str, Any]]] = {}
    for subject, rows in raw.items():
        side = all(sbs is not None for _, _, sbs, _ in rows) and len({run for *_, run in rows}) == 1
        out[subject] = [{**p, "fps": sbs if side else fps, "fps_side_by_side": side} for p, fps, sbs, _ in rows]
    return out


def failed_points(records: Sequence[Record]) -> dict[str, list[dict[str, Any]]]:
    """Per subject, the capacity runs that failed: ``{"budget", "seed", "reason"}``."""
    out: dict[str, list[dict[str, Any]]] = {}
    for r in records:
        if r.protocol.name == "capacity" and r.failed:
            out.setdefault(r.subject.name, []).append({"budget": _budget(r), "seed": r.seed, "reason": r.status.reason or ""})
    return out
