"""The pixel scorers: SyncNet-shaped networks in ONNX Runtime on face crops (the official ``syncnet-v2``,
the bundled ``bundled-sync``).

A scorer shapes the 224x224 BGR crops of :mod:`~lmgs_eval.metrics.sync.crops` as its network
reads them (a region of the crop, resized, 0-255 or 0-1) and embeds syncnet_python's windows
(:mod:`~lmgs_eval.metrics.sync.maths`) a batch at a time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.sync.crops import CROP_SIZE, crop_faces, face_boxes
from lmgs_eval.metrics.sync.maths import audio_windows, video_windows

PREPARE_CHUNK = 256  # frames cropped and shaped at a time
MOUTH_BOX = (84, 196, 56, 168)  # rows, columns of the 224 crop around the mouth (region "mouth", bundled scorer)


@dataclass
class SyncScorer:
    """A loaded scorer: ONNX session + how to shape its inputs + what to record."""

    name: str
    session: object
    sha256: str
    input_hw: tuple[int, int]
    region: str  # "full", "lower_half" or "mouth" (MOUTH_BOX) of the 224 crop
    pixel: str  # "bgr_0_255" or "bgr_0_1"
    standin: str = ""
    source: str = ""  # the weights file, for messages

    def prepare(self, crops224: np.ndarray) -> np.ndarray:
        """``[T, 224, 224, 3]`` BGR crops (uint8, or float of integer values) as the network's float32 input."""
        import cv2

        x = np.asarray(crops224, np.float32)  # the one conversion to float: the resize below averages floats
        if self.region == "lower_half":
            x = x[:, CROP_SIZE // 2:]
        elif self.region == "mouth":
            r0, r1, c0, c1 = MOUTH_BOX
            x = x[:, r0:r1, c0:c1]
        h, w = self.input_hw
        if x.shape[1:3] != (h, w):
            x = np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA) for f in x])
        if self.pixel == "bgr_0_1":
            x = x / 255.0
        return x.astype(np.float32)

    def embed_clip(self, frames, crops, audio16k, mfcc, last, detect_every=1, lms=None):
        """Audio and video embeddings of windows ``0 .. last-1``, the still-face embedding, flags and notes."""
        flags, notes = [], []
        if crops is None:
            if frames is None:
                raise UserError(f"{self.name} scores face crops of frames; landmarks alone are not enough")
            if getattr(frames, "is_face_clip", False):
                crops, n_missing = frames.crops(detect_every)  # found once per clip, uint8
            else:  # an array: boxes now, crops a chunk at a time below
                boxes, n_missing = face_boxes(frames, detect_every)
            if n_missing:
                flags.append(f"no_face: {n_missing} detection(s) without a face, box held from the nearest frame")
            notes.append(f"crops: dlib HOG every {detect_every} frame(s), median-9 box smoothing, syncnet_python "
                         "crop_video geometry, 224x224 BGR 0-255")
        # crop and shape each frame once, a chunk at a time (a 5-minute clip's 224 crops alone are 4.5 GB)
        m = last + 4  # frames the windows use
        prepared = None
        for s in range(0, m, PREPARE_CHUNK):
            e = min(m, s + PREPARE_CHUNK)
            c = crops[s:e] if crops is not None else crop_faces(frames[s:e], boxes[s:e])
            p = self.prepare(c)
            if prepared is None:
                prepared = np.empty((m, *p.shape[1:]), np.float32)
            prepared[s:e] = p
        aw = audio_windows(mfcc, last)
        a_emb, v_emb = self.embed_frames(aw, prepared)
        _, still = self.embed_frames(aw[:1], np.repeat(prepared[:1], 5, axis=0))
        return a_emb, v_emb, still[0], flags, notes

    def embed_frames(self, audio_win: np.ndarray, frames: np.ndarray, batch: int = 16) -> tuple[np.ndarray, np.ndarray]:
        """Embeddings of window ``i`` = (``audio_win[i]``, prepared ``frames[i:i+5]``), a batch at a time.

        Same numbers as :meth:`embed` on :func:`windows`, without holding every window.
        """
        return self._embed(audio_win, lambda s, e: video_windows(frames, s, e), batch)

    def embed(self, audio_win: np.ndarray, video_win: np.ndarray, batch: int = 16) -> tuple[np.ndarray, np.ndarray]:
        return self._embed(audio_win, lambda s, e: video_win[s:e], batch)

    def _embed(self, audio_win: np.ndarray, video_of, batch: int) -> tuple[np.ndarray, np.ndarray]:
        a_out, v_out = [], []
        for s in range(0, audio_win.shape[0], batch):
            e = min(audio_win.shape[0], s + batch)
            a, v = self.session.run(["a_emb", "v_emb"], {"audio": audio_win[s:e], "video": video_of(s, e)})
            a_out.append(a)
            v_out.append(v)
        return np.concatenate(a_out), np.concatenate(v_out)
