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

from lmgs.fileio import sha256_file
from lmgs_eval.data.ingest import decode
from lmgs_eval.data.ingest.checks import INGEST_VERSION, check_decoded, check_length
from lmgs_eval.data.layout_writer import write_json
from lmgs_eval.errors import UserError


@dataclass(frozen=True)
class IngestConfig:
    """Every parameter of an ingest (all recorded in the manifest).

    Attributes:
        size: output frame side in pixels.
        crop: ``auto`` (crop around the head unless the video already is a head crop),
            ``head`` or ``none``.
        focal: focal length in output pixels; None searches it over the clip.
        smooth_window: Savitzky-Golay window of the landmark smoothing (frames, odd; 1 = off).
        pose_sigma: Gaussian smoothing of the pose (frames; 0 = off); None: Whittaker's smoother,
            its weight chosen per clip by generalised cross-validation (:func:`pose.smooth_gcv`).
        pose_refine: refine each frame's landmark pose by the upper head's texture tracked
            from a reference frame (:mod:`align`).
        pose_from: ``mesh`` (each frame's pose from the subject's shape fitted to the dense face
            mesh) or ``landmarks`` (from the 68-point template on dlib's landmarks).
        plate_frames: frames sampled for the background plate.
        priors: ``ellipsoid`` (the depth / normal priors of the posed head ellipsoid) or ``mesh``
            (the tracked face mesh over the face, the head ellipsoid moved to meet it beyond;
            measured in design.md, "Depth priors from the face mesh").
    """

    size: int = 512
    crop: str = "auto"
    focal: float | None = None
    smooth_window: int = 5
    pose_sigma: float | None = 0.0
    pose_refine: bool = True
    plate_frames: int = 60
    pose_from: str = "mesh"
    priors: str = "ellipsoid"


def pose_sigma_from(text: str) -> float | None:
    """``--pose-smooth``'s value as :attr:`IngestConfig.pose_sigma`: ``auto`` is None (cross-validated
    Whittaker smoothing), a number the Gaussian's sigma in frames; anything else a :class:`UserError`."""
    if text == "auto":
        return None
    try:
        sigma = float(text)
    except ValueError:
        sigma = -1.0
    if not sigma >= 0:
        raise UserError(f"--pose-smooth {text!r}: must be auto or a number of frames >= 0")
    return sigma


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
    workers: object = None  # frames.Workers: the worker processes of the per-frame stages (jobs > 1)

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
    import os

    from lmgs_eval.paths import check_out_dir, data_root as _data_root

    video = Path(video).expanduser()
    if name is None:
        name = video.stem
    if not name or "/" in name or "\0" in name or name.startswith("."):
        raise UserError(f"--name {name!r}: must be a plain folder name")
    if not (64 <= cfg.size <= 2048):
        raise UserError(f"--size {cfg.size}: must be between 64 and 2048 pixels")
    if cfg.crop not in ("auto", "head", "none"):
        raise UserError(f"--crop {cfg.crop!r}: must be auto, head or none")
    if cfg.pose_from not in ("mesh", "landmarks"):
        raise UserError(f"--pose-from {cfg.pose_from!r}: must be mesh or landmarks")
    if cfg.pose_sigma is not None and not cfg.pose_sigma >= 0:
        raise UserError(f"--pose-smooth {cfg.pose_sigma}: must be auto or a number of frames >= 0")
    if cfg.focal is not None and not cfg.focal > 0:
        raise UserError(f"--focal {cfg.focal}: must be positive")
    njobs = _jobs(jobs)
    # Every input is checked before anything is made: a refused ingest leaves the data root as it was.
    from lmgs_eval.data.ingest import vendored

    vendored.check_all()
    _check_file(video, "video")
    if audio is not None:
        _check_file(Path(audio).expanduser(), "audio")
        audio = Path(audio).expanduser()
    root = _data_root(data_root)
    flag = "--data-root" if data_root else ("$LMGS_DATA" if os.environ.get("LMGS_DATA") else "the data root")
    check_out_dir(root, flag)
    _check_name_length(name, root)
    final = root / name
    if final.exists() and not force:
        raise UserError(f"{final}: already exists (pass --force to replace it, or --name another)")
    info = decode.probe(video)
    cut_short = check_decoded(info)
    sound = decode.read_audio(video, audio, info)
    check_length(video, audio, info, len(sound[0]))
    made = _missing_parents(root)
    root.mkdir(parents=True, exist_ok=True)
    key = {"input_sha256": sha256_file(video), "audio_sha256": sha256_file(Path(audio)) if audio else None,
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
        write_json(state, {"key": key, "done": [], "flags": {}, "log": [], "timings": {}})
    ctx = _Ctx(video, Path(audio) if audio else None, name, cfg, work, sub, progress, njobs, [], {}, {})
    try:
        _run(ctx, key, info, sound, cut_short)
    except UserError:
        shutil.rmtree(work, ignore_errors=True)
        for d in made:  # the folders this ingest made for the data root, if they hold nothing else
            try:
                d.rmdir()
            except OSError:
                break
        raise
    if final.exists():
        shutil.rmtree(final)
    sub.rename(final)
    shutil.rmtree(work, ignore_errors=True)
    return final


def _check_file(path: Path, what: str) -> None:
    if path.is_dir():
        raise UserError(f"{path}: is a folder, not {'a video' if what == 'video' else 'an audio'} file")
    if not path.is_file():
        raise UserError(f"{path}: {what} {'not found' if what == 'video' else 'file not found'}")


def _check_name_length(name: str, root: Path) -> None:
    """The subject's folder and its work folder (``.<name>.ingest``) must be names the file system takes."""
    import os

    from lmgs_eval.paths import existing_ancestor

    try:
        limit = os.pathconf(existing_ancestor(root), "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    most = limit - len(".ingest") - 1
    if len(os.fsencode(name)) > most:
        raise UserError(f"--name {name[:24]}...: {len(os.fsencode(name))} bytes long; a subject name may have at most {most} "
                        f"(the file system's limit for a folder name is {limit})")


def _missing_parents(root: Path) -> list[Path]:
    """``root`` and those of its parents that do not exist yet, deepest first."""
    out = []
    while not root.exists() and root != root.parent:
        out.append(root)
        root = root.parent
    return out


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
    from lmgs.fileio import atomic_write

    atomic_write(ctx.work / "state.json", json.dumps(st, indent=1, sort_keys=True))


def _run(ctx: _Ctx, key: dict, info: decode.VideoInfo, sound: tuple, cut_short: str | None) -> None:
    from lmgs_eval.data.ingest import stages

    st = _load_state(ctx)
    ctx.flags.update(st.get("flags", {}))
    ctx.log.extend(st.get("log", []))
    ctx.timings.update(st.get("timings", {}))
    done = set(st["done"])
    audio, notes, source = sound
    if cut_short and "track" not in done:
        ctx.warn("cut_short", cut_short)
    ctx.log += notes
    if "track" not in done:
        stages.track(ctx, info)
        _done(ctx, "track")
    from lmgs_eval.data.ingest.frames import Workers

    pooled = ("parsing", "geometry", "composites")  # the stages whose frames the worker processes share
    with Workers(ctx.jobs) as workers:
        if ctx.jobs > 1 and not done.issuperset(pooled):
            ctx.workers = workers.start()  # they start up (imports, seconds each) while this process cuts the frames
        try:
            tr = np.load(ctx.work / "track.npz")
            if "frames" not in done:
                stages.frames(ctx, info, tr, audio)
                _done(ctx, "frames")
            sel = np.load(ctx.work / "frames.npz")
            for name in ("pose", *pooled):  # the stages that work on the selected frames
                if name not in done:
                    getattr(stages, name)(ctx, sel)
                    _done(ctx, name)
        finally:
            ctx.workers = None
    stages.finish(ctx, info, sel, audio, source, key)


__all__ = ["IngestConfig", "ingest"]
