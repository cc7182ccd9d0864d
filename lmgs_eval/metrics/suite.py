"""Score a rendered clip against ground truth with every available metric: one result record.

:func:`score` reads the two files (:class:`~lmgs_eval.data.frames.FrameFile`) and hands them to the
metric suite (:class:`~lmgs_eval.metrics.metric_suite.MetricSuite`), the one scorer of the toolkit.
"""

from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np

from lmgs_eval.data.audio import load_audio, to_mono_16k
from lmgs_eval.data.frames import FrameFile
from lmgs_eval.errors import UserError
from lmgs_eval.metrics.base import align_lengths
from lmgs_eval.metrics.config import SuiteConfig
from lmgs_eval.metrics.metric_suite import METRIC_NAMES, REFERENCE_METRICS, MetricSuite
from lmgs_eval.metrics.sync.maths import MIN_SAMPLES, too_short
from lmgs_eval.paths import git_state

RECORD_SCHEMA = "lmgs-eval/score/1"


def clip_audio(audio: str | Path | None, src: FrameFile, what: str = "--audio") -> tuple[np.ndarray | None, str, list[str]]:
    """16 kHz mono audio for LSE: the file ``audio``, else the video's own track; ``(audio, reason, notes)``.

    ``audio`` is None with a reason (naming the file) when there is none or it is too short for one
    LSE window.
    """
    if audio is not None:
        a16, notes = load_audio(Path(audio))
        name = f"{what} {audio}"
    elif src.audio is not None:
        a16, notes = to_mono_16k(src.audio, src.sr, f"{src.path} audio track")
        name = f"{src.path} audio track"
    else:
        return None, f"{src.path} has no audio track and --audio was not given", []
    if len(a16) < MIN_SAMPLES:
        return None, f"{name}: audio too short: {too_short(len(a16))}", notes
    return a16, "", notes


def require_scored(results: dict, what: str) -> None:
    """The rule of every scoring command: a metric that cannot be computed is reported as unavailable with its
    reason while the others are scored; when no metric asked for could be computed, that is an error.

    ``results``: ``{name: MetricResult.to_dict()}``. Raises :class:`UserError` (one line naming ``what``
    and each reason) when every one is unavailable.
    """
    if results and not any(r["available"] for r in results.values()):
        why = "; ".join(f"{name} unavailable: {r.get('reason', '')}" for name, r in results.items())
        raise UserError(f"{what}: nothing could be scored: {why}")


def score(pred: str | Path, gt: str | Path | None = None, audio: str | Path | None = None, truncate: bool = False,
          alexnet: str | None = None, lpips: str | None = None, landmarks: str = "dlib",
          metrics: list[str] | None = None, reference: bool = False, sync: str = "auto") -> dict:
    """Score ``pred`` (against ``gt`` when given) with every available metric; the result record.

    The clips are read through :class:`~lmgs_eval.data.frames.FrameFile` (a video or a frame folder, a few
    frames at a time) and scored by a :class:`~lmgs_eval.metrics.metric_suite.MetricSuite` built from
    the choices below.

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
        sync: the LSE scorer (``--sync``).
    """
    want = set(metrics or METRIC_NAMES)
    unknown = sorted(want - set(METRIC_NAMES))
    if unknown:
        raise UserError(f"--metrics: unknown metric {', '.join(unknown)}; known: {', '.join(METRIC_NAMES)}")
    needs_gt = sorted(want & set(REFERENCE_METRICS), key=METRIC_NAMES.index)
    if gt is None and metrics and needs_gt:
        raise UserError(f"--metrics {','.join(needs_gt)}: compares with a reference; pass --gt VIDEO_OR_FOLDER")
    suite = MetricSuite(SuiteConfig(sync=sync, lpips=lpips, alexnet=alexnet, landmarks=landmarks))
    src = FrameFile(pred)
    notes = list(src.notes)
    fps = src.fps
    flags: list[str] = []
    if fps is None:
        fps = 25.0
        notes.append("pred is a frame folder: 25 fps assumed")
    gsrc = None
    if gt is not None:
        gsrc = FrameFile(gt)
        notes += gsrc.notes
        if (src.height, src.width) != (gsrc.height, gsrc.width):
            raise UserError(f"{pred} and {gt}: frame sizes differ {(src.height, src.width)} vs {(gsrc.height, gsrc.width)}")
        n, flags = align_lengths(src.count(), gsrc.count(), truncate)
    else:
        n = src.count()
        notes.append("no --gt: only no-reference metrics")
    a16, reason = None, ""
    if "lse" in want:
        a16, reason, anotes = clip_audio(audio, src)
        notes += anotes
    results = suite.score(src, gsrc, a16, metrics=[m for m in METRIC_NAMES if m in want], n=n, fps=fps,
                          audio_reason=reason, in_sync=reference, flags=tuple(flags))
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
        "git": git_state(dirty=False)[0],
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
            sep = r["values"].get("separation")
            lines.append(f"{'':<{w + 2}}self-check: separation " + (f"{sep:.2f}" if isinstance(sep, float) else "n/a")
                         + f", {'trusted' if r['values']['trusted'] else 'NOT trusted'}")
    return "\n".join(lines)
