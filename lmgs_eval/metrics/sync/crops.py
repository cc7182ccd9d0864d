"""The face crops of the pixel scorers: syncnet_python's ``crop_video`` on dlib face boxes.

Deterministic and documented: dlib HOG face boxes (detected on a downscaled frame every
``detect_every`` frames, held in between, missing boxes filled from the nearest detected frame
and counted), centre and size each smoothed over time by a median filter of 9 frames
(syncnet_python smooths its S3FD track the same way), then syncnet_python's ``crop_video``
geometry: half-size ``bs = size / 2``, crop scale ``cs = 0.4``, frame padded with value 110,
rows ``[cy - bs, cy + bs (1 + 2 cs)]``, columns ``[cx - bs (1 + cs), cx + bs (1 + cs)]``,
resized to 224 x 224, BGR uint8 (the scorer reads them as raw 0-255 floats).
"""

from __future__ import annotations

import numpy as np

from lmgs_eval.errors import UserError

CROP_SIZE = 224  # syncnet_python's face crop side, the official network's input
CROP_SCALE = 0.4
PAD_VALUE = 110
SMOOTH_KERNEL = 9


def face_boxes(frames, detect_every: int = 1, detect_side: int = 320) -> tuple[np.ndarray, int]:
    """Per-frame face boxes ``[T, 3]`` = (cx, cy, size), smoothed; and the count of frames without a detection.

    ``frames``: ``[T, H, W, 3]`` (float in [0, 1] or uint8) or any iterable of frames (a
    :class:`~lmgs_eval.data.frames.FrameFile` is decoded once, a frame at a time).

    Raises:
        UserError: no face in any frame.
    """
    from scipy.signal import medfilt

    from lmgs_eval.data.images import to_u8
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

    from lmgs_eval.data.images import to_u8

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


def crop_faces(frames, boxes: np.ndarray, size: int = CROP_SIZE) -> np.ndarray:
    """syncnet_python ``crop_video`` geometry -> ``[T, size, size, 3]`` BGR uint8 (a scorer converts them to float once).

    ``frames``: an array or any iterable of frames, one per box."""
    out = np.empty((len(boxes), size, size, 3), np.uint8)
    for t, frame in zip(range(len(boxes)), frames):
        out[t] = crop_face(frame, boxes[t], size)
    return out


class FaceClip:
    """The video side of LSE for one clip, each part computed once from frames read in order.

    * :meth:`landmarks`: dlib's 68 landmarks, tracked (``DlibBackend(redetect=10)``, the landmark
      scorer's input);
    * :meth:`mesh_landmarks`: the dense face mesh tracked (:class:`~lmgs_eval.data.ingest.mesh.FaceMesh`),
      its 68 points in the canonical face frame (the mesh scorer's input);
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
        self._mesh: np.ndarray | None = None
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

    def mesh_landmarks(self) -> np.ndarray:
        """``[T, 68, 3]``: the face mesh's 68 points of this clip in the canonical face frame (metres; NaN where
        no face).

        The mesh is tracked over the clip's frames in order, once per clip
        (:meth:`~lmgs_eval.data.ingest.mesh.FaceMesh.step`: a detector seeds it and takes over again where
        the face is lost), and each frame brought into the canonical face frame by
        :func:`~lmgs_eval.data.ingest.lips.to_canonical`.
        """
        b = self._base
        if b._mesh is None:
            from lmgs_eval.data.images import to_u8
            from lmgs_eval.data.ingest.lips import to_canonical
            from lmgs_eval.data.ingest.mesh import FaceMesh

            fm = FaceMesh()
            pts = [fm.step(np.ascontiguousarray(to_u8(frame)))[0] for frame in self._frames()]
            mesh = np.stack(pts) if pts else np.zeros((0, 478, 3), np.float32)
            b._set_n(len(mesh))
            b._mesh = to_canonical(mesh)[0]
        return self._part(b._mesh)

    def crops(self, detect_every: int = 1) -> tuple[np.ndarray, int]:
        """``[T, 224, 224, 3]`` BGR uint8 face crops of this clip and the count of detections without a face.

        Raises:
            UserError: no face in any frame.
        """
        b = self._base
        if detect_every not in b._crops:
            boxes, n_missing = face_boxes(self._frames(), detect_every)
            b._set_n(len(boxes))
            b._crops[detect_every] = (crop_faces(self._frames(), boxes), n_missing)
        crops, n_missing = b._crops[detect_every]
        return self._part(crops), n_missing
