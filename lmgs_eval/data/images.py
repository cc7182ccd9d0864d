"""Images of a subject on disk: frames (RGB, RGBA), depth maps and normal maps.

Frames are uint8 ``[H, W, 3]`` RGB in memory (:func:`read_rgb_u8`); float32 in [0, 1] only
where a computation needs it (:func:`read_rgb`, :func:`read_rgba`). Every reader names the file
when it fails. Writers are deterministic (fixed JPEG quality, fixed PNG settings, no
timestamps), so a bundled subject built twice is byte-identical.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lmgs_eval.errors import UserError

JPEG_QUALITY = 95


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


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image as :func:`read_rgb_u8` reads it, from the file's header (nothing decoded).

    The EXIF orientation is applied as OpenCV applies it on reading (a quarter turn swaps the sides).
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: file not found")
    try:
        with Image.open(path) as im:
            w, h = im.size
            turned = im.getexif().get(0x0112) in (5, 6, 7, 8)
    except (UnidentifiedImageError, OSError, SyntaxError):
        raise UserError(f"{path}: not a readable image (corrupt or wrong format)") from None
    return (h, w) if turned else (w, h)


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


def to_u8(img: np.ndarray) -> np.ndarray:
    """Float [0, 1] values as uint8 (rounded, clipped); uint8 as it is."""
    if img.dtype == np.uint8:
        return img
    return np.clip(np.rint(np.asarray(img, np.float64) * 255.0), 0, 255).astype(np.uint8)


def encode_png(img: np.ndarray, compression: int | None = None) -> bytes:
    """A grey ``[H, W]``, RGB ``[H, W, 3]`` or RGBA ``[H, W, 4]`` image (uint8, or uint16) as PNG bytes.

    ``compression``: zlib level (0-9; every level is lossless, 1 writes 3-4x faster than the
    default); None keeps OpenCV's default.
    """
    cv2 = _cv2()
    data = img if img.ndim == 2 else img[:, :, [2, 1, 0, 3][: img.shape[2]]]
    params = [] if compression is None else [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(data), params)
    if not ok:
        raise UserError("could not encode a PNG")
    return buf.tobytes()


def write_png(path: Path, img: np.ndarray, compression: int | None = None) -> None:
    """Write :func:`encode_png`'s bytes of ``img`` to ``path``."""
    data = encode_png(img, compression)
    try:
        Path(path).write_bytes(data)
    except OSError as exc:
        raise UserError(f"{path}: could not write image ({exc.strerror})") from None


def write_rgb(path: Path, img: np.ndarray) -> None:
    """Write float [0, 1] or uint8 RGB ``[H, W, 3]``: ``.png``, else JPEG at :data:`JPEG_QUALITY`."""
    u8 = to_u8(img)
    if str(path).lower().endswith(".png"):
        write_png(path, u8)
        return
    cv2 = _cv2()
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if str(path).lower().endswith(".jpg") else []
    if not cv2.imwrite(str(path), u8[:, :, ::-1].copy(), params):
        raise UserError(f"{path}: could not write image")


def read_depth(path: Path, scale: float) -> np.ndarray:
    """A 16-bit depth PNG as float32 metres-like units: ``value / scale`` (0 = no surface)."""
    cv2 = _cv2()
    d = _imread(path, cv2.IMREAD_UNCHANGED)
    if d.dtype != np.uint16 or d.ndim != 2:
        raise UserError(f"{path}: depth map must be a single-channel 16-bit PNG, got {d.dtype} {d.shape}")
    return d.astype(np.float32) / float(scale)


def write_depth(path: Path, depth: np.ndarray, scale: float) -> None:
    """Write depth ``[H, W]`` as a 16-bit PNG of ``depth * scale`` (rounded, clipped to 0..65535)."""
    write_png(path, np.clip(np.rint(np.asarray(depth, np.float64) * scale), 0, 65535).astype(np.uint16))


def read_normal(path: Path) -> np.ndarray:
    """A normal-map PNG (RGB = (n + 1) * 127.5) as unit float32 ``[H, W, 3]``; 0 where no surface."""
    u8 = read_rgb_u8(path)
    n = u8.astype(np.float32) / 127.5 - 1.0
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    # black (what write_normal stores where there is no surface) decodes to (-1, -1, -1), of norm
    # sqrt(3): it is told apart by its bytes, not by its length
    surface = (norm > 0.5) & u8.any(axis=2, keepdims=True)
    return np.where(surface, n / np.maximum(norm, 1e-6), 0.0).astype(np.float32)


def write_normal(path: Path, normal: np.ndarray, *, dtype=np.float64, compression: int | None = None) -> None:
    """Write unit normals ``[H, W, 3]`` as RGB ``(n + 1) * 127.5`` (zeros = no surface, stored as black).

    ``dtype``: the float type the encoding is computed in (the bundled subjects' maps: float64,
    the ingest's: float32); ``compression`` as :func:`encode_png`'s.
    """
    n = np.asarray(normal, dtype)
    valid = np.linalg.norm(n, axis=2, keepdims=True) > 0.5
    u8 = np.where(valid, np.clip(np.rint((n + 1.0) * 127.5), 0, 255), 0).astype(np.uint8)
    write_png(path, u8, compression)
