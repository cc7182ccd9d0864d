"""The table of metrics: ``create_metric(name)``, ``list_metrics()`` and backend availability."""

from __future__ import annotations

import importlib.util

from lmgs_eval.metrics.base import MetricSpec, Registry
from lmgs_eval.metrics.image import PSNR, PSNR_SPEC, SSIM, SSIM_SPEC
from lmgs_eval.metrics.landmarks import LMD, LMD_SPEC, available_backends, create_backend
from lmgs_eval.metrics.lpips import (
    LPIPS,
    LPIPS_ALEX_SPEC,
    STLPIPS_ALEX_SPEC,
    find_alexnet,
    lpips_heads_path,
    stlpips_weights_path,
)
from lmgs_eval.metrics.sync import LSE_SPEC, find_scorer_status

METRICS = Registry("metric")


def _psnr(**kw):
    return PSNR()


def _ssim(**kw):
    return SSIM()


def _lpips_alex(alexnet=None, **kw):
    return LPIPS("lpips-alex", alexnet=alexnet, **kw)


def _stlpips_alex(**kw):
    kw.pop("alexnet", None)

    return LPIPS("stlpips-alex", **kw)


def _lmd(backend="dlib", **kw):
    return LMD(create_backend(backend))


METRICS.register("psnr", _psnr)
METRICS.register("ssim", _ssim)
METRICS.register("lpips-alex", _lpips_alex)
METRICS.register("stlpips-alex", _stlpips_alex)
METRICS.register("lmd", _lmd)


def create_metric(name: str, **kw):
    """Build a paired frame metric by name (``update`` / ``compute``; see :class:`Accumulator`).

    LSE is not a paired metric: use :func:`lmgs_eval.metrics.sync.lse`.
    """
    return METRICS.get(name)(**kw)


def specs() -> dict[str, MetricSpec]:
    return {s.name: s for s in (PSNR_SPEC, SSIM_SPEC, LPIPS_ALEX_SPEC, STLPIPS_ALEX_SPEC, LMD_SPEC, LSE_SPEC)}


def list_metrics(alexnet=None) -> list[dict]:
    """Every metric with its spec and whether it can run on this machine (and why not)."""
    trunk = find_alexnet(alexnet)
    lm = available_backends()
    ok_ort = importlib.util.find_spec("onnxruntime") is not None
    avail = {
        "psnr": (True, "closed form"),
        "ssim": (True, "closed form"),
        "lpips-alex": (trunk is not None and lpips_heads_path() is not None and ok_ort,
                       f"trunk {trunk}" if trunk else "AlexNet trunk alexnet-owt-7be5be79.pth not found (--alexnet PATH)"),
        "stlpips-alex": (stlpips_weights_path() is not None and ok_ort,
                         str(stlpips_weights_path()) if stlpips_weights_path() else "stlpips-pytorch not installed"),
        "lmd": (lm["dlib"] or lm["fan"], "landmark backends: " + ", ".join(k for k, v in lm.items() if v)),
        "lse": find_scorer_status(),
    }
    out = []
    for name, spec in specs().items():
        ok, why = avail[name]
        out.append({"name": name, "available": ok, "detail": why, **spec.to_dict()})
    return out
