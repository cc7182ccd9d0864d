"""LSE of one clip: a scorer's embeddings through syncnet_python's distances, with the self-check.

:func:`lse` scores with one loaded scorer; :class:`LSE`, the registry's ``lse`` metric, with the
scorers of the run's ``--sync`` choice (:class:`~lmgs_eval.metrics.sync.select.SyncScorers`,
resolved once by the metric suite), falling back from one to the next as ``auto`` says.
"""

from __future__ import annotations

import numpy as np

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.base import MetricResult, MetricSpec, unavailable
from lmgs_eval.metrics.sync.check import self_check
from lmgs_eval.metrics.sync.maths import MIN_SAMPLES, is_silent, lse_from_embeddings, mfcc_13, n_windows, too_short

LSE_SPEC = MetricSpec(
    name="lse",
    higher_is_better=False,
    unit="",
    backend="onnxruntime",
    version="1",
    definition=(
        "syncnet_python evaluate(): MFCC (python_speech_features defaults, int16-scale 16 kHz) windows of 20 "
        "steps at 4*i vs 5-frame 224x224 BGR 0-255 face-crop windows; calc_pdist(vshift=15); mdist = mean over "
        "windows per offset; LSE-D = min(mdist) (lower is better), LSE-C = median(mdist) - min(mdist) (higher is "
        "better), AV offset = 15 - argmin. per_item = each window's distance at the best offset."
    ),
    reference="Chung & Zisserman, 'Out of time', ACCV 2016 workshops; joonson/syncnet_python; Wav2Lip scores_LSE",
    per="window",
)


def _length(frames, crops, lms) -> int:
    return int(next(len(x) for x in (crops, frames, lms) if x is not None))


def lse(frames, audio16k: np.ndarray | None, *, scorer, fps: float = 25.0, crops: np.ndarray | None = None,
        detect_every: int = 1, audio_reason: str = "", lms: np.ndarray | None = None, reference: bool = False) -> MetricResult:
    """LSE-D / LSE-C / offset of one clip (no reference needed) with one scorer, and its self-check.

    Args:
        frames: ``[T, H, W, 3]`` uint8 RGB (or float in [0, 1]), or a
            :class:`~lmgs_eval.metrics.sync.crops.FaceClip` (the pixel scorer ignores it when ``crops`` is given).
        audio16k: 16 kHz mono float audio, or None (then unavailable with ``audio_reason``).
        scorer: a loaded scorer (:class:`~lmgs_eval.metrics.sync.pixel.SyncScorer` or
            :class:`~lmgs_eval.metrics.sync.landmark.LandmarkScorer`); :class:`LSE` tries the scorers of a
            ``--sync`` choice in turn.
        fps: frame rate; SyncNet windows assume 25 fps.
        crops: precomputed ``[T, 224, 224, 3]`` BGR 0-255 crops (pixel scorers: skips face detection).
        detect_every: run the face detector every k frames (pixel scorers).
        lms: precomputed ``[T, 68, 2]`` landmarks (landmark scorer: skips dlib).
        reference: the footage is known to be in sync (ground truth): the self-check also requires
            the offset to be 0 +- 1.

    ``values`` holds ``lse_d``, ``lse_c``, ``offset`` and the self-check's ``separation``,
    ``trusted``, ``null_lse_c``, ``null_lse_c_max``, ``still_lse_c`` (:mod:`~lmgs_eval.metrics.sync.check`).
    """
    n = _length(frames, crops, lms)
    if audio16k is not None and len(audio16k) < MIN_SAMPLES:
        audio_reason = f"audio too short: {too_short(len(audio16k))}"
        audio16k = None
    spec = LSE_SPEC.with_weights(scorer.sha256, backend=f"onnxruntime:{scorer.name}")
    if scorer.standin:
        spec = MetricSpec(**{**spec.to_dict(), "standin": scorer.standin})
    if audio16k is None:
        return unavailable(spec, audio_reason or "no audio (the video has no audio track and --audio was not given)", n)
    if abs(float(fps) - 25.0) > 0.01:
        return unavailable(spec, f"SyncNet windows assume 25 fps, the clip is {fps:g} fps", n)
    flags, notes = [], []
    if is_silent(audio16k):
        flags.append("silent_audio: RMS below 1e-4, LSE is meaningless on silence")
    try:
        last = n_windows(n, len(audio16k))
        mf = mfcc_13(audio16k)
        a_emb, v_emb, v_still, f2, n2 = scorer.embed_clip(frames, crops, audio16k, mf, last, detect_every, lms=lms)
    except UserError as exc:
        return unavailable(spec, str(exc), n)
    bad = [k for k, e in (("audio", a_emb), ("video", v_emb), ("still-face", v_still)) if not np.all(np.isfinite(e))]
    if bad:
        raise UserError(f"{scorer.name} ({getattr(scorer, 'source', '') or 'sha256 ' + scorer.sha256[:12]}): "
                        f"non-finite {' and '.join(bad)} embeddings; its weights are damaged (NaN or Inf)")
    flags += f2
    notes += n2
    if 4 * (last - 1) + 20 > mf.shape[1]:
        flags.append("audio_tail_padded: last MFCC window zero-filled")
    r = lse_from_embeddings(v_emb, a_emb)
    check, cflags = self_check(v_emb, a_emb, v_still, r["lse_c"], r["offset"], reference)
    values = {"lse_d": r["lse_d"], "lse_c": r["lse_c"], "offset": r["offset"], **check}
    flags += cflags
    if scorer.standin:
        notes.append("standin: " + scorer.standin)
    notes.append("mdist per offset -15..15: " + " ".join(f"{d:.3f}" for d in r["mdist"][::-1]))
    return MetricResult(spec, r["lse_d"], values, r["per_window"], max(0, n - 5), int(last), flags, notes)


class LSE:
    """The ``lse`` metric: LSE of one clip with the scorers of one ``--sync`` choice, tried in order.

    ``scorers``: ``(scorer, "")`` or ``(None, reason)`` per candidate
    (:class:`~lmgs_eval.metrics.sync.select.SyncScorers`). The first that is available and passes its
    self-check is kept; if none passes, the first available result (marked untrusted) stays, with a
    note naming what was tried.
    """

    spec = LSE_SPEC

    def __init__(self, scorers):
        self.scorers = scorers

    def score(self, frames, audio16k: np.ndarray | None, **kw) -> MetricResult:
        """:func:`lse` of ``frames`` and ``audio16k`` (same keywords) with the first scorer that can be believed."""
        results, reasons = [], []
        for sc, why in self.scorers:
            if sc is None:
                reasons.append(why)
                continue
            r = lse(frames, audio16k, scorer=sc, **kw)
            results.append(r)
            if r.available and r.values.get("trusted") is not False:
                break
        if not results:
            return unavailable(LSE_SPEC, "no SyncNet weights: " + "; ".join(reasons),
                               _length(frames, kw.get("crops"), kw.get("lms")))
        best = next((r for r in results if r.available and r.values.get("trusted") is not False), None)
        best = best or next((r for r in results if r.available), results[0])
        for r in results:
            if r is not best:
                best.notes.append(f"auto: {r.spec.backend} " + ("did not pass its self-check" if r.available
                                  else f"was unavailable ({r.reason})") + f" on this clip; kept {best.spec.backend}")
        return best
