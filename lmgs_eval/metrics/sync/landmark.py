"""The landmark sync scorer: mouth-shape trajectories against MFCC windows.

A pixel scorer sees the face it was trained on; this one sees only where the 20 mouth
points of the 68-point scheme move, in a head-fixed frame, relative to where they rest in
this clip. Who is talking, the skin, the light and the crop cannot reach it.

Video input, per frame (:func:`mouth_features`):

1. dlib's 68 landmarks (frames without a face are filled by linear interpolation and counted);
2. each frame is mapped by the similarity transform that puts the outer-and-inner eye
   corners' midpoints at (-0.5, 0) and (0.5, 0) (inter-ocular distance 1, eye line level),
   then refined by a least-squares similarity (Umeyama) of the rigid points (nose bridge and
   base, eye corners) onto their clip mean: scale, roll and translation of the head go away;
3. the clip's mean mouth shape is subtracted (the speaker's own lips; or, with the
   manifest's ``highpass``, a centred moving average: expression and posture drift too),
   and the result is divided by the clip's RMS motion (at least :data:`MIN_RMS` inter-ocular distances, so
   a still face stays still rather than amplified jitter).

Audio input: :func:`~lmgs_eval.metrics.sync.maths.mfcc_13` (syncnet_python's MFCC) with each coefficient normalised to
zero mean and unit variance over the clip (cepstral mean and variance normalisation: the
voice's timbre and the channel are removed, the timing stays).

Windows are syncnet_python's (window ``i``: frames ``i .. i+4``, MFCC steps ``4 i .. 4 i + 19``),
widened symmetrically to ``context`` frames (and ``4 context`` MFCC steps) around the same
centre when the manifest says so: a mouth shape alone says less than a pixel crop, a
syllable's worth of trajectory says more. The window index, the distances, LSE-D, LSE-C and
the offset search of :func:`~lmgs_eval.metrics.sync.maths.lse_from_embeddings` are unchanged; only the
embedding networks differ. Trained by :mod:`lmgs_eval.metrics.sync.train.landmark`; loaded by
:func:`lmgs_eval.metrics.sync.scorers.load_landmark`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lmgs_eval.errors import UserError

EYES = ((36, 39), (42, 45))  # corners of each eye (outer, inner)
RIGID = (27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 39, 42, 45)  # nose bridge + base, eye corners
MOUTH = slice(48, 68)
N_FEAT = 40  # 20 mouth points x (x, y)
MIN_RMS = 0.01  # inter-ocular distances
ONNX_NAME, JSON_NAME = "landmark_sync.onnx", "landmark_sync.json"


# ----------------------------------------------------------------------------- features
def fill_missing(lms: np.ndarray, tracker: str = "dlib 68 landmarks") -> tuple[np.ndarray, int]:
    """Frames without landmarks (NaN) filled by linear interpolation over time; the count filled.

    ``tracker`` names what found the landmarks in the error.

    Raises:
        UserError: no frame has landmarks.
    """
    lms = np.asarray(lms, np.float64)
    ok = np.isfinite(lms).all(axis=(1, 2))
    if not ok.any():
        raise UserError(f"sync: no face found in any frame ({tracker})")
    n_missing = int((~ok).sum())
    if n_missing:
        t = np.arange(len(lms))
        flat = lms.reshape(len(lms), -1).copy()
        for j in range(flat.shape[1]):
            flat[~ok, j] = np.interp(t[~ok], t[ok], flat[ok, j])
        lms = flat.reshape(lms.shape)
    return lms, n_missing


def _similarity(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares ``s, R, t`` with ``s R src + t ~ dst`` per frame (Umeyama 1991), 2-D, no reflection.

    ``src`` ``[T, K, 2]``, ``dst`` ``[K, 2]``; returns ``s [T]``, ``R [T, 2, 2]``, ``t [T, 2]``.
    """
    ms, md = src.mean(1, keepdims=True), dst.mean(0)
    a, b = src - ms, dst - md
    u, sig, vt = np.linalg.svd(np.einsum("kj,tki->tji", b, a))  # [T, 2, 2] = b^T a
    d = np.sign(np.linalg.det(u @ vt))
    dm = np.stack([np.ones_like(d), d], -1)  # diagonal of D
    r = u @ (dm[:, :, None] * vt)
    s = (sig * dm).sum(1) / np.maximum((a * a).sum((1, 2)), 1e-12)
    t = md - s[:, None] * np.einsum("tij,tj->ti", r, ms[:, 0])
    return s, r, t


def normalise_pose(lms: np.ndarray) -> np.ndarray:
    """``[T, 68, 2]`` landmarks in a head-fixed frame (inter-ocular distance 1), see the module doc."""
    lms = np.asarray(lms, np.float64)
    le = lms[:, list(EYES[0])].mean(1)
    re = lms[:, list(EYES[1])].mean(1)
    d = re - le
    iod = np.maximum(np.linalg.norm(d, axis=1), 1e-6)
    c, s = d[:, 0] / iod, d[:, 1] / iod
    rot = np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], 1)  # [T, 2, 2] undoes the roll
    mid = (le + re) / 2
    x = np.einsum("tij,tkj->tki", rot, lms - mid[:, None]) / iod[:, None, None]
    ref = x[:, list(RIGID)].mean(0)
    sc, r, tr = _similarity(x[:, list(RIGID)], ref)
    return sc[:, None, None] * np.einsum("tij,tkj->tki", r, x) + tr[:, None]


def mouth_features(lms: np.ndarray, highpass: int = 0) -> np.ndarray:
    """``[T, 40]`` float32 mouth motion of one clip (pose-normalised, own mean removed, RMS-scaled).

    ``highpass`` > 1: the centred moving average over that many frames is removed instead of
    the clip mean (speech moves the lips at syllable rate, 2-8 Hz; slower motion is
    expression and posture).
    """
    x = normalise_pose(lms)[:, MOUTH].reshape(len(lms), N_FEAT)
    if highpass > 1:
        from scipy.ndimage import uniform_filter1d

        x = x - uniform_filter1d(x, int(highpass), axis=0, mode="nearest")
    else:
        x = x - x.mean(0)
    rms = max(float(np.sqrt(np.mean(x * x))), MIN_RMS)
    return (x / rms).astype(np.float32)


def audio_features(mfcc: np.ndarray) -> np.ndarray:
    """``[13, M]`` MFCCs with each coefficient at zero mean and unit variance over the clip."""
    m = np.asarray(mfcc, np.float64)
    return ((m - m.mean(1, keepdims=True)) / (m.std(1, keepdims=True) + 1e-3)).astype(np.float32)


def video_windows(feat: np.ndarray, last: int, context: int = 5) -> np.ndarray:
    """``[last, 40, context]``: for window ``i`` the frames ``i - p .. i + 4 + p`` (``p = (context - 5) / 2``),
    zero (the clip's mean shape) outside the clip; ``context`` 5 is syncnet_python's window exactly."""
    p = (int(context) - 5) // 2
    padded = np.concatenate([np.zeros((p, feat.shape[1]), np.float32), feat, np.zeros((p, feat.shape[1]), np.float32)])
    idx = np.arange(last)[:, None] + np.arange(5 + 2 * p)[None, :]
    return np.ascontiguousarray(padded[idx].transpose(0, 2, 1), np.float32)


def audio_windows(mfcc_norm: np.ndarray, last: int, context: int = 5) -> np.ndarray:
    """``[last, 13, 4 context]``: the normalised MFCC steps ``4 (i - p) .. 4 (i + 5 + p)``, centred on the video
    window (20 steps from ``4 i`` for ``context`` 5, syncnet_python's); zero outside the audio."""
    p = (int(context) - 5) // 2
    n = 20 + 8 * p
    m = np.concatenate([np.zeros((13, 4 * p), np.float32), np.asarray(mfcc_norm, np.float32),
                        np.zeros((13, n), np.float32)], axis=1)
    idx = 4 * np.arange(last)[:, None] + np.arange(n)[None, :]
    return np.ascontiguousarray(m[:, idx].transpose(1, 0, 2), np.float32)


# ----------------------------------------------------------------------------- network
def build_net(dim: int = 128, width: int = 128, context: int = 5):
    """The scorer network (torch): ``forward(audio [N,13,4c], video [N,40,c]) -> (a_emb, v_emb)``, ``c = context``.

    audio: Conv1d 13-w k3 p1, ReLU, Conv1d w-w k3 s2 p1, ReLU, Conv1d w-w k3 s2 p1, ReLU,
    flatten (w x c), Linear 256, ReLU, Linear ``dim``. video: Conv1d 40-w k3 p1, ReLU,
    Conv1d w-w k3 p1, ReLU, flatten (w x c), Linear 256, ReLU, Linear ``dim``.
    """
    from torch import nn

    c = int(context)

    class LandmarkSyncNet(nn.Module):
        def __init__(self):
            super().__init__()
            self.aud = nn.Sequential(nn.Conv1d(13, width, 3, 1, 1), nn.ReLU(), nn.Conv1d(width, width, 3, 2, 1), nn.ReLU(),
                                     nn.Conv1d(width, width, 3, 2, 1), nn.ReLU(), nn.Flatten(),
                                     nn.Linear(width * c, 256), nn.ReLU(), nn.Linear(256, dim))
            self.vid = nn.Sequential(nn.Conv1d(N_FEAT, width, 3, 1, 1), nn.ReLU(), nn.Conv1d(width, width, 3, 1, 1), nn.ReLU(),
                                     nn.Flatten(), nn.Linear(width * c, 256), nn.ReLU(), nn.Linear(256, dim))

        def forward(self, audio, video):
            return self.aud(audio), self.vid(video)

    return LandmarkSyncNet()


def export(net, out_dir: Path, meta: dict, name: str = "landmark-sync", files: tuple[str, str] = (ONNX_NAME, JSON_NAME),
           points: str = "mouth_features") -> dict:
    """Write the trained network as ``files[0]`` (ONNX) and its manifest ``files[1]`` (recipe, seed, sha256, and
    what ``meta`` adds) into ``out_dir``; ``points`` says where the mouth features come from."""
    import torch

    from lmgs.fileio import atomic_write, sha256_file
    from lmgs_eval.metrics.ort import export_onnx

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    onnx_name, json_name = files
    c = int(meta.get("context", 5))
    export_onnx(net.eval(), (torch.randn(2, 13, 4 * c), torch.randn(2, N_FEAT, c)), out_dir / onnx_name,
                ["audio", "video"], ["a_emb", "v_emb"],
                {"audio": {0: "n"}, "video": {0: "n"}, "a_emb": {0: "n"}, "v_emb": {0: "n"}})
    m = {"name": name, "context": c, "highpass": int(meta.get("highpass", 0)),
         "input": f"{points} windows [N,40,{c}] + audio_features windows [N,13,{4 * c}]", **meta,
         "sha256": sha256_file(out_dir / onnx_name)}
    atomic_write(out_dir / json_name, json.dumps(m, indent=2))
    return m


# ----------------------------------------------------------------------------- scorer
@dataclass
class LandmarkScorer:
    """A loaded landmark scorer; :meth:`embed_clip` is the interface LSE calls (:mod:`~lmgs_eval.metrics.sync.scoring`)."""

    session: object
    sha256: str
    context: int = 5
    highpass: int = 0
    name: str = "landmark-sync"
    standin: str = ("landmark-sync is trained by this project on synthetic clips (mouth landmarks vs MFCC); its LSE "
                    "values are not comparable with SyncNet LSE in papers")

    def embed(self, audio_win: np.ndarray, video_win: np.ndarray, batch: int = 512) -> tuple[np.ndarray, np.ndarray]:
        a_out, v_out = [], []
        for s in range(0, len(audio_win), batch):
            a, v = self.session.run(["a_emb", "v_emb"], {"audio": audio_win[s:s + batch], "video": video_win[s:s + batch]})
            a_out.append(a)
            v_out.append(v)
        return np.concatenate(a_out), np.concatenate(v_out)

    def embed_clip(self, frames, crops, audio16k, mfcc, last, detect_every=1, lms=None):
        """Audio and video embeddings of windows ``0 .. last-1``, the still-face embedding, flags and notes.

        ``lms``: precomputed ``[T, 68, 2]`` landmarks (skips dlib); otherwise dlib on ``frames``.
        """
        flags, notes = [], []
        if lms is None:
            if frames is None:
                raise UserError("landmark-sync needs frames or landmarks, not face crops")
            if getattr(frames, "is_face_clip", False):  # found once per clip (crops.FaceClip)
                lms = frames.landmarks()
            else:
                from lmgs_eval.metrics.landmarks import DlibBackend, cached_landmarks

                # uint8 frames are read as they are (the tracker converts one frame at a time)
                lms = cached_landmarks(DlibBackend(redetect=10), frames[:last + 4])
            notes.append("video: dlib 68 landmarks (HOG, tracked, re-detected every 10 frames), " + self.feature_note())
        else:
            notes.append("video: the 68 landmarks given with the clip (the metric suite passes LMD's, found by the "
                         "same dlib tracker), " + self.feature_note())
        return (*self.embed_points(lms, mfcc, last, flags, "dlib 68 landmarks"), flags, notes)

    def feature_note(self) -> str:
        """How the mouth points become features (for the result's notes)."""
        drift = (f"their {self.highpass}-frame moving average removed" if self.highpass > 1 else "clip mean removed")
        return f"mouth points 48-67 pose-normalised on eye corners and nose, {drift}, RMS-scaled"

    def embed_points(self, lms: np.ndarray, mfcc: np.ndarray, last: int, flags: list[str],
                     tracker: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Audio and video embeddings of windows ``0 .. last-1`` and the still-face embedding from ``[T, 68, 2]``
        landmarks (frames without a face filled in and counted in ``flags``)."""
        lms, n_missing = fill_missing(np.asarray(lms)[:last + 4], tracker)
        if n_missing:
            flags.append(f"no_face: {n_missing} frame(s) without landmarks ({tracker}), interpolated from their "
                         "neighbours")
        feat = mouth_features(lms, self.highpass)
        aw = audio_windows(audio_features(mfcc), last, self.context)
        a_emb, v_emb = self.embed(aw, video_windows(feat, last, self.context))
        _, still = self.embed(aw[:1], np.zeros((1, N_FEAT, self.context), np.float32))
        return a_emb, v_emb, still[0]

