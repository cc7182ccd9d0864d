"""How small a model each scene needs: ``lmgs`` trained at a range of Gaussian budgets.

Each budget is a run of the self-driven protocol recorded under protocol ``capacity`` with
clip ``budget-<N>`` (the budget is set through ``train.budget_density = N / face area``, so
the config hash changes with it). The knee and the curves are read from the records
(:mod:`lmgs_eval.report.capacity`).
"""

from __future__ import annotations

import time
from typing import Any, Sequence

from lmgs.errors import TrainingDiverged
from lmgs.init import face_area_px
from lmgs.strategy import budget_from_face_area
from lmgs_eval import results as store
from lmgs_eval.convert import driving_from_clip, subject_to_clip
from lmgs_eval.data.registry import find_subject
from lmgs_eval.results.records import RunId, build_record, stored
from lmgs_eval.runner import RunConfig, build_method, fit_method, fit_render_score, head_of, log

DEFAULT_BUDGETS = (500, 1000, 2000, 5000, 10000, 20000)


def _failed_record(cfg: RunConfig, run: RunId, reason: str) -> store.Record:
    rec = build_record(run, split="test", n_frames=0, metrics={}, cost={}, artefacts={},
                       status={"state": "failed", "reason": reason[:500]})
    store.write_record(cfg.results, rec)
    return rec


def run_capacity(cfg: RunConfig, budgets: Sequence[int] = DEFAULT_BUDGETS) -> list[store.Record]:
    """Train ``lmgs`` at each budget on the subject, score it, record it (resumable)."""
    subject = find_subject(cfg.subject, cfg.data_root, progress=cfg.progress)
    train = subject_to_clip(subject, subject.train_ids, progress=cfg.progress)
    test = subject_to_clip(subject, subject.test_ids, progress=cfg.progress)
    driving = driving_from_clip(test)
    area = face_area_px(train)
    points = budget_overrides(cfg, subject, area, budgets)
    records, trained = [], []
    for n, over in points.items():
        for seed in cfg.seeds:
            method = build_method(cfg, "lmgs", subject, overrides=over)
            run = RunId(subject, method.describe(), seed, "capacity", f"budget-{n}")
            trained.append((n, seed, method))
            if not cfg.force and stored(cfg.results, run, finished=True):
                log(f"budget {n} seed {seed}: already in {cfg.results}; skipped")
                continue
            try:
                records.append(fit_render_score(cfg, method, run, train, driving, test.frames,
                                                f"{run.renders}/capacity/{run.stem}-{run.clip}.mp4"))
            except TrainingDiverged as exc:  # recorded as failed; the other budgets go on
                log(f"budget {n} seed {seed}: FAILED: {exc}")
                records.append(_failed_record(cfg, run, f"training diverged: {exc}"))
    retime_side_by_side(cfg, subject, train, driving, trained)
    return records


def budget_overrides(cfg: RunConfig, subject, area: float, budgets: Sequence[int]) -> dict[int, dict]:
    """The budgets a capacity run trains (those asked for, the default's, the preset's), each with its overrides."""
    base = dict(cfg.method_options.get("overrides", {}))
    density = build_method(cfg, "lmgs", subject).cfg.train.budget_density
    # the preset's (or the run's --set) density: the subject's method without its knee, so that every other
    # setting (recorded footage's, the lip weights it reads) is the subject's
    preset_density = build_method(cfg, "lmgs", subject, budget_density=None).cfg.train.budget_density
    default = budget_from_face_area(area, density)
    # Budgets that are a density of their own (the preset's, the subject's knee) are trained at
    # exactly that density, so their configs, and trained models, are those of the other protocols.
    preset_budget = budget_from_face_area(area, preset_density)
    exact = {preset_budget: preset_density, default: density}
    budgets = sorted(set(budgets) | set(exact))  # the default (and the preset's) budget is always a point
    why = "" if density == preset_density else f", this subject's knee; the preset's {preset_density:g} gives {preset_budget}"
    log(f"capacity on {subject.name}: face area {area:.0f} px; budgets {', '.join(map(str, budgets))} "
        f"(default {default} = {density:g} x face area{why})")
    # the default as every other protocol builds it; any other budget at its density
    return {n: ({**base} if n == default else {**base, "train.budget_density": exact.get(n, round(n / area, 6))})
            for n in budgets}


SIDE_BY_SIDE_ROUNDS = 3
SIDE_BY_SIDE_FRAMES = 100


def retime_side_by_side(cfg: RunConfig, subject, train, driving, trained: Sequence[tuple[int, int, Any]],
                        rounds: int = SIDE_BY_SIDE_ROUNDS, frames: int = SIDE_BY_SIDE_FRAMES) -> dict[tuple[int, int], float]:
    """Time every budget's model in one run, round-robin, and write the FPS into its record.

    Each record's own ``fps`` was measured when that budget was trained, possibly hours
    apart on a shared machine (the same model measured 41.5 and 26.0 FPS in two sittings
    on one host), so a curve of those is partly a curve of the host's load. Here every
    model (reloaded from its checkpoint, nothing retrained) renders the same first
    ``frames`` test frames once per round, budgets interleaved, for ``rounds`` rounds; the
    best round per model gives ``cost.fps_side_by_side``, which the capacity chart uses.

    Returns ``{(budget, seed): fps}``.
    """
    clip = head_of(driving, frames)
    n = clip.n_frames
    recorded, away = [], set()
    for budget, seed, method in trained:
        run = RunId(subject, method.describe(), seed, "capacity", f"budget-{budget}")
        rec = stored(cfg.results, run, finished=True)
        if rec is not None:
            recorded.append((budget, run, method, rec))
            if not (run.model_dir / "model.pt").exists():
                away.add(budget)
    if away:
        # Records copied from another machine (tables/records): their models are not here, and
        # "reloading" them would retrain each one; a partial re-timing would mix two runs.
        log(f"capacity: side-by-side timing skipped: the models of budget(s) {', '.join(map(str, sorted(away)))} are not on "
            "this machine (records made elsewhere); each record keeps the FPS it was made with")
        return {}
    loaded = []
    for budget, run, method, rec in recorded:
        fit_method(method, train, run, False)  # reloads the checkpoint
        method.render(clip)  # warm-up
        loaded.append((budget, run.seed, method, rec))
    if not loaded:
        return {}
    log(f"capacity: timing {len(loaded)} models side by side ({rounds} rounds of {n} frames, interleaved)")
    best = {(b, s): float("inf") for b, s, _, _ in loaded}
    for _ in range(rounds):
        for b, s, method, _ in loaded:
            t0 = time.perf_counter()
            method.render(clip)
            best[(b, s)] = min(best[(b, s)], time.perf_counter() - t0)
    out = {}
    # the run's identity: to the microsecond, as two timing runs can fall in one second on a fast host
    run = store.now_iso("microseconds")
    for b, s, _, rec in loaded:
        fps = n / best[(b, s)]
        out[(b, s)] = fps
        note = (f"fps_side_by_side: all {len(loaded)} capacity models of this subject timed in one run, round-robin, "
                f"best of {rounds} rounds of {n} frames")
        rec = store.replace(rec, cost=store.replace(rec.cost, fps_side_by_side=fps, fps_side_by_side_run=run),
                            notes=(*(x for x in rec.notes if not x.startswith("fps_side_by_side:")), note))
        store.write_record(cfg.results, rec)
    return out
