"""Table I's reference row "GT head on plate": the best a head-only renderer can score after compositing."""

from __future__ import annotations

import numpy as np

from baselines.protocol import MethodInfo
from lmgs_eval.convert import subject_to_clip
from lmgs_eval.metrics.image import psnr


PLATE_VERSION = "1"


PLATE_DESCRIPTION = (
    "the test frames inside the subject's head mask (parsing, head colour) composited on its plate (torso_imgs over "
    "bc.jpg) outside it, as every method's head is: what a renderer drawing the head exactly, and nothing outside "
    "the head mask, would score. Well below the Ground Truth, it says the frames show something outside the head "
    "that the plate does not (a method that also paints there can score above it)")

PLATE_INFO = MethodInfo("plate-reference", "GT head on plate", "reference", PLATE_DESCRIPTION,
                        config={"version": PLATE_VERSION}, config_hash=f"plate-v{PLATE_VERSION}")
"""The row's method (scored by :func:`lmgs_eval.protocols.self_driven.run_self` on :func:`plate_composite`)."""


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
