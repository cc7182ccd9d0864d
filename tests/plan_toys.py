"""A cheap method for the plan tests, registered when imported (a plan's ``imports``).

``plan-toy`` renders the driving backgrounds with a bar that follows the audio energy. Its
``--set`` options make a run misbehave on its first fits, counted in files under ``marks``
(one per fit: seed and process id), so a retry in another process sees the earlier tries:
``fail_times`` (raise), ``kill_times`` (SIGKILL its own process, as an out-of-memory killer
would), ``interrupt_seed`` (Ctrl-C on that seed's first fit).
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np

from baselines import protocol as methods
from baselines.protocol import MethodInfo
from lmgs.config import config_hash


class PlanToy:
    def __init__(self, preset: str = "quick", device=None, overrides=None, **_):
        self.opts = dict(overrides or {})

    def describe(self):
        return MethodInfo("plan-toy", "Plan toy", "2D", "test method of the plan runner", config=self.opts,
                          config_hash=config_hash(self.opts))

    def fit(self, clip, *, seed, workdir, progress=True):
        marks = Path(self.opts["marks"])
        marks.mkdir(parents=True, exist_ok=True)
        n = len(list(marks.glob(f"fit-seed{seed}-*")))
        (marks / f"fit-seed{seed}-{n}-{os.getpid()}").touch()
        if n < self.opts.get("kill_times", 0):
            os.kill(os.getpid(), signal.SIGKILL)
        if n < self.opts.get("fail_times", 0):
            raise RuntimeError(f"toy failure {n + 1}")
        if seed == self.opts.get("interrupt_seed") and n == 0:
            raise KeyboardInterrupt

    def render(self, driving):
        n = driving.n_frames
        a = driving.audio[: n * 640].reshape(n, 640)
        rms = np.sqrt((a.astype(np.float64) ** 2).mean(axis=1))
        out = driving.backgrounds.copy()
        for t in range(n):
            out[t, 40:40 + int(min(20, 200 * rms[t])), 28:36] = 0
        return out

    def cost(self):
        return {"n_params": 0, "model_mb": 0.0}


def fits(marks: Path, seed: int) -> list[str]:
    """The fits a seed has had: ``[pid, ...]`` in order."""
    found = sorted(Path(marks).glob(f"fit-seed{seed}-*"), key=lambda p: int(p.name.split("-")[2]))
    return [p.name.split("-")[3] for p in found]


if not methods.is_registered("plan-toy"):
    methods.register("plan-toy")(PlanToy)
