"""Audio feature front ends: one feature window per 25 fps video frame, shape ``[N, W, C]``.

Computed here from a 16 kHz mono waveform: ``logmel`` (default) and ``mfcc``. Precomputed by
the user: ``ds`` (``aud_ds.npy``, DeepSpeech, ``[N, 16, 29]``), ``hu`` (``aud_hu.npy``,
HuBERT, ``[N, 2, 1024]``), ``wavlm`` (``[N, T, C]`` or ``[N, C]``).

Frame convention (the field's): video frame ``i`` covers samples ``[640 i, 640 (i+1))`` at
16 kHz / 25 fps, and a waveform gives ``n_frames = floor(n_samples / 640)`` frames
(the count syncnet_python and ER-NeRF use). A caller may ask for more frames
(``n_frames=``): the tail is padded with silence, never truncated silently.

Spectrogram steps: step ``t`` is centred on sample ``160 t`` (10 ms hop; the waveform is
zero-padded on both sides), and frame ``i`` takes the ``W`` (16) steps centred on its centre
``640 i + 320``, i.e. steps ``4i + 2 - W/2 ... 4i + 1 + W/2``. Steps outside the audio see
zero-padded (silent) samples, so they carry the log floor, not garbage.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import scipy.signal

from lmgs.errors import InputError

SAMPLE_RATE = 16000
FPS = 25
SAMPLES_PER_FRAME = SAMPLE_RATE // FPS  # 640
LOG_FLOOR = 1e-10  # power floor before the log: silence gives log(1e-10) = -23.03, never -inf


def load_waveform(array: np.ndarray, sr: int) -> np.ndarray:
    """Any waveform as 16 kHz mono float32 in [-1, 1].

    Args:
        array: ``[S]`` mono, or ``[S, C]`` / ``[C, S]`` multichannel (the axis with at most
            8 entries and fewer than the other is taken as channels). Integer arrays are
            scaled by their type's range (int16: /32768). Floats beyond [-1, 1] are clipped
            (as a DAC would); floats with a peak above 256 look like integer-scaled samples
            and are refused.
        sr: sample rate in Hz; anything but 16000 is resampled with
            ``scipy.signal.resample_poly`` (polyphase, Kaiser-windowed FIR).

    Returns:
        ``[S']`` float32 at 16 kHz, channels averaged.

    Raises:
        InputError: wrong rank, non-finite samples, bad rate, integer-scaled floats.
    """
    x = np.asarray(array)
    if x.ndim == 2:
        ch_axis = 1 if x.shape[1] <= 8 and x.shape[1] <= x.shape[0] else 0
        if x.shape[ch_axis] > 8:
            raise InputError(f"audio array of shape {x.shape}: expected [samples] or [samples, channels<=8]")
    elif x.ndim != 1:
        raise InputError(f"audio array must be [samples] or [samples, channels], got shape {x.shape}")
    if np.issubdtype(x.dtype, np.integer):
        x = x.astype(np.float64) / float(-np.iinfo(x.dtype).min)
    elif np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    else:
        raise InputError(f"audio array has non-numeric dtype {x.dtype}")
    if x.ndim == 2:
        x = x.mean(axis=ch_axis)
    if not np.all(np.isfinite(x)):
        raise InputError("audio contains NaN or infinite samples")
    peak = float(np.abs(x).max()) if x.size else 0.0
    if peak > 256.0:
        raise InputError(f"audio float samples reach {peak:.1f}: looks integer-scaled; divide by 32768 first")
    x = np.clip(x, -1.0, 1.0)
    if not isinstance(sr, (int, np.integer)) or sr <= 0:
        raise InputError(f"sample rate must be a positive integer, got {sr!r}")
    if sr != SAMPLE_RATE and x.size:
        f = Fraction(SAMPLE_RATE, int(sr))
        x = scipy.signal.resample_poly(x, f.numerator, f.denominator)
        x = np.clip(x, -1.0, 1.0)  # the FIR can overshoot slightly at clipped edges
    return x.astype(np.float32)


def frame_count(n_samples: int) -> int:
    """Video frames of a 16 kHz waveform: :math:`\\lfloor S / 640 \\rfloor` (the field's convention)."""
    return int(n_samples) // SAMPLES_PER_FRAME


def hz_to_mel(f):
    """HTK mel scale: :math:`m = 2595 \\log_{10}(1 + f / 700)`."""
    return 2595.0 * np.log10(1.0 + np.asarray(f, dtype=np.float64) / 700.0)


def mel_to_hz(m):
    """Inverse HTK mel scale: :math:`f = 700 (10^{m / 2595} - 1)`."""
    return 700.0 * (10.0 ** (np.asarray(m, dtype=np.float64) / 2595.0) - 1.0)


def mel_filterbank(n_mels: int, n_fft: int, sr: int = SAMPLE_RATE, fmin: float = 0.0, fmax: float | None = None) -> np.ndarray:
    """Triangular mel filters on the rfft bins, ``[n_mels, n_fft // 2 + 1]``.

    Centres are equally spaced on the HTK mel scale between ``fmin`` and ``fmax`` (Nyquist);
    filter ``m`` rises linearly from centre ``m-1`` to centre ``m`` and falls to centre
    ``m+1`` (peak 1, no area normalisation; torchaudio's ``melscale_fbanks(norm=None,
    mel_scale="htk")``). Unlike python_speech_features' integer-bin filters, the triangles
    are evaluated at the exact bin frequencies, so narrow low bands never vanish.
    """
    fmax = sr / 2 if fmax is None else fmax
    if not 0 <= fmin < fmax <= sr / 2:
        raise InputError(f"mel range must satisfy 0 <= fmin < fmax <= sr/2, got {fmin}, {fmax}")
    edges = mel_to_hz(np.linspace(hz_to_mel(fmin), hz_to_mel(fmax), n_mels + 2))
    freqs = np.arange(n_fft // 2 + 1) * sr / n_fft
    lo, ce, hi = edges[:-2, None], edges[1:-1, None], edges[2:, None]
    up = (freqs[None] - lo) / (ce - lo)
    down = (hi - freqs[None]) / (hi - ce)
    return np.maximum(0.0, np.minimum(up, down))


def power_spectrogram(wave: np.ndarray, win: int = 400, hop: int = 160, n_fft: int = 512) -> np.ndarray:
    """Framed power spectrum, ``[T, n_fft // 2 + 1]``, frames starting at ``hop * t`` (no padding).

    .. math::

        P_t(k) = \\frac{1}{N_{fft}} \\Big| \\sum_{n=0}^{w-1} x[t h + n]\\, \\mathrm{hann}(n)\\, e^{-2\\pi i k n / N_{fft}} \\Big|^2

    with the periodic Hann window (python_speech_features' ``powspec`` scaling).
    ``T = 1 + (S - w) // h`` (0 if the signal is shorter than one window).
    """
    if n_fft < win:
        raise InputError(f"n_fft ({n_fft}) must be >= the window length ({win} samples)")
    x = np.asarray(wave, dtype=np.float64)
    n = 0 if x.size < win else 1 + (x.size - win) // hop
    if n == 0:
        return np.zeros((0, n_fft // 2 + 1))
    frames = np.lib.stride_tricks.sliding_window_view(x, win)[::hop][:n]
    spec = np.fft.rfft(frames * scipy.signal.get_window("hann", win), n=n_fft, axis=-1)
    return (spec.real**2 + spec.imag**2) / n_fft


def log_mel_spectrogram(wave: np.ndarray, n_mels: int = 80, win_ms: float = 25.0, hop_ms: float = 10.0, n_fft: int = 512) -> np.ndarray:
    """Log mel energies of a 16 kHz waveform, ``[T, n_mels]`` (frames as :func:`power_spectrogram`).

    .. math::

        E_t(m) = \\log \\max\\big(\\textstyle\\sum_k M_{mk} P_t(k),\\ 10^{-10}\\big)
    """
    win, hop = _win_hop(win_ms, hop_ms)
    p = power_spectrogram(wave, win, hop, n_fft)
    fb = mel_filterbank(n_mels, n_fft)
    return np.log(np.maximum(p @ fb.T, LOG_FLOOR))


def mfcc_from_log_mel(log_mel: np.ndarray, n_mfcc: int) -> np.ndarray:
    """MFCC: orthonormal DCT-II of the log mel energies, first ``n_mfcc`` coefficients (no lifter).

    .. math::

        c_t(q) = \\sqrt{\\tfrac{2 - [q = 0]}{M}} \\sum_{m=0}^{M-1} E_t(m) \\cos\\Big(\\frac{\\pi q (2m + 1)}{2M}\\Big)
    """
    import scipy.fft

    if not 1 <= n_mfcc <= log_mel.shape[-1]:
        raise InputError(f"n_mfcc must be in [1, n_mels={log_mel.shape[-1]}], got {n_mfcc}")
    return scipy.fft.dct(log_mel, type=2, norm="ortho", axis=-1)[..., :n_mfcc]


def _win_hop(win_ms: float, hop_ms: float) -> tuple[int, int]:
    win = int(round(win_ms * SAMPLE_RATE / 1000))
    hop = int(round(hop_ms * SAMPLE_RATE / 1000))
    if hop <= 0 or win <= 0 or SAMPLES_PER_FRAME % hop:
        raise InputError(f"hop {hop_ms} ms must be positive and divide the 40 ms video frame; window {win_ms} ms")
    return win, hop


def waveform_features(
    wave: np.ndarray,
    kind: str = "logmel",
    *,
    n_frames: int | None = None,
    n_mels: int = 80,
    n_mfcc: int = 20,
    win_ms: float = 25.0,
    hop_ms: float = 10.0,
    n_fft: int = 512,
    window_steps: int = 16,
) -> np.ndarray:
    """Per-video-frame windows of log-mel (or MFCC) steps, ``[N, window_steps, C]`` float32.

    Args:
        wave: 16 kHz mono float waveform (see :func:`load_waveform`).
        kind: ``"logmel"`` (C = n_mels) or ``"mfcc"`` (C = n_mfcc).
        n_frames: frames wanted; default :func:`frame_count` (floor). More frames than the
            audio holds are padded with silence at the tail.
        window_steps: spectrogram steps per frame, centred on the frame's centre.

    Returns:
        ``[N, W, C]`` float32, finite for any input (silence gives the log floor).
    """
    if kind not in ("logmel", "mfcc"):
        raise InputError(f"waveform feature kind must be 'logmel' or 'mfcc', got {kind!r}")
    x = np.asarray(wave, dtype=np.float64)
    if x.ndim != 1:
        raise InputError(f"waveform must be 1-D 16 kHz mono (use load_waveform), got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise InputError("waveform contains NaN or infinite samples")
    if window_steps < 1:
        raise InputError(f"window_steps must be >= 1, got {window_steps}")
    win, hop = _win_hop(win_ms, hop_ms)
    n = frame_count(x.size) if n_frames is None else int(n_frames)
    if n < 0:
        raise InputError(f"n_frames must be >= 0, got {n_frames}")
    spf = SAMPLES_PER_FRAME // hop  # spectrogram steps per video frame (4)
    C = n_mels if kind == "logmel" else n_mfcc
    if n == 0:
        return np.zeros((0, window_steps, C), dtype=np.float32)
    first = spf // 2 - window_steps // 2  # first step of frame 0's window (2 - 8 = -6)
    last = spf * (n - 1) + first + window_steps - 1  # last step needed
    # step t is centred on sample hop * t; its window starts at hop * t - win // 2
    start = hop * first - win // 2
    stop = hop * last - win // 2 + win
    padded = np.zeros(stop - start)
    lo, hi = max(0, start), min(x.size, stop)
    if hi > lo:
        padded[lo - start : hi - start] = np.clip(x[lo:hi], -1.0, 1.0)
    feats = log_mel_spectrogram(padded, n_mels, win_ms, hop_ms, n_fft)  # steps first..last
    if kind == "mfcc":
        feats = mfcc_from_log_mel(feats, n_mfcc)
    idx = spf * np.arange(n)[:, None] + np.arange(window_steps)[None]
    return feats[idx].astype(np.float32)


def frontend_from_array(kind: str, array: np.ndarray) -> np.ndarray:
    """Normalise a precomputed feature array to ``[N, W, C]`` float32.

    Args:
        kind: ``"ds"`` (DeepSpeech ``aud_ds.npy``: ``[N, 16, 29]``), ``"hu"`` (HuBERT
            ``aud_hu.npy``: ``[N, 2, 1024]``, or ``[2N, 1024]`` 50 Hz steps, reshaped as
            ER-NeRF does), ``"wavlm"`` (``[N, T, C]``, or ``[N, C]`` taken as ``W = 1``), or
            ``"logmel"`` / ``"mfcc"`` (an array made by :func:`waveform_features`).
        array: the loaded array.

    Raises:
        InputError: the shape does not fit the kind, or values are not finite.
    """
    a = np.asarray(array)
    if not np.issubdtype(a.dtype, np.number):
        raise InputError(f"{kind} features: non-numeric dtype {a.dtype}")
    a = a.astype(np.float32)
    if kind == "ds":
        if a.ndim != 3 or a.shape[2] != 29:
            raise InputError(f"ds features (aud_ds.npy) must be [N, 16, 29] (DeepSpeech windows), got shape {a.shape}")
    elif kind == "hu":
        if a.ndim == 2 and a.shape[1] == 1024 and a.shape[0] % 2 == 0:
            a = a.reshape(-1, 2, 1024)
        if a.ndim != 3 or a.shape[1:] != (2, 1024):
            raise InputError(f"hu features (aud_hu.npy) must be [N, 2, 1024] or [2N, 1024], got shape {a.shape}")
    elif kind == "wavlm":
        if a.ndim == 2:
            a = a[:, None, :]
        if a.ndim != 3:
            raise InputError(f"wavlm features must be [N, T, C] or [N, C], got shape {a.shape}")
    elif kind in ("logmel", "mfcc"):
        if a.ndim != 3:
            raise InputError(f"{kind} features must be [N, W, C], got shape {a.shape}")
    else:
        raise InputError(f"unknown audio feature kind {kind!r}; expected one of ds, hu, wavlm, logmel, mfcc")
    if a.shape[0] == 0 or a.shape[1] == 0 or a.shape[2] == 0:
        raise InputError(f"{kind} features are empty: shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{kind} features contain NaN or infinite values")
    return np.ascontiguousarray(a)
