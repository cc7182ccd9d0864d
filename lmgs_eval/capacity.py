"""How small a model each scene needs (issue 8): ``lmgs`` trained at a range of Gaussian budgets.

Each budget is a run of the self-driven protocol recorded under protocol ``capacity`` with
clip ``budget-<N>`` (the budget is set through ``train.budget_density = N / face area``, so
the config hash changes with it). The *knee* is the smallest budget whose quality is within
:data:`TOLERANCE` of the best budget on every quality metric.
"""

from __future__ import annotations

from typing import Any, Sequence

from lmgs_eval.protocols import RunConfig, log

DEFAULT_BUDGETS = (500, 1000, 2000, 5000, 10000, 20000)
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


def points_from_records(records: Sequence[dict]) -> dict[str, list[dict[str, Any]]]:
    """Per subject, one point per capacity record: budget, count, quality and cost."""
    out: dict[str, list[dict[str, Any]]] = {}
    for r in records:
        if r["protocol"]["name"] != "capacity" or (r.get("status") or {}).get("state") == "failed":
            continue
        m, c = r["metrics"], r.get("cost") or {}
        out.setdefault(r["subject"]["name"], []).append({
            "budget": int(r["protocol"]["clip"].split("-", 1)[1]), "n_gaussians": c.get("n_gaussians"),
            "psnr": m.get("psnr", {}).get("value"), "lpips": m.get("lpips", {}).get("value"),
            "lmd": m.get("lmd", {}).get("value"), "fps": c.get("fps"), "model_mb": c.get("model_mb"),
            "train_seconds": c.get("train_seconds"), "seed": r["seed"]})
    return out


def run_capacity(cfg: RunConfig, budgets: Sequence[int] = DEFAULT_BUDGETS) -> list[dict]:
    """Train ``lmgs`` at each budget on the subject, score it, record it (resumable)."""
    from lmgs.init import face_area_px
    from lmgs.strategy import budget_from_face_area
    from lmgs_eval import results as store
    from lmgs_eval.data.registry import find_subject
    from lmgs_eval.methods import create_method, driving_from_subject, subject_to_clip
    from lmgs_eval.protocols import fit_render_score

    subject = find_subject(cfg.subject, cfg.data_root, progress=cfg.progress)
    train = subject_to_clip(subject, subject.train_ids, progress=cfg.progress)
    test = subject_to_clip(subject, subject.test_ids, progress=cfg.progress)
    driving = driving_from_subject(subject, subject.test_ids, test)
    area = face_area_px(train)
    base = dict(cfg.method_options.get("overrides", {}))
    probe = create_method("lmgs", **{**cfg.method_options, "preset": cfg.preset})
    density = probe.cfg.train.budget_density
    default = budget_from_face_area(area, density)
    budgets = sorted(set(budgets) | {default})  # the preset's own budget is always a point (same config: reused)
    log(f"capacity on {subject.name}: face area {area:.0f} px; budgets {', '.join(map(str, budgets))} "
        f"(default {default} = {density:g} x face area)")
    records = []
    for n in budgets:
        for seed in cfg.seeds:
            over = {**base} if n == default else {**base, "train.budget_density": round(n / area, 6)}
            opts = {**{k: v for k, v in cfg.method_options.items() if k != "overrides"}, "overrides": over, "preset": cfg.preset}
            method = create_method("lmgs", **opts)
            info = method.describe()
            clip = f"budget-{n}"
            if not cfg.force and store.find_record(cfg.results, info.name, subject.name, "capacity", clip, seed, info.config_hash):
                log(f"budget {n} seed {seed}: already in {cfg.results}; skipped")
                continue
            records.append(fit_render_score(cfg, method, subject, seed, train, driving, test.frames,
                                            f"renders/{subject.name}/capacity/lmgs-{clip}-seed{seed}.mp4", "capacity", clip))
    return records
