"""LSE's arithmetic: syncnet_python's MFCC, windows and distances, independent of the scorer network.

Procedure (joonson/syncnet_python ``SyncNetInstance.evaluate``, as used by Wav2Lip's
``evaluation/scores_LSE``; the repository's docs/field.md, "Metric definitions"):

* audio: 16 kHz mono at int16 scale, ``python_speech_features.mfcc`` defaults -> 13 x 100 Hz;
* video: 25 fps face crops, windows of 5 frames; audio windows of 20 MFCC steps at ``4 * i``;
* ``min_length = min(n_frames, floor(n_samples / 640))``, ``lastframe = min_length - 5``,
  windows ``i = 0 .. lastframe - 1``;
* ``calc_pdist(vshift=15)``: the audio embeddings zero-padded by 15 on both ends, for
  window ``i`` the distances ``|v_i - a_{i+k-15} + 1e-6|_2`` for ``k = 0..30`` (torch's
  ``pairwise_distance`` adds ``eps = 1e-6`` to the difference);
* ``mdist[k]`` = mean over windows; **LSE-D** = ``min mdist``, **LSE-C** =
  ``median(mdist) - min(mdist)``, **offset** = ``15 - argmin mdist``.
"""

from __future__ import annotations

import math

import numpy as np

from lmgs_eval.errors import UserError

VSHIFT = 15
SAMPLES_PER_FRAME = 640  # 16 kHz / 25 fps
MIN_SAMPLES = 6 * SAMPLES_PER_FRAME  # one 5-frame window needs 6 frames of audio (syncnet_python's min_length - 5 >= 1)


def too_short(n_samples: int) -> str:
    """Why ``n_samples`` of 16 kHz audio cannot give one LSE window: its length and the minimum."""
    return (f"{n_samples / 16000:.2f} s ({n_samples} samples at 16 kHz); LSE needs at least {MIN_SAMPLES / 16000:.2f} s "
            f"({MIN_SAMPLES} samples: 6 frames at 25 fps)")


def mfcc_13(audio16k: np.ndarray) -> np.ndarray:
    """``[13, T]`` MFCCs at 100 Hz of float [-1, 1] 16 kHz mono audio, at int16 scale.

    syncnet_python reads the wav with ``scipy.io.wavfile`` (int16 values) and calls
    ``python_speech_features.mfcc(audio, 16000)`` with every default.
    """
    import python_speech_features

    x = np.clip(np.rint(np.asarray(audio16k, np.float64) * 32768.0), -32768, 32767)
    return np.asarray(python_speech_features.mfcc(x, 16000), np.float64).T


def is_silent(audio16k: np.ndarray, rms_floor: float = 1e-4) -> bool:
    x = np.asarray(audio16k, np.float64)
    return x.size == 0 or float(np.sqrt(np.mean(x * x))) < rms_floor


def n_windows(n_frames: int, n_samples: int) -> int:
    """syncnet_python's window count: ``min(n_frames, floor(n_samples / 640)) - 5``.

    Raises:
        UserError: fewer than one window.
    """
    last = min(int(n_frames), int(math.floor(n_samples / SAMPLES_PER_FRAME))) - 5
    if last <= 0:
        raise UserError(f"sync: clip too short for 5-frame windows ({n_frames} frames, {n_samples} samples)")
    return last


def video_windows(frames: np.ndarray, start: int, stop: int) -> np.ndarray:
    """Video windows ``start .. stop-1`` as ``[N, 3, 5, H, W]`` float32 from ``[T, H, W, 3]`` frames."""
    v = np.stack([frames[i:i + 5] for i in range(start, stop)])  # [N, 5, H, W, 3]
    return np.ascontiguousarray(v.transpose(0, 4, 1, 2, 3), np.float32)


def audio_windows(mfcc: np.ndarray, last: int) -> np.ndarray:
    """Audio windows ``[last, 1, 13, 20]``: 20 MFCC steps from ``4 * i`` (a short tail zero-filled)."""
    a = np.zeros((last, 1, 13, 20), np.float32)
    for i in range(last):
        seg = mfcc[:, 4 * i:4 * i + 20]
        a[i, 0, :, :seg.shape[1]] = seg  # syncnet_python would fail on a short tail; zero-fill is flagged by lse()
    return a


def windows(crops: np.ndarray, mfcc: np.ndarray, n_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Video ``[N, 3, 5, H, W]`` and audio ``[N, 1, 13, 20]`` windows, syncnet_python's indexing.

    Holds every video window in memory (5 copies of each frame); LSE builds them a batch at a
    time instead (:meth:`~lmgs_eval.metrics.sync.pixel.SyncScorer.embed_frames`), so a long clip fits.

    Args:
        crops: ``[T, H, W, 3]`` face crops in the scorer's pixel convention.
        mfcc: ``[13, M]`` from :func:`mfcc_13`.
        n_samples: number of 16 kHz audio samples.
    """
    last = n_windows(crops.shape[0], n_samples)
    return video_windows(crops, 0, last), audio_windows(mfcc, last)


def lse_from_embeddings(v_emb: np.ndarray, a_emb: np.ndarray, vshift: int = VSHIFT) -> dict:
    """LSE-D, LSE-C and the offset from per-window embeddings (``calc_pdist`` + ``evaluate``).

    .. math::
        \\mathrm{mdist}_k = \\frac{1}{N}\\sum_i \\| v_i - a_{i+k-s} + \\epsilon \\|_2,\\quad
        \\text{LSE-D} = \\min_k \\mathrm{mdist}_k,\\quad
        \\text{LSE-C} = \\operatorname{median}_k \\mathrm{mdist}_k - \\min_k \\mathrm{mdist}_k
    """
    v = np.asarray(v_emb, np.float64)
    a = np.asarray(a_emb, np.float64)
    n = v.shape[0]
    win = 2 * vshift + 1
    ap = np.concatenate([np.zeros((vshift, a.shape[1])), a, np.zeros((vshift, a.shape[1]))])
    idx = np.arange(n)[:, None] + np.arange(win)[None, :]
    dists = np.linalg.norm(v[:, None, :] - ap[idx] + 1e-6, axis=-1)  # [N, 31]
    mdist = dists.mean(axis=0)
    k = int(np.argmin(mdist))
    return {
        "lse_d": float(mdist[k]),
        "lse_c": float(np.median(mdist) - mdist[k]),
        "offset": int(vshift - k),
        "mdist": mdist,
        "per_window": dists[:, k],
    }
