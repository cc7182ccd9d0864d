"""Table I's reference row "GT head on plate": the best a head-only renderer can score after compositing."""

from __future__ import annotations

import numpy as np

from baselines.protocol import MethodInfo
from lmgs_eval import results as store
from lmgs_eval.convert import subject_to_clip
from lmgs_eval.metrics.image import psnr
from lmgs_eval.results.records import build_record, metrics_block, stored
from lmgs_eval.runner import RunConfig, log, write_render


PLATE_VERSION = "1"


PLATE_DESCRIPTION = (
    "the test frames inside the subject's head mask (parsing, head colour) composited on its plate (torso_imgs over "
    "bc.jpg) outside it, as every method's head is: what a renderer drawing the head exactly, and nothing outside "
    "the head mask, would score. Well below the Ground Truth, it says the frames show something outside the head "
    "that the plate does not (a method that also paints there can score above it)")


def plate_composite(clip) -> np.ndarray | None:
    """``uint8 [N, H, W, 3]``: the clip's frames inside its head masks, its plate outside (None without masks)."""
    if clip.head_masks is None:
        return None
    return np.where(clip.head_masks[..., None], clip.frames, clip.backgrounds)


def plate_reference_psnr(subject) -> float | None:
    """Mean PSNR (dB) of :func:`plate_composite` on the test split, or None without head masks."""
    test = subject_to_clip(subject, subject.test_ids)
    frames = plate_composite(test)
    return None if frames is None else float(psnr(frames / 255.0, test.frames / 255.0).value)


def run_plate_reference(cfg: RunConfig, subject, test) -> list[store.Record]:
    """Table I's reference row "GT head on plate" (skipped without head masks or when in the store)."""
    info = MethodInfo("plate-reference", "GT head on plate", "reference", PLATE_DESCRIPTION,
                      config={"version": PLATE_VERSION}, config_hash=f"plate-v{PLATE_VERSION}")
    if not cfg.force and stored(cfg.results, subject, info.name, "self", "test", 0, info.config_hash):
        return []
    frames = plate_composite(test)
    if frames is None:
        log(f"no head masks (parsing/) in {subject.name}: no 'GT head on plate' reference row")
        return []
    log("scoring the ground truth's head on the plate (reference row)")
    res = cfg.suite.score(frames, test.frames, test.audio, in_sync=True)
    art = {"render": write_render(cfg.results, f"renders/{subject.name}/plate-reference.mp4", frames, test.audio)}
    rec = build_record(info=info, subject=subject, protocol="self", clip="test", split="test", n_frames=len(frames),
                       seed=0, metrics=metrics_block(res), cost={}, artefacts=art, notes=list(subject.notes))
    store.write_record(cfg.results, rec)
    return [rec]
