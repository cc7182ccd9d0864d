"""The protocols' metrics as one suite: each network, ONNX session and detector loaded once per run.

A protocol run scores many clips (the ground truth, its controls, every method and seed). The
suite builds each metric (LPIPS's session, dlib's detector and predictor, the sync scorer) the
first time it is needed and reuses it for every later clip. It pickles without what it loaded, so
a worker process that receives it loads its own copies.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.base import MetricResult, merge_stats
from lmgs_eval.data.frames import CHUNK
from lmgs_eval.metrics.landmarks import frames_digest
from lmgs_eval.metrics.lpips import ALEX_NAMES, find_alexnet
from lmgs_eval.metrics.registry import create_metric
from lmgs_eval.metrics.sync import lse
from lmgs_eval.metrics.sync_select import set_backend


class MetricSuite:
    """Every applicable metric on uint8 frames: PSNR, SSIM, LPIPS, LMD against ground truth; LSE on the audio.

    Args:
        alexnet: an AlexNet trunk checkpoint for the official LPIPS (else found in the torch hub
            caches; without one, ST-LPIPS, a named stand-in, is used).
        sync: the LSE scorer (``--sync``: ``auto``, ``landmark``, ``pixel``, ``syncnet-v2``); its
            networks are loaded once per process by :mod:`lmgs_eval.metrics.sync_select`.
    """

    def __init__(self, alexnet: str | None = None, sync: str = "auto"):
        self.alexnet = alexnet
        self.sync = sync
        self._metrics: dict[str, Any] = {}
        self.timings: dict[str, float] = {}
        self._lpips_name = ""

    def __getstate__(self) -> dict:
        return {"alexnet": self.alexnet, "sync": self.sync, "_metrics": {}, "timings": {}, "_lpips_name": ""}

    @property
    def lpips_name(self) -> str:
        """The LPIPS network asked for: ``lpips-alex`` when a trunk is found (its result is named
        ``lpips-alex-custom`` when the trunk is not torchvision's), else ``stlpips-alex``."""
        if self._lpips_name:
            return self._lpips_name
        return "lpips-alex" if find_alexnet(self.alexnet) else "stlpips-alex"

    def use_lpips(self, metric) -> None:
        """Score LPIPS with an already built :class:`~lmgs_eval.metrics.lpips.LPIPS` (benchmarks, tests)."""
        self._lpips_name = metric.spec.name
        self._metrics[metric.spec.name] = metric

    def metric(self, name: str):
        """The paired metric ``name`` (``psnr``, ``ssim``, ``lpips-alex``, ``stlpips-alex``, ``lmd``), built once."""
        if name not in self._metrics:
            self._metrics[name] = create_metric(name, **({"alexnet": self.alexnet} if name in ALEX_NAMES else {}))
        return self._metrics[name]

    def paired(self, name: str, pred: np.ndarray, gt: np.ndarray) -> MetricResult:
        """One paired metric of float frames in [0, 1] (or uint8 for LPIPS and LMD; its result's ``spec.name`` may differ from ``name``:
        ``lpips-alex`` scores as ``lpips-alex-custom`` with a trunk that is not torchvision's)."""
        m = self.metric(name)
        return m.compute(m.update(pred, gt))

    def lse(self, frames: np.ndarray, audio16k: np.ndarray | None, *, in_sync: bool = False, **kw) -> MetricResult:
        """LSE-D / LSE-C / offset and its self-check, with the run's sync scorer (``in_sync``: see :meth:`score`)."""
        set_backend(self.sync)  # this process's selection (a worker process gets the run's too)
        return lse(frames, audio16k, fps=25.0, reference=in_sync, **kw)

    def score(self, pred: np.ndarray, gt: np.ndarray | None, audio16k: np.ndarray | None, *, reference: bool = True,
              lmd: bool = True, in_sync: bool = False) -> dict[str, MetricResult]:
        """Every applicable metric of uint8 frames ``pred`` (against ``gt``); ``{name: MetricResult}``.

        ``in_sync``: the frames and audio are known to be in sync (the ground truth), so the LSE
        self-check also requires an AV offset of 0 +- 1 frame.

        The ground truth's side is computed once per clip: its LPIPS features are kept (keyed by
        the frames' sha256) and its landmarks are cached on disk; LSE reads the landmarks LMD found
        on ``pred`` instead of detecting the face again. Seconds per metric: :attr:`timings`.
        """
        clock = time.perf_counter
        self.timings = {}
        t0 = clock()
        out = {}
        pred_lms = None
        if gt is not None and (reference or lmd):
            if gt.shape != pred.shape:
                raise UserError(f"rendered frames {tuple(pred.shape)} and ground truth {tuple(gt.shape)} differ")
            gt_key = frames_digest(gt)
            same = pred is gt  # the ground-truth row: its side is computed once
            self.timings["convert+hash"] = clock() - t0
            names = ["psnr", "ssim", self.lpips_name] if reference else []
            for name in names:
                t = clock()
                m = self.metric(name)
                if name == self.lpips_name:  # uint8 frames, converted a batch at a time
                    r = m.compute(m.update(pred, gt, gt_key=gt_key, same=same))
                    if m.cache_note:
                        r.notes.append(m.cache_note)
                else:
                    r = m.compute(merge_stats(m.update(_unit(pred[s:s + CHUNK]), _unit(gt[s:s + CHUNK]))
                                              for s in range(0, len(pred), CHUNK)))
                out[r.spec.name] = r  # an official trunk's result is lpips-alex, another's lpips-alex-custom
                self.timings[r.spec.name] = clock() - t
            if lmd:
                t = clock()
                m = self.metric("lmd")
                stats = m.update(pred, gt, same=same, gt_key=gt_key)  # the tracker reads uint8 frames as they are
                out["lmd"] = m.compute(stats)
                pred_lms = stats["pred_lms"]
                self.timings["lmd"] = clock() - t
        t = clock()
        out["lse"] = self.lse(pred, audio16k, audio_reason="" if audio16k is not None else "no audio", in_sync=in_sync,
                              lms=pred_lms)
        self.timings["lse"] = clock() - t
        self.timings["total"] = clock() - t0
        return out


def _unit(x: np.ndarray) -> np.ndarray:
    """uint8 frames as float32 in [0, 1] (a chunk at a time: the suite never holds a float copy of a clip)."""
    return x.astype(np.float32) / 255.0
