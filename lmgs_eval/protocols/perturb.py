"""The fixed, versioned set of perturbed driving audio of the stability suite.

Each condition is made from the subject's clean test audio (16 kHz mono float32) and, for
"another voice", a bundled cross-driven clip. The set is deterministic: the same input,
seed and :data:`VERSION` give the same bytes.

=================  ==================================================================  =========
condition          what                                                                aligned
=================  ==================================================================  =========
clean              the test audio as is                                                yes
silence            zeros of the same length                                            no
noise-snr30        white noise at 30 dB SNR (low-level)                                yes
noise-snr10        white noise at 10 dB SNR                                            yes
noise-snr0         white noise at 0 dB SNR (loud)                                      yes
clipping           gain x8, hard-clipped at +-1                                        yes
speed-0.7x ...     time-stretched by 0.7, 0.85, 1.25, 1.5 (pitch kept, phase vocoder)  no
pitch+4st, -4st    pitch shifted by +-4 semitones (duration kept)                      yes
other-voice        a bundled clip in a voice not used in training                      own GT
long-5min          the test audio repeated to 5 minutes                                no
rate-44k           resampled to 44.1 kHz (the pipeline must resample back)             yes
stereo             two channels (left = audio, right = audio delayed 1 ms x 0.8)       yes
very-short         the first 0.2 s (5 frames)                                          yes
=================  ==================================================================  =========

"aligned" says whether the ground-truth frames of the test split still match the audio in
time, so that LMD against them applies.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction

import numpy as np
from scipy.signal import istft, resample_poly, stft

VERSION = "1"
SR = 16000


@dataclass(frozen=True)
class Condition:
    """One perturbed driving clip.

    Attributes:
        name: condition name (see the module table).
        audio: ``[S]`` or ``[S, C]`` float32 samples at ``sample_rate``.
        sample_rate: its sample rate.
        aligned: the test split's ground-truth frames still match it in time.
        description: one line for tables.
        silent_spans: ``[(start_s, end_s)]`` where the audio is silence (mouth should rest).
    """

    name: str
    audio: np.ndarray
    sample_rate: int
    aligned: bool
    description: str
    silent_spans: tuple = ()


def add_noise(x: np.ndarray, snr_db: float, rng: np.random.Generator) -> np.ndarray:
    """White Gaussian noise scaled so that ``10 log10(P_signal / P_noise) = snr_db``."""
    p = float(np.mean(x.astype(np.float64) ** 2))
    noise = rng.standard_normal(len(x))
    noise *= np.sqrt(max(p, 1e-12) / 10 ** (snr_db / 10) / np.mean(noise**2))
    return (x + noise).astype(np.float32)


def time_stretch(x: np.ndarray, rate: float, n_fft: int = 512, hop: int = 128) -> np.ndarray:
    """Phase-vocoder time stretch: duration divided by ``rate``, pitch kept.

    STFT with a Hann window, phase advance accumulated from the instantaneous frequency of
    each bin (Flanagan & Golden 1966; Laroche & Dolson 1999), overlap-add resynthesis.
    """
    _, _, Z = stft(x.astype(np.float64), nperseg=n_fft, noverlap=n_fft - hop, boundary="zeros", padded=True)
    n_bins, n_frames = Z.shape
    steps = np.arange(0, n_frames - 1, rate)
    omega = 2 * np.pi * hop * np.arange(n_bins) / n_fft
    phase = np.angle(Z[:, 0])
    out = np.empty((n_bins, len(steps)), np.complex128)
    for k, s in enumerate(steps):
        i = int(s)
        frac = s - i
        mag = (1 - frac) * np.abs(Z[:, i]) + frac * np.abs(Z[:, i + 1])
        out[:, k] = mag * np.exp(1j * phase)
        dphi = np.angle(Z[:, i + 1]) - np.angle(Z[:, i]) - omega
        dphi -= 2 * np.pi * np.round(dphi / (2 * np.pi))
        phase = phase + omega + dphi
    _, y = istft(out, nperseg=n_fft, noverlap=n_fft - hop, boundary=True)
    target = int(round(len(x) / rate))
    y = y[:target] if len(y) >= target else np.pad(y, (0, target - len(y)))
    return y.astype(np.float32)


def resample(x: np.ndarray, sr_in: int, sr_out: int) -> np.ndarray:
    f = Fraction(int(sr_out), int(sr_in))
    return resample_poly(x.astype(np.float64), f.numerator, f.denominator).astype(np.float32)


def pitch_shift(x: np.ndarray, semitones: float) -> np.ndarray:
    """Pitch moved by ``semitones``, duration kept: stretch by ``1/r`` then resample by ``r``."""
    r = 2 ** (semitones / 12)
    y = time_stretch(x, 1 / r)
    # y is r times longer; playing it r times faster restores the duration and raises pitch by r.
    z = resample(y, int(round(SR * r)), SR)
    return (z[: len(x)] if len(z) >= len(x) else np.pad(z, (0, len(x) - len(z)))).astype(np.float32)


def make_conditions(audio: np.ndarray, *, seed: int = 0, other_voice: np.ndarray | None = None, long_seconds: float = 300.0) -> list[Condition]:
    """The whole stability set for one clean clip (16 kHz mono float32)."""
    x = np.asarray(audio, np.float32)
    if x.ndim != 1 or len(x) < SR // 5:
        raise ValueError(f"clean audio must be mono and at least 0.2 s, got shape {x.shape}")
    rng = np.random.default_rng([seed, int(VERSION)])
    dur = len(x) / SR
    conds = [
        Condition("clean", x, SR, True, "the test audio as is"),
        Condition("silence", np.zeros_like(x), SR, False, "digital silence", ((0.0, dur),)),
    ]
    for snr in (30, 10, 0):
        conds.append(Condition(f"noise-snr{snr}", add_noise(x, snr, rng), SR, True, f"white noise at {snr} dB SNR"))
    conds.append(Condition("clipping", np.clip(x * 8.0, -1.0, 1.0), SR, True, "gain x8, hard-clipped at +-1"))
    for rate in (0.7, 0.85, 1.25, 1.5):
        conds.append(Condition(f"speed-{rate:g}x", time_stretch(x, rate), SR, False, f"time-stretched x{rate:g} (pitch kept)"))
    for st in (4, -4):
        conds.append(Condition(f"pitch{st:+d}st", pitch_shift(x, st), SR, True, f"pitch shifted {st:+d} semitones"))
    if other_voice is not None:
        conds.append(Condition("other-voice", np.asarray(other_voice, np.float32), SR, False, "a voice not used in training"))
    reps = int(np.ceil(long_seconds * SR / len(x)))
    conds.append(Condition(f"long-{long_seconds / 60:g}min", np.tile(x, reps)[: int(long_seconds * SR)], SR, False,
                           f"the test audio repeated to {long_seconds / 60:g} minutes"))
    conds.append(Condition("rate-44k", resample(x, SR, 44100), 44100, True, "resampled to 44.1 kHz"))
    delayed = np.concatenate([np.zeros(16, np.float32), x[:-16]]) * 0.8
    conds.append(Condition("stereo", np.stack([x, delayed], axis=1), SR, True, "two channels"))
    conds.append(Condition("very-short", x[: SR // 5].copy(), SR, True, "the first 0.2 s (5 frames)"))
    return conds
