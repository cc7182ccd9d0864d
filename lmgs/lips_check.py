"""Whether a clip's mouth follows its speech: the generic lip model's predicted inner-lip gap against the tracked
one, correlated at lags near zero and far from it (the chance level of that clip)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lmgs.lips import MOUTH, RetargetedLips, lip_gap, logmel
from lmgs.lips_weights import DEFAULT

# speech_coherence: the lags that count as "in sync" (the lip model's own lag, a tracker's, a frame of AV offset) and
# the shortest lag of the chance level (half a second and more: another syllable, another word).
NEAR_LAG, FAR_LAG, MAX_FAR_LAG = 3, 25, 150
COHERENT_Z = 3.0  # the near peak this many chance-level spreads above the chance level: the lips follow the speech
OFFSET_Z = 4.0  # a far peak this far above it, where the near one is not: the audio is offset from the video
MIN_COHERENCE_FRAMES = 100


def speech_coherence(audio, landmarks3d, weights: str | Path = DEFAULT) -> dict:
    """How far a clip's mouth opening follows its speech: the lip model's predicted inner-lip gap (retargeted to the clip,
    ``weights``) against the tracked one (68 landmarks ``[N, 68, 3]`` of a 16 kHz waveform's ``N`` frames), correlated at
    every lag up to :data:`MAX_FAR_LAG` frames (at most a third of the clip). The correlation within +-:data:`NEAR_LAG`
    frames is the clip's; lags of :data:`FAR_LAG` frames and more pair each frame with other words and give its chance
    level (its median, and its spread as the scaled median absolute deviation). ``verdict``: ``follows`` (near peak at least :data:`COHERENT_Z` spreads above chance),
    ``offset`` (not so, but a far lag :data:`OFFSET_Z` spreads above: the audio is shifted by ``best_far_lag`` frames),
    ``not shown`` (no better than chance: lips that move with expression more than with speech, such as smiles or an
    open mouth in pauses, or dubbing; or a clip too short, or a model too weak, to show it), or ``too short`` (fewer
    than :data:`MIN_COHERENCE_FRAMES` frames). A model that was trained on the
    clip itself follows it better than it would a new one: pass weights that never saw it."""
    y = np.asarray(landmarks3d, np.float64)
    n = len(y)
    out: dict = {"weights": str(weights), "frames": int(n), "near_lag": NEAR_LAG, "far_lag": FAR_LAG}
    max_lag = min(MAX_FAR_LAG, n // 3)
    if n < MIN_COHERENCE_FRAMES or max_lag < FAR_LAG + 10:
        return {**out, "verdict": "too short"}
    ok = np.isfinite(y).all(axis=(1, 2))
    if ok.sum() < MIN_COHERENCE_FRAMES:
        return {**out, "verdict": "too short"}
    y = np.where(ok[:, None, None], y, np.nanmedian(y, axis=0))  # untracked frames hold the median face
    feats = logmel(audio, n)
    ret = RetargetedLips.fit(feats[ok], y[ok], name=str(weights))
    pred = lip_gap(ret.predict(feats))
    track = lip_gap(y[:, MOUTH])
    c = correlation_at_lags(pred, track, max_lag)
    near = {k: v for k, v in c.items() if abs(k) <= NEAR_LAG and np.isfinite(v)}
    far = {k: v for k, v in c.items() if abs(k) >= FAR_LAG and np.isfinite(v)}
    if not near or len(far) < 10:
        return {**out, "verdict": "too short"}
    # the chance level's centre and spread robustly (median, scaled median absolute deviation): an offset track's own
    # peak, and its neighbours, are among the far lags and would widen a plain standard deviation
    fv = np.asarray(list(far.values()))
    mu = float(np.median(fv))
    sd = float(1.4826 * np.median(np.abs(fv - mu)))
    lag = max(near, key=lambda k: near[k])
    best = max(far, key=lambda k: far[k])
    z_near = (near[lag] - mu) / max(sd, 1e-6)
    z_far = (far[best] - mu) / max(sd, 1e-6)
    verdict = "follows" if z_near >= COHERENT_Z else "offset" if z_far >= OFFSET_Z else "not shown"
    return {**out, "verdict": verdict, "r": round(float(near[lag]), 3), "lag": int(lag), "chance_mean": round(mu, 3),
            "chance_sd": round(sd, 3), "z": round(float(z_near), 2), "best_far_lag": int(best),
            "best_far_r": round(float(far[best]), 3), "best_far_z": round(float(z_far), 2)}


def correlation_at_lags(a: np.ndarray, b: np.ndarray, max_lag: int = 5) -> dict[int, float]:
    """Pearson correlation of ``a[t]`` with ``b[t + lag]`` for every lag in ``[-max_lag, max_lag]`` (overlap only)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    out = {}
    for lag in range(-max_lag, max_lag + 1):
        x, y = (a, b[lag:]) if lag >= 0 else (a[-lag:], b)
        m = min(len(x), len(y))
        x, y = x[:m], y[:m]
        if len(x) < 3 or x.std() == 0 or y.std() == 0:
            out[lag] = math.nan
        else:
            out[lag] = float(np.corrcoef(x, y)[0, 1])
    return out
