"""The mesh sync scorer (``--sync mesh``): its weights, the face mesh of a clip, where ``auto`` puts it, its LSE.

Clips are made by the bundled generator (a held-out voice and text, as the landmark scorer's tests) and
read back by the face mesh tracker like any user's footage. One slow test reads the development footage
(``../shared/footage``) when it is there.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lmgs.fileio import sha256_file
from lmgs_eval.errors import UserError
from lmgs_eval.metrics.sync import mesh as M
from lmgs_eval.metrics.sync import scorers, select
from lmgs_eval.metrics.sync.crops import FaceClip
from lmgs_eval.metrics.sync.probe import shifted
from lmgs_eval.metrics.sync.scoring import LSE

FOOTAGE = Path(__file__).resolve().parents[1] / ".." / "shared" / "footage"


@pytest.fixture(autouse=True)
def _without_official(monkeypatch, tmp_path):
    # other test modules import a random-weight SyncNet into the session's cache; ``auto`` here is about a
    # machine without the official weights
    monkeypatch.setattr(scorers, "syncnet_manifest_path", lambda: tmp_path / "cache" / "syncnet_v2.json")


@pytest.fixture(scope="module")
def clip():
    """Two held-out sentences by a held-out espeak voice on the astronaut, about 8 s at 192 px, uint8 frames."""
    from lmgs_eval.data.bundled import synthesize_clip
    from lmgs_eval.data.bundled.generator import load_corpus

    corpus = load_corpus()
    c = synthesize_clip("astronaut", " ".join(corpus["cross-a"][1:3]), "espeak:en-us+f4", size=192, seed=777)
    return c.frames, c.audio


@pytest.fixture(scope="module")
def face_clip(clip):
    return FaceClip(clip[0])


def _weights_copy(tmp_path: Path) -> Path:
    folder = tmp_path / "weights"
    shutil.copytree(scorers.WEIGHTS, folder, ignore=shutil.ignore_patterns("*.md"))
    return folder


# ----------------------------------------------------------------------------- weights
def test_mesh_weights_load_and_match_their_manifest():
    onnx, meta = scorers.WEIGHTS / M.ONNX_NAME, scorers.WEIGHTS / M.JSON_NAME
    m = json.loads(meta.read_text())
    assert m["sha256"] == sha256_file(onnx)
    assert onnx.stat().st_size <= 20 * 2**20
    sc, why = scorers.load("mesh")
    assert sc is not None, why
    assert isinstance(sc, M.MeshScorer) and sc.name == "mesh-sync" and sc.sha256 == m["sha256"]
    assert sc.context == int(m["context"]) and sc.highpass == int(m["highpass"]) and sc.standin
    assert scorers.entry("mesh").record_name == "mesh-sync"
    assert scorers.weights_file("onnxruntime:mesh-sync") == onnx


def test_altered_mesh_weights_are_refused_naming_the_file(tmp_path):
    folder = _weights_copy(tmp_path)
    onnx = folder / M.ONNX_NAME
    data = bytearray(onnx.read_bytes())
    data[len(data) // 2] ^= 0xFF
    onnx.write_bytes(bytes(data))
    with pytest.raises(UserError, match=r"mesh_sync\.onnx: sha256 .* does not match .*mesh_sync\.json"):
        scorers.load_mesh(folder)
    (folder / M.JSON_NAME).unlink()
    sc, why = scorers.load_mesh(folder)
    assert sc is None and "mesh-sync weights not present" in why and str(folder) in why


# ----------------------------------------------------------------------------- the clip's face mesh
def test_face_clip_tracks_the_mesh_once_and_slices_share_it(face_clip, clip):
    lms = face_clip.mesh_landmarks()
    assert lms.shape == (len(clip[0]), 68, 3)
    assert np.isfinite(lms).all()  # the generated face is found on every frame
    width = np.linalg.norm(lms[:, 48] - lms[:, 54], axis=1)  # mouth corners, canonical frame (metres)
    assert 0.02 < np.median(width) < 0.08
    part = face_clip[5:20]
    assert part.mesh_landmarks() is not None and len(part) == 15
    np.testing.assert_array_equal(part.mesh_landmarks(), lms[5:20])
    assert np.shares_memory(part.mesh_landmarks(), lms)  # the base clip's points, not a second track


def test_mesh_landmarks_read_float_frames_as_uint8(clip):
    frames = clip[0][:12]
    a = FaceClip(frames).mesh_landmarks()
    b = FaceClip(frames.astype(np.float32) / 255.0).mesh_landmarks()
    np.testing.assert_allclose(a, b, atol=1e-9)


# ----------------------------------------------------------------------------- selection
def _manifest(folder: Path, loso: dict | None) -> None:
    j = folder / M.JSON_NAME
    m = json.loads(j.read_text())
    m.pop("loso", None)
    if loso is not None:
        m["loso"] = loso
    j.write_text(json.dumps(m))


def test_auto_puts_mesh_first_only_when_its_manifest_meets_acceptance(tmp_path, monkeypatch):
    folder = _weights_copy(tmp_path)
    monkeypatch.setattr(scorers, "WEIGHTS", folder)

    _manifest(folder, {"meets_acceptance": True, "clips": 11, "passes": 10, "per_clip": []})
    assert select.mesh_is_default()
    assert select.candidates("auto") == ["mesh", "landmark", "pixel"]
    assert select.SyncScorers("auto").names == ("mesh", "landmark", "pixel")
    ok, why = select.status()
    assert ok and why.startswith("default mesh-sync (stand-in)") and "import-syncnet" in why
    assert "leave-one-speaker-out" in why and "mesh_sync.json: 10/11 clips pass" in why

    _manifest(folder, {"meets_acceptance": False, "clips": 11, "passes": 6})
    assert not select.mesh_is_default()
    assert select.candidates("auto") == ["landmark", "pixel"]
    ok, why = select.status()
    assert ok and why.startswith("default landmark-sync") and "do not meet its acceptance" in why

    _manifest(folder, None)  # no figures recorded
    assert select.candidates("auto") == ["landmark", "pixel"]
    assert "not recorded" in select.status()[1]

    _manifest(folder, {"meets_acceptance": True})
    (folder / M.ONNX_NAME).unlink()  # a manifest without its weights does not make mesh the default
    assert select.candidates("auto") == ["landmark", "pixel"]
    assert select.status("mesh") == (False, "--sync mesh (weights not present)")

    (folder / M.JSON_NAME).write_text("{not json")
    assert not select.mesh_is_default()


def test_sync_mesh_is_a_choice_of_every_scoring_command():
    from lmgs_eval.cli import build_parser
    from lmgs_eval.commands._sync import SYNC_CHOICES
    from lmgs_eval.metrics.config import SYNC_CHOICES as CONFIG_CHOICES

    assert SYNC_CHOICES == CONFIG_CHOICES and "mesh" in SYNC_CHOICES
    assert select.candidates("mesh") == ["mesh"]
    assert build_parser().parse_args(["score", "--pred", "x.mp4", "--sync", "mesh"]).sync == "mesh"
    assert build_parser().parse_args(["sync-check", "x.mp4", "--sync", "mesh"]).sync == "mesh"


# ----------------------------------------------------------------------------- bench sync
def test_bench_sync_without_footage_is_one_line_exit_2(tmp_path):
    for where in (Path("/nonexistent"), tmp_path):  # not there; there but no *.mp4
        res = subprocess.run([sys.executable, "-m", "lmgs_eval", "bench", "sync", "--footage", str(where)],
                             capture_output=True, text=True, env={**os.environ, "PYTHONWARNINGS": "ignore"})
        assert res.returncode == 2, res.stderr
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and "--footage" in lines[0] and str(where) in lines[0], res.stderr
        assert "Traceback" not in res.stderr and res.stdout == ""


# ----------------------------------------------------------------------------- LSE
def test_mesh_lse_finds_sync_and_an_injected_delay(face_clip, clip):
    """``--sync mesh`` through the LSE metric on the generated clip's frames: offset 0 in sync, ``-k`` with
    the audio delayed by ``k`` frames (the shifted copies take their part of the clip's one mesh track)."""
    lse = LSE(select.SyncScorers("mesh"))
    audio = clip[1]
    r = lse.score(face_clip, audio, reference=True)
    assert r.available and r.spec.backend == "onnxruntime:mesh-sync", r.reason
    assert abs(r.values["offset"]) <= 1 and r.values["trusted"] is True, r.values
    assert any("dense face mesh" in n for n in r.notes) and any(n.startswith("standin: mesh-sync") for n in r.notes)
    for k in (5, -5):
        f, a = shifted(face_clip, audio, k)
        got = lse.score(f, a).values["offset"]
        assert abs(got + k) <= 1, (k, got)


@pytest.mark.slow
@pytest.mark.skipif(not FOOTAGE.is_dir(), reason="../shared/footage (real development clips) is not here")
def test_mesh_lse_on_real_footage_through_the_metric_suite():
    """A real in-sync clip (the 20 s news anchor) decoded from its file, scored by the metric suite with
    ``--sync mesh``: the offset is within a frame of 0. (The shipped weights are adapted on every clip of the
    footage; the held-out figures are ``lmgs-eval bench sync``'s.)"""
    from lmgs_eval.data.frames import FrameFile
    from lmgs_eval.metrics.config import SuiteConfig
    from lmgs_eval.metrics.metric_suite import MetricSuite
    from lmgs_eval.metrics.suite import clip_audio

    src = FrameFile(FOOTAGE / "anchor_de_20s.mp4")
    a16, why, _ = clip_audio(None, src)
    assert a16 is not None, why
    r = MetricSuite(SuiteConfig(sync="mesh")).lse(FaceClip(src), a16, in_sync=True, fps=src.fps)
    assert r.available and r.spec.backend == "onnxruntime:mesh-sync", r.reason
    assert abs(r.values["offset"]) <= 1, r.values


# ----------------------------------------------------------------------------- the recipe
def test_acceptance_needs_nine_in_eleven_no_trusted_failure_and_the_generated_figures():
    from lmgs_eval.metrics.sync.train.mesh import meets_acceptance

    gen_ok = {"clips": 10, "synced_offset0": 10, "shift_exact": 60, "shift_trials": 60}
    assert meets_acceptance({"clips": 11, "passes": 9, "confident_wrong": 0}, gen_ok)
    assert not meets_acceptance({"clips": 11, "passes": 8, "confident_wrong": 0}, gen_ok)
    assert not meets_acceptance({"clips": 11, "passes": 10, "confident_wrong": 1}, gen_ok)  # a confident wrong offset
    assert not meets_acceptance({"clips": 11, "passes": 11, "confident_wrong": 0}, {**gen_ok, "shift_exact": 59})
    assert not meets_acceptance({"clips": 11, "passes": 11, "confident_wrong": 0}, {**gen_ok, "synced_offset0": 9})
    assert meets_acceptance({"clips": 22, "passes": 18, "confident_wrong": 0}, None)  # 9 in 11 of more clips


def test_adapted_network_scores_the_same_exported_as_during_training(face_clip, clip, tmp_path):
    """A few adaptation steps on the generated clip (as a 'real' recording) and a shifted copy of it, scored
    through the torch network and then through its exported ONNX graph loaded like the shipped one: the same
    LSE, and the manifest carries what the loader reads."""
    from lmgs_eval.metrics.sync.scoring import lse
    from lmgs_eval.metrics.sync.train import mesh as T

    lms, audio = face_clip.mesh_landmarks(), clip[1]
    a = T.clip_inputs("a", lms, audio, seed=0)
    b = T.clip_inputs("b", lms[7:], audio[7 * 640:], seed=0)
    assert a["feat"].shape[:2] == (T.N_VARIANTS, len(lms)) and a["mfcc"].shape[:2] == (T.N_VARIANTS, 13)
    np.testing.assert_array_equal(a["feat"], T.clip_inputs("a", lms, audio, seed=0)["feat"])  # seeded draws
    base, sc = T.pretrained_net()
    net, final = T.adapt(base, [a], [b], seed=0, steps=3, segments=2, context=sc.context)
    assert set(final) >= {"ce", "con", "acc"}
    assert any((p1 - p0).abs().max() > 0 for p0, p1 in zip(base.parameters(), net.parameters()))
    torch_scorer = M.MeshScorer(T.TorchSession(net), "fold", sc.context, T.HIGHPASS)
    m = M.export(net, tmp_path, {"context": sc.context, "highpass": T.HIGHPASS})
    assert m["highpass"] == T.HIGHPASS and m["sha256"] == sha256_file(tmp_path / M.ONNX_NAME)
    onnx_scorer, why = scorers.load_mesh(tmp_path)
    assert onnx_scorer is not None, why
    r0 = lse(None, audio, scorer=torch_scorer, lms=lms)
    r1 = lse(None, audio, scorer=onnx_scorer, lms=lms)
    assert r0.values["offset"] == r1.values["offset"]
    assert abs(r0.values["lse_c"] - r1.values["lse_c"]) < 1e-4 and abs(r0.values["lse_d"] - r1.values["lse_d"]) < 1e-4


@pytest.mark.slow
@pytest.mark.skipif(not FOOTAGE.is_dir(), reason="../shared/footage (real development clips) is not here")
def test_a_held_out_speaker_is_found_in_sync_by_a_fold_that_never_saw_them():
    """One leave-one-speaker-out fold of the shipped recipe (the news anchor held out): its model finds the
    clip in sync, every injected delay, its own speech above every other speaker's, and trusts it."""
    from lmgs_eval.data.lip_corpus import real_recordings
    from lmgs_eval.metrics.sync.train import mesh as T

    recs = real_recordings(FOOTAGE)
    rows = T.fold_rows(recs, ["anchor_de_20s"])
    assert [r["clip"] for r in rows] == ["anchor_de_20s"] and "anchor_de_20s" not in rows[0]["trained_on"]
    assert rows[0]["passes"], rows[0]


def test_the_dlib_comparison_reads_a_footage_folder_as_the_bench_does(clip, tmp_path, monkeypatch):
    """``bench sync``'s comparison row: a folder of in-sync videos (two generated ones here) tracked by the lip
    tracker and by dlib at 25 fps (both cached outside the repository), scored by the shipped landmark scorer
    with the other video's speech as the other speaker's: the clip in sync is found at 0 +- 1 and its figures
    carry every key of the table."""
    from lmgs_eval.data.lip_corpus import real_recordings
    from lmgs_eval.data.video import write_video
    from lmgs_eval.metrics.sync.train import mesh as T

    monkeypatch.setenv("LMGS_LIPS_CACHE", str(tmp_path / "cache"))
    frames, audio = clip
    footage = tmp_path / "footage"
    footage.mkdir()
    write_video(footage / "a.mp4", frames, 25, audio)
    other = np.roll(audio, len(audio) // 2)  # the same voice elsewhere in its text: out of sync with the frames
    write_video(footage / "b.mp4", frames, 25, other)
    recs = real_recordings(footage)
    assert [r.name for r in recs] == ["a", "b"] and T.folds(recs) == ["a", "b"]
    rows = T.landmark_rows(recs, footage)
    a = rows[0]
    assert a["clip"] == "a" and abs(a["offset"]) <= 1, a
    assert set(a) >= {"offset", "shifts", "lse_c", "other_lse_c_max", "separation", "trusted", "passes", "confident_wrong"}
    assert len(list((tmp_path / "cache").glob("a-*-dlib-v1.npy"))) == 1  # cached by content
