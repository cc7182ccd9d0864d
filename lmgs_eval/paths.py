"""Where things live on disk: the data root, the cache, atomic writes."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from lmgs.fileio import atomic_path, atomic_write_bytes, public_mode

__all__ = ["atomic_dir", "atomic_path", "atomic_write_bytes", "atomic_write_text", "cache_root", "data_root", "public_mode"]


def cache_root() -> Path:
    """The user cache directory of the project (``$XDG_CACHE_HOME/lmgs`` or ``~/.cache/lmgs``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "lmgs"


def data_root(explicit: str | os.PathLike | None = None) -> Path:
    """The folder holding subjects: ``--data-root``, else ``$LMGS_DATA``, else ``<cache>/data``."""
    if explicit:
        return Path(explicit).expanduser()
    env = os.environ.get("LMGS_DATA")
    if env:
        return Path(env).expanduser()
    return cache_root() / "data"


@contextlib.contextmanager
def atomic_dir(final: Path) -> Iterator[Path]:
    """Build a folder in a temporary sibling and rename it to ``final`` only on success.

    An interrupted build leaves no half-written ``final``; its temporary folder is removed
    (and a stale one from a killed process is ignored, as its name is unique).
    """
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-", dir=final.parent))
    public_mode(tmp, directory=True)
    try:
        yield tmp
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))
