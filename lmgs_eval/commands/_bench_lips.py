"""``lmgs-eval bench lips``: the generic lip model against the per-subject CNN and the mean mouth, leaving each speaker out.

Reads the development footage (``--footage``, default ``../shared/footage``: videos of real people, never
copied anywhere; their lip tracks are cached outside the repository, :mod:`lmgs_eval.data.ingest.lips`).
For every clip, i.e. every held-out speaker:

- **generic**: the shipped generated-only weights (``lips_generated.pt``) adapted on the *other* speakers'
  clips with the recipe of the shipped model (:data:`lmgs_eval.data.lip_corpus.ADAPT`), retargeted to
  this clip's training split (its neutral mouth, width and audio statistics), predicting the test split;
- **subject CNN**: :func:`lmgs.landmarks.fit_landmark_predictor` (lmgs's per-subject predictor, its default
  400 steps) fitted on the training split's 68 points, predicting the test split;
- **generic fine-tuned** (``tuned_*``): the same model fine-tuned on the training split first
  (:data:`lmgs.lips.TUNE_STEPS`; lmgs's ``train.landmark_source=generic-tuned``), and, for comparison, the
  generated-only weights fine-tuned the same way (``tuned_gen_*``: what the real speakers' adaptation adds);
- **mean mouth**: the training split's mean mouth on every test frame;
- **main-mode oracle** (``oracle_mm``, a reference that reads the truth): the test mouths projected onto the
  training split's first principal mode of motion (mostly the opening), i.e. a perfect predictor of that one
  mode: how far below the mean mouth any predictor of the opening alone can get.

The split is the field's (lmgs's): the first 10/11 of the frames train, the rest test. Errors are the mean
distance of the 20 mouth points (48-67) in the track's frame (the canonical face, up to the fit of its skull
points), in millimetres (MediaPipe's canonical face is metric); the inner-lip gap (62-66) correlation of prediction and track is given at lag 0 and at its
peak within +-5 frames (positive: the prediction leads). The test split of an 8 s clip is 19 frames, so the
generic model is also scored on the whole clip (``generic_all_*``: it never saw the speaker), where the
correlations rest on every frame.

Deterministic: one thread, fixed seeds. A minute or two a fold on one core (11 clips: about 20-30 minutes); one
line a fold on standard error.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

IN_ALL = False  # trains a model per held-out speaker: `bench all` leaves it out
HELP = "the generic lip model against lmgs's per-subject CNN and the mean mouth, each real speaker held out"
FOOTAGE = Path("../shared/footage")
MAX_LAG = 5
CNN_STEPS = 400  # the per-subject predictor's steps, as lmgs fits it by default


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--footage", default=str(FOOTAGE), help=f"folder of real talking clips (*.mp4; default {FOOTAGE})")
    p.add_argument("--clip", action="append", default=[], help="score only this clip (file stem; repeatable)")
    p.add_argument("--weights", default=None,
                   help="a generated-only lip model file to adapt from (default: the shipped lips_generated.pt)")


def _gap_stats(pred_mouth: np.ndarray, true_mouth: np.ndarray) -> tuple[float, int, float]:
    from lmgs.lips import lip_gap
    from lmgs.lips_check import correlation_at_lags

    c = correlation_at_lags(lip_gap(pred_mouth), lip_gap(true_mouth), MAX_LAG)
    finite = {k: v for k, v in c.items() if np.isfinite(v)}
    if not finite:
        return float("nan"), 0, float("nan")
    peak = max(finite, key=lambda k: finite[k])
    return c[0], peak, finite[peak]  # peak > 0: the prediction leads the track by that many frames


def mouth_in_world(ret, feats) -> np.ndarray:
    """A retargeted model's mouth ``[N, 20, 3]`` in the recording's own frame, where the track (the truth), the
    subject CNN and the mean mouth are: the retargeting's canonical frame is fitted to the skull points of the
    training split and differs from the track's by a similarity."""
    return ret.predict(feats).astype(np.float64)


def main_mode_oracle(train_mouth: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """What a perfect predictor of the mouth's main mode of motion would give ``[N, 20, 3]``: the truth projected
    onto the first principal component of the training split's mouths ``[T, 20, 3]`` about their mean. A
    reference, not a method: it reads the test frames, and bounds what predicting the opening alone can gain."""
    mu = train_mouth.mean(0)
    _, _, vt = np.linalg.svd((train_mouth - mu).reshape(len(train_mouth), -1), full_matrices=False)
    v = vt[0]
    coef = (truth - mu).reshape(len(truth), -1) @ v
    return mu + (coef[:, None] * v[None]).reshape(truth.shape)


def evaluate_clip(rec, model, base=None) -> dict:
    """One held-out clip: the three predictors' errors and gap correlations (see the module's text)."""
    import torch

    from lmgs.landmarks import fit_landmark_predictor
    from lmgs.lips import MOUTH, TUNE_STEPS, RetargetedLips
    from lmgs_eval.data.layout import split_point
    from lmgs_eval.data.lip_corpus import features

    n = len(rec.lms68)
    ok = np.isfinite(rec.lms68).all(axis=(1, 2))
    if not ok.all():  # the footage's faces are tracked on every frame; a clip that is not is scored on its tracked part
        first = int(np.argmax(~ok)) if not ok[0] else 0
        n = first if first > 16 else n
    cut = split_point(n)
    feats = features(rec.audio, len(rec.lms68))[:n]
    y = rec.lms68[:n].astype(np.float64)
    tr, te = slice(0, cut), slice(cut, n)
    truth = y[te, MOUTH]
    ret = RetargetedLips.fit(feats[tr], y[tr], model=model, name="adapted without this speaker")
    generic = mouth_in_world(ret, feats[te])
    tuned = mouth_in_world(RetargetedLips.fit(feats[tr], y[tr], model=model, name="adapted without this speaker",
                                              tune_steps=TUNE_STEPS, seed=0), feats[te])
    tuned_gen = None if base is None else mouth_in_world(
        RetargetedLips.fit(feats[tr], y[tr], model=base, name="generated only", tune_steps=TUNE_STEPS, seed=0), feats[te])
    cnn = fit_landmark_predictor(torch.from_numpy(feats[tr]), torch.from_numpy(y[tr]).float(), steps=CNN_STEPS, seed=0)
    subject = cnn.predict(torch.from_numpy(feats[te])).numpy()[:, MOUTH]
    mean = np.broadcast_to(y[tr, MOUTH].mean(0), truth.shape)
    oracle = main_mode_oracle(y[tr, MOUTH], truth)
    err = lambda p: float(1000 * np.linalg.norm(p - truth, axis=-1).mean())  # noqa: E731
    whole = mouth_in_world(ret, feats)
    row = {"clip": rec.name, "test_frames": n - cut,
           "generic_mm": err(generic), "tuned_mm": err(tuned), "subject_cnn_mm": err(subject), "mean_mouth_mm": err(mean),
           "oracle_mm": err(oracle)}
    if tuned_gen is not None:
        row["tuned_gen_mm"] = err(tuned_gen)
    row["gap_r0"], row["gap_peak_lag"], _ = _gap_stats(generic, truth)
    row["tuned_gap_r0"], row["tuned_peak_lag"], _ = _gap_stats(tuned, truth)
    if tuned_gen is not None:
        row["tuned_gen_gap_r0"], _, _ = _gap_stats(tuned_gen, truth)
    row["cnn_gap_r0"], _, _ = _gap_stats(subject, truth)
    row["generic_all_mm"] = float(1000 * np.linalg.norm(whole - y[:, MOUTH], axis=-1).mean())
    row["mean_all_mm"] = float(1000 * np.linalg.norm(y[tr, MOUTH].mean(0) - y[:, MOUTH], axis=-1).mean())
    row["gap_all_r0"], row["gap_all_peak_lag"], _ = _gap_stats(whole, y[:, MOUTH])
    return row


def run(args: argparse.Namespace) -> dict:
    import torch

    from lmgs import lips
    from lmgs_eval.data import lip_corpus
    from lmgs_eval.errors import UserError

    folder = Path(args.footage)
    videos = sorted(folder.glob("*.mp4")) if folder.is_dir() else []
    if not videos:
        raise UserError(f"{folder}: no real footage (*.mp4) here; bench lips needs talking clips (--footage FOLDER)")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        t0 = time.perf_counter()
        base = lips.load(args.weights or "lips_generated.pt")
        real = lip_corpus.real_recordings(folder)
        names = {r.name for r in real}
        unknown = [c for c in args.clip if c not in names]
        if unknown:
            raise UserError(f"--clip {unknown[0]}: not among the clips of {folder} ({', '.join(sorted(names))})")
        generated = lip_corpus.generated_recordings()
        rows = []
        for rec in real:
            if args.clip and rec.name not in args.clip:
                continue
            a = time.perf_counter()
            others = lip_corpus.without_speakers(real, [rec.name])
            model = lip_corpus.adapt(base, others, generated)
            rows.append(evaluate_clip(rec, model, base))
            print(f"bench lips: {rec.name} held out: generic {rows[-1]['generic_mm']:.2f} mm, fine-tuned {rows[-1]['tuned_mm']:.2f}, "
                  f"subject CNN {rows[-1]['subject_cnn_mm']:.2f}, mean mouth {rows[-1]['mean_mouth_mm']:.2f} "
                  f"({time.perf_counter() - a:.0f} s)", file=sys.stderr, flush=True)
        keys = ("generic_mm", "tuned_mm", "tuned_gen_mm", "subject_cnn_mm", "mean_mouth_mm", "oracle_mm", "gap_r0", "tuned_gap_r0",
                "tuned_gen_gap_r0", "cnn_gap_r0", "generic_all_mm", "mean_all_mm", "gap_all_r0")
        mean = {k: float(np.mean([r[k] for r in rows])) for k in keys}
        rel = lambda a, b: f"{100 * (mean[a] / mean[b] - 1):+.1f} %"  # noqa: E731
        out = {
            "footage": str(folder),
            "clips": len(rows),
            "split": "first 10/11 of each clip train (neutral mouth, CNN), the rest test",
            "units": "mean distance of the 20 mouth points in the track's (canonical face) frame, mm",
            "generic vs subject CNN": rel("generic_mm", "subject_cnn_mm") + " (goal <= -25 %)",
            "generic vs mean mouth": rel("generic_mm", "mean_mouth_mm") + " (goal <= -40 %)",
            "generic fine-tuned vs subject CNN": rel("tuned_mm", "subject_cnn_mm"),
            "generic fine-tuned vs mean mouth": rel("tuned_mm", "mean_mouth_mm"),
            "generated-only fine-tuned vs subject CNN": rel("tuned_gen_mm", "subject_cnn_mm"),
            "generated-only fine-tuned vs mean mouth": rel("tuned_gen_mm", "mean_mouth_mm"),
            "main-mode oracle vs mean mouth (a bound, not a method)": rel("oracle_mm", "mean_mouth_mm"),
            "gap correlation at lag 0, test splits (mean)": round(mean["gap_r0"], 3),
            "gap correlation at lag 0, fine-tuned, test splits (mean)": round(mean["tuned_gap_r0"], 3),
            "subject CNN gap correlation at lag 0, test splits (mean)": round(mean["cnn_gap_r0"], 3),
            "gap correlation at lag 0, whole clips (mean)": round(mean["gap_all_r0"], 3),
            "mean": {k: round(v, 4) for k, v in mean.items()},
            "rows": rows,
            "seconds": round(time.perf_counter() - t0, 1),
        }
        return out
    finally:
        torch.set_num_threads(threads)
