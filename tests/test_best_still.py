"""The oracle control of LMD: the ground-truth frame whose mouth, held still, is nearest the whole clip's."""

from __future__ import annotations

import numpy as np

from lmgs_eval.metrics.landmarks import lmd_per_frame
from lmgs_eval.protocols.calibration import best_still_frame, control_clips


def _faces(openings, rng):
    """68 points a frame: one face, its mouth opened by ``openings`` along a fixed pattern, moved about the frame."""
    base = rng.uniform(100, 200, (68, 2))
    pattern = rng.standard_normal((20, 2))
    out = np.repeat(base[None], len(openings), 0)
    out[:, 48:68] += np.asarray(openings, np.float64)[:, None, None] * pattern
    return out + rng.uniform(-20, 20, (len(openings), 1, 2))  # translation: LMD centres it away


def test_the_best_still_frame_is_the_median_mouth():
    """Mouths along one pattern: holding frame k costs the mean |a_k - a_t| (up to a scale), least at the median."""
    rng = np.random.default_rng(0)
    lms = _faces([3.0, 0.0, 1.0, 2.0, 10.0], rng)
    assert best_still_frame(lms) == 3


def test_it_is_the_frame_a_brute_force_lmd_picks():
    rng = np.random.default_rng(1)
    lms = _faces(rng.gamma(2.0, 1.0, 60), rng) + rng.normal(0, 0.5, (60, 68, 2))
    lms[[5, 17]] = np.nan  # frames without a face are never chosen and never counted
    ok = np.isfinite(lms).all(axis=(1, 2))
    cost = [np.nanmean(lmd_per_frame(np.repeat(lms[k:k + 1], 60, 0)[ok], lms[ok])) if ok[k] else np.inf for k in range(60)]
    assert best_still_frame(lms) == int(np.argmin(cost))
    assert best_still_frame(np.full((4, 68, 2), np.nan)) is None


def test_the_frame_is_chosen_as_the_scoring_will_see_it_held():
    """A held frame's landmarks found again by the detector decide among the shortlist: a frame best by the clip's
    own landmarks but found elsewhere when held loses to the next best."""
    rng = np.random.default_rng(3)
    lms = _faces([3.0, 0.0, 1.0, 2.0, 10.0, 2.5], rng)
    assert best_still_frame(lms) == 3

    def detect(ks):
        out = lms[ks].copy()
        out[[i for i, k in enumerate(ks) if k == 3], 48:68] += 4.0 * rng.standard_normal((20, 2))
        return out

    assert best_still_frame(lms, detect=detect) == 5
    assert best_still_frame(lms, detect=lambda ks: np.full((len(ks), 68, 2), np.nan)) == 3  # none found: the clip's choice


def test_the_control_holds_that_frame_with_the_true_audio():
    gt = np.random.default_rng(2).integers(0, 255, (6, 8, 8, 3), dtype=np.uint8)
    audio = np.zeros(6 * 640, np.float32)
    clips = {c[0]: c for c in control_clips(gt, audio, audio, best_still=4)}
    name, display, control, frames, aud = clips["control:best-still-frame"]
    assert control == {"kind": "best-still-frame", "frame": 4, "targets": ["lmd"]} and "oracle" in display
    assert (frames == gt[4]).all() and frames.shape == gt.shape and aud is audio
    assert "control:best-still-frame" not in {c[0] for c in control_clips(gt, audio, audio)}
