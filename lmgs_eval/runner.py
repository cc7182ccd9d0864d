"""The one runner of every protocol: fit (or reload) a method, render timed, score, write the record.

A protocol (:mod:`lmgs_eval.protocols`) says what to run: which subject split, which driving
audio, which controls and metrics. This module says how: the model cache and its data marker,
FPS audio in to frames out after a warm-up (median of repeats, host contention beside it),
the metric suite on uint8 frames, the render written with its audio, and one record per run.
"""

from __future__ import annotations

import contextlib
import inspect
import json
import shutil
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from baselines.protocol import TalkingHead, create_method
from lmgs.fileio import atomic_write
from lmgs.types import DrivingAudio
from lmgs_eval import results as store
from lmgs_eval.data.video import write_video
from lmgs_eval.errors import UserError
from lmgs_eval.hooks import adapter_hooks
from lmgs_eval.hosttime import HostSpeed, OthersCPU, peak_rss_mb
from lmgs_eval.metrics.metric_suite import MetricSuite
from lmgs_eval.paths import cache_root, claim
from lmgs_eval.results.records import RunId, build_record, manifest_sha, metrics_block

WARMUP_FRAMES = 3
REPEATS = 3  # timed renders of the clip (median reported) ...
REPEAT_BUDGET_S = 20.0  # ... while another one fits in this many seconds (slow methods are timed once)


@dataclass(frozen=True)
class RunConfig:
    """What a protocol run needs from the command line."""

    subject: str = "astronaut"
    methods: tuple[str, ...] = ("lmgs",)
    preset: str = "quick"
    seeds: tuple[int, ...] = (0,)
    results: Path = Path("results")
    data_root: str | None = None
    device: str | None = None
    progress: bool = True
    renders: str | None = None  # for external:NAME
    force: bool = False
    method_options: dict = field(default_factory=dict)
    # the metrics of the whole run, each network loaded once (not an option: left out of comparisons)
    suite: MetricSuite = field(default_factory=MetricSuite, compare=False, repr=False)


def build_method(cfg: RunConfig, name: str, subject, **options) -> TalkingHead:
    """A method as every protocol builds it: the run's ``--set`` overrides, preset and device.

    ``options`` add to (and win over) the run's; ``external:NAME`` takes ``--renders``. A bad
    override or preset is an :class:`~lmgs.errors.InputError` here, before anything is scored.
    """
    opts = {**cfg.method_options, **options}
    if name.startswith("external:"):
        opts.setdefault("renders", cfg.renders)
    else:
        opts.setdefault("preset", cfg.preset)
        opts.setdefault("device", cfg.device)
    method = create_method(name, subject=subject, hooks=adapter_hooks(), **opts)
    if subject is not None:
        check_lips_held_out(method, subject)
    return method


def source_sha256(folder) -> set[str]:
    """The sha256 of the video and audio files an ingested subject was made from (its ``manifest.json``); empty
    for a subject without one (bundled, or a processed folder from elsewhere)."""
    try:
        doc = json.loads((Path(folder) / "manifest.json").read_text())
    except (OSError, ValueError):
        return set()
    return {str(v) for v in ((doc.get("input") or {}).get("sha256"), (doc.get("audio") or {}).get("sha256")) if v}


def check_lips_held_out(method, subject) -> None:
    """A method that reads the generic lip model must not be scored on a clip the model was adapted on: its test
    split would not be held out. The weights' provenance (:func:`lmgs.lips_weights.adapted_on`) lists the video files by
    sha256; a match with the subject's source is a :class:`UserError` naming the way out (weights made without
    the clip). A re-encoded copy of a clip is not caught: the guard compares files, not content."""
    read = getattr(method, "lip_weights", None)
    weights = read() if callable(read) else None
    root = getattr(subject, "root", None)
    if weights is None or root is None:
        return
    from lmgs.lips_weights import adapted_on

    ours = source_sha256(root)
    hit = [c for c in adapted_on(weights) or () if c.get("sha256") in ours]
    if hit:
        clip = hit[0].get("clip", "?")
        raise UserError(f"subject {subject.name}: the lip model {weights} was adapted on this very clip ({clip}), so its "
                        f"test split is not held out; make weights without it (python scripts/train_lip_model.py "
                        f"--hold-out {clip} --out DIR) and pass --set train.lip_weights=DIR/lips_generic.pt "
                        "(lip_weights= for geneface and ip_lap), or read the per-subject predictor "
                        "(--set train.landmark_source=subject; landmark_source=subject for geneface and ip_lap)")


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


DATA_MARKER = "subject.sha256"
LOCK = ".lock"


@contextlib.contextmanager
def claim_model_dir(workdir: Path, run: RunId) -> Iterator[None]:
    """Hold a model folder for one fit of ``run``, on the data it is trained on.

    The claim (:func:`lmgs_eval.paths.claim`, on the folder's :data:`LOCK`): a second run of the
    same method, config and seed on this machine waits, then reloads the model the first one
    trained instead of training it again. The data: a cached model (or checkpoint) is reused only
    on the data it was trained on. The folder keeps the subject's manifest hash
    (:data:`DATA_MARKER`); a model of the same method, config and seed but other data of a subject
    of the same name (re-generated, re-processed) is a :class:`UserError`, not a silent reuse. A
    folder from before the marker is taken to be of the current data. Subjects without a manifest
    are not checked.
    """
    subject, workdir = run.subject, Path(workdir)
    with claim(workdir / LOCK, f"{run.label} on {subject.name}", log):
        sha = manifest_sha(subject.root)
        marker = workdir / DATA_MARKER
        old = marker.read_text().strip() if sha is not None and marker.exists() else None
        if old is not None and old != sha and any((workdir / f).exists() for f in ("model.pt", "checkpoint.pt")):
            raise UserError(f"{workdir}: a model trained on other data of subject '{subject.name}' (manifest sha256 "
                            f"{old[:12]}, now {sha[:12]}); delete the folder to train on this data")
        if sha is not None and old != sha:
            atomic_write(marker, sha + "\n")
        yield


def head_of(driving: DrivingAudio, k: int) -> DrivingAudio:
    """The first ``k`` frames (at most all) of a driving clip: audio, cameras, backgrounds, blink, features."""
    k = min(int(k), driving.n_frames)
    spf = driving.sample_rate // driving.fps
    return DrivingAudio(
        audio=driving.audio[: k * spf],
        w2c=None if driving.w2c is None else driving.w2c[:k],
        backgrounds=None if driving.backgrounds is None else driving.backgrounds[:k],
        blink=None if driving.blink is None else driving.blink[:k],
        audio_features=None if not driving.audio_features else {a: v[:k] for a, v in driving.audio_features.items()},
    )


def takes_timings(method) -> bool:
    """Whether a method's ``render`` takes ``timings=`` (a dict it fills in: seconds per stage, and for lmgs the
    share of face points Spatial Enhancement selected)."""
    return "timings" in inspect.signature(method.render).parameters


def timed_render(method, driving: DrivingAudio, timings: dict | None = None,
                 repeats: int = REPEATS) -> tuple[np.ndarray, dict]:
    """Render after a short warm-up; FPS is audio in to frames out, I/O outside the timer.

    The clip is rendered up to ``repeats`` times (while the next repeat fits in
    :data:`REPEAT_BUDGET_S`) and the median run is reported (``repeats`` in the result). A method whose ``render`` takes
    ``timings=`` fills in seconds per stage (audio, network, raster) of that run.
    """
    kw = {"timings": timings} if timings is not None and takes_timings(method) else {}
    n = driving.n_frames
    warm = head_of(driving, WARMUP_FRAMES)
    t0 = time.perf_counter()
    method.render(warm)
    first = time.perf_counter() - t0
    runs = []  # (seconds, stage timings) of each timed repeat; the median is reported
    frames = None
    with HostSpeed() as host, OthersCPU() as busy:
        while True:
            tk: dict = {} if kw else None
            t0 = time.perf_counter()
            out = method.render(driving, **({"timings": tk} if kw else {}))
            runs.append((time.perf_counter() - t0, tk))
            if frames is None:
                frames = out
            if len(runs) >= repeats or sum(r[0] for r in runs) + runs[-1][0] > REPEAT_BUDGET_S:
                break
    runs.sort(key=lambda r: r[0])
    secs, tk = runs[(len(runs) - 1) // 2]
    secs = float(np.median([r[0] for r in runs]))
    if kw and tk is not None:
        timings.update(tk)
    if np.issubdtype(frames.dtype, np.floating) and not np.isfinite(frames).all():
        raise RuntimeError(f"{method.describe().name} rendered non-finite output")
    if frames.shape[0] != n or frames.dtype != np.uint8:
        raise RuntimeError(f"{method.describe().name} rendered {frames.shape} {frames.dtype}, expected {n} uint8 frames")
    return frames, {"fps": n / secs if secs > 0 else None, "render_seconds": secs, "first_frame_ms": 1000 * first / max(warm.n_frames, 1),
                    "realtime_factor": (n / driving.fps) / secs if secs > 0 else None, "repeats": len(runs),
                    "others_cpu_share": busy.share, **host.cost()}


def fit_method(method, clip, run: RunId, progress: bool, workdir: Path | None = None) -> dict:
    """Fit (or reload) a method for ``run``, in its model folder (:func:`claim_model_dir`); returns the cost of training.

    A fit that fails in a folder it made, before anything was saved there, removes the folder
    (no empty model folders are left). ``workdir``: a folder of the caller's instead of the model
    cache (a benchmark that must train afresh); a model already in it is reloaded all the same.
    """
    own = workdir is None
    workdir = run.model_dir if own else Path(workdir)
    made = not workdir.exists()
    try:
        with claim_model_dir(workdir, run):
            reused = (workdir / "model.pt").exists()
            t0 = time.perf_counter()
            with OthersCPU() as busy:
                method.fit(clip, seed=run.seed, workdir=workdir, progress=progress)
            secs = time.perf_counter() - t0
            # a training resumed from a checkpoint: add what the interrupted runs had trained (lmgs saves it;
            # a reused model's time comes from its fit.json below)
            secs += float(getattr(getattr(method, "report", None), "prior_seconds", 0.0) or 0.0)
            rec = {"train_seconds": secs, "train_others_cpu_share": busy.share, "reused_checkpoint": reused,
                   "workdir": str(workdir)}
            if reused:
                fit = _recorded_fit(workdir)
                rec["train_seconds"] = fit.get("train_seconds")
                rec["train_others_cpu_share"] = fit.get("train_others_cpu_share")
                rec["train_peak_mb"] = fit.get("peak_mb")  # this process did not train: the training's peak is there
            else:
                atomic_write(workdir / "fit.json", json.dumps({"train_seconds": secs, "peak_mb": peak_rss_mb(),
                                                               "train_others_cpu_share": busy.share}))
            return rec
    except BaseException:
        if made and own:
            _drop_if_empty(workdir)
        raise


def _drop_if_empty(workdir: Path) -> None:
    """Remove a model folder holding nothing but its data marker and lock, and the empty folders above it."""
    if not workdir.is_dir() or any(p.name not in (DATA_MARKER, LOCK) for p in workdir.iterdir()):
        return
    shutil.rmtree(workdir, ignore_errors=True)
    top = cache_root() / "models"
    for d in workdir.parents:
        if d == top or top not in d.parents:
            break
        try:
            d.rmdir()
        except OSError:
            break


def _recorded_fit(workdir: Path) -> dict:
    """What ``fit.json`` says of the training that made a checkpoint (empty if it is not there)."""
    p = workdir / "fit.json"
    if p.exists():
        try:
            d = json.loads(p.read_text())
            return d if isinstance(d, dict) else {}
        except ValueError:
            return {}
    return {}


def cost_block(method, fit_cost: dict | None, render_cost: dict, timings: dict | None = None) -> dict:
    c = dict(method.cost() or {})
    # Prerendered frames (fit_cost None, render_cost {}): only what the user's sidecar states;
    # neither memory nor device of this process is theirs.
    pre = getattr(method, "prerendered", False)
    n = (timings or {}).get("frames") or 0
    ms = None
    if timings and n:
        ms = {k: 1000.0 * timings[k] / n for k in ("audio", "network", "raster") if k in timings}
        ms["total"] = 1000.0 / render_cost["fps"] if render_cost.get("fps") else None
    return {
        "train_seconds": (fit_cost or {}).get("train_seconds", c.get("train_seconds")),
        "train_others_cpu_share": (fit_cost or {}).get("train_others_cpu_share"),
        "fps": render_cost.get("fps") if render_cost.get("fps") is not None else c.get("fps"),
        "ms_per_frame": ms,
        "first_frame_ms": render_cost.get("first_frame_ms"),
        "render_repeats": render_cost.get("repeats"),
        "others_cpu_share": render_cost.get("others_cpu_share"),
        "host_slowdown": render_cost.get("host_slowdown"),
        "host_probe_ms": render_cost.get("host_probe_ms"),
        "host_probe_best_ms": render_cost.get("host_probe_best_ms"),
        "realtime_factor": render_cost.get("realtime_factor"),
        "n_params": c.get("n_params"),
        "n_gaussians": c.get("n_gaussians"),
        "model_mb": c.get("model_mb"),
        # the protocol's peak: this process's, or the training's that made a reused checkpoint if higher
        "peak_mb": None if pre else max(peak_rss_mb(), (fit_cost or {}).get("train_peak_mb") or 0.0),
        # the device the method's model is on (its cost(); an external method's sidecar says it or nobody does)
        "device": c.get("device"),
    }


def write_render(root: Path, rel: str, frames: np.ndarray, audio: np.ndarray) -> dict:
    """Write an mp4 with its driving audio under the store root; the artefact entry (relative path)."""
    path = Path(root) / rel
    write_video(path, frames, 25, audio, 16000)
    return {"path": rel, "sha256": store.sha256_file(path)}


def fit_render_score(cfg: RunConfig, method, run: RunId, train, driving: DrivingAudio, gt: np.ndarray, render_rel: str,
                     workdir: Path | None = None) -> store.Record:
    """Fit (or reload) the method of ``run``, render the test split from its audio, score, record; returns the (typed) record.

    ``workdir``: where the model is trained (:func:`fit_method`; default the model cache)."""
    info = run.info
    timings: dict = {}
    if getattr(method, "prerendered", False):
        # Frames rendered elsewhere: nothing to fit and nothing to time here (reading files is
        # not rendering); the cost comes from the method's sidecar or stays empty.
        fit_cost, rc = None, {}
        frames = method.render(driving)
        log(f"{info.name}: {len(frames)} frames read from its renders; scoring")
    else:
        log(f"{run.label}: fitting on {len(train)} frames")
        fit_cost = fit_method(method, train, run, cfg.progress, workdir)
        frames, rc = timed_render(method, driving, timings)
        log(f"{info.name}: {len(frames)} frames at {rc['fps']:.1f} FPS; scoring")
    res = cfg.suite.score(frames, gt, driving.audio)
    art = {"render": write_render(cfg.results, render_rel, frames, driving.audio)}
    ck = Path(fit_cost["workdir"]) / "model.pt" if fit_cost else None
    if ck is not None and ck.exists():
        art["checkpoint"] = {"path": str(ck), "sha256": store.sha256_file(ck)}
    rec = build_record(run, split="test", n_frames=len(frames), metrics=metrics_block(res),
                       cost=cost_block(method, fit_cost, rc, timings or None), artefacts=art,
                       se_fraction=timings.get("se_fraction"))
    store.write_record(cfg.results, rec)
    return rec


def cycle(a: np.ndarray, n: int) -> np.ndarray:
    reps = int(np.ceil(n / len(a)))
    return np.concatenate([a] * reps)[:n]
