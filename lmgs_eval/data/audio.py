"""Audio on disk: WAV files, the audio track of any media file (PyAV), and the 16 kHz mono a subject holds.

Samples are float32 in [-1, 1] in memory, ``[S, C]`` as read and ``[S]`` once mixed to mono.
Every reader names the file when it fails; :func:`write_wav` is deterministic.
"""

from __future__ import annotations

import io
import wave
from fractions import Fraction
from pathlib import Path

import numpy as np
from scipy.signal import resample_poly

from lmgs.fileio import atomic_write
from lmgs_eval.errors import UserError

SAMPLE_RATE = 16000


def read_wav(path: Path) -> tuple[np.ndarray, int]:
    """Read a PCM WAV file as float32 ``[S, C]`` in [-1, 1] and its sample rate.

    Other audio formats (mp3, m4a, ...) are decoded through PyAV (:func:`read_audio_track`).
    """
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: audio file not found")
    if path.stat().st_size == 0:
        raise UserError(f"{path}: audio file is empty")
    try:
        with wave.open(str(path), "rb") as w:
            sr, ch, width, n = w.getframerate(), w.getnchannels(), w.getsampwidth(), w.getnframes()
            raw = w.readframes(n)
    except (wave.Error, EOFError):
        x, sr, _ = read_audio_track(path)
        return x, sr
    if n == 0 or not raw:
        raise UserError(f"{path}: the WAV holds no samples (a header only)")
    if width == 2:
        x = np.frombuffer(raw, "<i2").astype(np.float32) / 32768.0
    elif width == 4:
        x = np.frombuffer(raw, "<i4").astype(np.float32) / 2147483648.0
    elif width == 1:
        x = (np.frombuffer(raw, np.uint8).astype(np.float32) - 128.0) / 128.0
    else:
        raise UserError(f"{path}: unsupported WAV sample width {width} bytes")
    return x.reshape(-1, ch), sr


def read_audio_track(path: Path) -> tuple[np.ndarray, int, float]:
    """The first audio track of a media file (a video's, or an mp3, m4a...), decoded through PyAV.

    Returns:
        float32 samples ``[S, C]`` in [-1, 1], the sample rate, and the presentation time of
        the first sample (seconds; 0 when the stream states none).

    Raises:
        UserError: no audio track, one that does not decode, or an empty one.
    """
    import av

    chunks, start, sr = [], None, None
    try:
        with av.open(str(path)) as c:
            if not c.streams.audio:
                raise UserError(f"{path}: has no audio track")
            st = c.streams.audio[0]
            sr = st.codec_context.sample_rate
            for fr in c.decode(st):
                if start is None:
                    start = float(fr.pts * st.time_base) if fr.pts is not None and st.time_base else 0.0
                a = fr.to_ndarray()
                if a.dtype == np.int16:
                    a = a.astype(np.float32) / 32768.0
                elif a.dtype == np.int32:
                    a = a.astype(np.float32) / 2147483648.0
                a = a.astype(np.float32)
                a = a.T if fr.format.is_planar else a.reshape(-1, len(fr.layout.channels))
                chunks.append(a)
    except av.error.FFmpegError as exc:
        raise UserError(f"{path}: not a readable audio file ({exc.__class__.__name__})") from None
    if not chunks or not sr:
        raise UserError(f"{path}: audio track is empty")
    return np.concatenate(chunks, axis=0), int(sr), float(start or 0.0)


def to_mono_16k(x: np.ndarray, sr: int, name: str = "audio") -> tuple[np.ndarray, list[str]]:
    """Mix ``[S, C]`` audio to mono and resample to 16 kHz; returns the signal and notes."""
    notes: list[str] = []
    x = np.asarray(x, np.float32)
    if x.ndim == 2:
        if x.shape[1] > 1:
            notes.append(f"{name}: {x.shape[1]} channels mixed to mono")
        x = x.mean(axis=1)
    if sr != SAMPLE_RATE:
        f = Fraction(SAMPLE_RATE, int(sr))
        x = resample_poly(x.astype(np.float64), f.numerator, f.denominator).astype(np.float32)
        notes.append(f"{name}: resampled from {sr} Hz to 16000 Hz")
    if not np.all(np.isfinite(x)):
        raise UserError(f"{name}: audio contains non-finite samples")
    return x, notes


def load_audio(path: Path) -> tuple[np.ndarray, list[str]]:
    """Any audio file as 16 kHz mono float32, with notes for each repair applied."""
    x, sr = read_wav(path)
    return to_mono_16k(x, sr, str(path))


def pcm16(x: np.ndarray, full_scale: float = 32767.0) -> np.ndarray:
    """Float audio in [-1, 1] as int16 samples: ``x * full_scale``, rounded and clipped."""
    return np.clip(np.rint(np.asarray(x, np.float64) * full_scale), -32768, 32767).astype(np.int16)


def write_wav(path: Path, x: np.ndarray, sr: int = SAMPLE_RATE) -> None:
    """Write mono float audio in [-1, 1] as 16-bit PCM WAV (through a temporary file and a rename)."""
    buf = io.BytesIO()
    with wave.open(buf, "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(int(sr))
        w.writeframes(pcm16(x).astype("<i2").tobytes())
    atomic_write(Path(path), buf.getvalue())
