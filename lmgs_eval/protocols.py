"""The self-driven and cross-driven protocols: fit, render, score, measure, record.

``self`` (paper, "Comparison Settings"): each method is trained on the subject's training
split (the first 10/11 of the frames) and driven by the test split's own audio; the frames
are scored against the test split's ground truth (full frame: the rendered head composited
on the ground-truth torso and background, as ER-NeRF / TalkingGaussian do).

``cross``: trained models are driven by other audio; only LSE-D / LSE-C apply, plus LMD
where the clip comes with ground-truth articulation (the bundled A / B clips).

Every record says how it was made (see :mod:`lmgs_eval.results`). A record whose method,
subject, protocol, clip, seed and config hash are already in the store is not redone.
"""

from __future__ import annotations

import os
import resource
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lmgs.types import DrivingAudio
from lmgs_eval.errors import UserError

PROTOCOL_VERSIONS = {"self": "1", "cross": "1", "stress": "1", "calibration": "1", "capacity": "1"}
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


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB; Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def model_dir(subject, method_name: str, config_hash: str, seed: int) -> Path:
    from lmgs_eval.paths import cache_root

    return cache_root() / "models" / subject.name / method_name / f"{config_hash}-seed{seed}"


DATA_MARKER = "subject.sha256"


def claim_model_dir(workdir: Path, subject) -> None:
    """A cached model (or checkpoint) is reused only on the data it was trained on.

    The folder keeps the subject's manifest hash (:data:`DATA_MARKER`); a model of the same
    method, config and seed but other data of a subject of the same name (re-generated,
    re-processed) is a :class:`UserError`, not a silent reuse. A folder from before the
    marker is taken to be of the current data. Subjects without a manifest are not checked.
    """
    from lmgs_eval.paths import atomic_write_text

    sha = subject_sha(subject)
    if sha is None:
        return
    marker = Path(workdir) / DATA_MARKER
    old = marker.read_text().strip() if marker.exists() else None
    if old == sha:
        return
    if old is not None and any((Path(workdir) / f).exists() for f in ("model.pt", "checkpoint.pt")):
        raise UserError(f"{workdir}: a model trained on other data of subject '{subject.name}' (manifest sha256 "
                        f"{old[:12]}, now {sha[:12]}); delete the folder to train on this data")
    Path(workdir).mkdir(parents=True, exist_ok=True)
    atomic_write_text(marker, sha + "\n")


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


def host_cpu_seconds() -> tuple[float, float] | None:
    """``(busy, total)`` CPU seconds of the whole host since boot (Linux ``/proc/stat``), else None."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            parts = f.readline().split()
        ticks = [int(x) for x in parts[1:9]]  # user nice system idle iowait irq softirq steal
        hz = os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None
    if parts[0] != "cpu" or len(ticks) < 8 or hz <= 0:
        return None
    total = sum(ticks) / hz
    return total - (ticks[3] + ticks[4]) / hz, total


class OthersCPU:
    """Share of the host's CPU time that other processes took during a span (contention while timing).

    ``share = (host busy - this process's CPU) / host total`` over the span: about 0 on a
    quiet host, 0.5 when another process keeps one of two cores busy. Hypervisor steal
    counts as taken by others. ``share`` is None where ``/proc/stat`` is not available.
    """

    def __enter__(self) -> "OthersCPU":
        self.share: float | None = None
        self._h0, self._p0 = host_cpu_seconds(), _own_cpu_seconds()
        return self

    def __exit__(self, *exc) -> None:
        h1, p1 = host_cpu_seconds(), _own_cpu_seconds()
        if self._h0 is None or h1 is None or h1[1] <= self._h0[1]:
            return
        others = (h1[0] - self._h0[0]) - (p1 - self._p0)
        self.share = min(1.0, max(0.0, others / (h1[1] - self._h0[1])))


PROBE_SLOW = 1.5
"""A render timed while the host ran the fixed probe this many times slower than its best is marked."""


def probe_ms() -> float:
    """Milliseconds of a fixed workload of the kind renders do (40 chained 256x256 float32 matmuls + tanh,
    torch's intra-op threads): the host's speed right now, independent of any method."""
    import torch

    g = torch.Generator().manual_seed(0)
    x = torch.randn(256, 256, generator=g)
    w = torch.randn(256, 256, generator=g) * 0.05
    t0 = time.perf_counter()
    for _ in range(40):
        x = torch.tanh(x @ w)
    return 1000.0 * (time.perf_counter() - t0)


def _probe_key() -> str:
    import platform

    import torch

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), cpu)
    except OSError:
        pass
    return f"{cpu}|cpus={os.cpu_count()}|threads={torch.get_num_threads()}|torch={torch.__version__}"


class HostSpeed:
    """How much slower than its best this host ran a fixed probe around a timed span.

    The probe (:func:`probe_ms`, median of 3) runs before and after the span;
    ``slowdown = max(before, after) / best``, where ``best`` is the fastest probe this
    machine (same CPU model, thread count and torch) has recorded in the ledger
    ``<cache>/host_probe.json`` (a first probe on a machine is compared with itself).
    It sees what :class:`OthersCPU` cannot: a virtual machine slowed by its hypervisor
    without guest-visible steal, frequency scaling, and threads of two processes
    oversubscribing the cores. ``ledger=None`` keeps no ledger (best = this span's probes).
    """

    def __init__(self, ledger: Path | None | str = "default", probe=None):
        from lmgs_eval.paths import cache_root

        self.ledger = cache_root() / "host_probe.json" if ledger == "default" else (Path(ledger) if ledger else None)
        self._probe = probe or (lambda: probe_ms())  # looked up at call time (tests replace it)
        self.before = self.after = self.best = self.slowdown = None

    def _median3(self) -> float:
        return float(np.median([self._probe() for _ in range(3)]))

    def __enter__(self) -> "HostSpeed":
        self._probe()  # warm-up (thread pool, allocator)
        self.before = self._median3()
        return self

    def __exit__(self, *exc) -> None:
        self.after = self._median3()
        best = min(self.before, self.after)
        key = _probe_key()
        if self.ledger is not None:
            import json

            from lmgs_eval.paths import atomic_write_text

            try:
                book = json.loads(self.ledger.read_text()) if self.ledger.exists() else {}
                if not isinstance(book, dict):
                    book = {}
            except (OSError, ValueError):
                book = {}  # an unreadable ledger is started again
            entry = book.get(key) if isinstance(book.get(key), dict) else {}
            known = entry.get("best_ms")
            if isinstance(known, (int, float)) and known > 0:
                best = min(best, float(known))
            book[key] = {"best_ms": best, "n": int(entry.get("n", 0)) + 1}
            try:
                self.ledger.parent.mkdir(parents=True, exist_ok=True)
                atomic_write_text(self.ledger, json.dumps(book, indent=1, sort_keys=True))
            except OSError:
                pass  # a read-only cache loses the ledger, not the timing
        self.best = best
        self.slowdown = max(self.before, self.after) / best if best > 0 else None

    def cost(self) -> dict:
        return {"host_probe_ms": [self.before, self.after], "host_probe_best_ms": self.best, "host_slowdown": self.slowdown}


def _own_cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system


def timed_render(method, driving: DrivingAudio, timings: dict | None = None,
                 repeats: int = REPEATS) -> tuple[np.ndarray, dict]:
    """Render after a short warm-up; FPS is audio in to frames out, I/O outside the timer.

    The clip is rendered up to ``repeats`` times (while the next repeat fits in
    :data:`REPEAT_BUDGET_S`) and the median run is reported (``repeats`` in the result). A method whose ``render`` takes
    ``timings=`` fills in seconds per stage (audio, network, raster) of that run.
    """
    import inspect

    kw = {"timings": timings} if timings is not None and "timings" in inspect.signature(method.render).parameters else {}
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


def fit_method(method, clip, subject, seed: int, progress: bool) -> dict:
    """Fit (or reload) a method; returns the cost of training."""
    info = method.describe()
    workdir = model_dir(subject, info.name, info.config_hash, seed)
    claim_model_dir(workdir, subject)
    reused = (workdir / "model.pt").exists()
    t0 = time.perf_counter()
    with OthersCPU() as busy:
        method.fit(clip, seed=seed, workdir=workdir, progress=progress)
    secs = time.perf_counter() - t0
    # a training resumed from a checkpoint: add what the interrupted runs had trained (lmgs saves it;
    # a reused model's time comes from its fit.json below)
    secs += float(getattr(getattr(method, "report", None), "prior_seconds", 0.0) or 0.0)
    rec = {"train_seconds": secs, "train_others_cpu_share": busy.share, "reused_checkpoint": reused, "workdir": str(workdir)}
    if reused:
        fit = _recorded_fit(workdir)
        rec["train_seconds"] = fit.get("train_seconds")
        rec["train_others_cpu_share"] = fit.get("train_others_cpu_share")
        rec["train_peak_mb"] = fit.get("peak_mb")  # this process did not train: the training's peak is there
    else:
        import json

        from lmgs_eval.paths import atomic_write_text

        atomic_write_text(workdir / "fit.json", json.dumps({"train_seconds": secs, "peak_mb": peak_rss_mb(),
                                                            "train_others_cpu_share": busy.share}))
    return rec


def _recorded_fit(workdir: Path) -> dict:
    """What ``fit.json`` says of the training that made a checkpoint (empty if it is not there)."""
    import json

    p = workdir / "fit.json"
    if p.exists():
        try:
            d = json.loads(p.read_text())
            return d if isinstance(d, dict) else {}
        except ValueError:
            return {}
    return {}


# ----------------------------------------------------------------------------- scoring
def score_clip(pred: np.ndarray, gt: np.ndarray | None, audio16k: np.ndarray | None, *, reference: bool = True,
               lmd: bool = True, alexnet: str | None = None) -> dict:
    """Every applicable metric on uint8 frames: PSNR, SSIM, LPIPS, LMD against ``gt``; LSE on the audio.

    Returns ``{name: MetricResult}``. The LPIPS network is the official one when the AlexNet
    trunk is on disk, else ST-LPIPS (a named stand-in).
    """
    from lmgs_eval.metrics.lpips import find_alexnet
    from lmgs_eval.metrics.registry import create_metric
    from lmgs_eval.metrics.sync import lse

    pf = pred.astype(np.float32) / 255.0
    out = {}
    if gt is not None and reference:
        gf = gt.astype(np.float32) / 255.0
        if gf.shape != pf.shape:
            raise UserError(f"rendered frames {pf.shape} and ground truth {gf.shape} differ")
        names = ["psnr", "ssim", "lpips-alex" if find_alexnet(alexnet) else "stlpips-alex"]
        if lmd:
            names.append("lmd")
        for name in names:
            m = create_metric(name, **({"alexnet": alexnet} if name == "lpips-alex" else {}))
            out[name] = m.compute(m.update(pf, gf))
    elif gt is not None and lmd:
        m = create_metric("lmd")
        out["lmd"] = m.compute(m.update(pf, gt.astype(np.float32) / 255.0))
    out["lse"] = lse(pf, audio16k, fps=25.0, audio_reason="" if audio16k is not None else "no audio")
    return out


def metrics_block(results: dict) -> dict:
    """MetricResults as the results file's ``metrics`` mapping (canonical keys, backends named)."""
    from lmgs_eval.results import metric_entries

    block = {}
    for r in results.values():
        block.update(metric_entries(r.to_dict()))
    return block


# ----------------------------------------------------------------------------- records
def _config_value(config, key: str):
    """The first ``key`` in a nested config dict (depth first), or None."""
    if isinstance(config, dict):
        if key in config:
            return config[key]
        for v in config.values():
            found = _config_value(v, key)
            if found is not None:
                return found
    return None


def budget_notes(info, subject) -> list[str]:
    """A record's note when its method was sized by the subject's own knee density."""
    from lmgs.presets import TrainConfig
    from lmgs_eval.results import BUDGET_NOTE

    d = getattr(subject, "budget_density", None)
    if d is None or _config_value(info.config, "budget_density") != d:
        return []
    return [f"{BUDGET_NOTE}{d:g} per pixel of face area, this subject's capacity knee (lmgs_eval.data.registry."
            f"KNEE_DENSITY), not the quick preset's {TrainConfig.budget_density:g}; every method sized by face area "
            "takes it on this subject"]


def _subject_block(subject) -> dict:
    return {
        "name": subject.name,
        "bundled": subject.bundled,
        "standin": subject.meta.get("standin") if subject.bundled else None,
        "frames": subject.n_frames,
        "width": subject.width,
        "height": subject.height,
        "path": str(subject.root),
        "sha256": subject_sha(subject),
    }


def stored(root, subject, method: str, protocol: str, clip: str, seed: int, config_hash: str, *,
           finished: bool = False) -> dict | None:
    """The store's record of this run on this subject's data, or None.

    ``finished``: a failed run counts as not done (it is retried). A record made on other data
    of a subject of the same name is a UserError (:func:`lmgs_eval.results.find_record`).
    """
    from lmgs_eval import results as store

    find = store.find_finished if finished else store.find_record
    return find(root, method, subject.name, protocol, clip, seed, config_hash, subject_sha(subject))


def subject_sha(subject) -> str | None:
    """sha256 of the subject's ``manifest.json`` (None without one): which data a record was made on."""
    p = subject.root / "manifest.json"
    return _sha_cached(p) if p.exists() else None


_SHA_CACHE: dict[tuple[str, int, int], str] = {}


def _sha_cached(path: Path) -> str:
    from lmgs_eval.results import sha256_file

    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _SHA_CACHE:
        _SHA_CACHE[key] = sha256_file(path)
    return _SHA_CACHE[key]


def input_artefacts(metrics: dict, subject) -> dict:
    """The inputs a record's numbers depend on, for ``lmgs-eval verify``: the subject's ground
    truth (its manifest, or its transforms files) and the weights files of the metrics used."""
    files: dict[str, Path | None] = {}
    root = Path(subject.root)
    if (root / "manifest.json").is_file():
        files["ground_truth"] = root / "manifest.json"
    else:
        for name in ("transforms_train.json", "transforms_val.json"):
            files[f"ground_truth:{name}"] = root / name
    lp = (metrics.get("lpips") or {}).get("backend")
    if lp:
        from lmgs_eval.metrics import lpips as L

        if lp == "stlpips-alex":
            files["weights:stlpips"] = L.stlpips_weights_path()
        elif lp == "lpips-alex":
            files["weights:lpips_heads"] = L.lpips_heads_path()
            files["weights:alexnet"] = L.find_alexnet()
    sb = (metrics.get("lse_d") or {}).get("backend") or ""
    if (metrics.get("lse_d") or {}).get("value") is not None:
        from lmgs_eval.metrics import sync as S

        if sb.endswith("bundled-sync"):
            files["weights:sync"] = S.BUNDLED_DIR / "bundled_sync.onnx"
        elif sb.endswith("syncnet-v2") and S.syncnet_manifest_path().is_file():
            import json

            files["weights:sync"] = Path(json.loads(S.syncnet_manifest_path().read_text())["onnx"])
    if (metrics.get("lmd") or {}).get("value") is not None:
        from lmgs_eval.metrics.landmarks import dlib_model_path

        files["weights:dlib"] = dlib_model_path()
    return {k: {"path": str(p.resolve()), "sha256": _sha_cached(p)} for k, p in files.items() if p is not None and p.is_file()}


def build_record(*, info, subject, protocol: str, clip: str, split: str, n_frames: int, seed: int, metrics: dict,
                 cost: dict, artefacts: dict, notes: list[str], control: dict | None = None) -> dict:
    """One results-file record (schema in :mod:`lmgs_eval.results`)."""
    from lmgs_eval.results import make_record

    method = {"name": info.name, "display_name": info.display_name, "family": info.family,
              "description": info.description, "standins": list(info.standins)}
    if control is not None:
        method["control"] = control
    if getattr(info, "variant", None) is not None:
        method["variant"] = info.variant
    notes = [*notes, *budget_notes(info, subject)]
    return make_record(
        method=method,
        subject=_subject_block(subject),
        protocol={"name": protocol, "version": PROTOCOL_VERSIONS[protocol], "clip": clip, "split": split, "n_frames": int(n_frames)},
        metrics=metrics, seed=seed, config=info.config, config_hash_=info.config_hash, cost=cost,
        artefacts={**input_artefacts(metrics, subject), **artefacts}, notes=notes,
    )


def _cost_block(method, fit_cost: dict | None, render_cost: dict, timings: dict | None = None) -> dict:
    import torch

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
        "device": c.get("device") or (None if pre else "cuda" if torch.cuda.is_available() else "cpu"),
    }


def render_stem(info, seed: int) -> str:
    """``<method>-<config hash[:8]>-seed<N>``: the file name of a run's render, distinct per config.

    Without the hash a re-run under a changed config overwrote the render an older record
    still points to (and hashes); the record then failed ``lmgs-eval verify``.
    """
    return f"{info.name.replace(':', '_')}-{info.config_hash[:8]}-seed{seed}"


def _write_render(root: Path, rel: str, frames: np.ndarray, audio: np.ndarray) -> dict:
    """Write an mp4 with its driving audio under the store root; the artefact entry (relative path)."""
    from lmgs_eval.data.io import write_video
    from lmgs_eval.results import sha256_file

    path = Path(root) / rel
    write_video(path, frames, 25, audio, 16000)
    return {"path": rel, "sha256": sha256_file(path)}


# ----------------------------------------------------------------------------- self
def run_self(cfg: RunConfig) -> list[dict]:
    """The self-driven protocol for every method and seed; returns the records written."""
    from lmgs_eval import results as store
    from lmgs_eval.data.registry import find_subject
    from lmgs_eval.methods import MethodInfo, create_method, driving_from_subject, subject_to_clip

    subject = find_subject(cfg.subject, cfg.data_root, progress=cfg.progress)
    log(f"subject {subject.name}: {subject.n_frames} frames {subject.width}x{subject.height}, "
        f"{len(subject.train_ids)} train / {len(subject.test_ids)} test" + (" (bundled stand-in)" if subject.bundled else ""))
    train = subject_to_clip(subject, subject.train_ids, progress=cfg.progress)
    test = subject_to_clip(subject, subject.test_ids, progress=cfg.progress)
    driving = driving_from_subject(subject, subject.test_ids, test)
    gt = test.frames
    renders_dir = f"renders/{subject.name}"
    records = []

    # The paper's "Ground Truth" row: the real test video scored like any method.
    gt_info = MethodInfo("ground-truth", "Ground Truth", "ground-truth", "the test split's own frames and audio", config={}, config_hash="gt")
    if cfg.force or stored(cfg.results, subject, "ground-truth", "self", "test", 0, "gt") is None:
        log("scoring the ground truth")
        res = score_clip(gt, gt, test.audio)
        art = {"render": _write_render(cfg.results, f"{renders_dir}/ground-truth.mp4", gt, test.audio)}
        rec = build_record(info=gt_info, subject=subject, protocol="self", clip="test", split="test", n_frames=len(gt), seed=0,
                           metrics=metrics_block(res), cost={}, artefacts=art, notes=list(subject.notes))
        store.write_record(cfg.results, rec)
        records.append(rec)

    records += run_plate_reference(cfg, subject, test)
    records += run_controls(cfg, subject, gt, test.audio, train.audio)

    for name in cfg.methods:
        for seed in cfg.seeds:
            opts = dict(cfg.method_options)
            if name.startswith("external:"):
                opts["renders"] = cfg.renders
            else:
                opts.setdefault("preset", cfg.preset)
            method = create_method(name, subject=subject, **opts)
            info = method.describe()
            if not cfg.force and stored(cfg.results, subject, info.name, "self", "test", seed, info.config_hash):
                log(f"{info.name} seed {seed}: already in {cfg.results} (same config {info.config_hash}); skipped")
                continue
            records.append(fit_render_score(cfg, method, subject, seed, train, driving, gt,
                                            f"{renders_dir}/{render_stem(info, seed)}.mp4"))
    return records


PLATE_VERSION = "1"
PLATE_DESCRIPTION = (
    "the test frames inside the subject's head mask (parsing, head colour) composited on its plate (torso_imgs over "
    "bc.jpg) outside it, as every method's head is: what a renderer drawing the head exactly, and nothing outside "
    "the head mask, would score. Well below the Ground Truth, it says the frames show something outside the head "
    "that the plate does not (a method that also paints there can score above it)")


def plate_composite(clip) -> np.ndarray | None:
    """``uint8 [N, H, W, 3]``: the clip's frames inside its head masks, its plate outside (None without masks)."""
    if clip.head_masks is None:
        return None
    return np.where(clip.head_masks[..., None], clip.frames, clip.backgrounds)


def plate_reference_psnr(subject) -> float | None:
    """Mean PSNR (dB) of :func:`plate_composite` on the test split, or None without head masks."""
    from lmgs_eval.methods import subject_to_clip
    from lmgs_eval.metrics.image import psnr

    test = subject_to_clip(subject, subject.test_ids)
    frames = plate_composite(test)
    return None if frames is None else float(psnr(frames / 255.0, test.frames / 255.0).value)


def run_plate_reference(cfg: RunConfig, subject, test) -> list[dict]:
    """Table I's reference row "GT head on plate" (skipped without head masks or when in the store)."""
    from lmgs_eval import results as store
    from lmgs_eval.methods import MethodInfo

    info = MethodInfo("plate-reference", "GT head on plate", "reference", PLATE_DESCRIPTION,
                      config={"version": PLATE_VERSION}, config_hash=f"plate-v{PLATE_VERSION}")
    if not cfg.force and stored(cfg.results, subject, info.name, "self", "test", 0, info.config_hash):
        return []
    frames = plate_composite(test)
    if frames is None:
        log(f"no head masks (parsing/) in {subject.name}: no 'GT head on plate' reference row")
        return []
    log("scoring the ground truth's head on the plate (reference row)")
    res = score_clip(frames, test.frames, test.audio)
    art = {"render": _write_render(cfg.results, f"renders/{subject.name}/plate-reference.mp4", frames, test.audio)}
    rec = build_record(info=info, subject=subject, protocol="self", clip="test", split="test", n_frames=len(frames),
                       seed=0, metrics=metrics_block(res), cost={}, artefacts=art, notes=list(subject.notes))
    store.write_record(cfg.results, rec)
    return [rec]


def fit_render_score(cfg: RunConfig, method, subject, seed: int, train, driving: DrivingAudio, gt: np.ndarray, render_rel: str,
                     protocol: str = "self", clip: str = "test") -> dict:
    """Fit (or reload) one method, render the test split from its audio, score, record; returns the record."""
    from lmgs_eval import results as store

    info = method.describe()
    timings: dict = {}
    if getattr(method, "prerendered", False):
        # Frames rendered elsewhere: nothing to fit and nothing to time here (reading files is
        # not rendering); the cost comes from the method's sidecar or stays empty.
        fit_cost, rc = None, {}
        frames = method.render(driving)
        log(f"{info.name}: {len(frames)} frames read from its renders; scoring")
    else:
        log(f"{info.name} seed {seed}: fitting on {len(train)} frames")
        fit_cost = fit_method(method, train, subject, seed, cfg.progress)
        frames, rc = timed_render(method, driving, timings)
        log(f"{info.name}: {len(frames)} frames at {rc['fps']:.1f} FPS; scoring")
    res = score_clip(frames, gt, driving.audio)
    art = {"render": _write_render(cfg.results, render_rel, frames, driving.audio)}
    ck = Path(fit_cost["workdir"]) / "model.pt" if fit_cost else None
    if ck is not None and ck.exists():
        art["checkpoint"] = {"path": str(ck), "sha256": store.sha256_file(ck)}
    notes = list(subject.notes)
    if timings.get("se_fraction") is not None:
        theta = (info.config.get("guidance") or {}).get("theta")
        notes.append(store.SE_NOTE.format(pct=100 * timings["se_fraction"])
                     + (f" (theta = {theta:g}; the paper reports about 20% at 0.6)" if theta is not None else ""))
    rec = build_record(info=info, subject=subject, protocol=protocol, clip=clip, split="test", n_frames=len(frames),
                       seed=seed, metrics=metrics_block(res), cost=_cost_block(method, fit_cost, rc, timings or None),
                       artefacts=art, notes=notes)
    store.write_record(cfg.results, rec)
    return rec


# ----------------------------------------------------------------------------- calibration
CONTROLS_VERSION = "1"
SHIFTS = (-10, -5, 5, 10)


def shift_audio(audio: np.ndarray, frames: int, fps: int = 25, sr: int = 16000) -> np.ndarray:
    """The audio moved by ``frames`` video frames (positive: later), circularly, same length."""
    return np.roll(np.asarray(audio, np.float32), int(round(frames * sr / fps)))


def control_clips(gt: np.ndarray, audio: np.ndarray, other_audio: np.ndarray) -> list[tuple[str, str, dict, np.ndarray, np.ndarray]]:
    """The negative controls of issue 9: ``(name, display, control, frames, audio)``.

    * ground truth with its audio shifted by -10, -5, +5, +10 frames: LSE-D/LSE-C take the
      best of +-15 offsets by definition, so these target the AV offset;
    * ground truth with audio from elsewhere in the recording (same voice, other words):
      targets LSE-D, LSE-C and the AV offset;
    * the first ground-truth frame repeated, with the true audio: targets LMD and LSE.
    """
    n = len(audio)
    other = np.asarray(other_audio, np.float32)
    if len(other) >= 2 * n:  # start half-way in, far from the test split's neighbour frames
        other = other[len(other) // 2 - n // 2:][:n] if len(other) // 2 + n // 2 <= len(other) else other[-n:]
    other = _cycle(other, n) if len(other) else np.zeros(n, np.float32)
    out = []
    for k in SHIFTS:
        out.append((f"control:gt-audio{k:+d}", f"GT, audio {k:+d} frames", {"kind": "audio-shift", "frames": k, "targets": ["av_offset"]},
                    gt, shift_audio(audio, k)))
    out.append(("control:gt-other-audio", "GT, other audio", {"kind": "other-audio", "targets": ["lse_d", "lse_c", "av_offset"]},
                gt, other))
    still = np.repeat(gt[:1], len(gt), axis=0)
    out.append(("control:still-frame", "Still frame", {"kind": "still-frame", "targets": ["lmd", "lse_d", "lse_c"]}, still, audio))
    return out


def run_controls(cfg: RunConfig, subject, gt: np.ndarray, audio: np.ndarray, other_audio: np.ndarray) -> list[dict]:
    """Score the calibration controls (recorded under protocol ``calibration``); skips those in the store."""
    from lmgs_eval import results as store
    from lmgs_eval.methods import MethodInfo
    from lmgs_eval.metrics.registry import create_metric
    from lmgs_eval.metrics.sync import crop_faces, face_boxes, lse

    todo = [c for c in control_clips(gt, audio, other_audio)
            if cfg.force or stored(cfg.results, subject, c[0], "calibration", "test", 0, f"controls-v{CONTROLS_VERSION}") is None]
    if not todo:
        return []
    log(f"scoring {len(todo)} calibration controls")
    gf = gt.astype(np.float32) / 255.0
    gt_crops = None
    records = []
    for name, display, control, frames, aud in todo:
        if frames is gt:  # same frames as the ground truth: reuse its face crops
            if gt_crops is None:
                try:
                    gt_crops = crop_faces(gf, face_boxes(gf)[0])
                except UserError:  # no face: lse() reports it as unavailable
                    gt_crops = False
            res = {"lse": lse(gf, aud, crops=gt_crops if gt_crops is not False else None)}
        else:
            pf = frames.astype(np.float32) / 255.0
            res = {"lse": lse(pf, aud)}
            m = create_metric("lmd")
            res["lmd"] = m.compute(m.update(pf, gf))
        info = MethodInfo(name, display, "control", f"negative control: {display} (targets {', '.join(control['targets'])})",
                          config={"control": control, "version": CONTROLS_VERSION}, config_hash=f"controls-v{CONTROLS_VERSION}")
        rec = build_record(info=info, subject=subject, protocol="calibration", clip="test", split="test", n_frames=len(frames),
                           seed=0, metrics=metrics_block(res), cost={}, artefacts={}, notes=list(subject.notes), control=control)
        store.write_record(cfg.results, rec)
        records.append(rec)
    return records


# ----------------------------------------------------------------------------- cross
@dataclass(frozen=True)
class CrossClip:
    """A driving clip of the cross-driven protocol (and its ground truth when it has one)."""

    name: str
    audio: np.ndarray  # 16 kHz mono
    source: str
    w2c: np.ndarray | None = None
    gt_frames: np.ndarray | None = None
    notes: tuple[str, ...] = ()


def bundled_cross_clips(subject) -> list[CrossClip]:
    """The bundled subject's clips A and B (voices and texts not used in training, with GT)."""
    import json

    from lmgs.types import Camera
    from lmgs_eval.data.io import load_audio, read_rgb_u8

    clips = []
    for name in ("A", "B"):
        d = subject.root / "cross" / name
        if not (d / "aud.wav").exists():
            continue
        audio, notes = load_audio(d / "aud.wav")
        w2c = gt = None
        tj = d / "transforms.json"
        if tj.exists():
            t = json.loads(tj.read_text())
            frames = sorted(t["frames"], key=lambda f: int(f["img_id"]))
            w2c = np.stack([Camera.from_nerf_c2w(np.asarray(f["transform_matrix"]), t["focal_len"], subject.width, subject.height,
                                                 t.get("cx"), t.get("cy")).world_to_camera.numpy() for f in frames])
            if (d / "gt_imgs").is_dir():
                gt = np.stack([read_rgb_u8(d / "gt_imgs" / f"{int(f['img_id'])}.jpg") for f in frames])
        clips.append(CrossClip(name, audio, str(d), w2c, gt, tuple(notes)))
    return clips


def user_cross_clips(paths: list[str]) -> tuple[list[CrossClip], list[str]]:
    """User audio files (any rate, mono or stereo). Bad files are reported and skipped."""
    from lmgs_eval.data.io import load_audio

    clips, errors = [], []
    for p in paths:
        try:
            audio, notes = load_audio(Path(p))
        except UserError as exc:
            errors.append(str(exc))
            continue
        if len(audio) < 5 * 640:
            errors.append(f"{p}: {len(audio) / 16000:.2f} s of audio is shorter than 5 frames (0.2 s)")
            continue
        if float(np.max(np.abs(audio))) == 0.0:
            notes.append(f"{p}: the audio is digital silence")
        clips.append(CrossClip(Path(p).stem, audio, str(p), None, None, tuple(notes)))
    return clips, errors


def _cycle(a: np.ndarray, n: int) -> np.ndarray:
    reps = int(np.ceil(n / len(a)))
    return np.concatenate([a] * reps)[:n]


def run_cross(cfg: RunConfig, audio_paths: list[str] | None = None) -> tuple[list[dict], list[str]]:
    """Drive trained models with other audio; LSE per clip, and LMD where the clip has GT.

    Returns the records written and the per-file errors (the other clips still run).
    """
    from lmgs_eval import results as store
    from lmgs_eval.data.registry import find_subject
    from lmgs_eval.methods import create_method, subject_to_clip

    subject = find_subject(cfg.subject, cfg.data_root, progress=cfg.progress)
    if audio_paths:
        clips, errors = user_cross_clips(audio_paths)
    else:
        clips, errors = bundled_cross_clips(subject), []
        if not clips:
            raise UserError(f"{subject.root}: no bundled cross-driven clips (cross/A, cross/B); pass --audio A.wav B.wav")
    if not clips:
        return [], errors
    train = None
    test = subject_to_clip(subject, subject.test_ids)
    renders_dir = f"renders/{subject.name}"
    records = []
    for name in cfg.methods:
        if name.startswith("external:"):
            errors.append(f"{name}: cross-driven renders of external methods are scored with `lmgs-eval score --pred`")
            continue
        for seed in cfg.seeds:
            method = create_method(name, subject=subject, **{"preset": cfg.preset, **cfg.method_options})
            info = method.describe()
            todo = [c for c in clips if cfg.force or not stored(cfg.results, subject, info.name, "cross", c.name, seed, info.config_hash)]
            if not todo:
                log(f"{info.name} seed {seed}: cross clips already in {cfg.results}; skipped")
                continue
            if train is None:
                train = subject_to_clip(subject, subject.train_ids, progress=cfg.progress)
            fit_cost = fit_method(method, train, subject, seed, cfg.progress)
            for c in todo:
                n = len(c.audio) // 640
                w2c = c.w2c[:n] if c.w2c is not None and len(c.w2c) >= n else _cycle(test.w2c, n)
                backs = _cycle(test.backgrounds, n)
                driving = DrivingAudio(audio=c.audio[: n * 640], w2c=w2c, backgrounds=backs)
                frames, rc = timed_render(method, driving)
                log(f"{info.name} on clip {c.name}: {n} frames at {rc['fps']:.1f} FPS; scoring")
                gt = c.gt_frames[:n] if c.gt_frames is not None and len(c.gt_frames) >= n else None
                res = score_clip(frames, gt, driving.audio, reference=False, lmd=gt is not None)
                art = {"render": _write_render(cfg.results, f"{renders_dir}/{render_stem(info, seed)}-cross-{c.name}.mp4", frames, driving.audio)}
                rec = build_record(info=info, subject=subject, protocol="cross", clip=c.name, split=c.source, n_frames=n, seed=seed,
                                   metrics=metrics_block(res), cost=_cost_block(method, fit_cost, rc), artefacts=art,
                                   notes=list(c.notes))
                store.write_record(cfg.results, rec)
                records.append(rec)
    return records, errors
