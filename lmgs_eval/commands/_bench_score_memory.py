"""``lmgs-eval bench score-memory``: peak memory and wall time of ``sync-check`` beside ``ingest`` on one clip.

Scoring reads a clip a frame at a time (:mod:`lmgs_eval.data.frames`): its memory should not grow with the
clip's resolution or length, and reading a phone video to score it should not take longer than ingesting it.
Both commands run here, one after the other, each in a process of its own on the same clip; each one's peak
resident memory (its own, or that of the largest worker it waited for) and wall time are printed with their
ratios. CPU seconds are given too: on a shared machine the wall time includes waiting for the cores.

By default the clip is generated: a 1080x1920 portrait at 25 fps (scikit-image's astronaut, 400 px, drifting
over a gradient, a tone as its audio), ``--seconds`` long; ``--video`` measures another clip (25 fps, with its
audio and a face).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

IN_ALL = False  # it runs an ingest (minutes on a 1080x1920 clip): `bench all` leaves it out
HELP = "peak memory and wall time of sync-check scoring beside ingest on one clip (default: a generated 1080x1920 portrait)"

# run in a process of its own: one command, then its peak memory and CPU time as one JSON line on stderr
_PROBE = """
import json, resource, sys
from lmgs_eval.cli import main
rc = main(sys.argv[1:])
me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({"rc": rc, "peak_mb": max(me.ru_maxrss, kids.ru_maxrss) / 1024,
                  "cpu_s": me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime}), file=sys.stderr)
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--video", help="measure this clip (25 fps, with its audio and a face) instead of a generated one")
    p.add_argument("--seconds", type=float, default=10.0, help="length of the generated clip (default 10)")
    p.add_argument("--width", type=int, default=1080, help="width of the generated clip (default 1080)")
    p.add_argument("--height", type=int, default=1920, help="height of the generated clip (default 1920)")
    from lmgs_eval.commands._sync import SYNC_CHOICES

    p.add_argument("--sync", default="auto", choices=SYNC_CHOICES, help="sync-check's scorer (default auto)")


def _tone(seconds: float, sr: int = 16000) -> np.ndarray:
    t = np.arange(int(seconds * sr)) / sr
    return 0.3 * np.sin(2 * np.pi * 220 * t) * (0.6 + 0.4 * np.sin(2 * np.pi * 3 * t))


def portrait_clip(path: Path, seconds: float = 10.0, width: int = 1080, height: int = 1920) -> Path:
    """Write a ``width`` x ``height`` 25 fps H.264 clip with AAC audio: a face (scikit-image's astronaut, 400 px)
    drifting over a grey gradient, a 220 Hz tone swelling at 3 Hz as its sound."""
    import cv2
    from skimage import data

    from lmgs_eval.data.video import write_video

    n = int(round(seconds * 25))
    side = min(400, width // 2, height // 2)
    face = cv2.resize(data.astronaut()[0:300, 80:380], (side, side), interpolation=cv2.INTER_AREA)
    bg = np.broadcast_to(np.linspace(40, 200, width).astype(np.uint8)[None, :, None], (height, width, 3))

    def frames():  # made and encoded one at a time: the clip is never held whole
        for i in range(n):
            img = np.array(bg)
            y, x = height // 3 + 3 * (i % 7), (width - side) // 2 + 2 * (i % 5)
            img[y:y + side, x:x + side] = face
            yield img

    write_video(path, frames(), 25, _tone(seconds), 16000, crf="23", preset="ultrafast")
    return path


def measure(argv: list[str], env: dict | None = None) -> dict:
    """Run ``lmgs-eval ARGV`` in a process of its own: exit code, peak resident MB, wall and CPU seconds."""
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", _PROBE, *argv], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    lines = r.stderr.strip().splitlines()
    try:
        got = json.loads(lines[-1])
    except (IndexError, json.JSONDecodeError):
        got = {"rc": r.returncode, "peak_mb": None, "cpu_s": None}
    out = {"rc": got["rc"], "peak_mb": None if got["peak_mb"] is None else round(got["peak_mb"], 1),
           "wall_s": round(wall, 1), "cpu_s": None if got["cpu_s"] is None else round(got["cpu_s"], 1)}
    if got["rc"]:
        out["error"] = next((ln for ln in reversed(lines[:-1]) if "error" in ln), lines[-2] if len(lines) > 1 else "")
    return out


def run(args: argparse.Namespace) -> dict:
    from lmgs_eval.data.frames import FrameFile

    with tempfile.TemporaryDirectory(prefix="lmgs-bench-score-memory-") as tmp:
        video = Path(args.video) if args.video else portrait_clip(Path(tmp) / "portrait.mp4", args.seconds, args.width,
                                                                  args.height)
        src = FrameFile(video)
        n = src.count()
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(Path(__file__).resolve().parents[2]),
                                                                          os.environ.get("PYTHONPATH")]))}
        sync = measure(["sync-check", str(video), "--sync", args.sync, "--json"], env)
        ingest = measure(["ingest", str(video), "--name", "bench", "--data-root", str(Path(tmp) / "data"), "--quiet"], env)
    whole_mb = n * src.height * src.width * 3 / 2**20

    def ratio(a, b):
        return round(a / b, 3) if a is not None and b else None

    rows = [{"command": "sync-check", **sync}, {"command": "ingest", **ingest}]
    return {
        "video": str(args.video) if args.video else f"generated portrait, {src.width}x{src.height}, {args.seconds:g} s",
        "frames": n,
        "size": f"{src.width}x{src.height}",
        "all_frames_uint8_mb": round(whole_mb, 1),
        "cores": os.cpu_count(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "peak_ratio_sync_over_ingest": ratio(sync["peak_mb"], ingest["peak_mb"]),
        "wall_ratio_sync_over_ingest": ratio(sync["wall_s"], ingest["wall_s"]),
        "rows": rows,
    }
