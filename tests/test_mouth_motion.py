"""benchmarks/mouth_motion.py's measurement: the inner lips' opening of a render against the truth's."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "mouth_motion.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("mouth_motion", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def frames():
    from lmgs_eval.data.bundled import synthesize_clip

    # about 4 s of generated speech: the mouth opens and closes
    return synthesize_clip("astronaut", "Bob moved a map. Seven bright lamps were lit.", "espeak:en-us+m3",
                           size=160, seed=1).frames


def test_a_render_equal_to_the_truth_moves_with_it(bench, frames):
    row = bench.motion_row("same", frames, frames)
    assert row["n"] == len(frames) and row["lmd"] == 0.0 and row["psnr"] == 100.0  # identical frames: the metric's cap
    assert row["opening_render"] == row["opening_truth"] and row["opening_r"] > 0.999
    assert row["opening_truth"][1] > 0.2 * row["opening_truth"][0]  # the clip's mouth does move


def test_a_still_mouth_does_not_follow_the_truth(bench, frames):
    # the first frame held: a mouth that does not move scores a moderate LMD and follows none of the speech
    row = bench.motion_row("frozen", np.repeat(frames[:1], len(frames), axis=0), frames)
    assert row["lmd"] > 0.3
    unit = frames.astype(np.float32) / 255.0  # the toolkit's one conversion of uint8 frames (metrics.base.unit)
    want = np.mean([-10 * np.log10(np.mean((unit[0].astype(np.float64) - f) ** 2)) for f in unit[1:]] + [100.0])
    assert row["psnr"] == pytest.approx(want, rel=1e-9)  # per frame, the held first one capped, then the mean
    assert abs(row["opening_r"]) < 0.3
    assert row["opening_render"][1] < row["opening_truth"][1]
