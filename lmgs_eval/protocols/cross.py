"""The cross-driven protocol: trained models driven by other audio.

Only LSE-D / LSE-C apply, plus LMD where the clip comes with ground-truth articulation (the
bundled A / B clips). A user's own audio files are driving clips too.

A user's clip is identified by the sha256 of its audio file, not by its name: its clip id is
``<file stem>-<first 12 hex digits of the sha256>`` (the stem kept for display), so two
different files of one name (``x/a.wav``, ``y/a.wav``, ``a.m4a``) are two clips and one file
copied under two names is one. The bundled names (``A``, ``B``) are reserved: a user's ``A.wav``
never passes for the bundled clip. The record keeps the file's absolute path and hash
(artefact ``driving_audio``).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lmgs.types import Camera, DrivingAudio
from lmgs_eval import results as store
from lmgs_eval.convert import subject_to_clip
from lmgs_eval.data.audio import load_audio
from lmgs_eval.data.images import read_rgb_u8
from lmgs_eval.data.registry import find_subject
from lmgs_eval.errors import UserError
from lmgs_eval.results.records import RunId, build_record, metrics_block, stored
from lmgs_eval.runner import RunConfig, build_method, cost_block, cycle, fit_method, log, timed_render, write_render


@dataclass(frozen=True)
class CrossClip:
    """A driving clip of the cross-driven protocol (and its ground truth when it has one)."""

    name: str
    audio: np.ndarray  # 16 kHz mono
    source: str
    w2c: np.ndarray | None = None
    gt_frames: np.ndarray | None = None
    notes: tuple[str, ...] = ()
    audio_file: dict | None = None  # a user's clip: {"path": absolute, "sha256": ...}


BUNDLED_CLIPS = ("A", "B")


def bundled_cross_clips(subject) -> list[CrossClip]:
    """The bundled subject's clips A and B (voices and texts not used in training, with GT)."""
    clips = []
    for name in BUNDLED_CLIPS:
        d = subject.root / "cross" / name
        if not (d / "aud.wav").exists():
            continue
        audio, notes = load_audio(d / "aud.wav")
        w2c = gt = None
        tj = d / "transforms.json"
        if tj.exists():
            t = json.loads(tj.read_text())
            frames = sorted(t["frames"], key=lambda f: int(f["img_id"]))
            w2c = np.stack([Camera.from_nerf_c2w(np.asarray(f["transform_matrix"]), t["focal_len"], subject.width, subject.height,
                                                 t.get("cx"), t.get("cy")).world_to_camera.numpy() for f in frames])
            if (d / "gt_imgs").is_dir():
                gt = np.stack([read_rgb_u8(d / "gt_imgs" / f"{int(f['img_id'])}.jpg") for f in frames])
        clips.append(CrossClip(name, audio, str(d), w2c, gt, tuple(notes)))
    return clips


def user_cross_clips(paths: list[str]) -> tuple[list[CrossClip], list[str]]:
    """User audio files (any rate, mono or stereo). Bad files are reported and skipped."""
    clips, errors = [], []
    for p in paths:
        try:
            audio, notes = load_audio(Path(p))
        except UserError as exc:
            errors.append(str(exc))
            continue
        if len(audio) < 5 * 640:
            errors.append(f"{p}: {len(audio) / 16000:.2f} s of audio is shorter than 5 frames (0.2 s)")
            continue
        if float(np.max(np.abs(audio))) == 0.0:
            notes.append(f"{p}: the audio is digital silence")
        path = Path(p).resolve()
        sha = store.sha256_file(path)
        if any(c.audio_file["sha256"] == sha for c in clips):
            continue  # the same audio given twice (or under two names): one clip
        clips.append(CrossClip(f"{path.stem}-{sha[:12]}", audio, str(path), None, None, tuple(notes),
                               {"path": str(path), "sha256": sha}))
    return clips, errors


def run_cross(cfg: RunConfig, audio_paths: list[str] | None = None) -> tuple[list[store.Record], list[str]]:
    """Drive trained models with other audio; LSE per clip, and LMD where the clip has GT.

    Returns the records written and the per-file errors (the other clips still run).

    Raises:
        UserError: none of ``audio_paths`` can drive a model (the message joins the files' errors).
    """
    subject = find_subject(cfg.subject, cfg.data_root, progress=cfg.progress)
    if audio_paths:
        clips, errors = user_cross_clips(audio_paths)
        if not clips:
            raise UserError("; ".join(errors))
    else:
        clips, errors = bundled_cross_clips(subject), []
        if not clips:
            raise UserError(f"{subject.root}: no bundled cross-driven clips (cross/A, cross/B); pass --audio A.wav B.wav")
    if not clips:
        return [], errors
    train = None
    test = subject_to_clip(subject, subject.test_ids)
    records = []
    for name in cfg.methods:
        if name.startswith("external:"):
            errors.append(f"{name}: cross-driven renders of external methods are scored with `lmgs-eval score --pred`")
            continue
        for seed in cfg.seeds:
            method = build_method(cfg, name, subject)
            info = method.describe()
            run = RunId(subject, info, seed, "cross")
            todo = [c for c in clips if cfg.force or not _done(cfg, dataclasses.replace(run, clip=c.name))]
            if not todo:
                log(f"{run.label}: cross clips already in {cfg.results}; skipped")
                continue
            if train is None:
                train = subject_to_clip(subject, subject.train_ids, progress=cfg.progress)
            fit_cost = fit_method(method, train, run, cfg.progress)
            for c in todo:
                n = len(c.audio) // 640
                w2c = c.w2c[:n] if c.w2c is not None and len(c.w2c) >= n else cycle(test.w2c, n)
                backs = cycle(test.backgrounds, n)
                driving = DrivingAudio(audio=c.audio[: n * 640], w2c=w2c, backgrounds=backs)
                frames, rc = timed_render(method, driving)
                log(f"{info.name} on clip {c.name}: {n} frames at {rc['fps']:.1f} FPS; scoring")
                gt = c.gt_frames[:n] if c.gt_frames is not None and len(c.gt_frames) >= n else None
                res = cfg.suite.score(frames, gt, driving.audio, reference=False, lmd=gt is not None)
                art = {"render": write_render(cfg.results, _render_rel(run, c.name), frames, driving.audio)}
                if c.audio_file is not None:
                    art["driving_audio"] = dict(c.audio_file)
                rec = build_record(dataclasses.replace(run, clip=c.name), split=c.source, n_frames=n,
                                   metrics=metrics_block(res), cost=cost_block(method, fit_cost, rc), artefacts=art,
                                   notes=list(c.notes))
                store.write_record(cfg.results, rec)
                records.append(rec)
    return records, errors


def _render_rel(run: RunId, clip: str) -> str:
    return f"{run.renders}/{run.stem}-cross-{clip}.mp4"


def _done(cfg: RunConfig, run: RunId) -> bool:
    """A clip (``run.clip``) is done when its record is in the store and the render it points to is still there."""
    rec = stored(cfg.results, run)
    if rec is None:
        return False
    render = rec.artefacts.get("render")
    rel = render.path if render is not None else _render_rel(run, run.clip)
    if not (Path(cfg.results) / rel).is_file():
        log(f"{run.label}: the render of clip {run.clip} is missing ({Path(cfg.results) / rel}); made again")
        return False
    return True
