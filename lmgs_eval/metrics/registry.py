"""The table of metrics: ``create_metric(name)``, ``list_metrics()`` and backend availability.

Every factory takes the run's choices by the names of :class:`~lmgs_eval.metrics.config.SuiteConfig`'s
fields (``alexnet``, ``lpips``, ``landmarks``, ``sync``) and ignores the others, so the metric suite
builds any metric the same way. ``lpips`` is the network those choices give (``lpips-alex`` when a
trunk is found, else ``stlpips-alex``: :func:`~lmgs_eval.metrics.lpips.resolve_lpips`).
"""

from __future__ import annotations

import importlib.util

from lmgs_eval.metrics.base import MetricSpec, Registry
from lmgs_eval.metrics.image import PSNR, PSNR_SPEC, SSIM, SSIM_SPEC
from lmgs_eval.metrics.landmarks import LMD, LMD_SPEC, available_backends, create_backend
from lmgs_eval.errors import UserError
from lmgs_eval.metrics.lpips import (
    ALEXNET_CKPT,
    LPIPS,
    LPIPS_ALEX_CUSTOM_SPEC,
    LPIPS_ALEX_SPEC,
    STLPIPS_ALEX_SPEC,
    alex_weights,
    custom_trunk_line,
    find_alexnet,
    stlpips_weights_path,
)
from lmgs_eval.metrics.sync.scoring import LSE, LSE_SPEC
from lmgs_eval.metrics.sync.select import SyncScorers, status

METRICS = Registry("metric")


def _psnr(**kw):
    return PSNR()


def _ssim(**kw):
    return SSIM()


def _lpips(lpips=None, alexnet=None, **kw):
    """The LPIPS network of the run's choices: ``lpips`` when forced, else by the trunk found."""
    return LPIPS(lpips, alexnet=alexnet)


def _lmd(landmarks="dlib", **kw):
    return LMD(create_backend(landmarks))


def _lse(sync="auto", scorers=None, **kw):
    """LSE with ``scorers`` (a :class:`SyncScorers` the suite resolved once), else those of the choice ``sync``."""
    return LSE(scorers if scorers is not None else SyncScorers(sync))


METRICS.register("psnr", _psnr)
METRICS.register("ssim", _ssim)
METRICS.register("lpips", _lpips)
# one network by name; ``lpips-alex-custom`` builds ``lpips-alex`` (the trunk's sha256 names the result)
for _name, _net in (("lpips-alex", "lpips-alex"), ("lpips-alex-custom", "lpips-alex"), ("stlpips-alex", "stlpips-alex")):
    METRICS.register(_name, lambda _net=_net, **kw: _lpips(lpips=_net, **kw))
METRICS.register("lmd", _lmd)
METRICS.register("lse", _lse)


def create_metric(name: str, **kw):
    """Build a metric by name with the run's choices as keywords (see the module doc).

    The paired metrics ``update`` / ``compute`` (see :class:`Accumulator`) and ``stream`` uint8 chunks;
    ``lse`` (no reference) scores one clip and its audio with :meth:`~lmgs_eval.metrics.sync.scoring.LSE.score`.
    """
    return METRICS.get(name)(**kw)


def specs() -> dict[str, MetricSpec]:
    return {s.name: s for s in (PSNR_SPEC, SSIM_SPEC, LPIPS_ALEX_SPEC, LPIPS_ALEX_CUSTOM_SPEC, STLPIPS_ALEX_SPEC,
                                LMD_SPEC, LSE_SPEC)}


def alex_status(alexnet=None) -> dict[str, tuple[bool, str]]:
    """Whether ``lpips-alex`` and ``lpips-alex-custom`` can run here, and why (the trunk's sha256 decides which)."""
    trunk = find_alexnet(alexnet)
    if trunk is None:
        why = f"AlexNet trunk {ALEXNET_CKPT} not found (--alexnet PATH)"
        return {"lpips-alex": (False, why), "lpips-alex-custom": (False, why)}
    try:
        w = alex_weights(trunk)
    except UserError as exc:
        return {"lpips-alex": (False, str(exc)), "lpips-alex-custom": (False, str(exc))}
    if w.official:
        return {"lpips-alex": (True, f"trunk {trunk}"),
                "lpips-alex-custom": (False, f"the trunk {trunk} is torchvision's published one: it scores as lpips-alex")}
    return {"lpips-alex": (False, custom_trunk_line(trunk, w.trunk_sha256)), "lpips-alex-custom": (True, f"trunk {trunk} (sha256 {w.trunk_sha256[:8]}...)")}


def list_metrics(alexnet=None) -> list[dict]:
    """Every metric with its spec and whether it can run on this machine (and why not)."""
    lm = available_backends()
    ok_ort = importlib.util.find_spec("onnxruntime") is not None
    alex = alex_status(alexnet)
    avail = {
        "psnr": (True, "closed form"),
        "ssim": (True, "closed form"),
        "lpips-alex": (alex["lpips-alex"][0] and ok_ort, alex["lpips-alex"][1]),
        "lpips-alex-custom": (alex["lpips-alex-custom"][0] and ok_ort, alex["lpips-alex-custom"][1]),
        "stlpips-alex": (stlpips_weights_path() is not None and ok_ort,
                         str(stlpips_weights_path()) if stlpips_weights_path() else "stlpips-pytorch not installed"),
        "lmd": (lm["dlib"] or lm["fan"], "landmark backends: " + ", ".join(k for k, v in lm.items() if v)),
        "lse": status(),
    }
    out = []
    for name, spec in specs().items():
        ok, why = avail[name]
        out.append({"name": name, "available": ok, "detail": why, **spec.to_dict()})
    return out
