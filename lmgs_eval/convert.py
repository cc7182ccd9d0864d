"""The toolkit's subjects as the model library's input types.

Every method takes :class:`lmgs.types.TrainingClip` and :class:`lmgs.types.DrivingAudio`;
nothing below the toolkit knows a folder layout. :func:`subject_to_clip` loads a split of a
:class:`~lmgs_eval.data.Subject` (frames, plate behind the head, cameras, audio, landmarks,
masks, geometry priors); :func:`driving_from_clip` is the self-driven input of a loaded split.
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from lmgs.types import DrivingAudio, TrainingClip
from lmgs_eval.data.images import to_u8
from lmgs_eval.data.subject import Subject

PARSING_HEAD = (255, 0, 0)


def _background(torso: np.ndarray | None, bc: np.ndarray) -> np.ndarray:
    """A frame's torso (``torso_imgs`` RGBA, if any) composited over ``bc.jpg``: what lies behind the head."""
    if torso is None:
        return bc
    a = torso[..., 3:4]
    return torso[..., :3] * a + bc * (1 - a)


def subject_to_clip(subject: Subject, ids: np.ndarray, *, progress: bool = False) -> TrainingClip:
    """Load frames ``ids`` of a subject into a :class:`TrainingClip` (uint8/float16 storage)."""
    ids = np.asarray(ids)
    bc = subject.background()
    frames = np.empty((len(ids), subject.height, subject.width, 3), np.uint8)
    backs = np.empty_like(frames)
    mouth = np.zeros((len(ids), subject.height, subject.width), bool)
    head = np.zeros_like(mouth)
    have_mouth = have_head = False
    depth = normal = None
    if subject.has_geometry:
        depth = np.zeros((len(ids), subject.height, subject.width), np.float16)
        normal = np.zeros((len(ids), subject.height, subject.width, 3), np.int8)
    it = enumerate(ids)
    if progress:
        it = tqdm(list(it), desc=f"loading {subject.name}", unit="frame", leave=False)
    for k, i in it:
        frames[k] = subject.frame(i)
        backs[k] = to_u8(_background(subject.torso(i), bc))
        m = subject.mouth_mask(i)
        if m is not None:
            mouth[k], have_mouth = m, True
        p = subject.parsing(i)
        if p is not None:
            head[k], have_head = np.all(p == PARSING_HEAD, axis=-1), True
        if depth is not None:
            depth[k] = subject.depth(i)
            normal[k] = np.clip(np.rint(subject.normal(i) * 127), -127, 127).astype(np.int8)
    w2c = np.stack([subject.camera(i).world_to_camera.numpy() for i in ids]).astype(np.float32)
    spf = subject.samples_per_frame()
    audio = subject.audio[int(ids[0]) * spf : (int(ids[-1]) + 1) * spf]
    feats = {k: v[ids] for k, v in subject.audio_features.items()}
    return TrainingClip(
        frames=frames,
        backgrounds=backs,
        w2c=w2c,
        focal=subject.focal,
        cx=subject.cx,
        cy=subject.cy,
        audio=np.ascontiguousarray(audio),
        blink=subject.blink[ids],
        landmarks2d=subject.landmarks[ids],
        landmarks3d=None if subject.landmarks3d is None else subject.landmarks3d[ids],
        audio_features=feats or None,
        mouth_masks=mouth if have_mouth else None,
        head_masks=head if have_head else None,
        depth=depth,
        normal=normal,
        priors_derived=subject.priors_derived,
    )


def driving_from_clip(clip: TrainingClip) -> DrivingAudio:
    """The self-driven input of a loaded split (:func:`subject_to_clip`): its audio, cameras, backgrounds and blinks."""
    return DrivingAudio(
        audio=clip.audio,
        w2c=clip.w2c,
        backgrounds=clip.backgrounds,
        blink=clip.blink,
        audio_features=clip.audio_features,
    )
