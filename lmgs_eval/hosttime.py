"""How busy the host was while something was timed: the CPU others took, and a probe of its speed.

A figure timed on a shared 2-core machine is only worth as much as the quiet it was taken in.
:class:`OthersCPU` reads the CPU time other processes took during a span from ``/proc/stat``;
:class:`HostSpeed` runs a fixed probe before and after it and compares it with the fastest this
machine has recorded. Records carry both, and tables mark figures timed on a busy host.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import time
from pathlib import Path

import numpy as np
import torch

from lmgs.fileio import atomic_write
from lmgs_eval.paths import cache_root


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB; Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def host_cpu_seconds() -> tuple[float, float] | None:
    """``(busy, total)`` CPU seconds of the whole host since boot (Linux ``/proc/stat``), else None."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            parts = f.readline().split()
        ticks = [int(x) for x in parts[1:9]]  # user nice system idle iowait irq softirq steal
        hz = os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None
    if parts[0] != "cpu" or len(ticks) < 8 or hz <= 0:
        return None
    total = sum(ticks) / hz
    return total - (ticks[3] + ticks[4]) / hz, total


def own_cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system


class OthersCPU:
    """Share of the host's CPU time that other processes took during a span (contention while timing).

    ``share = (host busy - this process's CPU) / host total`` over the span: about 0 on a
    quiet host, 0.5 when another process keeps one of two cores busy. Hypervisor steal
    counts as taken by others. ``share`` is None where ``/proc/stat`` is not available.
    """

    def __enter__(self) -> "OthersCPU":
        self.share: float | None = None
        self._h0, self._p0 = host_cpu_seconds(), own_cpu_seconds()
        return self

    def __exit__(self, *exc) -> None:
        h1, p1 = host_cpu_seconds(), own_cpu_seconds()
        if self._h0 is None or h1 is None or h1[1] <= self._h0[1]:
            return
        others = (h1[0] - self._h0[0]) - (p1 - self._p0)
        self.share = min(1.0, max(0.0, others / (h1[1] - self._h0[1])))


PROBE_SLOW = 1.5
"""A render timed while the host ran the fixed probe this many times slower than its best is marked."""


def probe_ms() -> float:
    """Milliseconds of a fixed workload of the kind renders do (40 chained 256x256 float32 matmuls + tanh,
    torch's intra-op threads): the host's speed right now, independent of any method."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(256, 256, generator=g)
    w = torch.randn(256, 256, generator=g) * 0.05
    t0 = time.perf_counter()
    for _ in range(40):
        x = torch.tanh(x @ w)
    return 1000.0 * (time.perf_counter() - t0)


def probe_key() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), cpu)
    except OSError:
        pass
    return f"{cpu}|cpus={os.cpu_count()}|threads={torch.get_num_threads()}|torch={torch.__version__}"


class HostSpeed:
    """How much slower than its best this host ran a fixed probe around a timed span.

    The probe (:func:`probe_ms`, median of 3) runs before and after the span;
    ``slowdown = max(before, after) / best``, where ``best`` is the fastest probe this
    machine (same CPU model, thread count and torch) has recorded in the ledger
    ``<cache>/host_probe.json`` (a first probe on a machine is compared with itself).
    It sees what :class:`OthersCPU` cannot: a virtual machine slowed by its hypervisor
    without guest-visible steal, frequency scaling, and threads of two processes
    oversubscribing the cores. ``ledger=None`` keeps no ledger (best = this span's probes).
    """

    def __init__(self, ledger: Path | None | str = "default", probe=None):
        self.ledger = cache_root() / "host_probe.json" if ledger == "default" else (Path(ledger) if ledger else None)
        self._probe = probe or (lambda: probe_ms())  # looked up at call time (tests replace it)
        self.before = self.after = self.best = self.slowdown = None

    def _median3(self) -> float:
        return float(np.median([self._probe() for _ in range(3)]))

    def __enter__(self) -> "HostSpeed":
        self._probe()  # warm-up (thread pool, allocator)
        self.before = self._median3()
        return self

    def __exit__(self, *exc) -> None:
        self.after = self._median3()
        best = min(self.before, self.after)
        key = probe_key()
        if self.ledger is not None:
            try:
                book = json.loads(self.ledger.read_text()) if self.ledger.exists() else {}
                if not isinstance(book, dict):
                    book = {}
            except (OSError, ValueError):
                book = {}  # an unreadable ledger is started again
            entry = book.get(key) if isinstance(book.get(key), dict) else {}
            known = entry.get("best_ms")
            if isinstance(known, (int, float)) and known > 0:
                best = min(best, float(known))
            book[key] = {"best_ms": best, "n": int(entry.get("n", 0)) + 1}
            try:
                self.ledger.parent.mkdir(parents=True, exist_ok=True)
                atomic_write(self.ledger, json.dumps(book, indent=1, sort_keys=True))
            except OSError:
                pass  # a read-only cache loses the ledger, not the timing
        self.best = best
        self.slowdown = max(self.before, self.after) / best if best > 0 else None

    def cost(self) -> dict:
        return {"host_probe_ms": [self.before, self.after], "host_probe_best_ms": self.best, "host_slowdown": self.slowdown}
