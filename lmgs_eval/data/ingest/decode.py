"""Opening a raw video: probe, frames resampled to 25 fps, audio as 16 kHz mono.

Frames are taken by presentation time, not by decode order: output frame ``k`` is the
decoded frame nearest in time to ``t0 + k / 25`` (what ffmpeg's ``fps`` filter does), so a
30 fps, 24 fps or variable-frame-rate recording lands on the layout's 25 fps clock with its
audio still in sync. Rotation metadata (phone videos) is applied to every frame, and frames
larger than ``MAX_SIDE`` are downscaled while decoding (a 4K input never sits in memory at
full size).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lmgs_eval.data.audio import read_audio_track, read_wav, to_mono_16k
from lmgs_eval.errors import UserError

FPS = 25
MAX_SIDE = 1920  # frames with a longer side are downscaled on decode (4K -> 1080p-ish)


@dataclass(frozen=True)
class VideoInfo:
    """What :func:`probe` found in a video file.

    Attributes:
        path: the file.
        width, height: decoded frame size after rotation and downscaling.
        src_width, src_height: size as stored in the file.
        fps: average frame rate of the stream as the file states it.
        rotation: clockwise degrees applied to make frames upright (0, 90, 180, 270).
        scale: downscaling factor applied on decode (1.0 = none).
        n_frames: number of 25 fps output frames.
        duration: seconds covered by the video stream.
        t0: presentation time of the first frame (seconds).
        has_audio: whether the file carries an audio track.
        stated_duration: seconds of video the file's header states (the stream's duration, else its
            frame count over its rate; None when it states neither): more than ``duration`` when
            the file was cut short.
        corrupt_frames: decoded frames the decoder marked as corrupt.
    """

    path: Path
    width: int
    height: int
    src_width: int
    src_height: int
    fps: float
    rotation: int
    scale: float
    n_frames: int
    duration: float
    t0: float
    has_audio: bool
    stated_duration: float | None = None
    corrupt_frames: int = 0

    @property
    def missing_seconds(self) -> float:
        """Seconds of the stated video that did not decode (0 when the header states no duration)."""
        return max(0.0, self.stated_duration - self.duration) if self.stated_duration else 0.0

    def to_json(self) -> dict:
        return {k: (str(v) if isinstance(v, Path) else v) for k, v in self.__dict__.items()}


def _open(path: Path):
    import av

    if not path.exists():
        raise UserError(f"{path}: video not found")
    if path.stat().st_size == 0:
        raise UserError(f"{path}: file is empty")
    try:
        c = av.open(str(path))
    except (av.error.FFmpegError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not a readable video ({exc.__class__.__name__})") from None
    if not c.streams.video:
        c.close()
        raise UserError(f"{path}: has no video track")
    return c


def _rotation_of(frame, stream) -> int:
    """Clockwise degrees that make the frame upright, from the display matrix or 'rotate' tag."""
    rot = getattr(frame, "rotation", 0) or 0
    if not rot:
        tag = (stream.metadata or {}).get("rotate")
        if tag:
            try:
                rot = -float(tag)  # the legacy tag is clockwise; the display matrix counter-clockwise
            except ValueError:
                rot = 0
    return int(round(-float(rot) / 90.0)) % 4 * 90


def _timed_frames(path: Path, max_side: int, counts: dict | None = None,
                  images: bool = True) -> Iterator[tuple[float, np.ndarray | None, int, float]]:
    """Decoded frames as ``(time, rgb uint8, clockwise rotation, scale)`` in presentation order
    (``counts["corrupt"]``, when given, counts the frames the decoder marked corrupt; ``images``
    False: every frame is decoded but only the first converted to RGB, the others' image None)."""
    import av

    c = _open(path)
    try:
        vs = c.streams.video[0]
        vs.thread_type = "AUTO"
        tb = float(vs.time_base) if vs.time_base else 1.0 / FPS
        fallback = 1.0 / float(vs.average_rate) if vs.average_rate else 1.0 / FPS
        k = 0
        for fr in c.decode(vs):
            t = float(fr.pts) * tb if fr.pts is not None else k * fallback
            if counts is not None and getattr(fr, "is_corrupt", False):
                counts["corrupt"] = counts.get("corrupt", 0) + 1
            rot = _rotation_of(fr, vs)
            if not images and k > 0:
                yield t, None, rot, 1.0
                k += 1
                continue
            w, h = fr.width, fr.height
            s = min(1.0, max_side / max(w, h))
            if s < 1.0:
                w2, h2 = int(round(w * s / 2)) * 2, int(round(h * s / 2)) * 2
                img = fr.reformat(width=w2, height=h2, format="rgb24", interpolation="AREA").to_ndarray()
            else:
                img = fr.to_ndarray(format="rgb24")
            if rot:
                img = np.ascontiguousarray(np.rot90(img, -rot // 90))
            yield t, img, rot, s
            k += 1
    except av.error.FFmpegError as exc:
        raise UserError(f"{path}: decoding failed after {k} frames ({exc.__class__.__name__}: the file is corrupt or truncated)") from None
    finally:
        c.close()


def probe(path: str | Path, max_side: int = MAX_SIDE) -> VideoInfo:
    """Decode the whole video stream once (times only are kept) and describe it."""
    path = Path(path)
    c = _open(path)
    vs = c.streams.video[0]
    fps = float(vs.average_rate) if vs.average_rate else 0.0
    has_audio = bool(c.streams.audio)
    stated = None
    if vs.duration and vs.time_base:
        stated = float(vs.duration * vs.time_base)
    elif vs.frames and fps:
        stated = vs.frames / fps
    c.close()
    times, first, rot, scale = [], None, 0, 1.0
    counts: dict = {}
    for t, img, r, s in _timed_frames(path, max_side, counts, images=False):  # the first frame's image alone
        if first is None:
            first, rot, scale = img, r, s
        times.append(t)
    if first is None:
        raise UserError(f"{path}: video has no frames")
    times = np.sort(np.asarray(times))
    step = float(np.median(np.diff(times))) if len(times) > 1 else 1.0 / (fps or FPS)
    duration = float(times[-1] - times[0] + step)
    n = max(1, int(np.floor(duration * FPS + 1e-6)))
    h, w = first.shape[:2]
    sw, sh = (h, w) if rot in (90, 270) else (w, h)
    return VideoInfo(path, w, h, int(round(sw / scale)), int(round(sh / scale)), fps or 1.0 / step, rot, scale, n,
                     duration, float(times[0]), has_audio, stated, int(counts.get("corrupt", 0)))


def frames_25fps(info: VideoInfo, max_side: int = MAX_SIDE) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(k, rgb uint8 [H, W, 3])`` for every 25 fps output frame ``k < info.n_frames``.

    Frame ``k`` is the decoded frame nearest in time to ``t0 + k / 25``.
    """
    k = 0
    prev_t, prev = None, None
    for t, img, _, _ in _timed_frames(info.path, max_side):
        if prev is not None:
            mid = 0.5 * (prev_t + t)
            while k < info.n_frames and info.t0 + k / FPS < mid:
                yield k, prev
                k += 1
        prev_t, prev = t, img
    while prev is not None and k < info.n_frames:
        yield k, prev
        k += 1


def read_audio(video: Path, audio: Path | None, info: VideoInfo) -> tuple[np.ndarray, list[str], str]:
    """16 kHz mono audio aligned with the first video frame; notes of repairs; where it came from.

    From ``audio`` when given, else from the video's own track (shifted by the difference of
    the two streams' start times).
    """
    if audio is not None:
        x, sr = read_wav(Path(audio))
        y, notes = to_mono_16k(x, sr, str(audio))
        return y, notes, str(audio)
    if not info.has_audio:
        raise UserError(f"{video}: has no audio track; give the speech as --audio WAV")
    try:
        x, sr, start = read_audio_track(video)
    except UserError as exc:
        raise UserError(f"{exc}; give the speech as --audio WAV") from None
    y, notes = to_mono_16k(x, sr, str(video))
    shift = int(round((start - info.t0) * 16000))
    if shift > 0:
        y = np.concatenate([np.zeros(shift, np.float32), y])
        notes.append(f"{video}: audio starts {shift / 16000:.3f} s after the first frame; padded with silence")
    elif shift < 0:
        y = y[-shift:]
        notes.append(f"{video}: audio starts {-shift / 16000:.3f} s before the first frame; that part is dropped")
    return y, notes, f"{video} (its own audio track)"


def scene_cuts(small: np.ndarray, *, floor: float = 0.12, factor: float = 8.0) -> list[int]:
    """Frames ``k`` that start a new shot: the mean absolute change from frame ``k - 1``
    (64x64 grey thumbnails in [0, 1], ``[N, 64, 64]``) is above ``floor`` and ``factor`` times
    the clip's median change (a talking head changes a few grey levels a frame; a cut changes
    most of the picture)."""
    if len(small) < 2:
        return []
    d = np.abs(np.diff(small.astype(np.float32), axis=0)).mean(axis=(1, 2))
    thr = max(floor, factor * float(np.median(d)))
    return [int(k) + 1 for k in np.nonzero(d > thr)[0]]


def light_jumps(small: np.ndarray, cuts: list[int], *, same: float = 0.9) -> list[int]:
    """Of the ``cuts`` (:func:`scene_cuts`), those where the picture stays the same and only its
    light changes (a lamp switched, an exposure jump): the two thumbnails, each brought to zero
    mean and unit spread, correlate above ``same``."""
    out = []
    for k in cuts:
        a, b = (small[i].astype(np.float64).ravel() for i in (k - 1, k))
        a, b = a - a.mean(), b - b.mean()
        r = float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12))
        if r > same:
            out.append(k)
    return out
