"""The Watch page's videos: small H.264 previews of the renders and error maps |render - GT|.

A preview is the render downscaled so its longer side is at most ``max_side`` pixels and
re-encoded as H.264 in mp4 (``yuv420p``, CRF :data:`CRF`; error maps :data:`ERROR_CRF`), the format every Chromium,
Firefox and Safari plays; the ground truth's preview keeps the clip's audio (AAC), the
methods' are silent (the page plays one audio for all). The error map is the per-pixel
mean over channels of ``|render - GT|`` times :data:`ERROR_GAIN`, clipped to [0, 1], in grey.

Files are named by the sha256 the record gives its render (and the ground truth's for an
error map), so a rebuild reuses a preview of the same render and never shows a stale one.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np

from lmgs_eval.data.frames import FrameFile
from lmgs_eval.data.video import write_video
from lmgs_eval.errors import UserError
from lmgs_eval.results.store import resolve_artefact
from lmgs_eval.results.types import Record

CRF = "30"
ERROR_CRF = "36"  # error maps are grey noise: at CRF 30 they cost three times a preview (8 s at 256 px: 431 vs 148 KiB)
ERROR_GAIN = 4.0
MAX_SIDE = 256


def _downscale(clip: FrameFile, max_side: int) -> np.ndarray:
    """A clip's frames as float32 ``[T, H, W, 3]`` in [0, 1], the longer side at most ``max_side`` (area
    filter), even sizes; decoded and scaled a frame at a time."""
    h, w = clip.height, clip.width
    s = min(1.0, max_side / max(h, w))
    nh, nw = max(2, int(round(h * s)) // 2 * 2), max(2, int(round(w * s)) // 2 * 2)
    import cv2

    out = []
    for f in clip:
        f = f.astype(np.float32) / 255.0
        out.append(f if (nh, nw) == (h, w) else cv2.resize(f, (nw, nh), interpolation=cv2.INTER_AREA))
    return np.stack(out)


def _encode(path: Path, frames: np.ndarray, fps: float, audio: np.ndarray | None, sr: int | None,
            crf: str = CRF) -> None:
    """A preview: :func:`~lmgs_eval.data.video.write_video` at ``crf`` and x264's medium preset (renders are
    stored at CRF 18; previews trade quality for size), audio mixed to mono."""
    frames = np.clip(np.rint(frames * 255.0), 0, 255).astype(np.uint8)  # float32 arithmetic, as the previews were made
    mono = None
    if audio is not None and len(audio) and sr:
        mono = np.asarray(audio, np.float64)
        mono = mono.mean(axis=1) if mono.ndim == 2 else mono
    write_video(path, frames, int(round(fps)), mono, sr or 16000, crf=crf, preset="medium",
                options={"movflags": "+faststart"})


def error_map(render: np.ndarray, gt: np.ndarray, gain: float = ERROR_GAIN) -> np.ndarray:
    """``clip(gain * mean_c |render - gt|, 0, 1)`` as grey ``[T, H, W, 3]`` frames (same shapes required)."""
    if render.shape != gt.shape:
        raise UserError(f"error map needs frames of one shape: render {render.shape}, ground truth {gt.shape}")
    e = np.clip(gain * np.abs(render - gt).mean(axis=-1, keepdims=True), 0.0, 1.0)
    return np.repeat(e, 3, axis=-1).astype(np.float32)


class Previews:
    """Makes (or reuses) the preview files of a site's ``media/`` folder.

    Args:
        store: the results store (render paths are relative to it).
        media: the site's media folder being written.
        reuse: an older site's media folder whose files of the same names are copied, not re-encoded.
        max_side: longer side of the previews, in pixels.
    """

    def __init__(self, store: Path, media: Path, reuse: Path | None = None, max_side: int = MAX_SIDE):
        self.store, self.media, self.reuse, self.max_side = Path(store), Path(media), reuse, max_side
        self._decoded: dict[str, tuple[np.ndarray, float, Any, Any]] = {}
        self._gt_key: str | None = None
        self.fps: float | None = None  # of the last clip decoded

    def _source(self, rec: Record) -> tuple[Path | None, str | None, str | None]:
        """``(file, sha256, why not)`` of a record's render."""
        art = rec.artefacts.get("render")
        if not art:
            return None, None, "this run recorded no render"
        path = resolve_artefact(self.store, art.path)
        if not path.is_file():
            where = rec.machine.cpu or "another machine"
            return None, art.sha256, (f"render not on this machine ({art.path}; made on {where}, "
                                      f"{rec.created[:10]}): metrics and curves only")
        return path, art.sha256, None

    def full(self, rec: Record) -> Path | None:
        """The record's render file when it is on this machine."""
        return self._source(rec)[0]

    def _frames(self, path: Path) -> tuple[np.ndarray, float, Any, Any]:
        key = str(path)
        if key not in self._decoded:
            clip = FrameFile(path)
            self.fps = clip.fps
            if len(self._decoded) >= 2:  # the ground truth and one render at a time
                self._decoded.pop(next(k for k in self._decoded if k != self._gt_key))
            self._decoded[key] = (_downscale(clip, self.max_side), clip.fps, clip.audio, clip.sr)
        return self._decoded[key]

    def _file(self, name: str, make) -> str:
        out = self.media / name
        if not out.is_file():
            old = self.reuse / name if self.reuse is not None else None
            self.media.mkdir(parents=True, exist_ok=True)
            if old is not None and old.is_file():
                shutil.copyfile(old, out)
            else:
                make(out)
        return f"media/{name}"

    def preview(self, rec: Record, audio: bool) -> tuple[str | None, str | None]:
        """``(site-relative file, None)`` for a record's render preview, or ``(None, why)``
        (no render here, or one that does not decode: the page says so, the rest of the site is made)."""
        try:
            return self._preview(rec, audio)
        except UserError as exc:
            return None, f"render not readable: {exc}"

    def _preview(self, rec: Record, audio: bool) -> tuple[str | None, str | None]:
        path, sha, why = self._source(rec)
        if path is None:
            return None, why

        def make(out: Path) -> None:
            frames, fps, aud, sr = self._frames(path)
            _encode(out, frames, fps, aud if audio else None, sr)

        return self._file(f"{sha[:16]}-{self.max_side}{'-a' if audio else ''}.mp4", make), None

    def error(self, rec: Record, gt: Record) -> tuple[str | None, str | None]:
        """``(site-relative file, None)`` for the error map of a render against the ground truth's, or ``(None, why)``."""
        try:
            return self._error(rec, gt)
        except UserError as exc:
            return None, f"no error map: {exc}"

    def _error(self, rec: Record, gt: Record) -> tuple[str | None, str | None]:
        path, sha, why = self._source(rec)
        gpath, gsha, gwhy = self._source(gt)
        if path is None or gpath is None:
            return None, why or gwhy
        self._gt_key = str(gpath)
        g = self._frames(gpath)[0]
        r = self._frames(path)[0]
        if r.shape != g.shape:
            return None, f"no error map: render {r.shape[:3]} and ground truth {g.shape[:3]} differ in frames or size"

        def make(out: Path) -> None:
            rr, fps, _, _ = self._frames(path)
            gg = self._frames(gpath)[0]
            _encode(out, error_map(rr, gg), fps, None, None, crf=ERROR_CRF)

        return self._file(f"{sha[:16]}-{self.max_side}-err-{gsha[:8]}.mp4", make), None


__all__ = ["CRF", "ERROR_CRF", "ERROR_GAIN", "MAX_SIDE", "Previews", "error_map"]
