"""The bundled talking-head subjects: synthetic, fully ground-truthed stand-ins.

The paper's subjects (Obama, May, Lieu) cannot be shipped. These subjects are made offline
and deterministically from two public-domain photographs shipped by installed packages
(scikit-image's astronaut, matplotlib's Grace Hopper) and offline text-to-speech (piper,
espeak-ng), in the ER-NeRF / TalkingGaussian processed layout plus ground truth
(3D landmarks, depth, normals, phoneme timeline, articulation). See ``design.md``.
"""

from __future__ import annotations

from lmgs_eval.data.bundled.generator import GENERATOR_VERSION, Clip, build, list_voices, speech_is_shipped, synthesize_clip
from lmgs_eval.data.bundled.motion import Motion
from lmgs_eval.data.bundled.preview import contact_sheet, make_preview

BUNDLED_NAMES: tuple[str, ...] = ("astronaut", "hopper")

__all__ = ["BUNDLED_NAMES", "GENERATOR_VERSION", "Clip", "Motion", "build", "contact_sheet", "list_voices", "make_preview", "speech_is_shipped", "synthesize_clip"]
