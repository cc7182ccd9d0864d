"""Lip tracks of a raw video: the dense face mesh per 25 fps frame, its 68 points in a canonical head frame.

Per frame the shipped mesh model (:mod:`mesh`) gives 478 points in image pixels (z in the same
scale); the 68 points of the iBUG 300-W layout are read off the mesh by the standard 468 -> 68
correspondence (:data:`MESH_TO_68`), and every frame is brought into MediaPipe's canonical face
frame (metres, OpenCV axes) by the similarity that best maps the mesh's skull-fixed vertices
(:func:`focal.rigid_points`) onto the canonical face (Umeyama). What is left of the mouth's motion
in that frame is speech: the head's pose and the distance to the camera are gone.

The tracks are what :mod:`lmgs.lips` learns from and is scored on (``lmgs-eval bench lips``). They
are cached (:func:`cached_track`) outside the repository, keyed by the video's sha256: footage that
is not ours never enters it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lmgs_eval.errors import UserError

TRACK_VERSION = 1  # bump when what a track holds changes: cached tracks of another version are remade

# The 68 iBUG points on MediaPipe's 468-vertex face mesh (the correspondence in common use, e.g. by
# the mediapipe -> dlib converters): jaw 0-16, brows 17-26, nose 27-35, eyes 36-47, outer lips 48-59,
# inner lips 60-67.
MESH_TO_68 = (
    162, 234, 93, 58, 172, 136, 149, 148, 152, 377, 378, 365, 397, 288, 323, 454, 389,
    71, 63, 105, 66, 107, 336, 296, 334, 293, 301,
    168, 197, 5, 4, 75, 97, 2, 326, 305,
    33, 160, 158, 133, 153, 144, 362, 385, 387, 263, 373, 380,
    61, 39, 37, 0, 267, 269, 291, 405, 314, 17, 84, 181,
    78, 82, 13, 312, 308, 317, 14, 87,
)
assert len(MESH_TO_68) == 68


def to_canonical(mesh: np.ndarray, canonical: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Frames of the mesh ``[T, 478, 3]`` (image pixels) -> their 68 points in the canonical face frame
    ``[T, 68, 3]`` (metres) and the skull points' RMS residual of each frame's fit ``[T]`` (metres);
    NaN where the frame has no mesh."""
    from lmgs.lips import similarity
    from lmgs_eval.data.ingest.focal import canonical_face, rigid_points

    face = canonical_face() if canonical is None else canonical
    rig = rigid_points(face)
    out = np.full((len(mesh), 68, 3), np.nan)
    resid = np.full(len(mesh), np.nan)
    idx = np.asarray(MESH_TO_68)
    for k, m in enumerate(np.asarray(mesh, np.float64)):
        if not np.isfinite(m[:468]).all():
            continue
        s, rot, t = similarity(m[rig], face[rig])
        out[k] = s * m[idx] @ rot.T + t
        resid[k] = float(np.sqrt((((s * m[rig] @ rot.T + t) - face[rig]) ** 2).sum(1).mean()))
    return out, resid


@dataclass
class LipTrack:
    """One video's lip track.

    Attributes:
        name: the video's file name without suffix.
        sha256: the video's.
        lms68: ``[T, 68, 3]`` the 68 points per 25 fps frame in the canonical face frame (metres, OpenCV
            axes: x to the subject's left in the image, y down, z away from the camera); NaN where no face.
        fit_rms: ``[T]`` RMS residual (metres) of each frame's similarity fit on the skull points.
        audio: ``[S]`` 16 kHz mono, aligned with frame 0 (``S >= 640 T`` is not promised: the last frames
            may lack audio; :func:`lmgs.audio.compute_features` pads with silence).
    """

    name: str
    sha256: str
    lms68: np.ndarray
    fit_rms: np.ndarray
    audio: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """Frames with a face."""
        return np.isfinite(self.lms68).all(axis=(1, 2))


def track_video(path: str | Path, progress=None) -> LipTrack:
    """Decode ``path`` at 25 fps, track the mesh on every frame, read its audio: a :class:`LipTrack`."""
    from lmgs.fileio import sha256_file
    from lmgs_eval.data.ingest import decode
    from lmgs_eval.data.ingest.mesh import FaceMesh

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such video")
    info = decode.probe(path)
    audio, _, _ = decode.read_audio(path, None, info)
    fm = FaceMesh()
    mesh = np.full((info.n_frames, 478, 3), np.nan, np.float32)
    for k, img in decode.frames_25fps(info):
        mesh[k] = fm.step(img)[0]
        if progress is not None:
            progress(k, info.n_frames)
    lms, resid = to_canonical(mesh)
    return LipTrack(path.stem, sha256_file(path), lms.astype(np.float32), resid.astype(np.float32), np.asarray(audio, np.float32))


def cache_dir() -> Path:
    """Where lip tracks are cached: ``$LMGS_LIPS_CACHE``, else ``~/.cache/lmgs-dev/lips``."""
    return Path(os.environ.get("LMGS_LIPS_CACHE") or Path.home() / ".cache" / "lmgs-dev" / "lips")


def cached_track(path: str | Path, progress=None) -> LipTrack:
    """:func:`track_video`, computed once per video content and :data:`TRACK_VERSION` and kept in :func:`cache_dir`."""
    from lmgs.fileio import sha256_file

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such video")
    sha = sha256_file(path)
    f = cache_dir() / f"{path.stem}-{sha[:16]}-v{TRACK_VERSION}.npz"
    if f.is_file():
        z = np.load(f)
        return LipTrack(path.stem, sha, z["lms68"], z["fit_rms"], z["audio"])
    tr = track_video(path, progress)
    f.parent.mkdir(parents=True, exist_ok=True)
    tmp = f.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, lms68=tr.lms68, fit_rms=tr.fit_rms, audio=tr.audio)
    tmp.replace(f)
    return tr
