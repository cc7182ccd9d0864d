"""Where things live on disk: the data root, the cache, atomic writes, the claim on a piece of work."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from lmgs.fileio import public_mode

__all__ = ["atomic_dir", "cache_root", "check_out_dir", "claim", "data_root", "existing_ancestor"]


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


def existing_ancestor(path: Path) -> Path:
    """``path`` itself if it exists, else its nearest parent that does."""
    path = Path(path)
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_out_dir(out: Path, flag: str) -> None:
    """An output folder must be a folder this user can write, or one that can be made; checked before any
    file is written (and nothing is made here: a run that stops early leaves no empty folder).

    Raises:
        UserError: ``out`` is a file, is not writable, lies under a file or under a folder that is
            not writable, or has a name the file system refuses; the message starts ``{flag} {out}:``.
    """
    from lmgs_eval.errors import UserError

    out = Path(out)
    try:
        exists = out.exists()
    except OSError as exc:  # e.g. a name longer than the file system allows
        raise UserError(f"{flag} {out}: not a usable folder name ({exc.strerror or exc})") from None
    if exists:
        if not out.is_dir():
            raise UserError(f"{flag} {out}: exists and is not a folder")
        if not os.access(out, os.W_OK | os.X_OK):
            raise UserError(f"{flag} {out}: folder is not writable")
        return
    up = existing_ancestor(out.parent)
    if not up.is_dir():
        raise UserError(f"{flag} {out}: cannot create the folder ({up} is not a folder)")
    if not os.access(up, os.W_OK | os.X_OK):
        raise UserError(f"{flag} {out}: cannot create the folder ({up} is not writable)")


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


@contextlib.contextmanager
def claim(lock: Path, what: str, say=None) -> Iterator[None]:
    """Hold an exclusive claim on a piece of work (one model's training) for the ``with`` block.

    The claim is an advisory ``flock`` on the file ``lock``, which records who holds it (pid,
    host, start time). A second process asking for the same claim says who holds it (through
    ``say``, one line) and waits; when the holder finishes (or dies: the kernel drops the lock
    with the process) the waiter goes on and finds the work done. The file is left in place:
    removing it while another process waits on it would let a third take a second lock.

    Args:
        lock: the lock file (its folder is made).
        what: what is claimed, for the waiting message.
        say: callable taking one line (default: print to stderr).
    """
    import datetime
    import fcntl
    import socket
    import sys

    lock = Path(lock)
    lock.parent.mkdir(parents=True, exist_ok=True)
    with open(lock, "a+", encoding="utf-8") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            (say or (lambda m: print(m, file=sys.stderr, flush=True)))(
                f"{what}: {holder} holds {lock}; waiting for it to finish (Ctrl-C to stop)")
            fcntl.flock(f, fcntl.LOCK_EX)
        f.seek(0)
        f.truncate()
        now = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        f.write(f"pid {os.getpid()} on {socket.gethostname()} since {now}\n")
        f.flush()
        try:
            yield
        finally:
            f.seek(0)
            f.truncate()
            f.flush()
            fcntl.flock(f, fcntl.LOCK_UN)


def git_state(dirty: bool = True) -> tuple[str | None, bool | None]:
    """The commit of the checkout this code runs from and whether its tracked files differ from it:
    ``(commit, dirty)``; the commit is None outside git, ``dirty`` None when not asked for or unknown."""
    import subprocess

    here = Path(__file__).resolve().parent
    commit: str | None = None
    changed: bool | None = None
    try:
        r = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10)
        if r.returncode == 0:
            commit = r.stdout.strip() or None
            if dirty:
                s = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                                   capture_output=True, text=True, timeout=10)
                changed = bool(s.stdout.strip()) if s.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        pass
    return commit, changed
