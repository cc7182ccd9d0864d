"""The stability suite: drive trained models with perturbed audio, record where they break.

For each method and each condition of :mod:`lmgs_eval.protocols.perturb` (made from the subject's
clean test audio and, for "another voice", the bundled cross-driven clip A), the driving
audio goes through the same loading path as a user's file (:func:`~lmgs_eval.data.audio.to_mono_16k`:
stereo mixed down, other rates resampled), is rendered, and is recorded under protocol
``stress`` with clip = the condition name:

* LSE-D / LSE-C / |AV offset| (flagged on silence, where they mean nothing);
* LMD against ground truth where the condition keeps the test split's timing (``aligned``)
  or brings its own (other voice);
* **jitter**: mean over frames and mouth points 48-67 of ``|l[t+1] - 2 l[t] + l[t-1]|`` in
  pixels (landmark acceleration; dlib landmarks of the rendered frames);
* **silence_open**: mean inner-lip opening ``|l66 - l62|`` in pixels over the frames inside
  the condition's silent spans (a resting mouth is near 0 px);
* failures: a crash, non-finite or wrongly shaped output, frozen output (every frame equal
  while the audio is not silent), no face found in most frames. A failed condition gets
  ``status.state = "failed"`` with the reason, and the suite goes on.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import pickle
import time
import traceback
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import torch
from tqdm import tqdm

from baselines import protocol as methods
from lmgs.lips import lip_gap
from lmgs.types import DrivingAudio
from lmgs_eval import results as store
from lmgs_eval.convert import driving_from_clip, subject_to_clip
from lmgs_eval.data.audio import to_mono_16k
from lmgs_eval.data.registry import find_subject
from lmgs_eval.errors import UserError
from lmgs_eval.metrics.base import MetricResult, MetricSpec
from lmgs_eval.metrics.landmarks import DlibBackend, lmd_result
from lmgs_eval.metrics.metric_suite import MetricSuite
from lmgs_eval.protocols.cross import bundled_cross_clips
from lmgs_eval.protocols.perturb import VERSION as PERTURB_VERSION
from lmgs_eval.protocols.perturb import SR, Condition, make_conditions
from lmgs_eval.results.records import RunId, build_record, metrics_block, stored
from lmgs_eval.runner import REPEATS, RunConfig, build_method, cost_block, cycle, fit_method, log, timed_render, write_render

MOUTH = slice(48, 68)
JITTER_SPEC = MetricSpec(
    name="jitter", higher_is_better=False, unit="px", backend="dlib", version="1",
    definition="mouth points 48-67 of dlib 68-point landmarks of the rendered frames; per frame t the mean over the "
               "20 points of |l[t+1] - 2 l[t] + l[t-1]| (pixels of the full frame); mean over frames with a face in "
               "all three", per="frame")
SILENCE_OPEN_SPEC = MetricSpec(
    name="silence_open", higher_is_better=False, unit="px", backend="dlib", version="1",
    definition="inner-lip opening |l66 - l62| of dlib 68-point landmarks in pixels, mean over the frames inside the "
               "condition's silent spans (a resting mouth is near 0)", per="frame")
LONG_CLIP_FRAMES = 1000  # above this, LSE detects faces every 5 frames (boxes are median-smoothed anyway)


def jitter_result(lms: np.ndarray) -> MetricResult:
    """Landmark acceleration of the mouth (see :data:`JITTER_SPEC`) from ``[T, 68, 2]`` (NaN rows: no face)."""
    m = np.asarray(lms, np.float64)[:, MOUTH]
    n = len(m)
    if n < 3:
        return MetricResult(JITTER_SPEC, None, {}, np.zeros(0), n, 0, available=False, reason="fewer than 3 frames")
    acc = np.linalg.norm(m[2:] - 2 * m[1:-1] + m[:-2], axis=-1).mean(axis=1)
    ok = np.isfinite(acc)
    flags = [] if ok.all() else [f"no_face: {int((~ok).sum())} of {len(acc)} triple(s) without landmarks, not scored"]
    val = float(acc[ok].mean()) if ok.any() else None
    return MetricResult(JITTER_SPEC, val, {"jitter": val}, acc, len(acc), int(ok.sum()), flags,
                        available=val is not None, reason="" if val is not None else "no face found")


def silence_open_result(lms: np.ndarray, spans, fps: float = 25.0) -> MetricResult | None:
    """Mean inner-lip opening over the frames in ``spans`` (seconds); None without spans."""
    if not spans:
        return None
    t = (np.arange(len(lms)) + 0.5) / fps
    sel = np.zeros(len(lms), bool)
    for a, b in spans:
        sel |= (t >= a) & (t < b)
    opening = lip_gap(lms)[sel]
    ok = np.isfinite(opening)
    val = float(opening[ok].mean()) if ok.any() else None
    return MetricResult(SILENCE_OPEN_SPEC, val, {"silence_open": val}, opening, int(sel.sum()), int(ok.sum()),
                        available=val is not None, reason="" if val is not None else "no face found")


def lse_u8(suite: MetricSuite, frames: np.ndarray, audio: np.ndarray, lms: np.ndarray):
    """LSE of uint8 frames with the run's sync scorer (cropped a chunk at a time by ``lse``, no float
    copy of the clip), reading ``lms`` (the frames' landmarks, found by the tracker the landmark scorer
    uses) instead of tracking the face again; a long clip detects faces every 5 frames (the boxes are
    median-smoothed anyway)."""
    if len(frames) <= LONG_CLIP_FRAMES:
        return suite.lse(frames, audio, lms=lms)
    r = suite.lse(frames, audio, detect_every=5, lms=lms)
    r.notes.append(f"long clip ({len(frames)} frames): faces detected every 5th frame")
    return r


def check_output(frames, n: int, audio: np.ndarray) -> str | None:
    """Why an output counts as failed (None when it does not)."""
    if not isinstance(frames, np.ndarray) or frames.ndim != 4 or frames.shape[0] != n:
        return f"wrong output shape {getattr(frames, 'shape', type(frames).__name__)}, expected {n} frames"
    if frames.dtype != np.uint8 and not np.isfinite(frames).all():
        return "non-finite output"
    if n > 1 and float(np.sqrt(np.mean(audio.astype(np.float64) ** 2))) > 1e-4:
        if np.array_equal(frames[0], frames[-1]) and not np.any(frames.reshape(n, -1).std(axis=0) > 0):
            return "frozen output: every frame identical while the audio is not silent"
    return None


def condition_driving(cond: Condition, test_clip) -> tuple[np.ndarray, DrivingAudio, list[str]]:
    """The condition's audio through the user-file path, and a driving clip cycled over the test cameras."""
    audio, notes = to_16k(cond)
    n = len(audio) // 640
    if n < 1:
        raise UserError(f"condition {cond.name}: shorter than one frame")
    audio = audio[: n * 640]
    driving = DrivingAudio(audio=audio, w2c=cycle(test_clip.w2c, n), backgrounds=cycle(test_clip.backgrounds, n),
                           blink=None if test_clip.blink is None else cycle(test_clip.blink, n))
    return audio, driving, notes


def to_16k(cond: Condition) -> tuple[np.ndarray, list[str]]:
    return to_mono_16k(cond.audio, cond.sample_rate, f"condition {cond.name}")


def _context(cfg: RunConfig, long_seconds: float) -> dict:
    """What every method's run shares: the subject, its test clip, the conditions, the landmark
    backend and the ground truth's landmarks; built once per process (a worker of ``jobs`` > 1
    keeps it across the methods it runs)."""
    key = (cfg.subject, cfg.data_root, float(long_seconds))
    if key not in _CONTEXTS:
        subject = find_subject(cfg.subject, cfg.data_root, progress=cfg.progress)
        test = subject_to_clip(subject, subject.test_ids, progress=cfg.progress)
        clips = bundled_cross_clips(subject) if subject.bundled else []
        other = clips[0] if clips else None
        conds = make_conditions(test.audio, seed=0, other_voice=None if other is None else other.audio,
                                long_seconds=long_seconds)
        backend = DlibBackend()
        gt_lms = backend.landmarks(test.frames)
        _CONTEXTS.clear()  # one subject per process at a time
        _CONTEXTS[key] = {"subject": subject, "test": test, "other": other, "conds": conds, "backend": backend,
                          "gt_lms": gt_lms, "gt_found": float(np.isfinite(gt_lms).all(axis=(1, 2)).mean()),
                          "other_gt_lms": None, "train": None}
    return _CONTEXTS[key]


_CONTEXTS: dict = {}


def _selected(conds: list[Condition], names) -> list[Condition]:
    """The conditions asked for (all when ``names`` is empty), clean always among them."""
    if not names:
        return list(conds)
    unknown = sorted(set(names) - {c.name for c in conds})
    if unknown:
        raise UserError(f"unknown condition(s) {', '.join(unknown)}; known: {', '.join(c.name for c in conds)}")
    return [c for c in conds if c.name in names or c.name == "clean"]


class _Lazy:
    """An object made on first attribute access (the training clip: about a minute to load)."""

    def __init__(self, make):
        self._make, self._obj = make, None

    def _get(self):
        if self._obj is None:
            self._obj = self._make()
        return self._obj

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self._get(), name)

    def __len__(self) -> int:  # special methods are looked up on the type, not through __getattr__
        return len(self._get())

    def __getitem__(self, key):
        return self._get()[key]

    def __iter__(self):
        return iter(self._get())


def run_stress(cfg: RunConfig, conditions: tuple[str, ...] | None = None, max_minutes: float = 15.0,
               long_seconds: float = 300.0, jobs: int = 1) -> tuple[list[store.Record], list[str]]:
    """The stability suite for every method and seed; returns (records written, messages).

    ``max_minutes``: a condition whose predicted rendering time (frames / clean FPS) is
    longer is not run and is reported (never recorded as a failure it did not have).
    ``jobs`` > 1 runs that many (method, seed) suites at once in worker processes, each with
    its share of the CPU threads; their costs are then measured beside each other and the
    records say so.
    """
    if jobs < 1:
        raise UserError(f"--jobs must be at least 1, got {jobs}")
    pairs = [(name, seed) for name in cfg.methods for seed in cfg.seeds]
    if jobs > 1 and len(pairs) > 1:
        # The workers build the context (subject, clips, conditions, ground-truth landmarks)
        # themselves; here only the names are checked, on conditions made from half a second of
        # zeros (a subject without a second voice rejects other-voice in its worker).
        half = np.zeros(SR // 2, np.float32)
        _selected(make_conditions(half, seed=0, other_voice=half, long_seconds=long_seconds), conditions)
        return _run_parallel(cfg, pairs, conditions, max_minutes, long_seconds, min(jobs, len(pairs)))
    ctx = _context(cfg, long_seconds)
    conds = _selected(ctx["conds"], conditions)
    records, messages = [], []
    try:
        for name, seed in pairs:
            recs, msgs = _stress_one(cfg, ctx, conds, name, seed, max_minutes)
            records += recs
            messages += msgs
        return records, messages
    finally:
        _CONTEXTS.clear()  # the training clip is large: not kept past the suite


def _run_parallel(cfg: RunConfig, pairs, conditions, max_minutes: float, long_seconds: float,
                  jobs: int) -> tuple[list[store.Record], list[str]]:
    """Each (method, seed) suite in a worker process (spawned: no forked torch threads)."""
    shipped = _ship(cfg.methods)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    threads = max(1, cores // jobs)
    note = (f"run with --jobs {jobs} ({threads} thread(s) each): beside other methods' stress runs, so its FPS "
            "and wall time are contended")
    log(f"stress: {len(pairs)} method/seed suites in {jobs} worker processes, {threads} thread(s) each")
    sub = dataclasses.replace(cfg, progress=False)
    records, messages = [], []
    with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_worker_init, initargs=(threads,)) as pool:
        futures = [pool.submit(_worker, dataclasses.replace(sub, methods=(name,), seeds=(seed,)), conditions,
                               max_minutes, long_seconds, note, {name: shipped.get(name)}) for name, seed in pairs]
        bar = None
        if cfg.progress:
            bar = tqdm(total=len(futures), desc="stress suites", unit="suite", leave=False)
        try:
            for fut in futures:  # in submission order: the records come back as a serial run lists them
                recs, msgs = fut.result()
                records += recs
                messages += msgs
                if bar is not None:
                    bar.update(1)
        except BaseException:  # an error or Ctrl-C: no queued suite starts (the running ones finish first)
            for fut in futures:
                fut.cancel()
            raise
        finally:
            if bar is not None:
                bar.close()
    return records, messages


def _ship(names) -> dict:
    """What a spawned worker needs to build methods registered at run time (not by an import).

    name -> (factory, scene_budget) for such a method, so that in a worker it takes a subject's
    knee density as a serial run does; None for a built-in (the worker registers it, flag and
    all, by importing its module: a built-in's lambda does not pickle, a class goes by reference).
    """
    shipped = {}
    for name in names:
        reg = methods.registration(name)
        try:
            pickle.dumps(reg[0] if reg else None)
            shipped[name] = reg
        except Exception:
            shipped[name] = None
    return shipped


def _adopt(shipped: dict) -> None:
    """In a worker: register what :func:`_ship` sent, with its flag."""
    methods.load_adapters()
    for name, item in shipped.items():
        if item is not None and not methods.is_registered(name):
            factory, scene_budget = item
            methods.register(name, scene_budget=scene_budget)(factory)


def _worker_init(threads: int) -> None:
    torch.set_num_threads(threads)


def _worker(cfg: RunConfig, conditions, max_minutes: float, long_seconds: float, note: str,
            shipped: dict) -> tuple[list[store.Record], list[str]]:
    _adopt(shipped)
    ctx = _context(cfg, long_seconds)
    conds = _selected(ctx["conds"], conditions)
    (name,), (seed,) = cfg.methods, cfg.seeds
    return _stress_one(cfg, ctx, conds, name, seed, max_minutes, note=note)


def _stress_one(cfg: RunConfig, ctx: dict, conds, name: str, seed: int, max_minutes: float,
                note: str | None = None) -> tuple[list[store.Record], list[str]]:
    """Every condition of ``conds`` for one method and seed (resumable: finished ones are skipped)."""
    subject, test, other, backend = ctx["subject"], ctx["test"], ctx["other"], ctx["backend"]
    gt_lms, gt_found = ctx["gt_lms"], ctx["gt_found"]
    messages, records = [], []
    method = build_method(cfg, name, subject)
    info = method.describe()
    run = RunId(subject, info, seed, "stress", config_hash=f"{info.config_hash}-stress{PERTURB_VERSION}")
    todo = [c for c in conds if cfg.force or not _done(cfg.results, dataclasses.replace(run, clip=c.name))]
    if not todo:
        log(f"{run.label}: stress conditions already in {cfg.results}; skipped")
        return records, messages
    if ctx["train"] is None:  # loaded only if a method trains (or reads it): a cached model does not
        ctx["train"] = _Lazy(lambda: subject_to_clip(subject, subject.train_ids, progress=cfg.progress))
    fit_cost = fit_method(method, ctx["train"], run, cfg.progress)
    clean_fps = None
    for cond in sorted(todo, key=lambda c: c.name != "clean"):
        t0 = time.perf_counter()
        try:
            audio, driving, notes = condition_driving(cond, test)
        except UserError as exc:
            messages.append(f"{info.name}: {exc}")
            continue
        if note:
            notes = list(notes) + [note]
        n = driving.n_frames
        if clean_fps and n / clean_fps > 60 * max_minutes:
            messages.append(f"{info.name} / {cond.name}: not run, {n} frames at {clean_fps:.1f} FPS would take "
                            f"{n / clean_fps / 60:.0f} min (> --max-minutes {max_minutes:g})")
            continue
        status, metrics, art, rc = None, {}, {}, {}
        try:
            if cond.name == "clean":
                driving = driving_from_clip(test)
            # the clean clip is timed like the self protocol (median of repeats); a perturbed
            # clip once: its FPS is a cost column, and the repeats would double the suite's time
            frames, rc = timed_render(method, driving, repeats=REPEATS if cond.name == "clean" else 1)
            if cond.name == "clean":
                clean_fps = rc.get("fps")
            why = check_output(frames, n, audio)
            if why is None:
                lms = backend.landmarks(frames)  # the tracker reads uint8 frames as they are
                res = {"jitter": jitter_result(lms)}
                res["lse"] = lse_u8(cfg.suite, frames, audio, lms)
                so = silence_open_result(lms, cond.silent_spans)
                if so is not None:
                    res["silence_open"] = so
                gl = None
                if cond.aligned and n <= len(gt_lms):
                    gl = gt_lms[:n]
                elif cond.name == "other-voice" and other is not None and other.gt_frames is not None:
                    if ctx["other_gt_lms"] is None:
                        ctx["other_gt_lms"] = backend.landmarks(other.gt_frames)
                    gl = ctx["other_gt_lms"][:n] if len(ctx["other_gt_lms"]) >= n else None
                if gl is not None:
                    res["lmd"] = lmd_result(lms, gl)
                if cond.name == "clean":  # the reference-based metrics too (no audio: LSE is above)
                    res.update({k: v for k, v in cfg.suite.score(frames, test.frames, None, lmd=False).items() if k != "lse"})
                metrics = metrics_block(res)
                found = float(np.isfinite(lms).all(axis=(1, 2)).mean())
                if gt_found >= 0.5 and found < 0.5:  # only when dlib finds the ground truth's face
                    why = f"no face detected in {100 * (1 - found):.0f}% of frames"
                elif gt_found < 0.5:
                    notes = list(notes) + [f"no-face check off: dlib finds a face in only {100 * gt_found:.0f}% "
                                           "of the ground-truth test frames"]
            if why is not None:
                status = {"state": "failed", "reason": why}
            if n <= LONG_CLIP_FRAMES:
                art = {"render": write_render(cfg.results, f"{run.renders}/stress/{run.stem}-{cond.name}.mp4", frames, audio)}
        except Exception as exc:  # a crash on one condition is a recorded failure, the suite goes on
            if isinstance(exc, KeyboardInterrupt):
                raise
            status = {"state": "failed", "reason": f"crash: {exc.__class__.__name__}: {str(exc)[:200]}"}
            notes = list(notes) + ["traceback: " + traceback.format_exc(limit=3).replace("\n", " | ")[-600:]]
        cost = cost_block(method, fit_cost, rc) if rc else {}
        cost["wall_seconds"] = time.perf_counter() - t0
        rec = build_record(dataclasses.replace(run, clip=cond.name), split=cond.description, n_frames=n, metrics=metrics,
                           cost=cost, artefacts=art, notes=list(notes) + [f"perturbation set v{PERTURB_VERSION}: {cond.description}"],
                           status=status)
        store.write_record(cfg.results, rec)
        records.append(rec)
        state = "FAILED: " + status["reason"] if status else "ok"
        log(f"{info.name} / {cond.name}: {n} frames, {state} [{cost['wall_seconds']:.0f} s]")
    return records, messages


def _done(root, run: RunId) -> bool:
    """A finished record (a failed run is retried: the failure may have been fixed)."""
    return stored(root, run, finished=True) is not None
