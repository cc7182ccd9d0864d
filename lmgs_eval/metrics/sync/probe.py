"""Probe a sync scorer on footage known to be in sync: offset, injected shifts, audio from elsewhere.

What the scorer should do on an in-sync clip, measured on the clip itself:

* its own audio: offset 0 (+-1) and a trusted self-check;
* its audio delayed by ``k`` frames (frames and audio trimmed to the overlap): offset ``-k``
  (syncnet_python's sign convention);
* other speech of the same length (another file, cut at several starts): LSE-C clearly below
  the clip's own.

``lmgs-eval sync-check VIDEO --other-audio WAV`` prints these figures for any clip.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.base import MetricResult
from lmgs_eval.metrics.sync.crops import FaceClip
from lmgs_eval.metrics.sync.maths import SAMPLES_PER_FRAME, is_silent

SHIFTS = (-10, -5, 5, 10)
OTHER_MIN_S = 2.0  # other speech shorter than this (or than the clip) is too short to loop into a control


def check_other(other: np.ndarray, n_samples: int, what: str) -> None:
    """Refuse other speech that cannot serve as a control: empty, silent, or under :data:`OTHER_MIN_S`
    (or the clip's length, when the clip is shorter); ``what`` names it in the message.

    Raises:
        UserError: naming ``what``, its length and the minimum.
    """
    need = min(int(OTHER_MIN_S * 16000), int(n_samples))
    if len(other) < need:
        raise UserError(f"{what}: {len(other) / 16000:.2f} s of audio ({len(other)} samples at 16 kHz); other speech "
                        f"must last at least {need / 16000:.2f} s (it is looped to the clip's length)")
    if is_silent(other):
        raise UserError(f"{what}: silent (RMS below 1e-4): not speech to compare the clip's own with")


def shifted(x: np.ndarray, audio: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame ``x`` with the audio delayed by ``k`` frames (``k < 0``: advanced), both trimmed to the overlap."""
    spf, t = SAMPLES_PER_FRAME, len(x)
    if k > 0:
        return x[k:], audio[:(t - k) * spf]
    if k < 0:
        return x[:t + k], audio[-k * spf:t * spf]
    return x, audio


def probe(frames: np.ndarray, audio: np.ndarray, measure: Callable[..., MetricResult], other: np.ndarray | None = None,
          shifts=SHIFTS, n_other: int = 6) -> dict:
    """The figures of the module doc for one clip (``frames`` ``[T, H, W, 3]`` or a
    :class:`~lmgs_eval.metrics.sync.crops.FaceClip`, 16 kHz audio). The clip's faces are found once; each
    shifted copy takes its part of them.

    ``measure(frames, audio, reference=...)``: the LSE to probe (the ``lse`` metric's
    :meth:`~lmgs_eval.metrics.sync.scoring.LSE.score`, with the run's ``--sync`` scorers)."""
    if not getattr(frames, "is_face_clip", False):
        frames = FaceClip(frames)
    own = measure(frames, audio, reference=True)
    if not own.available:
        return {"available": False, "reason": own.reason}
    out = {"available": True, "backend": own.spec.backend,
           "own": {k: own.values.get(k) for k in ("offset", "lse_c", "lse_d", "separation", "trusted")},
           "flags": own.flags, "shifts": {}}
    for k in shifts:
        f, a = shifted(frames, audio, k)
        out["shifts"][k] = measure(f, a).values.get("offset")
    out["shifts_within_1"] = sum(v is not None and abs(v + k) <= 1 for k, v in out["shifts"].items())
    if other is not None:
        n = len(audio)
        starts = [0] if len(other) <= n else np.linspace(0, len(other) - n, n_other).astype(int).tolist()
        cs = []
        for s in starts:
            seg = np.resize(other[s:s + n], n)  # a shorter file is looped to the clip's length
            r = measure(frames, seg)
            cs.append(r.values.get("lse_c"))
        out["other_lse_c"] = cs
        out["own_above_every_other"] = bool(all(c is not None and own.values["lse_c"] > c for c in cs))
    return out
