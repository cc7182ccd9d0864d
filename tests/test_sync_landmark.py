"""The landmark sync scorer and LSE's self-check, on held-out generated clips.

Clips are synthesised here with texts and voices the scorer never trained on (the bundled
subjects' cross-driven texts; espeak voices held out by ``sync.train.landmark.split``),
rendered, and read back by dlib like any user's footage.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from lmgs_eval.metrics.sync import check, maths, scorers, scoring
from lmgs_eval.metrics.sync import landmark as L
from lmgs.fileio import sha256_file

CASES = [  # (face, held-out voice, held-out text section and index, injected audio delay in frames)
    ("astronaut", "espeak:en-us+f4", ("cross-a", 1), 5),
    ("hopper", "espeak:en-gb-x-rp+f4", ("cross-b", 2), -3),
]


@pytest.fixture(scope="module")
def scorer():
    sc, why = scorers.load_landmark()
    assert sc is not None, why
    return sc


@pytest.fixture(scope="module")
def clips():
    from lmgs_eval.data.bundled import list_voices, synthesize_clip
    from lmgs_eval.data.bundled.generator import load_corpus
    from lmgs_eval.metrics.landmarks import DlibBackend

    corpus = load_corpus()
    voices = set(list_voices())
    out = []
    for i, (face, voice, (sec, j), k) in enumerate(CASES):
        assert voice in voices
        text = " ".join(corpus[sec][j:j + 2])  # two sentences, about 7 s, as the acceptance clips
        c = synthesize_clip(face, text, voice, size=192, seed=777 + i)
        frames = c.frames  # uint8, as a reader gives them
        out.append({"frames": frames, "audio": c.audio, "k": k, "gt_lms": c.lms2d,
                    "lms": DlibBackend(redetect=10).landmarks(frames)})
    return out


def _shift(x, audio, k):
    """Per-frame ``x`` with the audio delayed by ``k`` frames (``k < 0``: advanced), trimmed; SyncNet reports ``-k``."""
    spf, t = maths.SAMPLES_PER_FRAME, len(x)
    if k > 0:
        return x[k:], audio[:(t - k) * spf]
    return x[:t + k], audio[-k * spf:t * spf]


def test_shipped_weights_match_their_manifest():
    onnx, meta = scorers.WEIGHTS / L.ONNX_NAME, scorers.WEIGHTS / L.JSON_NAME
    m = json.loads(meta.read_text())
    assert m["sha256"] == sha256_file(onnx)
    assert onnx.stat().st_size <= 20 * 2**20
    assert {"recipe", "seed", "acceptance"} <= set(m)
    held = set(m["recipe"]["voices"]) & {v for _, v, _, _ in CASES}
    assert not held  # the test voices were never trained on


def test_features_ignore_head_pose_scale_and_identity():
    rng = np.random.default_rng(0)
    base = rng.normal(size=(68, 2)) * 20 + 100
    t = 30
    lms = np.repeat(base[None], t, 0)
    lms[:, 48:68, 1] += np.sin(np.arange(t) / 3)[:, None] * 2.0  # the mouth moves
    ang, sc, tr = rng.uniform(-0.3, 0.3, t), rng.uniform(0.5, 2.0, t), rng.normal(size=(t, 2)) * 30
    rot = np.stack([np.stack([np.cos(ang), -np.sin(ang)], -1), np.stack([np.sin(ang), np.cos(ang)], -1)], 1)
    moved = sc[:, None, None] * np.einsum("tij,tkj->tki", rot, lms) + tr[:, None]
    np.testing.assert_allclose(L.mouth_features(moved), L.mouth_features(lms), atol=1e-4)
    other_face = lms.copy()
    other_face[:, 48:68] *= 1.1  # a different resting mouth, same motion relative to it
    other_face[:, 48:68] += 3.0
    f0, f1 = L.mouth_features(lms), L.mouth_features(other_face)
    assert np.corrcoef(f0.ravel(), f1.ravel())[0, 1] > 0.999
    assert np.abs(L.mouth_features(np.repeat(base[None], t, 0))).max() < 1e-9  # a still face has no motion


def test_fill_missing_interpolates_and_counts():
    lms = np.arange(5 * 68 * 2, dtype=float).reshape(5, 68, 2)
    gap = lms.copy()
    gap[2] = np.nan
    filled, n = L.fill_missing(gap)
    assert n == 1
    np.testing.assert_allclose(filled, lms)


def test_synced_and_shifted_clips(scorer, clips):
    for d in clips:
        r = scoring.lse(d["frames"], d["audio"], scorer=scorer, reference=True)  # the full path: dlib on the frames
        assert r.available and r.values["offset"] == 0, r.values
        assert r.values["trusted"] is True, r.values
        for k in (d["k"], -10):
            x, a = _shift(d["lms"], d["audio"], k)
            assert scoring.lse(None, a, scorer=scorer, lms=x).values["offset"] == -k


def test_self_check_rejects_still_face_and_other_audio(scorer, clips):
    for i, d in enumerate(clips):
        other = np.resize(clips[(i + 1) % len(clips)]["audio"], d["audio"].shape)
        gt = scoring.lse(None, d["audio"], scorer=scorer, lms=d["lms"]).values
        wrong = scoring.lse(None, other, scorer=scorer, lms=d["lms"]).values
        still = scoring.lse(None, d["audio"], scorer=scorer, lms=np.repeat(d["lms"][:1], len(d["lms"]), 0)).values
        assert gt["trusted"] is True and gt["separation"] >= check.MIN_SEPARATION, gt
        assert wrong["trusted"] is False and wrong["separation"] < gt["separation"], wrong
        assert still["trusted"] is False, still
        assert gt["lse_c"] > wrong["lse_c"]


def test_self_check_on_reference_requires_offset_zero(scorer, clips):
    d = clips[0]
    x, a = _shift(d["lms"], d["audio"], 5)
    free = scoring.lse(None, a, scorer=scorer, lms=x).values
    ref = scoring.lse(None, a, scorer=scorer, lms=x, reference=True)
    assert free["offset"] == -5 and free["trusted"] is True  # a clear, if shifted, sync signal
    assert ref.values["trusted"] is False and any("offset -5" in f for f in ref.flags)


def test_self_check_skips_short_clips(scorer, clips):
    d = clips[0]
    n = 2 * check.MIN_ROLL + 4  # windows = frames - 5
    r = scoring.lse(None, d["audio"][:n * maths.SAMPLES_PER_FRAME], scorer=scorer, lms=d["lms"][:n])
    assert r.values["trusted"] is None and any(f.startswith("self_check_skipped") for f in r.flags)


def test_pixel_scorer_reports_its_self_check(clips):
    sc, why = scorers.find_scorer("bundled-sync")
    assert sc is not None, why
    d = clips[0]
    r = scoring.lse(d["frames"], d["audio"], scorer=sc)
    assert {"lse_d", "lse_c", "offset"} <= set(r.values)  # the existing names stay
    # the clip is in sync: offset 0 +- 1, and the self-check separates it from its controls
    # (measured: offset 0, separation 21.8, LSE-C 0.59 against rolled audio's 0.14 at most)
    v = r.values
    assert abs(v["offset"]) <= 1 and v["trusted"] is True and v["separation"] >= check.MIN_SEPARATION, v
    assert v["lse_c"] > v["null_lse_c_max"] >= v["null_lse_c"] and v["lse_c"] >= check.STILL_RATIO * v["still_lse_c"]
    # its first 5 s with the audio delayed by k frames: the offset found is -k
    x, a = _shift(d["frames"][:125], d["audio"][:125 * maths.SAMPLES_PER_FRAME], d["k"])
    shifted = scoring.lse(x, a, scorer=sc).values
    assert shifted["offset"] == -d["k"] and shifted["trusted"] is True, shifted
