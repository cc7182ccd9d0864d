"""What a run scores with: the choices behind its metrics, one frozen value the command line fills in.

:class:`~lmgs_eval.metrics.metric_suite.MetricSuite` is built from it; a worker process given a
suite (or a run config holding one) gets this value and resolves the same choices.
"""

from __future__ import annotations

from dataclasses import dataclass

SYNC_CHOICES = ("auto", "mesh", "landmark", "pixel", "syncnet-v2")


@dataclass(frozen=True)
class SuiteConfig:
    """The scoring choices of one run.

    Attributes:
        sync: the LSE scorer (``--sync``): ``auto``, ``mesh``, ``landmark``, ``pixel`` or ``syncnet-v2``
            (:mod:`lmgs_eval.metrics.sync.select`).
        lpips: force one LPIPS network (``--lpips``: ``lpips-alex`` or ``stlpips-alex``); None: ``lpips-alex``
            when an AlexNet trunk is found, else ``stlpips-alex`` (a stand-in, labelled).
        alexnet: the AlexNet trunk checkpoint for the official LPIPS (``--alexnet``; else looked for in the
            torch hub caches). A trunk that is not torchvision's scores as ``lpips-alex-custom``.
        landmarks: LMD's landmark detector (``--landmarks``: ``dlib`` or ``fan``).
    """

    sync: str = "auto"
    lpips: str | None = None
    alexnet: str | None = None
    landmarks: str = "dlib"
