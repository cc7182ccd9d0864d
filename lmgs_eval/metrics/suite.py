"""Score a rendered clip against ground truth with every available metric: one result record."""

from __future__ import annotations

import datetime
import subprocess
from pathlib import Path

import numpy as np

from lmgs_eval.data.io import list_frames, load_audio, read_rgb, read_video, to_mono_16k
from lmgs_eval.errors import UserError
from lmgs_eval.metrics.base import align_lengths, check_frames
from lmgs_eval.metrics.lpips import ALEX_NAMES, find_alexnet
from lmgs_eval.metrics.registry import create_metric
from lmgs_eval.metrics.sync import lse

RECORD_SCHEMA = "lmgs-eval/score/1"

METRIC_NAMES = ("psnr", "ssim", "lpips", "lmd", "lse")
REFERENCE_METRICS = ("psnr", "ssim", "lpips", "lmd")
"""The names ``score --metrics`` takes; the first four compare with the ground truth."""


def load_frames(path: str | Path) -> tuple[np.ndarray, float | None, np.ndarray | None, int | None, list[str]]:
    """Frames of a video file or a folder of images (in frame order, no gap: :func:`lmgs_eval.data.io.list_frames`).

    Returns frames ``[T, H, W, 3]`` float32 [0, 1], fps (None for a folder), audio, sample rate, notes.
    """
    path = Path(path)
    if path.is_dir():
        files = list_frames(path)
        frames = [read_rgb(f) for f in files]
        shapes = {f.shape for f in frames}
        if len(shapes) != 1:
            raise UserError(f"{path}: images differ in size {sorted(shapes)}")
        return np.stack(frames), None, None, None, [f"{path}: {len(files)} images, sorted by number in the name"]
    frames, fps, audio, sr = read_video(path)
    return frames, fps, audio, sr, []


def git_hash() -> str | None:
    try:
        r = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                           cwd=Path(__file__).resolve().parent)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() or None


def score(pred: str | Path, gt: str | Path | None = None, audio: str | Path | None = None, truncate: bool = False,
          alexnet: str | None = None, lpips: str | None = None, landmarks: str = "dlib",
          metrics: list[str] | None = None, reference: bool = False) -> dict:
    """Score ``pred`` (against ``gt`` when given) with every available metric; the result record.

    Args:
        pred: rendered video or frame folder.
        gt: ground-truth video or folder; without it only no-reference metrics (LSE) run.
        audio: driving audio; default: the pred video's audio track.
        truncate: score the common prefix when the clips differ in length (recorded).
        alexnet: path of torchvision's AlexNet checkpoint (enables official LPIPS; another AlexNet-shaped
            trunk scores as ``lpips-alex-custom``).
        lpips: force ``"lpips-alex"`` or ``"stlpips-alex"`` (``lpips-alex`` with a trunk that is not
            torchvision's scores as ``lpips-alex-custom``).
        landmarks: LMD backend name.
        metrics: subset of names to run (default all).
        reference: ``pred`` is footage known to be in sync: LSE's self-check also requires offset 0 +- 1.
    """
    want = set(metrics or METRIC_NAMES)
    unknown = sorted(want - set(METRIC_NAMES))
    if unknown:
        raise UserError(f"--metrics: unknown metric {', '.join(unknown)}; known: {', '.join(METRIC_NAMES)}")
    needs_gt = sorted(want & set(REFERENCE_METRICS), key=METRIC_NAMES.index)
    if gt is None and metrics and needs_gt:
        raise UserError(f"--metrics {','.join(needs_gt)}: compares with a reference; pass --gt VIDEO_OR_FOLDER")
    p_frames, fps, p_audio, p_sr, notes = load_frames(pred)
    check_frames(p_frames, str(pred))
    flags: list[str] = []
    results = {}
    if fps is None:
        fps = 25.0
        notes.append("pred is a frame folder: 25 fps assumed")
    if gt is not None:
        g_frames, _, _, _, gnotes = load_frames(gt)
        notes += gnotes
        check_frames(g_frames, str(gt))
        n, tflags = align_lengths(p_frames.shape[0], g_frames.shape[0], truncate)
        flags += tflags
        pf, gf = p_frames[:n], g_frames[:n]
        if pf.shape != gf.shape:
            raise UserError(f"{pred} and {gt}: frame sizes differ {pf.shape[1:3]} vs {gf.shape[1:3]}")
        names = [m for m in ("psnr", "ssim") if m in want]
        if "lpips" in want:
            names.append(lpips or ("lpips-alex" if find_alexnet(alexnet) else "stlpips-alex"))
        if "lmd" in want:
            names.append("lmd")
        for name in names:
            kw = {"alexnet": alexnet} if name in ALEX_NAMES else ({"backend": landmarks} if name == "lmd" else {})
            m = create_metric(name, **kw)
            r = m.compute(m.update(pf, gf))
            r.flags = sorted(set(r.flags + tflags))
            results[r.spec.name] = r  # lpips-alex-custom when the trunk is not torchvision's
    else:
        n = p_frames.shape[0]
        notes.append("no --gt: only no-reference metrics")
    if "lse" in want:
        reason = ""
        a16 = None
        if audio is not None:
            a16, anotes = load_audio(Path(audio))
            notes += anotes
        elif p_audio is not None:
            a16, anotes = to_mono_16k(p_audio, p_sr, f"{pred} audio track")
            notes += anotes
        else:
            reason = f"{pred} has no audio track and --audio was not given"
        results["lse"] = lse(p_frames[:n], a16, fps=fps, audio_reason=reason, reference=reference)
    return {
        "schema": RECORD_SCHEMA,
        "pred": str(pred),
        "gt": None if gt is None else str(gt),
        "audio": None if audio is None else str(audio),
        "n_frames": int(n),
        "fps": fps,
        "flags": flags,
        "notes": notes,
        "results": {k: v.to_dict() for k, v in results.items()},
        "git": git_hash(),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def format_record(rec: dict) -> str:
    """A short human table of a score record (arrows give the better direction)."""
    lines = [f"pred: {rec['pred']}", f"gt:   {rec['gt']}", f"frames: {rec['n_frames']} @ {rec['fps']:g} fps"]
    for f in rec["flags"]:
        lines.append(f"flag: {f}")
    w = max([14, *(len(n) + 1 for n in rec["results"])])
    for name, r in rec["results"].items():
        arrow = "↑" if r["spec"]["higher_is_better"] else "↓"
        if not r["available"]:
            lines.append(f"{name:<{w}} unavailable: {r['reason']}")
            continue
        vals = ", ".join(f"{k}={v:.4f}" if isinstance(v, float) else f"{k}={v}" for k, v in r["values"].items())
        lines.append(f"{name:<{w}}{arrow} {vals}  (n={r['n_effective']}/{r['n_original']}, {r['spec']['backend']})")
        for f in r["flags"]:
            lines.append(f"{'':<{w + 2}}flag: {f}")
        if r["spec"].get("standin"):
            lines.append(f"{'':<{w + 2}}STAND-IN: {r['spec']['standin']}")
        if r["values"].get("trusted") is not None:
            lines.append(f"{'':<{w + 2}}self-check: separation {r['values']['separation']:.2f}, "
                         f"{'trusted' if r['values']['trusted'] else 'NOT trusted'}")
    return "\n".join(lines)
