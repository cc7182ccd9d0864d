"""Device choice: CUDA when present, else CPU. Never hard-coded elsewhere."""

from __future__ import annotations

import os

import torch

from lmgs.errors import InputError


def choose_device(requested: str | None = None) -> torch.device:
    """Return the device to use.

    Args:
        requested: ``"cpu"``, ``"cuda"``, ``"cuda:1"``... or ``None`` for automatic
            (the ``LMGS_DEVICE`` environment variable, else CUDA if available, else CPU).
    """
    name = requested or os.environ.get("LMGS_DEVICE") or ("cuda" if torch.cuda.is_available() else "cpu")
    where = "--device" if requested else "LMGS_DEVICE" if os.environ.get("LMGS_DEVICE") else "device"
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError):
        raise InputError(f"{where} {name!r}: not a device (cpu, cuda, cuda:N)") from None
    if dev.type not in ("cpu", "cuda"):
        raise InputError(f"{where} {name!r}: this project runs on cpu or cuda")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"{where} {name!r}: CUDA is not available on this machine")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise InputError(f"{where} {name!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return dev
