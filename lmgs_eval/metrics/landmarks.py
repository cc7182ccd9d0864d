"""68-point landmarks (pluggable backends) and LMD, the mouth landmark distance.

LMD (Chen et al., "Lip Movements Generation at a Glance", ECCV 2018; the form used by
ER-NeRF and TalkingGaussian): for each frame take the 20 mouth points ``[48:68]`` of the
68-point scheme in pred and GT, mean-centre each set (translation only, no scale), and
average the L2 distances in pixels of the full frame; then average over frames.

.. math::
    \\mathrm{LMD}_t = \\frac{1}{20} \\sum_{k=48}^{67}
        \\big\\| (p_k - \\bar p) - (g_k - \\bar g) \\big\\|_2

The scale-normalised variant divides each frame's value by the GT inter-ocular distance
(outer eye corners 36 and 45), so it does not depend on the resolution.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import io
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from lmgs.device import choose_device
from lmgs.fileio import atomic_write
from lmgs_eval.data.images import to_u8
from lmgs_eval.errors import UserError
from lmgs_eval.metrics.base import MetricResult, MetricSpec, check_frames
from lmgs_eval.paths import cache_root

MOUTH = slice(48, 68)
EYE_OUTER = (36, 45)
FALLBACK_SIDE = 640  # the upsampled whole-frame search runs on at most this side (a 1080x1920 frame upsampled is 8 Mpx)

LMD_SPEC = MetricSpec(
    name="lmd",
    higher_is_better=False,
    unit="px",
    backend="dlib",
    version="1",
    definition=(
        "mouth points 48-67 of 68-point landmarks, each set mean-centred (translation only), per frame the mean "
        "L2 over the 20 points in pixels of the full frame, mean over frames with a face in both clips "
        "(frames without are counted in n_original - n_effective and flagged). values['lmd_norm'] divides each "
        "frame by the GT outer inter-ocular distance (points 36, 45)."
    ),
    reference="Chen et al. ECCV 2018; ER-NeRF / TalkingGaussian evaluation code",
)


# ----------------------------------------------------------------------------- LMD math
def lmd_per_frame(pred_lms: np.ndarray, gt_lms: np.ndarray, normalise: bool = False) -> np.ndarray:
    """Per-frame LMD of ``[T, 68, 2]`` landmark arrays (NaN where either frame has NaN).

    Args:
        pred_lms: predicted-frame landmarks in pixels, ``[T, 68, 2]``.
        gt_lms: ground-truth landmarks, same shape.
        normalise: divide by the GT inter-ocular distance ``|g_36 - g_45|``.
    """
    p = np.asarray(pred_lms, np.float64)
    g = np.asarray(gt_lms, np.float64)
    if p.shape != g.shape or p.ndim != 3 or p.shape[1:] != (68, 2):
        raise UserError(f"landmarks must both be [T, 68, 2], got {p.shape} and {g.shape}")
    pm = p[:, MOUTH] - p[:, MOUTH].mean(axis=1, keepdims=True)
    gm = g[:, MOUTH] - g[:, MOUTH].mean(axis=1, keepdims=True)
    d = np.linalg.norm(pm - gm, axis=-1).mean(axis=1)
    if normalise:
        iod = np.linalg.norm(g[:, EYE_OUTER[0]] - g[:, EYE_OUTER[1]], axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.where(iod > 0, d / iod, np.nan)
    return d


def lmd_result(pred_lms: np.ndarray, gt_lms: np.ndarray, spec: MetricSpec = LMD_SPEC,
               flags: list[str] | None = None, notes: list[str] | None = None) -> MetricResult:
    """LMD over frames with landmarks in both clips; missing frames counted, never dropped silently."""
    d = lmd_per_frame(pred_lms, gt_lms)
    dn = lmd_per_frame(pred_lms, gt_lms, normalise=True)
    ok = np.isfinite(d)
    flags = list(flags or [])
    n = d.shape[0]
    if (~ok).any():
        flags.append(f"no_face: {int((~ok).sum())} of {n} frame(s) without landmarks in pred or gt, not scored")
    value = float(d[ok].mean()) if ok.any() else None
    vnorm = float(dn[np.isfinite(dn)].mean()) if np.isfinite(dn).any() else None
    return MetricResult(spec, value, {"lmd": value, "lmd_norm": vnorm}, d, n, int(ok.sum()), flags, list(notes or []),
                        available=bool(ok.any()), reason="" if ok.any() else "no face found in any frame")


# ----------------------------------------------------------------------------- backends
@runtime_checkable
class LandmarkBackend(Protocol):
    """Anything that turns frames into 68-point landmarks (NaN rows where no face)."""

    name: str
    version: str

    def landmarks(self, frames: np.ndarray) -> np.ndarray:
        """``[T, H, W, 3]`` float RGB in [0, 1] -> ``[T, 68, 2]`` (x, y) pixels, NaN if no face."""
        ...


def dlib_model_path() -> Path | None:
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or not spec.submodule_search_locations:
        return None
    p = Path(list(spec.submodule_search_locations)[0]) / "models" / "shape_predictor_68_face_landmarks.dat"
    return p if p.is_file() else None


@functools.lru_cache(maxsize=2)
def _dlib_models(predictor_path: str):
    """dlib's HOG detector and the 68-point predictor, loaded once per process (about 0.8 s)."""
    import dlib

    return dlib.get_frontal_face_detector(), dlib.shape_predictor(predictor_path)


class DlibBackend:
    """dlib HOG face detector + the 68-point shape predictor (the classic LMD detector).

    Speed: detection dominates (about 17 ms per 512x512 frame vs 2 ms for the landmarks).
    So the face box is detected on the whole frame downscaled to at most ``detect_side``
    pixels every ``redetect`` frames; in between, the face is tracked by re-detecting only
    inside a window of twice the previous box, scaled so the face is about 100 px (a few
    ms; a smaller face is upscaled to that size). If the local search finds no face, the whole frame is searched again; if that
    fails too (after one more try with 1x upsampling, on the frame at full resolution or, for a
    frame larger than :data:`FALLBACK_SIDE`, on a copy downscaled to that side) the frame has no
    landmarks: NaN, counted by the metric, never filled in. With ``redetect=1`` every
    frame is detected independently on the whole frame.

    Frames are float RGB in [0, 1] or uint8 RGB (the same landmarks: the detector reads uint8).
    :meth:`tracker` follows a clip given a chunk at a time, with the result of one call on the
    whole clip.
    """

    name = "dlib"
    version = "dlib-hog+shape68"

    def __init__(self, redetect: int = 10, detect_side: int = 320):
        import dlib

        path = dlib_model_path()
        if path is None:
            raise UserError("dlib landmarks need face-recognition-models (shape_predictor_68_face_landmarks.dat)")
        self._dlib = dlib
        self.detector, self.predictor = _dlib_models(str(path))
        self.redetect = max(1, int(redetect))
        self.detect_side = int(detect_side)
        # local100: faces smaller than 100 px are upscaled to 100 px for local re-detection (was
        # dlib's 2x pyramid upsampling, 4x the pixels); faces >= 100 px are found exactly as before
        # fallback640: the upsampled whole-frame search of a frame larger than 640 px runs on a copy at 640 px (was the
        # full frame); frames up to 640 px are searched exactly as before
        self.version = (f"dlib-{dlib.__version__}-hog+shape68(redetect={self.redetect},side={self.detect_side},local100,"
                        "fallback640)")

    def detect(self, u8: np.ndarray):
        """The largest face box in an RGB uint8 frame, or None."""
        dlib = self._dlib
        h, w = u8.shape[:2]
        s = min(1.0, self.detect_side / max(h, w))
        if s < 1.0:
            import cv2

            small = cv2.resize(u8, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
            dets = self.detector(small, 0)
        else:
            dets = self.detector(u8, 0)
        if len(dets) == 0:
            s = min(1.0, FALLBACK_SIDE / max(h, w))
            if s < 1.0:
                import cv2

                mid = cv2.resize(u8, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
                dets = self.detector(mid, 1)
            else:
                dets = self.detector(u8, 1)
            if len(dets) == 0:
                return None
        d = max(dets, key=lambda r: r.width() * r.height())
        return dlib.rectangle(int(round(d.left() / s)), int(round(d.top() / s)),
                              int(round(d.right() / s)), int(round(d.bottom() / s)))

    def _shape(self, u8: np.ndarray, box) -> np.ndarray:
        sh = self.predictor(u8, box)
        return np.array([[sh.part(i).x, sh.part(i).y] for i in range(68)], np.float64)

    def detect_local(self, u8: np.ndarray, box):
        """Re-detect inside a window of twice the previous box, scaled so the face is ~100 px."""
        import cv2

        dlib = self._dlib
        h, w = u8.shape[:2]
        size = max(box.width(), box.height(), 1)
        cx, cy = (box.left() + box.right()) / 2, (box.top() + box.bottom()) / 2
        x0, y0 = int(max(0, cx - size)), int(max(0, cy - size))
        x1, y1 = int(min(w, cx + size)), int(min(h, cy + size))
        if x1 - x0 < 16 or y1 - y0 < 16:
            return None
        s = 100.0 / size  # the face at ~100 px: above HOG's 80 px window, no pyramid upsampling needed
        crop = np.ascontiguousarray(u8[y0:y1, x0:x1])
        if abs(s - 1.0) > 1e-6:
            crop = cv2.resize(crop, (max(1, round((x1 - x0) * s)), max(1, round((y1 - y0) * s))),
                              interpolation=cv2.INTER_AREA if s < 1.0 else cv2.INTER_LINEAR)
        dets = self.detector(crop, 0)
        if len(dets) == 0:
            return None
        d = max(dets, key=lambda r: r.width() * r.height())
        return dlib.rectangle(int(round(d.left() / s + x0)), int(round(d.top() / s + y0)),
                              int(round(d.right() / s + x0)), int(round(d.bottom() / s + y0)))

    def landmarks(self, frames: np.ndarray) -> np.ndarray:
        """``[T, 68, 2]`` of ``[T, H, W, 3]`` frames (float in [0, 1] or uint8), NaN where no face."""
        if np.asarray(frames).dtype != np.uint8:
            frames = check_frames(frames, "frames")
        return self.tracker()(frames)

    def tracker(self):
        """A function of successive chunks of one clip (``[k, H, W, 3]`` arrays, or an iterable of frames)
        returning each chunk's ``[k, 68, 2]`` landmarks; the track carries over from one chunk to the next."""
        state = {"box": None, "age": 0}

        def feed(frames) -> np.ndarray:
            out = []
            for frame in frames:
                u8 = np.ascontiguousarray(to_u8(frame))
                box, age = state["box"], state["age"]
                nb = None
                if box is not None and age < self.redetect:
                    nb = self.detect_local(u8, box)  # tracking: look for the face where it was
                if nb is None:
                    nb, age = self.detect(u8), 0  # whole-frame (downscaled) detection
                box = nb
                lm = np.full((68, 2), np.nan)
                if box is not None:  # no face: NaN, counted by the metric, never filled in
                    lm = self._shape(u8, box)
                    age += 1
                state["box"], state["age"] = box, age
                out.append(lm)
            return np.stack(out) if out else np.full((0, 68, 2), np.nan)

        return feed


class GivenBackend:
    """Landmarks supplied as arrays (e.g. a processed subject's ``ori_imgs/<i>.lms``)."""

    name = "given"
    version = "given"

    def __init__(self, lms: np.ndarray):
        lms = np.asarray(lms, np.float64)
        if lms.ndim != 3 or lms.shape[1:] != (68, 2):
            raise UserError(f"given landmarks must be [T, 68, 2], got {lms.shape}")
        self.lms = lms

    def landmarks(self, frames: np.ndarray) -> np.ndarray:
        n = np.asarray(frames).shape[0]
        if n != self.lms.shape[0]:
            raise UserError(f"given landmarks: {self.lms.shape[0]} frames of landmarks for {n} video frames")
        return self.lms


class FanBackend:
    """FAN 2D landmarks through the ``face_alignment`` package (ER-NeRF's detector), when installed.

    face_alignment fetches its networks on first use; here they must already be in its
    cache (nothing is downloaded by this project).
    """

    name = "fan"
    version = "face_alignment-2D"

    def __init__(self, device: str | None = None):
        if importlib.util.find_spec("face_alignment") is None:
            raise UserError("landmark backend 'fan' needs the face_alignment package")
        import face_alignment  # optional, and heavy

        dev = str(choose_device(device))
        lt = getattr(face_alignment.LandmarksType, "TWO_D", None) or face_alignment.LandmarksType._2D
        self.fa = face_alignment.FaceAlignment(lt, device=dev)

    def landmarks(self, frames: np.ndarray) -> np.ndarray:
        if np.asarray(frames).dtype != np.uint8:
            frames = check_frames(frames, "frames")
        out = np.full((frames.shape[0], 68, 2), np.nan)
        for t in range(frames.shape[0]):
            res = self.fa.get_landmarks_from_image(to_u8(frames[t]))
            if res:
                out[t] = np.asarray(res[0])[:, :2]
        return out


def available_backends() -> dict[str, bool]:
    return {
        "dlib": importlib.util.find_spec("dlib") is not None and dlib_model_path() is not None,
        "fan": importlib.util.find_spec("face_alignment") is not None,
        "given": True,
    }


def create_backend(name: str = "dlib", **kw) -> LandmarkBackend:
    if name == "dlib":
        return DlibBackend(**kw)
    if name == "fan":
        return FanBackend(**kw)
    raise UserError(f"unknown landmark backend {name!r} (dlib, fan; 'given' takes arrays)")


def landmark_stream(backend: LandmarkBackend):
    """A function of successive chunks of one clip returning their landmarks: the backend's
    :meth:`DlibBackend.tracker` (its track carried over), else ``backend.landmarks`` chunk by chunk."""
    return backend.tracker() if hasattr(backend, "tracker") else backend.landmarks


def frames_digest(frames: np.ndarray) -> str:
    """sha256 of a clip's frames (shape, dtype and bytes): the key of the ground-truth caches."""
    a = np.ascontiguousarray(frames)
    h = hashlib.sha256(f"{a.shape}|{a.dtype}|".encode())
    h.update(memoryview(a).cast("B"))
    return h.hexdigest()


def cached_landmarks(backend: LandmarkBackend, frames: np.ndarray, digest: str | None = None) -> np.ndarray:
    """``backend.landmarks(frames)``, kept on disk under the frames' sha256 and the backend version.

    Ground truth is scored again for every method, seed and protocol run of a subject; its
    landmarks depend only on the frames and the backend (name, version, settings), so they
    are computed once (``<cache>/landmarks/<key>.npy``, written atomically). A damaged or
    mismatched entry is recomputed. Backends without a ``version`` are not cached. ``digest``: the
    :func:`frames_digest` of the clip the frames were converted from, when the caller has it (the frames
    are then not hashed again).
    """
    version = getattr(backend, "version", None)
    if not version or getattr(backend, "name", "") == "given":
        return backend.landmarks(frames)


    digest = digest or frames_digest(frames)
    key = hashlib.sha256(f"{digest}|{backend.name}|{version}".encode()).hexdigest()
    path = cache_root() / "landmarks" / f"{key}.npy"
    if path.is_file():
        try:
            lms = np.load(path, allow_pickle=False)
            if lms.shape == (frames.shape[0], 68, 2):
                return lms
        except (OSError, ValueError):
            pass  # damaged entry: recompute below
    lms = backend.landmarks(frames)
    buf = io.BytesIO()
    np.save(buf, lms, allow_pickle=False)
    atomic_write(path, buf.getvalue())
    return lms


class LMD:
    """LMD between two clips with one landmark backend (see :data:`LMD_SPEC`).

    Ground-truth landmarks go through :func:`cached_landmarks` (same frames, same backend:
    same landmarks), so re-scoring a subject's ground truth costs a hash, not a detection.
    """

    def __init__(self, backend: LandmarkBackend | None = None, gt_backend: LandmarkBackend | None = None):
        self.backend = backend or DlibBackend()
        self.gt_backend = gt_backend or self.backend
        self.spec = LMD_SPEC.with_weights(None, backend=f"{self.backend.version}|gt:{self.gt_backend.version}")

    def update(self, pred: np.ndarray, gt: np.ndarray, same: bool = False, gt_key: str | None = None) -> dict[str, np.ndarray]:
        """Landmarks of both clips (``same``: ``pred`` is ``gt``, detected once when one backend reads both;
        ``gt_key``: the ground truth's :func:`frames_digest`, when the caller has it)."""
        gt_lms = cached_landmarks(self.gt_backend, gt, gt_key)
        if same and self.gt_backend is self.backend:
            return {"pred_lms": gt_lms, "gt_lms": gt_lms}
        return {"pred_lms": self.backend.landmarks(pred), "gt_lms": gt_lms}

    def stream(self, gt_key: str | None = None, same: bool = False):
        """The metric suite's feed (:meth:`~lmgs_eval.metrics.base.FloatFrames.stream`): uint8 chunks read as they
        are. With ``gt_key`` (one call on whole clips, :meth:`update`) the ground truth's landmarks come from the
        cache; else each clip is tracked across the chunks."""
        if gt_key is not None:
            return lambda pred, gt: self.update(pred, gt, same=same, gt_key=gt_key)
        feed_pred, feed_gt = landmark_stream(self.backend), landmark_stream(self.gt_backend)
        return lambda pred, gt: {"pred_lms": feed_pred(pred), "gt_lms": feed_gt(gt)}

    def sync_landmarks(self, stats: dict[str, np.ndarray]) -> np.ndarray | None:
        """The prediction's landmarks when the landmark sync scorer would find the same ones (dlib's tracker),
        so LSE need not detect them again; else None."""
        return stats["pred_lms"] if self.backend.name == "dlib" else None

    def compute(self, stats: dict[str, np.ndarray]) -> MetricResult:
        return lmd_result(stats["pred_lms"], stats["gt_lms"], self.spec)
