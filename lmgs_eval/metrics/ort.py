"""ONNX Runtime sessions and the on-disk cache of graphs exported by the project."""

from __future__ import annotations

import io
import os
import pickle
import warnings
import zipfile
from pathlib import Path

import torch

from lmgs.fileio import atomic_write
from lmgs_eval.errors import UserError
from lmgs_eval.paths import cache_root


def onnx_cache_dir() -> Path:
    return cache_root() / "onnx"


def n_threads() -> int:
    """Cores this process may use (affinity-aware), the intra-op thread count."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def providers() -> list[str]:
    """CUDA EP when onnxruntime offers it, always with the CPU EP behind it."""
    import onnxruntime as ort

    avail = ort.get_available_providers()
    return (["CUDAExecutionProvider"] if "CUDAExecutionProvider" in avail else []) + ["CPUExecutionProvider"]


def load_session(path: Path, threads: int | None = None):
    """An inference session with all graph optimisations and ``threads`` intra-op threads.

    Raises:
        UserError: the file is not a loadable ONNX graph (named in the message).
    """
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.intra_op_num_threads = int(threads or n_threads())
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    from onnxruntime.capi import onnxruntime_pybind11_state as st

    errors = tuple(getattr(st, n) for n in ("Fail", "InvalidProtobuf", "InvalidGraph", "NoSuchFile", "InvalidArgument",
                                            "NotImplemented", "RuntimeException") if hasattr(st, n))
    try:
        return ort.InferenceSession(str(path), sess_options=so, providers=providers())
    except (RuntimeError, ValueError, *errors) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else exc.__class__.__name__
        raise UserError(f"{path}: not a loadable ONNX graph ({first[:160]})") from None


def export_onnx(module, args: tuple, path: Path, input_names: list[str], output_names: list[str],
                dynamic_axes: dict[str, dict[int, str]], opset: int = 17) -> None:
    """Export with the TorchScript exporter (``dynamo=False``: no onnxscript needed) atomically.

    The exporter's own warnings (deprecation of the TorchScript path, constant folding
    notes) are silenced: they concern the exporter, not the graph, which the ONNX-vs-torch
    tests check.
    """
    buf = io.BytesIO()
    module.eval()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, args, buf, input_names=input_names, output_names=output_names,
                          dynamic_axes=dynamic_axes, opset_version=opset, dynamo=False)
    atomic_write(Path(path), buf.getvalue())


def load_torch_state(path: Path, what: str) -> dict:
    """``torch.load`` a state dict on CPU (weights only); a clear error when the file is bad."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: {what} not found")
    try:
        sd = torch.load(str(path), map_location="cpu", weights_only=True)
    # torch's unpickler meets a file of another kind (audio, text) with any of these
    except (RuntimeError, pickle.UnpicklingError, EOFError, zipfile.BadZipFile, ValueError, OSError, IndexError,
            KeyError, AttributeError, TypeError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not a readable {what} ({exc.__class__.__name__}); re-download or re-copy it") from None
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise UserError(f"{path}: {what} is not a state dict of tensors")
    return sd


def nonfinite_weights(path: Path) -> list[str]:
    """Names of the float weights (initializers and constants) of an ONNX graph that hold NaN or Inf."""
    import numpy as np
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(path))
    tensors = [(t.name, t) for t in model.graph.initializer]
    for node in model.graph.node:
        if node.op_type == "Constant":
            tensors += [(node.output[0], a.t) for a in node.attribute if a.name == "value"]
    bad = []
    for name, t in tensors:
        a = numpy_helper.to_array(t)
        if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            bad.append(name)
    return bad
