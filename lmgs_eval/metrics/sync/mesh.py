"""The mesh sync scorer: the mouth of the dense face mesh against MFCC windows, adapted on real speakers.

The landmark scorer (:mod:`~lmgs_eval.metrics.sync.landmark`) reads dlib's 68 points, and on a real face
dlib's mouth jitters and lags more than speech moves it. This scorer reads the same 20 mouth points from
the dense face mesh (MediaPipe's 478-point model, :mod:`lmgs_eval.data.ingest.mesh`), each frame brought
into the canonical face frame by the similarity of its skull-fixed vertices
(:func:`lmgs_eval.data.ingest.lips.to_canonical`): head pose, scale and distance are gone before the
features are made. From there on everything is the landmark scorer's: the features
(:func:`~lmgs_eval.metrics.sync.landmark.mouth_features` of the points' x and y), the windows, the network,
LSE-D / LSE-C and the offset search over +-15 frames.

Its weights start from the landmark scorer's (trained on generated clips) and are adapted on real
talking-head recordings with their own speech (:mod:`~lmgs_eval.metrics.sync.train.mesh`, which also
measures it leave-one-speaker-out; the figures are in ``mesh_sync.json``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.sync.landmark import LandmarkScorer

ONNX_NAME, JSON_NAME = "mesh_sync.onnx", "mesh_sync.json"
STANDIN = ("mesh-sync is trained by this project (generated clips, then real speakers' recordings; mouth points of the "
           "dense face mesh vs MFCC); its LSE values are not comparable with SyncNet LSE in papers")


def mouth_points(lms68: np.ndarray) -> np.ndarray:
    """``[T, 68, 2]``: the x and y of the 68 points in the canonical face frame (``[T, 68, 3]``, or already 2-D)."""
    x = np.asarray(lms68, np.float64)
    return x[..., :2]


@dataclass
class MeshScorer(LandmarkScorer):
    """A loaded mesh scorer (the interface LSE calls is :meth:`embed_clip`)."""

    name: str = "mesh-sync"
    standin: str = STANDIN

    def embed_clip(self, frames, crops, audio16k, mfcc, last, detect_every=1, lms=None):
        """Audio and video embeddings of windows ``0 .. last-1``, the still-face embedding, flags and notes.

        The mouth comes from the dense mesh tracked on ``frames`` (a
        :class:`~lmgs_eval.metrics.sync.crops.FaceClip` tracks it once per clip), or from ``lms`` when they are
        already the mesh's 68 points in the canonical face frame (``[T, 68, 3]``); 2-D landmarks (dlib's) are
        not what this scorer reads and are ignored when frames are given.
        """
        flags, notes = [], []
        canon = lms is not None and np.asarray(lms).ndim == 3 and np.asarray(lms).shape[-1] == 3
        if not canon:
            if frames is None:
                raise UserError("mesh-sync needs the frames (or the face mesh's canonical 68 points), not 2-D landmarks "
                                "or face crops")
            from lmgs_eval.metrics.sync.crops import FaceClip

            clip = frames if getattr(frames, "is_face_clip", False) else FaceClip(frames)
            lms = clip.mesh_landmarks()
        notes.append("video: the dense face mesh (MediaPipe face landmarker, 478 points) tracked per frame, each "
                     "frame brought to the canonical face frame by its skull points; its 68 points' "
                     + self.feature_note().replace("mouth points 48-67", "mouth points 48-67 (x, y)"))
        return (*self.embed_points(mouth_points(lms), mfcc, last, flags, "the dense face mesh"), flags, notes)


def export(net, out_dir, meta: dict) -> dict:
    """Write the adapted network as ``mesh_sync.onnx`` and its manifest (recipe, figures, sha256)."""
    from lmgs_eval.metrics.sync import landmark

    return landmark.export(net, out_dir, {"context": 15, **meta}, name="mesh-sync", files=(ONNX_NAME, JSON_NAME),
                           points="mouth_features of the mesh's canonical 68 points,")
