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
from lmgs_eval.convert import driving_from_subject, subject_to_clip
from lmgs_eval.data.registry import find_subject
from lmgs_eval.protocols.calibration import run_controls
from lmgs_eval.protocols.plate import run_plate_reference
from lmgs_eval.results.records import build_record, metrics_block, stored
from lmgs_eval.runner import RunConfig, build_method, fit_render_score, log, render_stem, write_render


def run_self(cfg: RunConfig) -> list[store.Record]:
    """The self-driven protocol for every method and seed; returns the records written."""
    subject = find_subject(cfg.subject, cfg.data_root, progress=cfg.progress)
    log(f"subject {subject.name}: {subject.n_frames} frames {subject.width}x{subject.height}, "
        f"{len(subject.train_ids)} train / {len(subject.test_ids)} test" + (" (bundled stand-in)" if subject.bundled else ""))
    train = subject_to_clip(subject, subject.train_ids, progress=cfg.progress)
    test = subject_to_clip(subject, subject.test_ids, progress=cfg.progress)
    driving = driving_from_subject(subject, subject.test_ids, test)
    gt = test.frames
    renders_dir = f"renders/{subject.name}"
    records = []
    # every method built before anything is scored: a bad --set or --preset stops the run here
    planned = [(build_method(cfg, name, subject), seed) for name in cfg.methods for seed in cfg.seeds]
    # and renders made elsewhere read and checked against the test split: bad renders stop it here too
    for method, _ in planned:
        if getattr(method, "prerendered", False) and hasattr(method, "check"):
            method.check(driving, gt.shape[1:3])

    # The paper's "Ground Truth" row: the real test video scored like any method.
    gt_info = MethodInfo("ground-truth", "Ground Truth", "ground-truth", "the test split's own frames and audio", config={}, config_hash="gt")
    if cfg.force or stored(cfg.results, subject, "ground-truth", "self", "test", 0, "gt") is None:
        log("scoring the ground truth")
        res = cfg.suite.score(gt, gt, test.audio, in_sync=True)
        art = {"render": write_render(cfg.results, f"{renders_dir}/ground-truth.mp4", gt, test.audio)}
        rec = build_record(info=gt_info, subject=subject, protocol="self", clip="test", split="test", n_frames=len(gt), seed=0,
                           metrics=metrics_block(res), cost={}, artefacts=art, notes=list(subject.notes))
        store.write_record(cfg.results, rec)
        records.append(rec)

    records += run_plate_reference(cfg, subject, test)
    records += run_controls(cfg, subject, gt, test.audio, train.audio)

    for method, seed in planned:
        info = method.describe()
        if not cfg.force and stored(cfg.results, subject, info.name, "self", "test", seed, info.config_hash):
            log(f"{info.name} seed {seed}: already in {cfg.results} (same config {info.config_hash}); skipped")
            continue
        records.append(fit_render_score(cfg, method, subject, seed, train, driving, gt,
                                        f"{renders_dir}/{render_stem(info, seed)}.mp4"))
    return records
