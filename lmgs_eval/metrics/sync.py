"""LSE-D / LSE-C and the AV offset: the syncnet_python procedure, scorer networks in ONNX Runtime.

Procedure (joonson/syncnet_python ``SyncNetInstance.evaluate``, as used by Wav2Lip's
``evaluation/scores_LSE``; the repository's docs/field.md, "Metric definitions"):

* audio: 16 kHz mono at int16 scale, ``python_speech_features.mfcc`` defaults -> 13 x 100 Hz;
* video: 25 fps face crops, windows of 5 frames; audio windows of 20 MFCC steps at ``4 * i``;
* ``min_length = min(n_frames, floor(n_samples / 640))``, ``lastframe = min_length - 5``,
  windows ``i = 0 .. lastframe - 1``;
* ``calc_pdist(vshift=15)``: the audio embeddings zero-padded by 15 on both ends, for
  window ``i`` the distances ``|v_i - a_{i+k-15} + 1e-6|_2`` for ``k = 0..30`` (torch's
  ``pairwise_distance`` adds ``eps = 1e-6`` to the difference);
* ``mdist[k]`` = mean over windows; **LSE-D** = ``min mdist``, **LSE-C** =
  ``median(mdist) - min(mdist)``, **offset** = ``15 - argmin mdist``.

Face crops (deterministic, documented): dlib HOG face boxes (detected on a downscaled
frame every ``detect_every`` frames, held in between, missing boxes filled from the
nearest detected frame and counted), centre and size each smoothed over time by a median
filter of 9 frames (syncnet_python smooths its S3FD track the same way), then
syncnet_python's ``crop_video`` geometry: half-size ``bs = size / 2``, crop scale
``cs = 0.4``, frame padded with value 110, rows ``[cy - bs, cy + bs (1 + 2 cs)]``,
columns ``[cx - bs (1 + cs), cx + bs (1 + cs)]``, resized to 224 x 224, BGR, raw 0-255
floats.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.base import MetricResult, MetricSpec, unavailable
from lmgs_eval.metrics.sync_nets import (  # noqa: F401  (the networks live there; their names stay importable here)
    CROP_SIZE,
    _export_sync,
    export_bundled,
    import_syncnet,
    nets,
    syncnet_manifest_path,
)

VSHIFT = 15
SAMPLES_PER_FRAME = 640  # 16 kHz / 25 fps
MIN_SAMPLES = 6 * SAMPLES_PER_FRAME  # one 5-frame window needs 6 frames of audio (syncnet_python's min_length - 5 >= 1)
PREPARE_CHUNK = 256  # frames cropped and shaped at a time
CROP_SCALE = 0.4
PAD_VALUE = 110
SMOOTH_KERNEL = 9
MOUTH_BOX = (84, 196, 56, 168)  # rows, columns of the 224 crop around the mouth (region "mouth", bundled scorer)
BUNDLED_DIR = Path(__file__).resolve().parent / "weights"

LSE_SPEC = MetricSpec(
    name="lse",
    higher_is_better=False,
    unit="",
    backend="onnxruntime",
    version="1",
    definition=(
        "syncnet_python evaluate(): MFCC (python_speech_features defaults, int16-scale 16 kHz) windows of 20 "
        "steps at 4*i vs 5-frame 224x224 BGR 0-255 face-crop windows; calc_pdist(vshift=15); mdist = mean over "
        "windows per offset; LSE-D = min(mdist) (lower is better), LSE-C = median(mdist) - min(mdist) (higher is "
        "better), AV offset = 15 - argmin. per_item = each window's distance at the best offset."
    ),
    reference="Chung & Zisserman, 'Out of time', ACCV 2016 workshops; joonson/syncnet_python; Wav2Lip scores_LSE",
    per="window",
)


# ----------------------------------------------------------------------------- audio
def too_short(n_samples: int) -> str:
    """Why ``n_samples`` of 16 kHz audio cannot give one LSE window: its length and the minimum."""
    return (f"{n_samples / 16000:.2f} s ({n_samples} samples at 16 kHz); LSE needs at least {MIN_SAMPLES / 16000:.2f} s "
            f"({MIN_SAMPLES} samples: 6 frames at 25 fps)")


def mfcc_13(audio16k: np.ndarray) -> np.ndarray:
    """``[13, T]`` MFCCs at 100 Hz of float [-1, 1] 16 kHz mono audio, at int16 scale.

    syncnet_python reads the wav with ``scipy.io.wavfile`` (int16 values) and calls
    ``python_speech_features.mfcc(audio, 16000)`` with every default.
    """
    import python_speech_features

    x = np.clip(np.rint(np.asarray(audio16k, np.float64) * 32768.0), -32768, 32767)
    return np.asarray(python_speech_features.mfcc(x, 16000), np.float64).T


def is_silent(audio16k: np.ndarray, rms_floor: float = 1e-4) -> bool:
    x = np.asarray(audio16k, np.float64)
    return x.size == 0 or float(np.sqrt(np.mean(x * x))) < rms_floor


def n_windows(n_frames: int, n_samples: int) -> int:
    """syncnet_python's window count: ``min(n_frames, floor(n_samples / 640)) - 5``.

    Raises:
        UserError: fewer than one window.
    """
    last = min(int(n_frames), int(math.floor(n_samples / SAMPLES_PER_FRAME))) - 5
    if last <= 0:
        raise UserError(f"sync: clip too short for 5-frame windows ({n_frames} frames, {n_samples} samples)")
    return last


def video_windows(frames: np.ndarray, start: int, stop: int) -> np.ndarray:
    """Video windows ``start .. stop-1`` as ``[N, 3, 5, H, W]`` float32 from ``[T, H, W, 3]`` frames."""
    v = np.stack([frames[i:i + 5] for i in range(start, stop)])  # [N, 5, H, W, 3]
    return np.ascontiguousarray(v.transpose(0, 4, 1, 2, 3), np.float32)


def audio_windows(mfcc: np.ndarray, last: int) -> np.ndarray:
    """Audio windows ``[last, 1, 13, 20]``: 20 MFCC steps from ``4 * i`` (a short tail zero-filled)."""
    a = np.zeros((last, 1, 13, 20), np.float32)
    for i in range(last):
        seg = mfcc[:, 4 * i:4 * i + 20]
        a[i, 0, :, :seg.shape[1]] = seg  # syncnet_python would fail on a short tail; zero-fill is flagged by lse()
    return a


def windows(crops: np.ndarray, mfcc: np.ndarray, n_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Video ``[N, 3, 5, H, W]`` and audio ``[N, 1, 13, 20]`` windows, syncnet_python's indexing.

    Holds every video window in memory (5 copies of each frame); :func:`lse` builds them a
    batch at a time instead (:meth:`SyncScorer.embed_frames`), so a long clip fits.

    Args:
        crops: ``[T, H, W, 3]`` face crops in the scorer's pixel convention.
        mfcc: ``[13, M]`` from :func:`mfcc_13`.
        n_samples: number of 16 kHz audio samples.
    """
    last = n_windows(crops.shape[0], n_samples)
    return video_windows(crops, 0, last), audio_windows(mfcc, last)


def lse_from_embeddings(v_emb: np.ndarray, a_emb: np.ndarray, vshift: int = VSHIFT) -> dict:
    """LSE-D, LSE-C and the offset from per-window embeddings (``calc_pdist`` + ``evaluate``).

    .. math::
        \\mathrm{mdist}_k = \\frac{1}{N}\\sum_i \\| v_i - a_{i+k-s} + \\epsilon \\|_2,\\quad
        \\text{LSE-D} = \\min_k \\mathrm{mdist}_k,\\quad
        \\text{LSE-C} = \\operatorname{median}_k \\mathrm{mdist}_k - \\min_k \\mathrm{mdist}_k
    """
    v = np.asarray(v_emb, np.float64)
    a = np.asarray(a_emb, np.float64)
    n = v.shape[0]
    win = 2 * vshift + 1
    ap = np.concatenate([np.zeros((vshift, a.shape[1])), a, np.zeros((vshift, a.shape[1]))])
    idx = np.arange(n)[:, None] + np.arange(win)[None, :]
    dists = np.linalg.norm(v[:, None, :] - ap[idx] + 1e-6, axis=-1)  # [N, 31]
    mdist = dists.mean(axis=0)
    k = int(np.argmin(mdist))
    return {
        "lse_d": float(mdist[k]),
        "lse_c": float(np.median(mdist) - mdist[k]),
        "offset": int(vshift - k),
        "mdist": mdist,
        "per_window": dists[:, k],
    }


# ----------------------------------------------------------------------------- crops
def face_boxes(frames, detect_every: int = 1, detect_side: int = 320) -> tuple[np.ndarray, int]:
    """Per-frame face boxes ``[T, 3]`` = (cx, cy, size), smoothed; and the count of frames without a detection.

    ``frames``: ``[T, H, W, 3]`` (float in [0, 1] or uint8) or any iterable of frames (a
    :class:`~lmgs_eval.data.frames.FrameFile` is decoded once, a frame at a time).

    Raises:
        UserError: no face in any frame.
    """
    from scipy.signal import medfilt

    from lmgs_eval.data.io import to_u8
    from lmgs_eval.metrics.landmarks import DlibBackend

    det = DlibBackend(redetect=1, detect_side=detect_side)
    every = max(1, int(detect_every))
    raw = []
    for i, frame in enumerate(frames):
        box = (np.nan, np.nan, np.nan)
        if i % every == 0:
            b = det.detect(np.ascontiguousarray(to_u8(frame)))
            if b is not None:
                box = ((b.left() + b.right()) / 2, (b.top() + b.bottom()) / 2, max(b.width(), b.height()))
        raw.append(box)
    raw = np.asarray(raw, np.float64).reshape(-1, 3)
    t = raw.shape[0]
    found = np.isfinite(raw[:, 0])
    detected_at = np.arange(0, t, every)
    n_missing = int((~found[detected_at]).sum())
    if not found.any():
        raise UserError("sync: no face detected in any frame")
    idx = np.flatnonzero(found)
    # hold: every frame takes the box of the nearest detected frame (ties -> earlier)
    nearest = idx[np.clip(np.searchsorted(idx, np.arange(t)), 0, len(idx) - 1)]
    prev = idx[np.clip(np.searchsorted(idx, np.arange(t)) - 1, 0, len(idx) - 1)]
    use = np.where(np.abs(prev - np.arange(t)) <= np.abs(nearest - np.arange(t)), prev, nearest)
    boxes = raw[use]
    if t >= SMOOTH_KERNEL:
        boxes = np.stack([medfilt(boxes[:, j], kernel_size=SMOOTH_KERNEL) for j in range(3)], axis=1)
    return boxes, n_missing


def crop_face(frame: np.ndarray, box, size: int = CROP_SIZE) -> np.ndarray:
    """One frame's syncnet_python ``crop_video`` crop -> ``[size, size, 3]`` BGR uint8.

    The frame padded by ``bsi`` on every side with :data:`PAD_VALUE` is sliced as numpy slices it;
    only the slice is built (a 1080x1920 frame is not padded whole).
    """
    import cv2

    from lmgs_eval.data.io import to_u8

    cs = CROP_SCALE
    cx, cy, s = box
    bs = s / 2
    bsi = int(bs * (1 + 2 * cs))
    img = to_u8(frame)
    h, w = img.shape[:2]
    my, mx = cy + bsi, cx + bsi
    r0, r1, _ = slice(int(my - bs), int(my + bs * (1 + 2 * cs))).indices(h + 2 * bsi)
    c0, c1, _ = slice(int(mx - bs * (1 + cs)), int(mx + bs * (1 + cs))).indices(w + 2 * bsi)
    face = np.full((max(0, r1 - r0), max(0, c1 - c0), 3), PAD_VALUE, np.uint8)
    fr0, fr1 = max(r0 - bsi, 0), min(r1 - bsi, h)  # the frame's own rows and columns inside the slice
    fc0, fc1 = max(c0 - bsi, 0), min(c1 - bsi, w)
    if fr1 > fr0 and fc1 > fc0:
        face[fr0 + bsi - r0:fr1 + bsi - r0, fc0 + bsi - c0:fc1 + bsi - c0] = img[fr0:fr1, fc0:fc1, ::-1]
    return cv2.resize(face, (size, size), interpolation=cv2.INTER_LINEAR)


def crop_faces(frames, boxes: np.ndarray, size: int = CROP_SIZE, dtype=np.float32) -> np.ndarray:
    """syncnet_python ``crop_video`` geometry -> ``[T, size, size, 3]`` BGR in 0..255 (integer values), ``dtype``.

    ``frames``: an array or any iterable of frames, one per box."""
    out = np.empty((len(boxes), size, size, 3), dtype)
    for t, frame in zip(range(len(boxes)), frames):
        out[t] = crop_face(frame, boxes[t], size)
    return out


class FaceClip:
    """The video side of LSE for one clip, each part computed once from frames read in order.

    * :meth:`landmarks`: dlib's 68 landmarks, tracked (``DlibBackend(redetect=10)``, the landmark
      scorer's input);
    * :meth:`crops`: face boxes (:func:`face_boxes`) and then the 224x224 BGR uint8 crops of the
      pixel scorers (:func:`crop_face`), a second pass over the frames.

    ``frames``: ``[T, H, W, 3]`` (float in [0, 1] or uint8), or a
    :class:`~lmgs_eval.data.frames.FrameFile` (decoded on each pass, never held). ``lms``:
    landmarks already found by the same tracker (LMD's). ``clip[a:b]`` shares what was computed
    and gives its part of it (the probe's shifted copies of one clip).
    """

    is_face_clip = True

    def __init__(self, frames, lms: np.ndarray | None = None):
        self._src = frames
        self._lms = None if lms is None else np.asarray(lms, np.float64)
        self._crops: dict[int, tuple[np.ndarray, int]] = {}
        self._n: int | None = len(frames) if isinstance(frames, np.ndarray) else None
        if self._lms is not None:
            self._set_n(len(self._lms))
        self._base, self._start, self._stop = self, 0, None

    def _set_n(self, n: int) -> None:
        if self._n is not None and n != self._n:
            raise UserError(f"{getattr(self._src, 'path', 'frames')}: {n} frames decoded where {self._n} were counted")
        self._n = n

    def _length(self) -> int:
        if self._n is None:
            self._n = int(self._src.count())
        return self._n

    def __len__(self) -> int:
        n = self._base._length()
        start, stop, _ = slice(self._start, self._stop).indices(n)
        return max(0, stop - start)

    def __getitem__(self, sl: slice) -> "FaceClip":
        if not isinstance(sl, slice) or sl.step not in (None, 1):
            raise TypeError("a FaceClip is sliced by a contiguous range")
        n = len(self)
        start, stop, _ = sl.indices(n)
        view = object.__new__(FaceClip)
        view._base = self._base
        view._start = self._start + start
        view._stop = self._start + max(start, stop)
        return view

    def _part(self, a: np.ndarray) -> np.ndarray:
        return a[self._start:self._stop]

    def _frames(self):
        """The clip's frames one at a time (a file is decoded again on each pass)."""
        return iter(self._base._src)

    def landmarks(self) -> np.ndarray:
        """``[T, 68, 2]`` dlib landmarks of this clip (NaN where no face)."""
        b = self._base
        if b._lms is None:
            from lmgs_eval.metrics.landmarks import DlibBackend

            lms = DlibBackend(redetect=10).tracker()(self._frames())
            b._set_n(len(lms))
            b._lms = lms
        return self._part(b._lms)

    def crops(self, detect_every: int = 1) -> tuple[np.ndarray, int]:
        """``[T, 224, 224, 3]`` BGR uint8 face crops of this clip and the count of detections without a face.

        Raises:
            UserError: no face in any frame.
        """
        b = self._base
        if detect_every not in b._crops:
            boxes, n_missing = face_boxes(self._frames(), detect_every)
            b._set_n(len(boxes))
            b._crops[detect_every] = (crop_faces(self._frames(), boxes, dtype=np.uint8), n_missing)
        crops, n_missing = b._crops[detect_every]
        return self._part(crops), n_missing


# ----------------------------------------------------------------------------- scorer
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
        import cv2

        x = crops224
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
            p = self.prepare(np.asarray(c, np.float32))
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


def find_scorer(prefer: str | None = None) -> tuple[SyncScorer | None, str]:
    """The official SyncNet if imported, else the bundled scorer; ``(None, reason)`` if neither."""
    from lmgs_eval.metrics.ort import load_session, nonfinite_weights, sha256_file

    reasons = []
    if prefer in (None, "syncnet-v2"):
        mp = syncnet_manifest_path()
        if mp.is_file():
            m = json.loads(mp.read_text())
            p = Path(m["onnx"])
            if not p.is_file():
                reasons.append(f"syncnet-v2: {p} listed in {mp} is missing (re-run lmgs-eval weights import-syncnet)")
            else:
                sha = sha256_file(p)
                if sha != m.get("onnx_sha256"):
                    raise UserError(f"{p}: sha256 {sha[:12]}... does not match {mp}; re-run lmgs-eval weights import-syncnet")
                bad = nonfinite_weights(p)
                if bad:
                    raise UserError(f"{p} (imported from {m.get('source')}): weights {bad[0]!r}"
                                    + (f" and {len(bad) - 1} more" if len(bad) > 1 else "") + " hold NaN or Inf; "
                                    "import a sound syncnet_v2.model with lmgs-eval weights import-syncnet")
                return SyncScorer("syncnet-v2", load_session(p), m["source_sha256"], tuple(m["input_hw"]),
                                  m.get("region", "full"), m.get("pixel", "bgr_0_255"), source=str(m.get("source", p))), ""
        else:
            reasons.append("syncnet-v2 not imported (lmgs-eval weights import-syncnet syncnet_v2.model)")
    if prefer in (None, "bundled-sync"):
        p, j = BUNDLED_DIR / "bundled_sync.onnx", BUNDLED_DIR / "bundled_sync.json"
        if p.is_file() and j.is_file():
            m = json.loads(j.read_text())
            sha = sha256_file(p)
            if m.get("sha256") and sha != m["sha256"]:
                raise UserError(f"{p}: sha256 {sha[:12]}... does not match {j} (corrupt or replaced weights)")
            return SyncScorer("bundled-sync", load_session(p), sha, tuple(m.get("input_hw", (48, 96))),
                              m.get("region", "lower_half"), m.get("pixel", "bgr_0_1"), source=str(p),
                              standin="bundled-sync is trained by this project on synthetic clips; its LSE values are "
                                      "not comparable with SyncNet LSE in papers"), ""
        reasons.append(f"bundled-sync weights not present ({p.name} + {j.name} in {BUNDLED_DIR})")
    return None, "; ".join(reasons)


def lse(frames: np.ndarray | None, audio16k: np.ndarray | None, fps: float = 25.0, scorer=None,
        crops: np.ndarray | None = None, detect_every: int = 1, audio_reason: str = "", lms: np.ndarray | None = None,
        reference: bool = False) -> MetricResult:
    """LSE-D / LSE-C / offset of one clip (no reference needed), with its self-check.

    Args:
        frames: ``[T, H, W, 3]`` float RGB in [0, 1] (the pixel scorer ignores it when ``crops`` is given).
        audio16k: 16 kHz mono float audio, or None (then unavailable with ``audio_reason``).
        fps: frame rate; SyncNet windows assume 25 fps.
        scorer: a loaded scorer (:class:`SyncScorer` or ``sync_landmark.LandmarkScorer``); default: the
            selection of :mod:`sync_select` (``--sync``, ``auto`` unless set).
        crops: precomputed ``[T, 224, 224, 3]`` BGR 0-255 crops (pixel scorers: skips face detection).
        detect_every: run the face detector every k frames (pixel scorers).
        lms: precomputed ``[T, 68, 2]`` landmarks (landmark scorer: skips dlib).
        reference: the footage is known to be in sync (ground truth): the self-check also requires
            the offset to be 0 +- 1.

    ``values`` holds ``lse_d``, ``lse_c``, ``offset`` and the self-check's ``separation``,
    ``trusted``, ``null_lse_c``, ``null_lse_c_max``, ``still_lse_c`` (:mod:`sync_check`).
    """
    n = int(next(len(x) for x in (crops, frames, lms) if x is not None))
    if audio16k is not None and len(audio16k) < MIN_SAMPLES:
        audio_reason = f"audio too short: {too_short(len(audio16k))}"
        audio16k = None
    if scorer is None:
        return _lse_selected(frames, audio16k, fps, crops, detect_every, audio_reason, lms, reference, n)
    spec = LSE_SPEC.with_weights(scorer.sha256, backend=f"onnxruntime:{scorer.name}")
    if scorer.standin:
        spec = MetricSpec(**{**spec.to_dict(), "standin": scorer.standin})
    if audio16k is None:
        return unavailable(spec, audio_reason or "no audio (the video has no audio track and --audio was not given)", n)
    if abs(float(fps) - 25.0) > 0.01:
        return unavailable(spec, f"SyncNet windows assume 25 fps, the clip is {fps:g} fps", n)
    flags, notes = [], []
    if is_silent(audio16k):
        flags.append("silent_audio: RMS below 1e-4, LSE is meaningless on silence")
    try:
        last = n_windows(n, len(audio16k))
        mf = mfcc_13(audio16k)
        a_emb, v_emb, v_still, f2, n2 = scorer.embed_clip(frames, crops, audio16k, mf, last, detect_every, lms=lms)
    except UserError as exc:
        return unavailable(spec, str(exc), n)
    bad = [k for k, e in (("audio", a_emb), ("video", v_emb), ("still-face", v_still)) if not np.all(np.isfinite(e))]
    if bad:
        raise UserError(f"{scorer.name} ({getattr(scorer, 'source', '') or 'sha256 ' + scorer.sha256[:12]}): "
                        f"non-finite {' and '.join(bad)} embeddings; its weights are damaged (NaN or Inf)")
    flags += f2
    notes += n2
    if 4 * (last - 1) + 20 > mf.shape[1]:
        flags.append("audio_tail_padded: last MFCC window zero-filled")
    r = lse_from_embeddings(v_emb, a_emb)
    from lmgs_eval.metrics.sync_check import self_check

    check, cflags = self_check(v_emb, a_emb, v_still, r["lse_c"], r["offset"], reference)
    values = {"lse_d": r["lse_d"], "lse_c": r["lse_c"], "offset": r["offset"], **check}
    flags += cflags
    if scorer.standin:
        notes.append("standin: " + scorer.standin)
    notes.append("mdist per offset -15..15: " + " ".join(f"{d:.3f}" for d in r["mdist"][::-1]))
    return MetricResult(spec, r["lse_d"], values, r["per_window"], max(0, n - 5), int(last), flags, notes)


def _lse_selected(frames, audio16k, fps, crops, detect_every, audio_reason, lms, reference, n) -> MetricResult:
    """``lse`` with the scorer(s) of the process-wide selection.

    ``auto`` tries its candidates in order and keeps the first that is available and passes
    its self-check; if none passes, the first available result (marked untrusted) stays.
    """
    from lmgs_eval.metrics.sync_select import candidates, load

    results, reasons = [], []
    for name in candidates():
        sc, why = load(name)
        if sc is None:
            reasons.append(why)
            continue
        r = lse(frames, audio16k, fps, sc, crops, detect_every, audio_reason, lms, reference)
        results.append(r)
        if r.available and r.values.get("trusted") is not False:
            break
    if not results:
        return unavailable(LSE_SPEC, "no SyncNet weights: " + "; ".join(reasons), n)
    best = next((r for r in results if r.available and r.values.get("trusted") is not False), None)
    best = best or next((r for r in results if r.available), results[0])
    for r in results:
        if r is not best:
            best.notes.append(f"auto: {r.spec.backend} " + ("did not pass its self-check" if r.available
                              else f"was unavailable ({r.reason})") + f" on this clip; kept {best.spec.backend}")
    return best


def find_scorer_status() -> tuple[bool, str]:
    """Which sync scorer would be used and why, without loading it (for ``lmgs-eval metrics``)."""
    from lmgs_eval.metrics.sync_select import status

    return status()
