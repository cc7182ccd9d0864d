"""Reading and writing the files of a subject: images, maps, audio, video.

Images are float32 in [0, 1] (RGB order) in memory. Every reader names the file when it
fails. Writers are deterministic (fixed JPEG quality, no timestamps) so a bundled subject
built twice is byte-identical.
"""

from __future__ import annotations

import io
import wave
from fractions import Fraction
from pathlib import Path

import numpy as np
from scipy.signal import resample_poly

from lmgs.fileio import atomic_path
from lmgs_eval.errors import UserError
from lmgs_eval.paths import atomic_write_bytes

JPEG_QUALITY = 95
IMAGE_EXT = frozenset({".jpg", ".jpeg", ".png", ".bmp", ".webp"})


def list_frames(folder: Path) -> list[Path]:
    """The images of a frame folder in frame order: by the last number in each name (``7.jpg``, ``frame_0007.png``).

    The numbers must run without a gap from the first: a missing frame would shift every later
    frame against its ground truth. Names without a number are allowed only when no name has one
    (then the order is by name).

    Raises:
        UserError: no images, names mixing numbered and unnumbered files, a number used twice
            (``7.png`` and ``007.png``), or a gap (naming the first missing number).
    """
    import re

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


def _cv2():
    import cv2

    return cv2


def _imread(path: Path, flags: int) -> np.ndarray:
    cv2 = _cv2()
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: file not found")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise UserError(f"{path}: not a readable image (corrupt or wrong format)")
    return img


def read_rgb_u8(path: Path) -> np.ndarray:
    """An image as uint8 ``[H, W, 3]`` RGB."""
    cv2 = _cv2()
    img = _imread(path, cv2.IMREAD_COLOR)
    return img[:, :, ::-1].copy()


def read_rgb(path: Path) -> np.ndarray:
    """An image as float32 ``[H, W, 3]`` RGB in [0, 1]."""
    return read_rgb_u8(path).astype(np.float32) / 255.0


def read_rgba(path: Path) -> np.ndarray:
    """A PNG as float32 ``[H, W, 4]`` RGBA in [0, 1] (opaque alpha added if it has none)."""
    cv2 = _cv2()
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 3:
        img = np.concatenate([img, np.full(img.shape[:2] + (1,), 255, img.dtype)], axis=2)
    img = img[:, :, [2, 1, 0, 3]]
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    return img.astype(np.float32) / scale


def write_rgb(path: Path, img: np.ndarray) -> None:
    """Write float [0, 1] or uint8 RGB ``[H, W, 3]`` (``.jpg`` at fixed quality, or ``.png``)."""
    cv2 = _cv2()
    u8 = to_u8(img)
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if str(path).lower().endswith(".jpg") else []
    if not cv2.imwrite(str(path), u8[:, :, ::-1].copy(), params):
        raise UserError(f"{path}: could not write image")


def write_rgba(path: Path, img: np.ndarray) -> None:
    cv2 = _cv2()
    u8 = to_u8(img)
    if not cv2.imwrite(str(path), u8[:, :, [2, 1, 0, 3]].copy()):
        raise UserError(f"{path}: could not write image")


def to_u8(img: np.ndarray) -> np.ndarray:
    if img.dtype == np.uint8:
        return img
    return np.clip(np.rint(np.asarray(img, np.float64) * 255.0), 0, 255).astype(np.uint8)


def read_depth(path: Path, scale: float) -> np.ndarray:
    """A 16-bit depth PNG as float32 metres-like units: ``value / scale`` (0 = no surface)."""
    cv2 = _cv2()
    d = _imread(path, cv2.IMREAD_UNCHANGED)
    if d.dtype != np.uint16 or d.ndim != 2:
        raise UserError(f"{path}: depth map must be a single-channel 16-bit PNG, got {d.dtype} {d.shape}")
    return d.astype(np.float32) / float(scale)


def write_depth(path: Path, depth: np.ndarray, scale: float) -> None:
    cv2 = _cv2()
    d = np.clip(np.rint(np.asarray(depth, np.float64) * scale), 0, 65535).astype(np.uint16)
    if not cv2.imwrite(str(path), d):
        raise UserError(f"{path}: could not write depth map")


def read_normal(path: Path) -> np.ndarray:
    """A normal-map PNG (RGB = (n + 1) * 127.5) as unit float32 ``[H, W, 3]``; 0 where no surface."""
    u8 = read_rgb_u8(path)
    n = u8.astype(np.float32) / 127.5 - 1.0
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    # black (what write_normal stores where there is no surface) decodes to (-1, -1, -1), of norm
    # sqrt(3): it is told apart by its bytes, not by its length
    surface = (norm > 0.5) & u8.any(axis=2, keepdims=True)
    return np.where(surface, n / np.maximum(norm, 1e-6), 0.0).astype(np.float32)


def write_normal(path: Path, normal: np.ndarray) -> None:
    """Write unit normals ``[H, W, 3]`` (zeros = no surface, stored as black)."""
    n = np.asarray(normal, np.float64)
    valid = np.linalg.norm(n, axis=2, keepdims=True) > 0.5
    u8 = np.where(valid, np.clip(np.rint((n + 1.0) * 127.5), 0, 255), 0).astype(np.uint8)
    write_rgb(path, u8)


# ----------------------------------------------------------------------------- audio
def read_wav(path: Path) -> tuple[np.ndarray, int]:
    """Read a PCM WAV file as float32 ``[S, C]`` in [-1, 1] and its sample rate.

    Other audio formats (mp3, m4a, ...) are decoded through PyAV.
    """
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: audio file not found")
    if path.stat().st_size == 0:
        raise UserError(f"{path}: audio file is empty")
    try:
        with wave.open(str(path), "rb") as w:
            sr, ch, width, n = w.getframerate(), w.getnchannels(), w.getsampwidth(), w.getnframes()
            raw = w.readframes(n)
    except (wave.Error, EOFError):
        return _read_audio_av(path)
    if n == 0 or not raw:
        raise UserError(f"{path}: the WAV holds no samples (a header only)")
    if width == 2:
        x = np.frombuffer(raw, "<i2").astype(np.float32) / 32768.0
    elif width == 4:
        x = np.frombuffer(raw, "<i4").astype(np.float32) / 2147483648.0
    elif width == 1:
        x = (np.frombuffer(raw, np.uint8).astype(np.float32) - 128.0) / 128.0
    else:
        raise UserError(f"{path}: unsupported WAV sample width {width} bytes")
    return x.reshape(-1, ch), sr


def _read_audio_av(path: Path) -> tuple[np.ndarray, int]:
    import av

    try:
        with av.open(str(path)) as c:
            if not c.streams.audio:
                raise UserError(f"{path}: has no audio track")
            st = c.streams.audio[0]
            chunks = []
            sr = st.codec_context.sample_rate
            for fr in c.decode(st):
                a = fr.to_ndarray()
                if a.dtype == np.int16:
                    a = a.astype(np.float32) / 32768.0
                a = a.astype(np.float32)
                if fr.format.is_planar:
                    a = a.T
                else:
                    a = a.reshape(-1, len(fr.layout.channels))
                chunks.append(a)
    except av.error.FFmpegError as exc:
        raise UserError(f"{path}: not a readable audio file ({exc.__class__.__name__})") from None
    if not chunks:
        raise UserError(f"{path}: audio track is empty")
    return np.concatenate(chunks, axis=0), sr


def to_mono_16k(x: np.ndarray, sr: int, name: str = "audio") -> tuple[np.ndarray, list[str]]:
    """Mix ``[S, C]`` audio to mono and resample to 16 kHz; returns the signal and notes."""
    notes: list[str] = []
    x = np.asarray(x, np.float32)
    if x.ndim == 2:
        if x.shape[1] > 1:
            notes.append(f"{name}: {x.shape[1]} channels mixed to mono")
        x = x.mean(axis=1)
    if sr != 16000:
        f = Fraction(16000, int(sr))
        x = resample_poly(x.astype(np.float64), f.numerator, f.denominator).astype(np.float32)
        notes.append(f"{name}: resampled from {sr} Hz to 16000 Hz")
    if not np.all(np.isfinite(x)):
        raise UserError(f"{name}: audio contains non-finite samples")
    return x, notes


def load_audio(path: Path) -> tuple[np.ndarray, list[str]]:
    """Any audio file as 16 kHz mono float32, with notes for each repair applied."""
    x, sr = read_wav(path)
    return to_mono_16k(x, sr, str(path))


def write_wav(path: Path, x: np.ndarray, sr: int = 16000) -> None:
    """Write mono float audio in [-1, 1] as 16-bit PCM WAV."""
    pcm = np.clip(np.rint(np.asarray(x, np.float64) * 32767.0), -32768, 32767).astype("<i2")
    buf = io.BytesIO()
    with wave.open(buf, "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(int(sr))
        w.writeframes(pcm.tobytes())

    atomic_write_bytes(Path(path), buf.getvalue())


# ----------------------------------------------------------------------------- video
def read_video(path: Path) -> tuple[np.ndarray, float, np.ndarray | None, int | None]:
    """Decode a video: frames float32 ``[T, H, W, 3]`` in [0, 1], fps, audio ``[S, C]`` or None, sr."""
    import av

    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: video not found")
    frames = []
    try:
        with av.open(str(path)) as c:
            if not c.streams.video:
                raise UserError(f"{path}: has no video track")
            vs = c.streams.video[0]
            fps = float(vs.average_rate) if vs.average_rate else 25.0
            for fr in c.decode(vs):
                frames.append(fr.to_ndarray(format="rgb24"))
    except av.error.FFmpegError as exc:
        raise UserError(f"{path}: not a readable video ({exc.__class__.__name__})") from None
    if not frames:
        raise UserError(f"{path}: video has no frames")
    audio, sr = None, None
    try:
        audio, sr = _read_audio_av(path)
    except UserError:
        pass
    return np.stack(frames).astype(np.float32) / 255.0, fps, audio, sr


def write_video(path: Path, frames: np.ndarray, fps: int = 25, audio: np.ndarray | None = None, sr: int = 16000,
                lossless: bool = False, *, threads: int | None = None, x264_params: str | None = None) -> None:
    """Encode ``[T, H, W, 3]`` frames (float [0,1] or uint8) as H.264 mp4, with mono audio (AAC).

    By default as a camera or a renderer's output is stored (CRF 18, 4:2:0 chroma); ``lossless``
    keeps every RGB value (x264's RGB encoder at quantiser 0), for footage whose processing is
    to be measured apart from its compression. Written to a temporary file and renamed, so a
    reader never sees half a video.

    x264 left to itself encodes with one slice thread per CPU, and each slice count gives other
    bytes: ``threads`` fixes the count (slice threads), and ``x264_params`` passes x264 options
    (e.g. ``asm=...`` to fix its kernels), for a file that must be the same bytes on every host.
    """
    import av

    frames = to_u8(np.asarray(frames))
    t, h, w, _ = frames.shape
    with atomic_path(path) as tmp, av.open(str(tmp), "w", format="mp4") as c:
        vs = c.add_stream("libx264rgb" if lossless else "libx264", rate=int(fps))
        vs.width, vs.height = w - w % 2, h - h % 2
        vs.pix_fmt = "rgb24" if lossless else "yuv420p"
        vs.options = {"qp": "0", "preset": "veryfast"} if lossless else {"crf": "18", "preset": "veryfast"}
        if x264_params:
            vs.options = {**vs.options, "x264-params": x264_params}
        if threads is not None:
            vs.codec_context.thread_count = int(threads)
            vs.codec_context.thread_type = "SLICE"
        as_ = None
        if audio is not None and len(audio):
            as_ = c.add_stream("aac", rate=int(sr))
            as_.layout = "mono"
        for i in range(t):
            fr = av.VideoFrame.from_ndarray(np.ascontiguousarray(frames[i, : vs.height, : vs.width]), format="rgb24")
            for p in vs.encode(fr):
                c.mux(p)
        for p in vs.encode():
            c.mux(p)
        if as_ is not None:
            pcm = np.clip(np.rint(np.asarray(audio, np.float64) * 32767), -32768, 32767).astype(np.int16)
            step = 1024
            for k in range(0, len(pcm), step):
                af = av.AudioFrame.from_ndarray(pcm[None, k : k + step], format="s16", layout="mono")
                af.sample_rate = int(sr)
                af.pts = k
                for p in as_.encode(af):
                    c.mux(p)
            for p in as_.encode():
                c.mux(p)
