"""The protocols' metrics as one suite: each network, ONNX session and detector loaded once per run.

A protocol run scores many clips (the ground truth, its controls, every method and seed). The
suite builds each metric (LPIPS's session, dlib's detector and predictor, the sync scorer) the
first time it is needed and reuses it for every later clip. It pickles without what it loaded, so
a worker process that receives it loads its own copies.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.base import MetricResult
from lmgs_eval.metrics.lpips import find_alexnet
from lmgs_eval.metrics.registry import create_metric
from lmgs_eval.metrics.sync import find_scorer, lse


class MetricSuite:
    """Every applicable metric on uint8 frames: PSNR, SSIM, LPIPS, LMD against ground truth; LSE on the audio.

    Args:
        alexnet: an AlexNet trunk checkpoint for the official LPIPS (else found in the torch hub
            caches; without one, ST-LPIPS, a named stand-in, is used).
    """

    def __init__(self, alexnet: str | None = None):
        self.alexnet = alexnet
        self._metrics: dict[str, Any] = {}
        self._scorer: tuple[Any, str] | None = None

    def __getstate__(self) -> dict:
        return {"alexnet": self.alexnet, "_metrics": {}, "_scorer": None}

    @property
    def lpips_name(self) -> str:
        return "lpips-alex" if find_alexnet(self.alexnet) else "stlpips-alex"

    def metric(self, name: str):
        """The paired metric ``name`` (``psnr``, ``ssim``, ``lpips-alex``, ``stlpips-alex``, ``lmd``), built once."""
        if name not in self._metrics:
            self._metrics[name] = create_metric(name, **({"alexnet": self.alexnet} if name == "lpips-alex" else {}))
        return self._metrics[name]

    def paired(self, name: str, pred: np.ndarray, gt: np.ndarray) -> MetricResult:
        """One paired metric of float frames in [0, 1]."""
        m = self.metric(name)
        return m.compute(m.update(pred, gt))

    def lse(self, frames: np.ndarray, audio16k: np.ndarray | None, **kw) -> MetricResult:
        """LSE-D / LSE-C / offset with the run's sync scorer (found once)."""
        if self._scorer is None:
            self._scorer = find_scorer()
        scorer, _ = self._scorer
        return lse(frames, audio16k, fps=25.0, scorer=scorer, **kw)

    def score(self, pred: np.ndarray, gt: np.ndarray | None, audio16k: np.ndarray | None, *, reference: bool = True,
              lmd: bool = True) -> dict[str, MetricResult]:
        """Every applicable metric of uint8 frames ``pred`` (against ``gt``); ``{name: MetricResult}``."""
        pf = pred.astype(np.float32) / 255.0
        out = {}
        if gt is not None and (reference or lmd):
            gf = gt.astype(np.float32) / 255.0
            if gf.shape != pf.shape:
                raise UserError(f"rendered frames {pf.shape} and ground truth {gf.shape} differ")
            names = ["psnr", "ssim", self.lpips_name] if reference else []
            if lmd:
                names.append("lmd")
            for name in names:
                out[name] = self.paired(name, pf, gf)
        out["lse"] = self.lse(pf, audio16k, audio_reason="" if audio16k is not None else "no audio")
        return out
