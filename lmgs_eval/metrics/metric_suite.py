"""The metrics as one suite, the only way anything is scored: each network, ONNX session and detector loaded once.

A protocol run scores many clips (the ground truth, its controls, every method and seed);
``lmgs-eval score`` scores one pair of files. The suite is built from the run's
:class:`~lmgs_eval.metrics.config.SuiteConfig` (``--sync``, ``--lpips``, ``--alexnet``,
``--landmarks``): the sync scorer choice is resolved when the suite is made
(:class:`~lmgs_eval.metrics.sync.select.SyncScorers`) and the LSE metric is built with it; every
metric (LPIPS's session, dlib's detector and predictor, the sync scorers) is built from the
registry the first time it is needed and reused for every later clip. The suite pickles as its
config, so a worker process that receives it resolves the same choices and loads its own copies.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from lmgs_eval.data.frames import chunk_for
from lmgs_eval.errors import UserError
from lmgs_eval.metrics.base import MetricResult, merge_stats
from lmgs_eval.metrics.config import SuiteConfig
from lmgs_eval.metrics.landmarks import frames_digest
from lmgs_eval.metrics.registry import create_metric
from lmgs_eval.metrics.sync.crops import FaceClip
from lmgs_eval.metrics.sync.select import SyncScorers

METRIC_NAMES = ("psnr", "ssim", "lpips", "lmd", "lse")
REFERENCE_METRICS = ("psnr", "ssim", "lpips", "lmd")
"""The suite's metrics (``score --metrics``); the first four compare with the ground truth."""
IMAGE_METRICS = ("psnr", "ssim", "lpips")


class MetricSuite:
    """Every applicable metric on uint8 frames: PSNR, SSIM, LPIPS, LMD against ground truth; LSE on the audio.

    Args:
        config: the run's scoring choices (default: ``--sync auto``, LPIPS by the trunk found, dlib).
    """

    def __init__(self, config: SuiteConfig | None = None):
        self.config = config or SuiteConfig()
        self.sync = SyncScorers(self.config.sync)  # the --sync choice, resolved once; LSE is built with it
        self._metrics: dict[str, Any] = {}
        self.timings: dict[str, float] = {}

    def __reduce__(self):
        return MetricSuite, (self.config,)

    @property
    def lpips_name(self) -> str:
        """The LPIPS network's result name: ``lpips-alex`` (``lpips-alex-custom`` for a trunk that is not
        torchvision's) when a trunk is found, else ``stlpips-alex`` (builds the metric)."""
        return self.metric("lpips").spec.name

    def use_lpips(self, metric) -> None:
        """Score LPIPS with an already built :class:`~lmgs_eval.metrics.lpips.LPIPS` (benchmarks, tests)."""
        self._metrics["lpips"] = metric

    def metric(self, name: str):
        """The metric ``name`` of the registry (``psnr``, ``ssim``, ``lpips``, ``lmd``, ``lse``...), built once with
        the suite's choices."""
        if name not in self._metrics:
            self._metrics[name] = create_metric(name, **vars(self.config), scorers=self.sync)
        return self._metrics[name]

    def paired(self, name: str, pred: np.ndarray, gt: np.ndarray) -> MetricResult:
        """One paired metric of uint8 frames, the ground truth's side cached as in :meth:`score` (its result's
        ``spec.name`` may differ from ``name``: ``lpips`` is the network the choices give)."""
        m = self.metric(name)
        return m.compute(m.stream(frames_digest(gt), pred is gt)(pred, gt))

    def lse(self, frames, audio16k: np.ndarray | None, *, in_sync: bool = False, fps: float = 25.0,
            **kw) -> MetricResult:
        """LSE-D / LSE-C / offset and its self-check, with the run's sync scorer (``in_sync``: see :meth:`score`)."""
        return self.metric("lse").score(frames, audio16k, fps=fps, reference=in_sync, **kw)

    def score(self, pred, gt, audio16k: np.ndarray | None, *, reference: bool = True, lmd: bool = True,
              in_sync: bool = False, metrics=METRIC_NAMES, n: int | None = None, fps: float = 25.0,
              audio_reason: str = "no audio", flags: tuple[str, ...] = ()) -> dict[str, MetricResult]:
        """Every applicable metric of ``pred`` (against ``gt``); ``{name: MetricResult}``.

        Args:
            pred, gt: uint8 frames ``[T, H, W, 3]``, or :class:`~lmgs_eval.data.frames.FrameFile` s read in step a
                few frames at a time (never held whole); ``gt`` None: LSE only.
            audio16k: 16 kHz mono audio, or None (LSE unavailable with ``audio_reason``).
            reference, lmd: score PSNR, SSIM, LPIPS / LMD (when there is a ``gt``).
            in_sync: the frames and audio are known to be in sync (the ground truth), so the LSE
                self-check also requires an AV offset of 0 +- 1.
            metrics: the subset of :data:`METRIC_NAMES` to score.
            n: frames to score (files: the common length); fps: the clip's rate.
            flags: how the two clips were aligned (a truncation), added to each paired metric's flags.

        The ground truth's side of held frames is computed once per clip: its LPIPS features are
        kept (keyed by the frames' sha256) and its landmarks are cached on disk; LSE reads the
        landmarks LMD found on ``pred`` instead of detecting the face again. Seconds per metric: :attr:`timings`.
        """
        clock = time.perf_counter
        self.timings = {}
        t0 = clock()
        out = {}
        sync_lms = None
        held = isinstance(pred, np.ndarray)
        n = len(pred) if n is None and held else n
        names = [m for m in metrics if m in REFERENCE_METRICS and (reference or m not in IMAGE_METRICS) and (lmd or m != "lmd")]
        if gt is not None and names:
            gt_key, same = None, False
            if held:  # the ground truth's side is computed once per clip, keyed by its content
                if gt.shape != pred.shape:
                    raise UserError(f"rendered frames {tuple(pred.shape)} and ground truth {tuple(gt.shape)} differ")
                gt_key, same = frames_digest(gt), pred is gt
                self.timings["convert+hash"] = clock() - t0
            made = {name: self.metric(name) for name in names}
            feeds = {name: m.stream(gt_key, same) for name, m in made.items()}
            parts: dict[str, list] = {name: [] for name in made}
            spent = dict.fromkeys(made, 0.0)
            got = 0
            for cp, cg in _in_step(pred, gt, n):
                for name, feed in feeds.items():
                    t = clock()
                    parts[name].append(feed(cp, cg))
                    spent[name] += clock() - t
                got += len(cp)
            if got != n:
                raise UserError(f"{pred.path} and {gt.path}: {got} frame pairs decoded where {n} were counted; the "
                                "shorter file is corrupt or truncated")
            for name, m in made.items():
                t = clock()
                stats = merge_stats(parts[name])
                r = m.compute(stats)
                r.flags = sorted(set(r.flags + list(flags)))
                out[r.spec.name] = r  # an official trunk's result is lpips-alex, another's lpips-alex-custom
                self.timings[r.spec.name] = spent[name] + clock() - t
                if hasattr(m, "sync_landmarks"):
                    sync_lms = m.sync_landmarks(stats)
        if "lse" in metrics:
            t = clock()
            if held:
                video, lms = pred, sync_lms
            else:  # a file, decoded again as LSE needs it; LMD's landmarks go with it
                video, lms = FaceClip(pred.head(n), lms=sync_lms), None
            out["lse"] = self.lse(video, audio16k, audio_reason="" if audio16k is not None else audio_reason,
                                  in_sync=in_sync, fps=fps, lms=lms)
            self.timings["lse"] = clock() - t
        self.timings["total"] = clock() - t0
        return out


def _in_step(pred, gt, n: int):
    """Both clips a chunk at a time: held frames as one chunk (the ground-truth caches key on whole clips),
    files as :func:`~lmgs_eval.data.frames.chunk_for` frames (stopping at the shorter one)."""
    if isinstance(pred, np.ndarray):
        yield pred[:n], gt[:n]
        return
    size = chunk_for(pred.height, pred.width)
    for cp, cg in zip(pred.chunks(size, stop=n), gt.chunks(size, stop=n)):
        if len(cp) != len(cg):
            break
        yield cp, cg
