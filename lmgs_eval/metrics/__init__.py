"""Evaluation metrics whose every number says how it was made.

Pure functions (:func:`psnr`, :func:`ssim`, :func:`lmd_per_frame`; lip sync's in :mod:`.sync`),
metric objects with ``update -> stats`` / ``compute -> MetricResult``, a streaming
:class:`Accumulator`, a registry (:func:`create_metric`, :func:`list_metrics`), and the one
scorer everything goes through, :class:`~lmgs_eval.metrics.metric_suite.MetricSuite`, built from
a :class:`~lmgs_eval.metrics.config.SuiteConfig`. Heavy dependencies (torch, onnxruntime, dlib)
load only when a metric is built. See ``design.md`` in this folder.
"""

from lmgs_eval.metrics.base import Accumulator, MetricResult, MetricSpec, Registry
from lmgs_eval.metrics.image import psnr, ssim
from lmgs_eval.metrics.registry import create_metric, list_metrics

__all__ = ["Accumulator", "MetricResult", "MetricSpec", "Registry", "create_metric", "list_metrics", "psnr", "ssim"]
