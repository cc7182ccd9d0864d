"""The self-driven protocol (the paper's "Comparison Settings").

Each method is trained on the subject's training split (the first 10/11 of the frames) and
driven by the test split's own audio; the frames are scored against the test split's ground
truth (full frame: the rendered head composited on the ground-truth torso and background, as
ER-NeRF / TalkingGaussian do). The run also scores the ground truth itself (the paper's
"Ground Truth" row), the reference row "GT head on plate" and the calibration controls.
"""

from __future__ import annotations

from baselines.protocol import MethodInfo
from lmgs_eval import results as store
from lmgs_eval.convert import driving_from_clip, subject_to_clip
from lmgs_eval.data.registry import find_subject
from lmgs_eval.protocols.calibration import run_controls
from lmgs_eval.protocols.plate import PLATE_INFO, plate_composite
from lmgs_eval.results.records import RunId, build_record, metrics_block, stored
from lmgs_eval.runner import RunConfig, build_method, fit_render_score, log, write_render

GT_INFO = MethodInfo("ground-truth", "Ground Truth", "ground-truth", "the test split's own frames and audio", config={},
                     config_hash="gt")


def run_self(cfg: RunConfig) -> list[store.Record]:
    """The self-driven protocol for every method and seed; returns the records written."""
    subject = find_subject(cfg.subject, cfg.data_root, progress=cfg.progress)
    log(f"subject {subject.name}: {subject.n_frames} frames {subject.width}x{subject.height}, "
        f"{len(subject.train_ids)} train / {len(subject.test_ids)} test" + (" (bundled stand-in)" if subject.bundled else ""))
    train = subject_to_clip(subject, subject.train_ids, progress=cfg.progress)
    test = subject_to_clip(subject, subject.test_ids, progress=cfg.progress)
    driving = driving_from_clip(test)
    gt = test.frames
    records = []
    # every method built before anything is scored: a bad --set or --preset stops the run here
    planned = [(build_method(cfg, name, subject), seed) for name in cfg.methods for seed in cfg.seeds]
    # and renders made elsewhere read and checked against the test split: bad renders stop it here too
    for method, _ in planned:
        if getattr(method, "prerendered", False) and hasattr(method, "check"):
            method.check(driving, gt.shape[1:3])

    # The paper's "Ground Truth" row: the real test video scored like any method.
    truth = RunId(subject, GT_INFO)
    if cfg.force or stored(cfg.results, truth) is None:
        log("scoring the ground truth")
        records.append(score_reference(cfg, truth, gt, test))
    # Table I's reference row "GT head on plate": the best a head-only renderer can score after compositing.
    plate = RunId(subject, PLATE_INFO)
    if cfg.force or not stored(cfg.results, plate):
        frames = plate_composite(test)
        if frames is None:
            log(f"no head masks (parsing/) in {subject.name}: no 'GT head on plate' reference row")
        else:
            log("scoring the ground truth's head on the plate (reference row)")
            records.append(score_reference(cfg, plate, frames, test))
    records += run_controls(cfg, truth, gt, test.audio, train.audio)

    for method, seed in planned:
        run = RunId(subject, method.describe(), seed)
        if not cfg.force and stored(cfg.results, run):
            log(f"{run.label}: already in {cfg.results} (same config {run.info.config_hash}); skipped")
            continue
        records.append(fit_render_score(cfg, method, run, train, driving, gt, f"{run.renders}/{run.stem}.mp4"))
    return records


def score_reference(cfg: RunConfig, run: RunId, frames, test) -> store.Record:
    """A reference row: ``frames`` scored against the test split with its own audio (in sync), written as the
    render ``<method>.mp4`` and recorded."""
    res = cfg.suite.score(frames, test.frames, test.audio, in_sync=True)
    art = {"render": write_render(cfg.results, f"{run.renders}/{run.info.name}.mp4", frames, test.audio)}
    rec = build_record(run, split="test", n_frames=len(frames), metrics=metrics_block(res), cost={}, artefacts=art)
    store.write_record(cfg.results, rec)
    return rec
