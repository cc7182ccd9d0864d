"""The calibration protocol: the ground truth against its negative controls, on the subject itself.

Does each metric separate good from bad on this very subject? The controls are the ground
truth with its audio shifted or taken from elsewhere, and a still frame; each names the
metrics it is a negative control for.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from baselines.protocol import MethodInfo
from lmgs_eval import results as store
from lmgs_eval.errors import UserError
from lmgs_eval.metrics.sync.crops import crop_faces, face_boxes
from lmgs_eval.results.records import RunId, build_record, metrics_block, stored
from lmgs_eval.runner import RunConfig, cycle, log


CONTROLS_VERSION = "1"


SHIFTS = (-10, -5, 5, 10)


def shift_audio(audio: np.ndarray, frames: int, fps: int = 25, sr: int = 16000) -> np.ndarray:
    """The audio moved by ``frames`` video frames (positive: later), circularly, same length."""
    return np.roll(np.asarray(audio, np.float32), int(round(frames * sr / fps)))


def still_costs(held: np.ndarray, gt_lms: np.ndarray, block: int = 64) -> np.ndarray:
    """Per held frame ``held`` ``[K, 68, 2]``, the LMD of holding it on every frame of ``gt_lms`` ``[T, 68, 2]``: the
    mean over the frames with landmarks of the mouth points' (48-67, each set mean-centred) mean distance; inf for a
    held frame without landmarks."""
    from lmgs_eval.metrics.landmarks import MOUTH

    def centred(x):
        m = np.asarray(x, np.float64)[:, MOUTH]
        return m - m.mean(axis=1, keepdims=True)

    g = centred(gt_lms)
    g = g[np.isfinite(g).all(axis=(1, 2))]
    h = centred(held)
    out = np.full(len(h), np.inf)
    if not len(g):
        return out
    for a in range(0, len(h), block):
        out[a:a + block] = np.linalg.norm(h[a:a + block, None] - g[None], axis=-1).mean(axis=(1, 2))
    return np.where(np.isfinite(h).all(axis=(1, 2)), out, np.inf)


def best_still_frame(gt_lms: np.ndarray, detect=None, shortlist: int = 16) -> int | None:
    """The ground-truth frame whose mouth, held on every frame, scores the lowest LMD against the clip (landmarks
    ``gt_lms`` ``[T, 68, 2]``); None when no frame has landmarks. The clip's landmarks are tracked, and a detector
    finds a held frame's points again from its own face box, a few tenths of a pixel elsewhere: with ``detect``
    (frame indices -> ``[K, 68, 2]`` as the scoring will find them on those frames held) the ``shortlist`` frames
    best by the clip's own landmarks are scored as they will be, and the best of those is taken."""
    lms = np.asarray(gt_lms, np.float64)
    cost = still_costs(lms, lms)
    if not np.isfinite(cost).any():
        return None
    if detect is None:
        return int(np.argmin(cost))
    cand = [int(k) for k in np.argsort(cost)[:shortlist] if np.isfinite(cost[k])]
    held = still_costs(np.asarray(detect(cand), np.float64), lms)
    return cand[int(np.argmin(held))] if np.isfinite(held).any() else int(np.argmin(cost))


def control_clips(gt: np.ndarray, audio: np.ndarray, other_audio: np.ndarray,
                  best_still: int | None = None) -> list[tuple[str, str, dict, np.ndarray, np.ndarray]]:
    """The negative controls: ``(name, display, control, frames, audio)``.

    * ground truth with its audio shifted by -10, -5, +5, +10 frames: LSE-D/LSE-C take the
      best of +-15 offsets by definition, so these target the AV offset;
    * ground truth with audio from elsewhere in the recording (same voice, other words):
      targets LSE-D, LSE-C and the AV offset;
    * the first ground-truth frame repeated, with the true audio: targets LMD and LSE;
    * with ``best_still`` (:func:`best_still_frame`), that ground-truth frame repeated: the frozen mouth nearest
      the whole clip's, chosen by reading the test frames (an oracle, like the head on the plate); a method whose
      LMD is not below it moves no mouth better than the best single frame of the truth would. Targets LMD.
    """
    n = len(audio)
    other = np.asarray(other_audio, np.float32)
    if len(other) >= 2 * n:  # start half-way in, far from the test split's neighbour frames
        other = other[len(other) // 2 - n // 2:][:n] if len(other) // 2 + n // 2 <= len(other) else other[-n:]
    other = cycle(other, n) if len(other) else np.zeros(n, np.float32)
    out = []
    for k in SHIFTS:
        out.append((f"control:gt-audio{k:+d}", f"GT, audio {k:+d} frames", {"kind": "audio-shift", "frames": k, "targets": ["av_offset"]},
                    gt, shift_audio(audio, k)))
    out.append(("control:gt-other-audio", "GT, other audio", {"kind": "other-audio", "targets": ["lse_d", "lse_c", "av_offset"]},
                gt, other))
    still = np.repeat(gt[:1], len(gt), axis=0)
    out.append(("control:still-frame", "Still frame", {"kind": "still-frame", "targets": ["lmd", "lse_d", "lse_c"]}, still, audio))
    if best_still is not None:
        out.append(("control:best-still-frame", "Best still frame (oracle)",
                    {"kind": "best-still-frame", "frame": int(best_still), "targets": ["lmd"]},
                    np.repeat(gt[best_still:best_still + 1], len(gt), axis=0), audio))
    return out


def _best_still(cfg: RunConfig, gt: np.ndarray) -> int | None:
    """:func:`best_still_frame` on the ground truth's landmarks as the run's LMD finds them (cached on disk)."""
    from lmgs_eval.metrics.landmarks import cached_landmarks

    lmd = cfg.suite.metric("lmd")
    return best_still_frame(cached_landmarks(lmd.gt_backend, gt),
                            detect=lambda ks: np.stack([lmd.backend.landmarks(gt[k:k + 1])[0] for k in ks]))


def run_controls(cfg: RunConfig, truth: RunId, gt: np.ndarray, audio: np.ndarray, other_audio: np.ndarray) -> list[store.Record]:
    """Score the calibration controls of the ground truth's run ``truth``: each is recorded as that run with the
    control's method, under protocol ``calibration``; those in the store are skipped."""
    controls = []
    for name, display, control, frames, aud in control_clips(gt, audio, other_audio, _best_still(cfg, gt)):
        info = MethodInfo(name, display, "control", f"negative control: {display} (targets {', '.join(control['targets'])})",
                          config={"control": control, "version": CONTROLS_VERSION}, config_hash=f"controls-v{CONTROLS_VERSION}")
        run = dataclasses.replace(truth, info=info, protocol="calibration")
        if cfg.force or stored(cfg.results, run) is None:
            controls.append((run, control, frames, aud))
    if not controls:
        return []
    log(f"scoring {len(controls)} calibration controls")
    gf = gt  # uint8, as the sync scorers and LMD read it (no float copy of the clip)
    gt_crops = None
    records = []
    for run, control, frames, aud in controls:
        if frames is gt:  # same frames as the ground truth: reuse its face crops
            if gt_crops is None:
                try:
                    gt_crops = crop_faces(gf, face_boxes(gf)[0])
                except UserError:  # no face: lse() reports it as unavailable
                    gt_crops = False
            res = {"lse": cfg.suite.lse(gf, aud, crops=gt_crops if gt_crops is not False else None)}
        else:
            res = {"lse": cfg.suite.lse(frames, aud), "lmd": cfg.suite.paired("lmd", frames, gf)}
        rec = build_record(run, split="test", n_frames=len(frames), metrics=metrics_block(res), cost={}, artefacts={},
                           control=control)
        store.write_record(cfg.results, rec)
        records.append(rec)
    return records
