"""The training corpora's clip cache: one ``.npz`` per clip spec, named by the spec's hash, written atomically."""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np


def cached_npz(spec: dict, folder: str | Path, make: Callable[[dict], dict]) -> str:
    """The path of ``spec``'s clip in ``folder`` (``<id>-<spec sha256[:12]>.npz``), made by ``make(spec)`` if absent.

    Written to a per-process temporary name and renamed, so parallel builders never see half a file.
    """
    key = hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:12]
    path = Path(folder) / f"{spec['id']}-{key}.npz"
    if not path.is_file():
        data = make(spec)
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
        np.savez(tmp, **data)
        tmp.replace(path)
    return str(path)
