"""From a phone timeline to per-frame articulation: mouth shape, blinks, head motion.

Mouth parameters follow the dominance model of coarticulation (Cohen & Massaro 1993): each
phone pulls every parameter towards its viseme target with a dominance that is flat over the
phone and decays exponentially outside it,

.. math::

    p(t) = \\frac{\\sum_i D_i(t)\\, T_i}{\\sum_i D_i(t)}, \\qquad
    D_i(t) = \\alpha_i \\exp\\left(-\\max(0, |t - c_i| - d_i/2) / \\tau\\right),

so bilabial closures and lip-teeth contacts (high :math:`\\alpha`) are reached even when short,
while alveolars and velars (low :math:`\\alpha`) take the shape of their neighbours. Blinks
and head motion are seeded smooth processes.
"""

from __future__ import annotations

import numpy as np

from lmgs_eval.data.bundled import exact
from lmgs_eval.data.bundled.speech import Phone

COLUMNS = (
    "jaw",  # jaw opening, 0 closed .. 1 wide open (about 12 degrees of jaw rotation)
    "lip_width",  # -1 narrow .. +1 spread
    "lip_round",  # 0 .. 1 protrusion and rounding
    "lip_closure",  # 0 .. 1 lips pressed together (p, b, m)
    "lip_teeth",  # 0 .. 1 lower lip raised to the upper teeth (f, v)
    "blink",  # 0 open .. 1 eyelids closed
    "yaw",  # head rotation about the vertical axis, degrees
    "pitch",  # head rotation about the horizontal axis, degrees (positive: chin down)
    "roll",  # head rotation about the view axis, degrees
    "tx",  # head translation, world units (metres): right
    "ty",  # up
    "tz",  # towards the camera
    "brow",  # 0 .. 1 eyebrow raise
)
MOUTH = COLUMNS[:5]
TAU = 0.055  # seconds: decay of a phone's dominance outside it

# viseme -> (targets for jaw, width, round, closure, lip_teeth), (dominances)
VISEME_TARGETS: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "sil": ((0.0, 0.0, 0.0, 0.3, 0.0), (1.0, 1.0, 1.0, 1.0, 1.0)),
    "PP": ((0.04, 0.0, 0.1, 1.0, 0.0), (3.0, 0.6, 0.6, 10.0, 3.0)),
    "FF": ((0.12, 0.1, 0.0, 0.0, 1.0), (2.5, 0.6, 1.0, 3.0, 10.0)),
    "TH": ((0.22, 0.15, 0.0, 0.0, 0.0), (1.5, 0.6, 0.6, 3.0, 3.0)),
    "DD": ((0.2, 0.2, 0.0, 0.0, 0.0), (0.6, 0.4, 0.4, 3.0, 3.0)),
    "kk": ((0.3, 0.1, 0.0, 0.0, 0.0), (0.4, 0.3, 0.3, 3.0, 3.0)),
    "CH": ((0.18, -0.4, 0.65, 0.0, 0.0), (1.5, 2.0, 2.0, 3.0, 3.0)),
    "SS": ((0.1, 0.45, 0.0, 0.0, 0.0), (1.5, 1.5, 1.0, 3.0, 3.0)),
    "nn": ((0.18, 0.1, 0.0, 0.0, 0.0), (0.6, 0.4, 0.4, 3.0, 3.0)),
    "RR": ((0.22, -0.2, 0.45, 0.0, 0.0), (1.0, 1.0, 1.2, 3.0, 3.0)),
    "aa": ((0.95, 0.15, 0.0, 0.0, 0.0), (1.6, 1.0, 1.0, 3.0, 3.0)),
    "E": ((0.5, 0.35, 0.0, 0.0, 0.0), (1.2, 1.0, 1.0, 3.0, 3.0)),
    "I": ((0.22, 0.7, 0.0, 0.0, 0.0), (1.2, 1.5, 1.0, 3.0, 3.0)),
    "O": ((0.6, -0.5, 0.8, 0.0, 0.0), (1.4, 1.5, 1.5, 3.0, 3.0)),
    "U": ((0.22, -0.8, 1.0, 0.0, 0.0), (1.2, 2.0, 2.0, 3.0, 3.0)),
}


def mouth_tracks(phones: tuple[Phone, ...] | list[Phone], times: np.ndarray) -> np.ndarray:
    """Mouth parameters ``[T, 5]`` (``MOUTH`` columns) at ``times`` (seconds).

    Times not covered by any phone count as silence (a weak pull to the rest shape).
    """
    times = np.asarray(times, np.float64)
    num = np.zeros((len(times), 5))
    den = np.zeros((len(times), 5))
    # A weak everywhere-present rest target so gaps between phones relax the mouth.
    rest_t, rest_d = VISEME_TARGETS["sil"]
    num += 0.05 * np.asarray(rest_d) * np.asarray(rest_t)
    den += 0.05 * np.asarray(rest_d)
    for p in phones:
        tgt, dom = VISEME_TARGETS.get(p.viseme, VISEME_TARGETS["sil"])
        c, half = 0.5 * (p.start + p.end), 0.5 * (p.end - p.start)
        lo, hi = np.searchsorted(times, [p.start - 8 * TAU, p.end + 8 * TAU])
        if hi <= lo:
            continue
        d = exact.exp(-np.maximum(0.0, np.abs(times[lo:hi] - c) - half) / TAU)[:, None] * np.asarray(dom)[None]
        num[lo:hi] += d * np.asarray(tgt)[None]
        den[lo:hi] += d
    return (num / den).astype(np.float32)


def _smooth_process(rng: np.random.Generator, t: np.ndarray, amp: float, fmin: float = 0.05, fmax: float = 0.4, k: int = 4) -> np.ndarray:
    """A smooth random signal: a sum of ``k`` sinusoids, scaled to peak ``amp``."""
    f = rng.uniform(fmin, fmax, k)
    ph = rng.uniform(0, 2 * np.pi, k)
    a = rng.uniform(0.5, 1.0, k)
    x = (a[None] * exact.sin(2 * np.pi * f[None] * t[:, None] + ph[None])).sum(1)
    return amp * x / (a.sum() * 0.75)


def blink_track(rng: np.random.Generator, times: np.ndarray) -> np.ndarray:
    """Eyelid closure in [0, 1]: a blink every 2-6 s, about 150 ms long (closing faster than opening)."""
    out = np.zeros(len(times))
    end = float(times[-1]) if len(times) else 0.0
    t0 = rng.uniform(0.8, 2.5)
    while t0 < end + 1.0:
        close, hold, reopen = 0.05, 0.04, 0.08
        x = times - t0
        b = np.where(x < 0, 0.0, np.where(x < close, x / close, np.where(x < close + hold, 1.0, 1.0 - (x - close - hold) / reopen)))
        out = np.maximum(out, np.clip(b, 0.0, 1.0))
        t0 += rng.uniform(2.0, 6.0)
    return out


def articulation(phones, n_frames: int, fps: int, rng: np.random.Generator) -> np.ndarray:
    """All ``COLUMNS`` per frame ``[N, K]`` float32, sampled at frame centres ``(i + 0.5) / fps``."""
    t = (np.arange(n_frames) + 0.5) / fps
    out = np.zeros((n_frames, len(COLUMNS)), np.float64)
    out[:, :5] = mouth_tracks(phones, t)
    out[:, 5] = blink_track(rng, t)
    speaking = _speaking(phones, t)
    for col, amp in (("yaw", 4.0), ("pitch", 2.5), ("roll", 2.0), ("tx", 0.006), ("ty", 0.004), ("tz", 0.005)):
        out[:, COLUMNS.index(col)] = _smooth_process(rng, t, amp)
    # Small nods on stressed, open syllables: pitch follows the jaw a little.
    out[:, COLUMNS.index("pitch")] += 0.8 * out[:, 0] * speaking
    out[:, COLUMNS.index("brow")] = np.clip(_smooth_process(rng, t, 1.2, 0.1, 0.5), 0.0, 1.0) * (0.3 + 0.7 * speaking)
    return out.astype(np.float32)


def _speaking(phones, t: np.ndarray) -> np.ndarray:
    s = np.zeros(len(t))
    for p in phones:
        if p.viseme != "sil":
            s[(t >= p.start - 0.1) & (t < p.end + 0.1)] = 1.0
    return exact.box5(s) if len(s) >= 5 else s  # a 5-frame moving average


def action_units(art: np.ndarray, lip_gap: np.ndarray) -> dict[str, np.ndarray]:
    """OpenFace-style action-unit intensities (0-5) derived from the articulation.

    ``lip_gap`` is the inner-lip opening per frame, normalised to [0, 1].
    """
    c = {name: art[:, i].astype(np.float64) for i, name in enumerate(COLUMNS)}
    zero = np.zeros(len(art))
    aus = {
        "AU01_r": 2.5 * c["brow"],
        "AU02_r": 2.0 * c["brow"],
        "AU04_r": zero,
        "AU05_r": 0.3 * c["brow"],
        "AU06_r": 0.5 * np.clip(c["lip_width"], 0, 1),
        "AU07_r": zero,
        "AU09_r": zero,
        "AU10_r": 0.8 * c["lip_teeth"],
        "AU12_r": 1.0 * np.clip(c["lip_width"], 0, 1),
        "AU14_r": zero,
        "AU15_r": zero,
        "AU17_r": 1.5 * c["lip_closure"],
        "AU20_r": 0.6 * np.clip(c["lip_width"], 0, 1),
        "AU23_r": 1.5 * c["lip_round"],
        "AU25_r": 5.0 * np.clip(lip_gap, 0, 1),
        "AU26_r": 5.0 * np.clip(c["jaw"], 0, 1),
        "AU45_r": 5.0 * c["blink"],
    }
    return {k: np.clip(v, 0.0, 5.0) for k, v in aus.items()}
