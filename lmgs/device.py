"""Device choice: CUDA when present, else CPU. Never hard-coded elsewhere."""

from __future__ import annotations

import os

import torch


def choose_device(requested: str | None = None) -> torch.device:
    """Return the device to use.

    Args:
        requested: ``"cpu"``, ``"cuda"``, ``"cuda:1"``... or ``None`` for automatic
            (the ``LMGS_DEVICE`` environment variable, else CUDA if available, else CPU).
    """
    name = requested or os.environ.get("LMGS_DEVICE") or ("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        from lmgs.errors import InputError

        raise InputError(f"device {name!r} was asked for but CUDA is not available on this machine")
    return dev
