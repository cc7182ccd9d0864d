"""The stability suite's perturbations: deterministic, and each does what its name says."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from lmgs_eval.protocols.perturb import add_noise, make_conditions, pitch_shift, time_stretch

SR = 16000


def _tone(freq=440.0, seconds=2.0, amp=0.3):
    t = np.arange(int(seconds * SR)) / SR
    return (amp * np.sin(2 * np.pi * freq * t)).astype(np.float32)


def _peak_hz(x, sr=SR):
    spec = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    return np.fft.rfftfreq(len(x), 1 / sr)[spec.argmax()]


def test_same_seed_same_bytes():
    x = _tone() + 0.01 * np.random.default_rng(1).standard_normal(2 * SR).astype(np.float32)
    a = make_conditions(x, seed=3, long_seconds=10)
    b = make_conditions(x, seed=3, long_seconds=10)
    c = make_conditions(x, seed=4, long_seconds=10)
    h = lambda cs: [hashlib.sha256(k.audio.tobytes()).hexdigest() for k in cs]
    assert h(a) == h(b)
    assert h(a) != h(c)  # the noise conditions depend on the seed
    assert [k.name for k in a] == [k.name for k in b]


@pytest.mark.parametrize("snr", [0, 10, 30])
def test_noise_has_the_requested_snr(snr):
    x = _tone()
    y = add_noise(x, snr, np.random.default_rng(0))
    measured = 10 * np.log10(np.mean(x.astype(np.float64) ** 2) / np.mean((y - x).astype(np.float64) ** 2))
    assert abs(measured - snr) < 0.05


@pytest.mark.parametrize("rate", [0.7, 0.85, 1.25, 1.5])
def test_time_stretch_changes_duration_not_pitch(rate):
    x = _tone(500)
    y = time_stretch(x, rate)
    assert len(y) == round(len(x) / rate)
    mid = y[len(y) // 4 : 3 * len(y) // 4]
    assert abs(_peak_hz(mid) - 500) < 8


@pytest.mark.parametrize("st", [4, -4])
def test_pitch_shift_moves_a_tone_by_semitones(st):
    x = _tone(400)
    y = pitch_shift(x, st)
    assert len(y) == len(x)
    mid = y[len(y) // 4 : 3 * len(y) // 4]
    assert abs(_peak_hz(mid) - 400 * 2 ** (st / 12)) < 10


def test_condition_shapes_and_names():
    x = _tone()
    conds = {c.name: c for c in make_conditions(x, long_seconds=12, other_voice=_tone(200, 1.0))}
    assert np.all(conds["silence"].audio == 0) and conds["silence"].silent_spans
    assert conds["clipping"].audio.max() <= 1.0 and np.mean(np.abs(conds["clipping"].audio) >= 0.999) > 0.5
    assert conds["rate-44k"].sample_rate == 44100 and abs(len(conds["rate-44k"].audio) - 2 * 44100) <= 1
    assert conds["stereo"].audio.shape == (2 * SR, 2)
    assert len(conds["very-short"].audio) == SR // 5
    assert len(conds["long-0.2min"].audio) == 12 * SR
    assert "other-voice" in conds and not conds["speed-1.5x"].aligned and conds["noise-snr10"].aligned


def test_rejects_too_short_or_stereo_input():
    with pytest.raises(ValueError):
        make_conditions(np.zeros(100, np.float32))
    with pytest.raises(ValueError):
        make_conditions(np.zeros((SR, 2), np.float32))
