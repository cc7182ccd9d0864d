"""The contention measure recorded beside every FPS (cost.others_cpu_share)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from lmgs_eval.protocols import OthersCPU, host_cpu_seconds

pytestmark = pytest.mark.skipif(host_cpu_seconds() is None, reason="needs /proc/stat (Linux)")


def _spin(seconds: float) -> None:
    t = time.perf_counter()
    while time.perf_counter() - t < seconds:
        pass


def test_others_cpu_share_counts_other_processes_and_not_this_one():
    ncpu = os.cpu_count() or 1
    with OthersCPU() as own:
        _spin(1.0)  # only this process is busy
    child = subprocess.Popen([sys.executable, "-c",
                              "import time\nt = time.perf_counter()\nwhile time.perf_counter() - t < 1.8: pass"])
    try:
        time.sleep(0.3)  # let it start
        with OthersCPU() as other:
            time.sleep(1.0)  # this process idles while the other one keeps a core busy
    finally:
        child.wait()
    assert own.share is not None and other.share is not None and 0 <= own.share <= 1 and 0 <= other.share <= 1
    assert other.share > 0.7 / ncpu  # one core of the host (about 0.5 on 2 cores)
    assert other.share - own.share > 0.5 / ncpu  # this process's own work is not contention
