"""A clip read from its file a frame at a time: a video or a folder of images.

Scoring never holds a whole clip at full size: a 60 s 1080x1920 video is 9 GB as uint8
frames (37 GB as float). :class:`FrameFile` decodes on demand, as uint8 RGB frames in order,
and every pass over the clip (paired metrics, face tracking, face crops) reads it again from
the file. What a pass keeps is per-frame and small: metric values, 68 landmarks, face boxes,
224x224 crops. A folder's images are in :func:`list_frames` order (by the number in each name,
without a gap).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from lmgs_eval.data.audio import read_audio_track
from lmgs_eval.data.images import read_rgb_u8
from lmgs_eval.errors import UserError

IMAGE_EXT = frozenset({".jpg", ".jpeg", ".png", ".bmp", ".webp"})
CHUNK = 16  # frames per chunk of a paired pass (a multiple of LPIPS's batch of 4)
CHUNK_BYTES = 64 * 2**20  # at most this much of one clip as float32 in a chunk


def chunk_for(height: int, width: int) -> int:
    """Frames per chunk of a paired pass over frames of this size: :data:`CHUNK` up to ~1 Mpx frames, fewer
    above (a 1080x1920 frame is 25 MB as float32), a multiple of LPIPS's batch of 4 when there are 4 or more."""
    n = max(1, min(CHUNK, CHUNK_BYTES // (height * width * 3 * 4)))
    return n - n % 4 if n >= 4 else n


def list_frames(folder: Path) -> list[Path]:
    """The images of a frame folder in frame order: by the last number in each name (``7.jpg``, ``frame_0007.png``).

    The numbers must run without a gap from the first: a missing frame would shift every later
    frame against its ground truth. Names without a number are allowed only when no name has one
    (then the order is by name).

    Raises:
        UserError: no images, names mixing numbered and unnumbered files, a number used twice
            (``7.png`` and ``007.png``), or a gap (naming the first missing number).
    """
    folder = Path(folder)
    files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXT and not p.name.startswith(".")]
    if not files:
        raise UserError(f"{folder}: folder has no images ({', '.join(sorted(IMAGE_EXT))})")
    nums = {p: re.findall(r"\d+", p.stem) for p in files}
    bare = sorted(p.name for p, n in nums.items() if not n)
    if len(bare) == len(files):
        return sorted(files, key=lambda p: p.name)
    if bare:
        raise UserError(f"{folder}: {len(bare)} image names carry no frame number (first: {bare[0]}) beside numbered "
                        "ones; the frame order is unknown")
    by_num: dict[int, Path] = {}
    for p, n in nums.items():
        k = int(n[-1])
        if k in by_num:
            raise UserError(f"{folder}: frame {k} twice ({by_num[k].name} and {p.name})")
        by_num[k] = p
    order = sorted(by_num)
    for a, b in zip(order, order[1:]):
        if b != a + 1:
            miss = f"{a + 1}" if b == a + 2 else f"{a + 1}-{b - 1}"
            raise UserError(f"{folder}: frame numbers jump from {a} to {b} (frame {miss} missing); every later frame "
                            "would be compared with the wrong one")
    return [by_num[k] for k in order]


class FrameFile:
    """The frames of a video file or a frame folder (:func:`list_frames` order), read on demand.

    Opening checks the file and reads what is small: frame rate, the audio track, the first
    frame's size. Iterating decodes the frames again each time, as uint8 ``[H, W, 3]`` RGB.

    Attributes:
        path: the video or folder.
        fps: the video stream's average rate (None for a folder).
        audio, sr: the video's audio track ``[S, C]`` and its rate (None when it has none, and for a folder).
        height, width: the frame size.
        notes: how the clip was read (a folder: its order).
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.fps: float | None = None
        self.audio, self.sr = None, None
        self.notes: list[str] = []
        self._files: list[Path] | None = None
        self._count: int | None = None
        if self.path.is_dir():
            self._files = list_frames(self.path)
            self._count = len(self._files)
            self.notes.append(f"{self.path}: {len(self._files)} images, sorted by number in the name")
        else:
            self._probe_video()
        it = iter(self)
        first = next(it, None)
        it.close()
        if first is None:
            raise UserError(f"{self.path}: video has no frames")
        self.height, self.width = first.shape[:2]

    def _probe_video(self) -> None:
        import av

        if not self.path.exists():
            raise UserError(f"{self.path}: video not found")
        try:
            with av.open(str(self.path)) as c:
                if not c.streams.video:
                    raise UserError(f"{self.path}: has no video track")
                vs = c.streams.video[0]
                self.fps = float(vs.average_rate) if vs.average_rate else 25.0
        except av.error.FFmpegError as exc:
            raise UserError(f"{self.path}: not a readable video ({exc.__class__.__name__})") from None
        try:
            self.audio, self.sr, _ = read_audio_track(self.path)
        except UserError:
            pass

    _stop: int | None = None

    def head(self, n: int) -> "FrameFile":
        """The same file read up to frame ``n`` (its first ``n`` frames)."""
        import copy

        out = copy.copy(self)
        out._stop = int(n) if self._stop is None else min(int(n), self._stop)
        return out

    def __iter__(self) -> Iterator[np.ndarray]:
        """Every frame in order, uint8 ``[H, W, 3]`` RGB (a folder's images must all have one size)."""
        for i, frame in enumerate(self._frames()):
            if self._stop is not None and i >= self._stop:
                break
            yield frame

    def _frames(self) -> Iterator[np.ndarray]:
        if self._files is not None:
            size = None
            for f in self._files:
                img = read_rgb_u8(f)
                if size is None:
                    size = img.shape
                elif img.shape != size:
                    raise UserError(f"{self.path}: images differ in size: {f.name} is {img.shape[1]}x{img.shape[0]}, "
                                    f"the first is {size[1]}x{size[0]}")
                yield img
            return
        yield from self._decode()

    def _decode(self) -> Iterator[np.ndarray]:
        import av

        k = 0
        try:
            with av.open(str(self.path)) as c:
                vs = c.streams.video[0]
                vs.thread_type = "AUTO"
                for fr in c.decode(vs):
                    yield fr.to_ndarray(format="rgb24")
                    k += 1
        except av.error.FFmpegError as exc:
            raise UserError(f"{self.path}: decoding failed after {k} frames ({exc.__class__.__name__}: the file is "
                            "corrupt or truncated)") from None

    def chunks(self, size: int = CHUNK, stop: int | None = None) -> Iterator[np.ndarray]:
        """Frames ``0 .. stop-1`` (all by default) as uint8 ``[k, H, W, 3]`` arrays of ``size`` frames (the last shorter)."""
        buf: list[np.ndarray] = []
        for i, f in enumerate(self):
            if stop is not None and i >= stop:
                break
            buf.append(f)
            if len(buf) == size:
                yield np.stack(buf)
                buf = []
        if buf:
            yield np.stack(buf)

    def count(self) -> int:
        """The number of frames: the folder's images, or the video stream's packets (read without decoding)."""
        n = self._count_all()
        return n if self._stop is None else min(n, self._stop)

    def _count_all(self) -> int:
        if self._count is None:
            import av

            try:
                with av.open(str(self.path)) as c:
                    vs = c.streams.video[0]
                    self._count = sum(1 for p in c.demux(vs) if p.size)
            except av.error.FFmpegError as exc:
                raise UserError(f"{self.path}: not a readable video ({exc.__class__.__name__})") from None
        return self._count

    def read(self) -> np.ndarray:
        """Every frame as one uint8 ``[T, H, W, 3]`` array (for clips known to be small)."""
        return np.stack(list(self))
