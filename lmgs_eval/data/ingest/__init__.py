"""Raw talking-head video in, a subject in the ER-NeRF / TalkingGaussian layout out.

``ingest(video, name)`` writes exactly what :func:`lmgs_eval.data.layout.read_subject`
reads, offline and on a CPU: frames at 25 fps, 16 kHz mono audio, dlib's 68 landmarks
(tracked, smoothed), a 68-point template fitted for head pose and focal length, parsing maps,
the background plate, torso and ground-truth images, blink action units, 3D landmarks and a
manifest. See ``design.md``.
"""

from __future__ import annotations

from lmgs_eval.data.ingest.checks import INGEST_VERSION
from lmgs_eval.data.ingest.pipeline import IngestConfig, ingest

__all__ = ["INGEST_VERSION", "IngestConfig", "ingest"]
