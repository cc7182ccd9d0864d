"""Writing video: frames (and mono audio) as H.264 / AAC in mp4.

Reading a video (or a folder of frames) is :class:`lmgs_eval.data.frames.FrameFile`'s.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from lmgs.fileio import atomic_path
from lmgs_eval.data.audio import SAMPLE_RATE, pcm16
from lmgs_eval.data.images import to_u8


def write_video(path: Path, frames: np.ndarray | Iterable[np.ndarray], fps: int = 25, audio: np.ndarray | None = None,
                sr: int = SAMPLE_RATE, lossless: bool = False, *, crf: str = "18", preset: str = "veryfast",
                options: dict | None = None, threads: int | None = None, x264_params: str | None = None) -> None:
    """Encode ``[T, H, W, 3]`` frames (float [0,1] or uint8; or any iterable of ``[H, W, 3]`` frames, encoded as
    they come) as H.264 mp4, with mono audio (AAC).

    By default as a camera or a renderer's output is stored (CRF 18, 4:2:0 chroma); ``crf`` and
    ``preset`` trade quality for size (``options``: more encoder options); ``lossless`` keeps
    every RGB value (x264's RGB encoder at quantiser 0), for footage whose processing is to be
    measured apart from its compression. Odd sizes lose their last row or column. Written to a
    temporary file and renamed, so a reader never sees half a video.

    x264 left to itself encodes with one slice thread per CPU, and each slice count gives other
    bytes: ``threads`` fixes the count (slice threads), and ``x264_params`` passes x264 options
    (e.g. ``asm=...`` to fix its kernels), for a file that must be the same bytes on every host.
    """
    import av

    if isinstance(frames, np.ndarray):
        h, w = frames.shape[1:3]
    else:
        it = iter(frames)
        first = next(it)
        h, w = first.shape[:2]
        frames = itertools.chain([first], it)
    with atomic_path(path) as tmp, av.open(str(tmp), "w", format="mp4") as c:
        vs = c.add_stream("libx264rgb" if lossless else "libx264", rate=int(fps))
        vs.width, vs.height = w - w % 2, h - h % 2
        vs.pix_fmt = "rgb24" if lossless else "yuv420p"
        vs.options = {"qp": "0", "preset": "veryfast"} if lossless else {"crf": crf, "preset": preset, **(options or {})}
        if x264_params:
            vs.options = {**vs.options, "x264-params": x264_params}
        if threads is not None:
            vs.codec_context.thread_count = int(threads)
            vs.codec_context.thread_type = "SLICE"
        as_ = None
        if audio is not None and len(audio):
            as_ = c.add_stream("aac", rate=int(sr))
            as_.layout = "mono"
        for frame in frames:
            fr = av.VideoFrame.from_ndarray(np.ascontiguousarray(to_u8(frame)[: vs.height, : vs.width]), format="rgb24")
            for p in vs.encode(fr):
                c.mux(p)
        for p in vs.encode():
            c.mux(p)
        if as_ is not None:
            pcm = pcm16(audio)
            step = 1024
            for k in range(0, len(pcm), step):
                af = av.AudioFrame.from_ndarray(pcm[None, k : k + step], format="s16", layout="mono")
                af.sample_rate = int(sr)
                af.pts = k
                for p in as_.encode(af):
                    c.mux(p)
            for p in as_.encode():
                c.mux(p)
