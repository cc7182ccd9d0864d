"""Audio: feature front ends (one window per 25 fps frame), the Audio Encoder, the smoother.

Front ends (:func:`compute_features` for a waveform, :func:`frontend_from_array` for
precomputed arrays) all return ``[N, W, C]`` float32; :class:`AudioNet` turns them into the
smoothed compact audio feature :math:`F_a` ``[N, dim]`` per frame.
"""

from lmgs.audio.encoder import AudioEncoder, AudioNet, AudioSmoother, frame_windows, sliding_pairs
from lmgs.audio.features import (
    FPS,
    SAMPLE_RATE,
    SAMPLES_PER_FRAME,
    frame_count,
    frontend_from_array,
    load_waveform,
    log_mel_spectrogram,
    mel_filterbank,
    mfcc_from_log_mel,
    power_spectrogram,
    waveform_features,
)

FRONTENDS = ("logmel", "mfcc", "ds", "hu", "wavlm")


def compute_features(wave, sr: int = SAMPLE_RATE, cfg=None, n_frames: int | None = None):
    """Waveform (any rate, mono or multichannel) -> ``[N, W, C]`` per the config's front end.

    Only ``logmel`` and ``mfcc`` are computed from a waveform; ``ds``/``hu``/``wavlm`` need
    their precomputed arrays (:func:`frontend_from_array`).
    """
    from lmgs.config import AudioConfig
    from lmgs.errors import InputError

    cfg = cfg or AudioConfig()
    if cfg.frontend not in ("logmel", "mfcc"):
        raise InputError(f"front end {cfg.frontend!r} is precomputed: load its .npy and use frontend_from_array")
    return waveform_features(
        load_waveform(wave, sr),
        cfg.frontend,
        n_frames=n_frames,
        n_mels=cfg.n_mels,
        n_mfcc=cfg.n_mfcc,
        win_ms=cfg.win_ms,
        hop_ms=cfg.hop_ms,
        n_fft=cfg.n_fft,
        window_steps=cfg.window_steps,
    )


__all__ = [
    "FPS",
    "FRONTENDS",
    "SAMPLE_RATE",
    "SAMPLES_PER_FRAME",
    "AudioEncoder",
    "AudioNet",
    "AudioSmoother",
    "compute_features",
    "frame_count",
    "frame_windows",
    "frontend_from_array",
    "load_waveform",
    "log_mel_spectrogram",
    "mel_filterbank",
    "mfcc_from_log_mel",
    "power_spectrogram",
    "sliding_pairs",
    "waveform_features",
]
