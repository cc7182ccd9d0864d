"""``ingest``: a raw talking-head video in, a subject in the ER-NeRF / TalkingGaussian layout out.

Stages (each timed; frames/s in the manifest): decode + track -> checks -> crop + frames ->
landmarks -> pose -> parsing + plate -> depth / normal priors -> composites -> audio, video,
manifest.

The subject is built in a hidden work folder beside its final place
(``<data root>/.<name>.ingest``) and renamed into place at the end, so no half-written subject
is ever visible. A bad input (:class:`UserError`) removes the work folder; an interruption
keeps it, and running the same command again resumes after the last finished stage (the
folder records the input's sha256 and every parameter, so a changed input starts afresh).
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from lmgs_eval.data.ingest import decode, writer
from lmgs_eval.errors import UserError

INGEST_VERSION = "6"  # 2: depth / normal priors; 3: the zoom check (pose.scale in the manifest); 4: head label on the jaw line, neck continued behind the head in torso_imgs, poses refined by tracked texture; 5: depth / normal priors cover the whole head mask; 6: the person's holes only where background does not reach the edge, the person grown against the plate
MIN_SECONDS = 10.0  # shorter clips are ingested with a warning: too little to train on
MIN_FACE_PX = 100  # jaw width in source pixels under which the face is flagged as small
MOVING_SHARE = 0.02  # moving-camera flag: background residual above STATIC_LEVELS in more than this share...
STATIC_LEVELS = 10.0  # ...of the sampled frames (grey levels, median over the background)


@dataclass(frozen=True)
class IngestConfig:
    """Every parameter of an ingest (all recorded in the manifest).

    Attributes:
        size: output frame side in pixels.
        crop: ``auto`` (crop around the head unless the video already is a head crop),
            ``head`` or ``none``.
        focal: focal length in output pixels; None searches it over the clip.
        smooth_window: Savitzky-Golay window of the landmark smoothing (frames, odd; 1 = off).
        pose_sigma: Gaussian smoothing of the pose (frames; 0 = off).
        pose_refine: refine each frame's landmark pose by the upper head's texture tracked
            from a reference frame (:mod:`align`).
        plate_frames: frames sampled for the background plate.
    """

    size: int = 512
    crop: str = "auto"
    focal: float | None = None
    smooth_window: int = 5
    pose_sigma: float = 2.0
    pose_refine: bool = True
    plate_frames: int = 60


@dataclass
class _Ctx:
    video: Path
    audio: Path | None
    name: str
    cfg: IngestConfig
    work: Path  # hidden work folder
    sub: Path  # the subject being written, inside it
    progress: bool
    jobs: int
    log: list[str]
    flags: dict
    timings: dict

    def bar(self, total: int, desc: str):
        if not self.progress:
            return None
        from tqdm import tqdm

        return tqdm(total=total, desc=f"ingest {self.name}: {desc}", unit="frame", leave=False)

    def warn(self, key: str, text: str) -> None:
        self.flags[key] = text
        print(f"warning: {text}", file=sys.stderr)

    def timed(self, stage: str, t0: float, frames: int) -> None:
        dt = time.perf_counter() - t0
        self.timings[stage] = {"seconds": round(dt, 3), "frames": int(frames), "frames_per_s": round(frames / dt, 1) if dt > 0 else None}


def ingest(video: str | Path, name: str | None = None, *, audio: str | Path | None = None, data_root: str | Path | None = None,
           cfg: IngestConfig = IngestConfig(), force: bool = False, progress: bool = True, jobs: int | None = None) -> Path:
    """Ingest ``video`` as subject ``name`` under the data root; returns the subject folder.

    ``jobs``: processes for the per-frame stages (default: the CPU count, at most 4); the
    files are the same for any number.

    Raises:
        UserError: a bad input (one line naming the file and what is wrong); nothing is left
            under the data root.
    """
    from lmgs_eval.paths import data_root as _data_root

    video = Path(video).expanduser()
    name = name or video.stem
    if not name or "/" in name or name.startswith("."):
        raise UserError(f"--name {name!r}: must be a plain folder name")
    if not (64 <= cfg.size <= 2048):
        raise UserError(f"--size {cfg.size}: must be between 64 and 2048 pixels")
    if cfg.crop not in ("auto", "head", "none"):
        raise UserError(f"--crop {cfg.crop!r}: must be auto, head or none")
    if cfg.focal is not None and not cfg.focal > 0:
        raise UserError(f"--focal {cfg.focal}: must be positive")
    njobs = _jobs(jobs)
    root = _data_root(data_root)
    final = root / name
    if final.exists() and not force:
        raise UserError(f"{final}: already exists (pass --force to replace it, or --name another)")
    if not video.is_file():
        raise UserError(f"{video}: video not found")
    if audio is not None and not Path(audio).is_file():
        raise UserError(f"{audio}: audio file not found")
    root.mkdir(parents=True, exist_ok=True)
    key = {"input_sha256": writer.sha256_file(video), "audio_sha256": writer.sha256_file(Path(audio)) if audio else None,
           "config": asdict(cfg), "ingest_version": INGEST_VERSION}
    work = root / f".{name}.ingest"
    state = work / "state.json"
    if work.exists():
        try:
            old = json.loads(state.read_text())
        except (OSError, json.JSONDecodeError):
            old = {}
        if old.get("key") != key:
            shutil.rmtree(work)
        elif progress:
            print(f"resuming {name} from {work} (done: {', '.join(old.get('done', [])) or 'nothing'})", file=sys.stderr)
    sub = work / "subject"
    sub.mkdir(parents=True, exist_ok=True)
    if not state.exists():
        writer.write_json(state, {"key": key, "done": [], "flags": {}, "log": [], "timings": {}})
    ctx = _Ctx(video, Path(audio) if audio else None, name, cfg, work, sub, progress, njobs, [], {}, {})
    try:
        _run(ctx, key)
    except UserError:
        shutil.rmtree(work, ignore_errors=True)
        raise
    if final.exists():
        shutil.rmtree(final)
    sub.rename(final)
    shutil.rmtree(work, ignore_errors=True)
    return final


def _jobs(jobs: int | None) -> int:
    import os

    if jobs is None:
        return max(1, min(4, os.cpu_count() or 1))
    if jobs < 1:
        raise UserError(f"--jobs {jobs}: must be at least 1")
    return int(jobs)


def _load_state(ctx: _Ctx) -> dict:
    return json.loads((ctx.work / "state.json").read_text())


def _done(ctx: _Ctx, stage: str, **extra) -> None:
    st = _load_state(ctx)
    st["done"].append(stage)
    st["flags"], st["log"], st["timings"] = ctx.flags, ctx.log, ctx.timings
    st.update(extra)
    from lmgs_eval.paths import atomic_write_text

    atomic_write_text(ctx.work / "state.json", json.dumps(st, indent=1, sort_keys=True))


def _run(ctx: _Ctx, key: dict) -> None:
    from lmgs_eval.data.ingest import stages

    st = _load_state(ctx)
    ctx.flags.update(st.get("flags", {}))
    ctx.log.extend(st.get("log", []))
    ctx.timings.update(st.get("timings", {}))
    done = set(st["done"])
    info = decode.probe(ctx.video)
    audio, notes, source = decode.read_audio(ctx.video, ctx.audio, info)
    ctx.log += notes
    if "track" not in done:
        stages.track(ctx, info)
        _done(ctx, "track")
    tr = np.load(ctx.work / "track.npz")
    if "frames" not in done:
        stages.frames(ctx, info, tr, audio)
        _done(ctx, "frames")
    sel = np.load(ctx.work / "frames.npz")
    if "pose" not in done:
        stages.pose(ctx, sel)
        _done(ctx, "pose")
    if "parsing" not in done:
        stages.parsing(ctx, sel)
        _done(ctx, "parsing")
    if "geometry" not in done:
        stages.geometry(ctx, sel)
        _done(ctx, "geometry")
    if "composites" not in done:
        stages.composites(ctx, sel)
        _done(ctx, "composites")
    stages.finish(ctx, info, sel, audio, source, key)


def check_frames(ctx: _Ctx, info: decode.VideoInfo, n_audio_frames: int, first: int, last: int,
                 left_out: tuple[int, ...] = ()) -> tuple[int, int]:
    """The frame range kept after the face coverage and the audio's length are taken into account
    (``left_out``: frames inside it without a face, which do not count towards the clip's length)."""
    if n_audio_frames < last:
        short = last - n_audio_frames
        if n_audio_frames - first < 1:
            raise UserError(f"{ctx.audio or ctx.video}: the audio ({n_audio_frames / 25:.2f} s) ends before the first frame with a face")
        ctx.warn("audio_shorter", f"the audio is {short} frames ({short / 25:.2f} s) shorter than the video; the last {short} frames are dropped")
        last = n_audio_frames
    kept = last - first - sum(1 for k in left_out if k < last)
    if kept / 25 < MIN_SECONDS:
        ctx.warn("short_clip", f"{ctx.video}: {kept / 25:.1f} s with a face: too short to train a model well (at least {MIN_SECONDS:g} s; the field uses 3-5 min)")
    return first, last


def save_npz(path: Path, **arrays) -> None:
    from lmgs_eval.paths import atomic_path

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


__all__ = ["INGEST_VERSION", "IngestConfig", "ingest"]
