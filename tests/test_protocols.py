"""The protocols end to end through the CLI on a tiny bundled subject (64x64, 2 s)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli, write_pcm_wav
from lmgs_eval.results import load_records, validate

SUBJECT = "astronaut-64px-2s"
FAST = ["--set", "train.static_steps=40", "--set", "train.dynamic_steps=40", "--set", "train.landmark_steps=20",
        "--set", "train.densify_every=20"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """One self-driven run of lmgs (tiny schedule) plus the ground-truth row."""
    root = tmp_path_factory.mktemp("results")
    rc, out, err = run_cli("self", "--subject", SUBJECT, "--results", str(root), "--no-progress", *FAST)
    assert rc == 0, err
    return root, out, err


def test_self_writes_valid_records_renders_and_rows(store):
    root, out, _ = store
    records, warnings = load_records(root)
    assert warnings == []
    for r in records:
        assert validate(r) == []
    controls = [r for r in records if r.method.family == "control"]
    assert sorted(r.method.name for r in controls) == [
        "control:gt-audio+10", "control:gt-audio+5", "control:gt-audio-10", "control:gt-audio-5",
        "control:gt-other-audio", "control:still-frame"]
    assert all(r.protocol.name == "calibration" and r.method.control.targets for r in controls)
    by = {r.method.name: r for r in records if r.method.family != "control"}
    assert set(by) == {"ground-truth", "plate-reference", "lmgs"}
    for r in by.values():
        render = root / r.artefacts["render"].path
        assert render.exists() and render.stat().st_size > 0
    lm = by["lmgs"]
    assert lm.subject.bundled and lm.subject.standin
    assert lm.to_dict()["protocol"] == {"name": "self", "version": "1", "clip": "test", "split": "test", "n_frames": 5}
    assert lm.config["train"]["dynamic_steps"] == 40  # --set reached the config and its hash
    assert lm.cost.fps > 0 and lm.cost.n_gaussians > 0 and lm.cost.train_seconds > 0
    assert 0 <= lm.cost.others_cpu_share <= 1  # how busy the host was while the FPS was timed
    assert any("GeneFace" in s for s in lm.method.standins)
    assert any(n.startswith("spatial enhancement selected") and "theta = 0.6" in n for n in lm.notes)
    assert lm.metrics["lpips"].backend in ("stlpips-alex", "lpips-alex")
    # verify re-hashes the inputs too: the subject's ground truth and the LPIPS weights
    assert lm.artefacts["ground_truth"].path.endswith("manifest.json")
    assert any(k.startswith("weights:") and "lpips" in k for k in lm.artefacts)
    assert by["ground-truth"].metrics["psnr"].value == 100.0  # identical frames: the cap
    assert by["ground-truth"].metrics["lpips"].value == pytest.approx(0.0, abs=1e-6)
    assert "Ground Truth" in out and "Ours (lmgs)" in out


def test_the_lmgs_row_scores_the_checkpoints_render_of_the_test_split(store):
    """The record's PSNR is its model's render of the test split against the test frames: the
    checkpoint the record names, reloaded and rendered again, scores the same with skimage's PSNR."""
    from skimage.metrics import peak_signal_noise_ratio

    from baselines.protocol import create_method
    from lmgs_eval.commands._common import parse_overrides
    from lmgs_eval.convert import driving_from_clip, subject_to_clip
    from lmgs_eval.data.registry import find_subject
    from lmgs.fileio import sha256_file

    root, _, _ = store
    lm = next(r for r in load_records(root)[0] if r.method.name == "lmgs")
    ck = Path(lm.artefacts["checkpoint"].path)
    assert sha256_file(ck) == lm.artefacts["checkpoint"].sha256
    subject = find_subject(SUBJECT, None, progress=False)
    method = create_method("lmgs", subject=subject, preset="quick", **parse_overrides(FAST[1::2]))
    assert method.describe().config_hash == lm.config_hash
    method.fit(subject_to_clip(subject, subject.train_ids), seed=0, workdir=ck.parent, progress=False)  # reloads
    test = subject_to_clip(subject, subject.test_ids)
    frames = method.render(driving_from_clip(test))
    assert frames.shape == test.frames.shape and frames.dtype == np.uint8
    want = [peak_signal_noise_ratio(g, f, data_range=255) for g, f in zip(test.frames, frames)]
    assert lm.metrics["psnr"].value == pytest.approx(np.mean(want), abs=1e-6)
    assert np.mean(want) < 60  # a render, not the ground truth


def test_the_plate_reference_row_is_the_ground_truth_head_on_the_subjects_plate(store):
    # recomputed from the subject's files (parsing, torso_imgs, bc.jpg, gt_imgs) with skimage's PSNR
    from skimage.metrics import peak_signal_noise_ratio

    from lmgs_eval.data.images import to_u8
    from lmgs_eval.data.registry import find_subject

    root, out, _ = store
    ref = next(r for r in load_records(root)[0] if r.method.name == "plate-reference")
    assert ref.method.family == "reference" and ref.protocol.name == "self"
    subject = find_subject(SUBJECT, None, progress=False)
    bc = subject.background()
    want = []
    for i in subject.test_ids:
        gt = subject.frame(i)
        torso = subject.torso(i)
        plate = to_u8(torso[..., :3] * torso[..., 3:] + bc * (1 - torso[..., 3:]))
        head = np.all(subject.parsing(i) == (255, 0, 0), axis=-1)
        assert 0 < head.mean() < 1
        comp = np.where(head[..., None], gt, plate)
        want.append(peak_signal_noise_ratio(gt, comp, data_range=255))
    assert ref.metrics["psnr"].value == pytest.approx(np.mean(want), abs=1e-6)
    assert ref.metrics["psnr"].value < 100
    assert "GT head on plate" in out
    lines = out.splitlines()
    assert [k for k, l in enumerate(lines) if "Ground Truth" in l][0] < [k for k, l in enumerate(lines) if "GT head on plate" in l][0]


def test_rerun_is_skipped_and_resumes(store):
    root, _, _ = store
    before = sorted(p.name for p in root.rglob("*.json"))
    rc, _, err = run_cli("self", "--subject", SUBJECT, "--results", str(root), "--no-progress", *FAST)
    assert rc == 0 and "already in" in err
    assert sorted(p.name for p in root.rglob("*.json")) == before


def test_table_and_verify_from_the_store(store, tmp_path):
    root, _, _ = store
    rc, out, _ = run_cli("table", "--results", str(root), "--out", str(tmp_path / "t"))
    assert rc == 0 and "Ground Truth" in out
    assert (tmp_path / "t" / "table1_self.md").exists() and (tmp_path / "t" / "table1_self.tex").exists()
    rc, _, _ = run_cli("verify", str(root))
    assert rc == 0


def test_a_second_config_keeps_the_first_configs_render(store, tmp_path):
    # a re-run under another config once overwrote the render an older record hashes
    import shutil

    root, _, _ = store
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    rc, _, err = run_cli("self", "--subject", SUBJECT, "--results", str(copy), "--no-progress", *FAST,
                         "--set", "train.lambda_lips=0.5")
    assert rc == 0, err
    runs = [r for r in load_records(copy)[0] if r.method.name == "lmgs"]
    assert len({r.config_hash for r in runs}) == 2
    paths = {r.artefacts["render"].path for r in runs}
    assert len(paths) == 2 and all(r.config_hash[:8] in r.artefacts["render"].path for r in runs)
    rc, out, err = run_cli("verify", str(copy))
    assert rc == 0, out + err


def test_verify_catches_a_changed_render(store, tmp_path):
    import shutil

    root, _, _ = store
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    rec = next(r for r in load_records(copy)[0] if r.method.name == "lmgs")
    with open(copy / rec.artefacts["render"].path, "ab") as f:
        f.write(b"tampered")
    rc, out, err = run_cli("verify", str(copy))
    assert rc == 1 and "changed" in (out + err)


def test_interrupted_run_leaves_no_partial_record(tmp_path, monkeypatch):
    from lmgs_eval.metrics.metric_suite import MetricSuite

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(MetricSuite, "score", boom)
    rc, _, err = run_cli("self", "--subject", SUBJECT, "--results", str(tmp_path), "--no-progress", *FAST)
    assert rc == 130 and "interrupted" in err
    assert list(tmp_path.rglob("*.json")) == []
    assert not [p for p in tmp_path.rglob("*") if ".tmp-" in p.name]


def test_cross_with_user_audio_and_a_bad_file(tmp_path):
    t = np.arange(int(44100 * 1.2)) / 44100
    tone = 0.3 * np.sin(2 * np.pi * 220 * t) * (0.5 + 0.5 * np.sin(2 * np.pi * 3 * t))
    good = tmp_path / "good.wav"
    write_pcm_wav(good, np.stack([tone, tone], 1), 44100)  # stereo, 44.1 kHz: accepted with notes
    empty = tmp_path / "empty.wav"
    empty.write_bytes(b"")
    short = tmp_path / "short.wav"
    write_pcm_wav(short, np.zeros(1000), 16000)
    res = tmp_path / "res"
    rc, out, err = run_cli("cross", "--audio", str(good), str(empty), str(short), "--subject", SUBJECT,
                           "--results", str(res), "--no-progress", *FAST)
    assert rc == 1
    assert "empty.wav" in err and "short.wav" in err and "shorter than 5 frames" in err
    records, _ = load_records(res)
    assert len(records) == 1
    r = records[0]
    sha = hashlib.sha256(good.read_bytes()).hexdigest()
    assert r.protocol.name == "cross" and r.protocol.clip == f"good-{sha[:12]}"
    assert r.protocol.n_frames == 30
    assert r.protocol.split == str(good.resolve()) and Path(r.protocol.split).is_absolute()
    assert r.to_dict()["artefacts"]["driving_audio"] == {"path": str(good.resolve()), "sha256": sha}
    assert any("mixed to mono" in n for n in r.notes) and any("44100" in n for n in r.notes)
    assert validate(r) == []


def test_cross_clips_are_their_audio_not_their_name(tmp_path, monkeypatch):
    # x/a.wav and y/a.wav differ: two clips; a user's A.wav is not the bundled clip A; the same
    # audio under two names is one clip. A deleted render is made again on the next run.
    t = np.arange(16000) / 16000
    (tmp_path / "x").mkdir()
    (tmp_path / "y").mkdir()
    write_pcm_wav(tmp_path / "x" / "a.wav", 0.3 * np.sin(2 * np.pi * 220 * t), 16000)
    write_pcm_wav(tmp_path / "y" / "a.wav", 0.3 * np.sin(2 * np.pi * 330 * t), 16000)
    write_pcm_wav(tmp_path / "A.wav", 0.3 * np.sin(2 * np.pi * 440 * t), 16000)
    (tmp_path / "same.wav").write_bytes((tmp_path / "x" / "a.wav").read_bytes())
    res = tmp_path / "res"
    monkeypatch.chdir(tmp_path)
    args = ["cross", "--audio", "x/a.wav", "y/a.wav", "A.wav", "same.wav", "--subject", SUBJECT, "--results", str(res),
            "--no-progress", *FAST]
    rc, out, err = run_cli(*args)
    assert rc == 0, err
    clips = sorted(r.protocol.clip for r in load_records(res)[0])
    assert len(clips) == 3 and "A" not in clips and sum(c.startswith("a-") for c in clips) == 2
    assert all(Path(r.protocol.split).is_absolute() for r in load_records(res)[0])
    rc, out, err = run_cli(*args)
    assert rc == 0 and "already in" in err
    victim = next(r for r in load_records(res)[0] if r.protocol.clip.startswith("A-"))
    (res / victim.artefacts["render"].path).unlink()
    rc, out, err = run_cli(*args)
    assert rc == 0 and "is missing" in err, err
    assert (res / victim.artefacts["render"].path).is_file()
    rc, out, err = run_cli("verify", str(res))
    assert rc == 0, out + err


def test_cross_bundled_clips_score_lmd_against_their_ground_truth_or_say_why(tmp_path):
    rc, _, err = run_cli("cross", "--subject", SUBJECT, "--results", str(tmp_path), "--no-progress", *FAST)
    assert rc == 0, err
    records, _ = load_records(tmp_path)
    assert sorted(r.protocol.clip for r in records) == ["A", "B"]
    from lmgs_eval.data.registry import find_subject

    subject = find_subject(SUBJECT, progress=False)
    for r in records:
        n_gt = len(list((subject.root / "cross" / r.protocol.clip / "gt_imgs").glob("*.jpg")))
        m = r.metrics["lmd"]
        # every frame of the clip is paired with its own ground truth ...
        assert m.n_original == r.protocol.n_frames == n_gt == len(m.per_item)
        # ... and at 64x64 no detector finds a face: no number, and the record says why
        assert m.value is None and m.n_effective == 0
        assert any(f.startswith("unavailable: no face found") for f in m.flags)


def test_unknown_method_and_subject(tmp_path):
    rc, _, err = run_cli("self", "--method", "nope", "--results", str(tmp_path))
    assert rc == 2 and "unknown method 'nope'" in err and "lmgs" in err
    rc, _, err = run_cli("self", "--subject", "nobody", "--results", str(tmp_path))
    assert rc == 2 and "unknown subject" in err and "astronaut" in err


def test_method_all_is_every_method_of_the_field_without_the_ablation_rows():
    """``--method all`` expands in place to the registered methods of the field (the nine compared and
    lmgs), not lmgs's ablation variants nor the external prefix; a method also named stays once."""
    import argparse

    from lmgs_eval.cli import build_parser
    from lmgs_eval.commands._common import run_config

    args = build_parser().parse_args(["self", "--method", "wav2lip", "--method", "all", "--results", "/tmp/unused"])
    methods = run_config(args).methods
    from baselines.protocol import field_methods

    # other tests may register methods of their own in this process: compare with the registry's field
    assert isinstance(args, argparse.Namespace) and methods == ("wav2lip",) + tuple(m for m in field_methods() if m != "wav2lip")
    assert {"lmgs", "talkinggaussian", "ernerf", "radnerf", "adnerf", "geneface", "gaussiantalker", "degstalk", "ip_lap"} <= set(methods)
    assert not any(m.startswith("lmgs-") or m.startswith("external:") for m in methods)


def test_a_training_that_diverges_is_one_line_and_exit_1(tmp_path, monkeypatch):
    import lmgs_eval.runner as runner
    from lmgs.train import TrainingDiverged

    def diverge(method, train, run, progress, workdir=None):
        raise TrainingDiverged("training collapsed at step 1040 (dynamic stage): the mean loss of the last 25 steps is 3.9x ...")

    monkeypatch.setattr(runner, "fit_method", diverge)
    rc, out, err = run_cli("self", "--subject", SUBJECT, "--results", str(tmp_path), "--no-progress", *FAST)
    assert rc == 1 and "lmgs-eval self: training failed: training collapsed at step 1040" in err
    assert "Traceback" not in err and not [r for r in load_records(tmp_path)[0] if r.method.name == "lmgs"]  # no record made of it


def test_timed_render_reports_the_median_of_repeats(monkeypatch):
    """FPS comes from the median of up to 3 timed renders (I/O outside), first-frame latency from the warm-up."""
    import itertools

    from lmgs.types import DrivingAudio
    from lmgs_eval import hosttime
    from lmgs_eval import runner as protocols

    class Toy:
        calls = 0

        def describe(self):
            return type("I", (), {"name": "toy"})()

        def render(self, driving):
            Toy.calls += 1
            return np.zeros((driving.n_frames, 4, 4, 3), np.uint8)

    # perf_counter pairs: warm-up 0.3 s, then repeats of 5, 1 and 3 s
    ticks = itertools.chain([0.0, 0.3], [10.0, 15.0], [20.0, 21.0], [30.0, 33.0])
    monkeypatch.setattr(hosttime, "probe_ms", lambda: 1.0)  # the host probe is not what is timed here
    monkeypatch.setattr(protocols.time, "perf_counter", lambda: next(ticks))
    monkeypatch.setattr(protocols, "REPEAT_BUDGET_S", 100.0)
    driving = DrivingAudio(audio=np.zeros(50 * 640, np.float32))
    frames, rc = protocols.timed_render(Toy(), driving)
    assert frames.shape[0] == 50 and Toy.calls == 4 and rc["repeats"] == 3
    assert rc["render_seconds"] == pytest.approx(3.0) and rc["fps"] == pytest.approx(50 / 3.0)
    assert rc["first_frame_ms"] == pytest.approx(1000 * 0.3 / 3)
    # a slow method is timed once: a second run would not fit in the budget
    ticks2 = itertools.chain([0.0, 0.3], [10.0, 25.0])
    monkeypatch.setattr(protocols.time, "perf_counter", lambda: next(ticks2))
    monkeypatch.setattr(protocols, "REPEAT_BUDGET_S", 20.0)
    _, rc = protocols.timed_render(Toy(), driving)
    assert rc["repeats"] == 1 and rc["fps"] == pytest.approx(50 / 15.0)


def _handmade_renders(folder: Path, offset: int = 0, drop: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The tiny subject's test frames, brightened by ``offset`` levels, written as numbered PNGs: ``(gt, pred)``."""
    import cv2

    from lmgs_eval.data.images import to_u8
    from lmgs_eval.data.registry import find_subject
    from lmgs_eval.convert import subject_to_clip

    subject = find_subject(SUBJECT, progress=False)
    gt = to_u8(subject_to_clip(subject, subject.test_ids, progress=False).frames)
    pred = np.clip(gt.astype(np.int16) + offset, 0, 255).astype(np.uint8)
    folder.mkdir(parents=True)
    for i, f in enumerate(pred[: len(pred) - drop]):
        cv2.imwrite(str(folder / f"{i}.png"), f[..., ::-1])  # ER-NeRF's test renders: 0.png, 1.png, ...
    return gt, pred


def test_external_scores_a_handmade_renders_folder(tmp_path):
    from skimage.metrics import peak_signal_noise_ratio

    renders = tmp_path / "ernerf_renders"
    gt, pred = _handmade_renders(renders, offset=12)
    (renders / "cost.json").write_text(json.dumps({"fps": 34.5, "train_hours": 2.0, "device": "RTX 3090"}))
    root = tmp_path / "results"
    rc, out, err = run_cli("self", "--subject", SUBJECT, "--method", "external:ernerf", "--renders", str(renders),
                           "--results", str(root), "--no-progress")
    assert rc == 0, err
    rec = next(r for r in load_records(root)[0] if r.method.name == "external:ernerf")
    assert validate(rec) == [] and rec.method.family == "external"
    expected = np.mean([peak_signal_noise_ratio(g, p, data_range=255) for g, p in zip(gt, pred)])
    assert rec.metrics["psnr"].value == pytest.approx(expected, abs=1e-3)
    assert rec.metrics["psnr"].n_original == len(gt) == rec.protocol.n_frames
    # cost from the sidecar only: given figures kept, missing ones empty, never guessed
    assert rec.cost.fps == 34.5 and rec.cost.train_seconds == 7200.0
    assert rec.cost.n_gaussians is None and rec.cost.model_mb is None
    assert rec.cost.others_cpu_share is None  # nothing was timed here


def test_external_with_a_missing_frame_is_a_clear_error(tmp_path):
    renders = tmp_path / "short_renders"
    gt, _ = _handmade_renders(renders, drop=1)
    rc, out, err = run_cli("self", "--subject", SUBJECT, "--method", "external:ernerf", "--renders", str(renders),
                           "--results", str(tmp_path / "results"), "--no-progress")
    assert rc != 0 and "Traceback" not in err
    assert str(renders) in err and f"{len(gt) - 1} frames" in err and f"has {len(gt)}" in err
    assert not any(r.method.name == "external:ernerf" for r in load_records(tmp_path / "results")[0])


@pytest.mark.parametrize("sidecar, words", [
    ('{"fps": "fast"}', "'fps' must be a non-negative number"),
    ('{"train_hours": -1}', "'train_hours' must be a non-negative number"),
    ('{"speed": 3}', "unknown keys ['speed']"),
    ('{"fps": 3', "not valid JSON"),
])
def test_external_sidecar_errors_name_the_file(tmp_path, sidecar, words):
    from baselines.external import ExternalRenders
    from lmgs.errors import InputError

    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "cost.json").write_text(sidecar)
    with pytest.raises(InputError) as e:
        ExternalRenders("x", tmp_path / "r")
    assert str(tmp_path / "r" / "cost.json") in str(e.value) and words in str(e.value)


def test_a_model_or_record_of_other_data_of_the_same_subject_is_not_reused(tmp_path):
    from types import SimpleNamespace

    from lmgs_eval.errors import UserError
    from lmgs_eval.results.records import RunId
    from lmgs_eval.runner import DATA_MARKER, claim_model_dir

    subject = SimpleNamespace(name="mine", root=tmp_path / "mine")
    subject.root.mkdir()
    (subject.root / "manifest.json").write_text('{"a": 1}')
    run = RunId(subject, SimpleNamespace(name="lmgs", config_hash="abc"))
    work = tmp_path / "models" / "lmgs" / "abc-seed0"

    def claim():
        with claim_model_dir(work, run):
            pass

    claim()  # a new folder takes the data's hash
    (work / "model.pt").write_bytes(b"model")
    first = (work / DATA_MARKER).read_text()
    claim()  # same data: reused
    (subject.root / "manifest.json").write_text('{"a": 2}')  # re-processed
    with pytest.raises(UserError, match=r"abc-seed0: a model trained on other data of subject 'mine'"):
        claim()
    assert (work / DATA_MARKER).read_text() == first and (work / "model.pt").exists()
    (work / DATA_MARKER).unlink()  # a folder from before the marker: taken to be of the current data
    claim()
    assert (work / DATA_MARKER).read_text() != first


def test_a_store_of_other_data_of_the_subject_stops_self_with_one_line(store, tmp_path):
    import shutil

    root, _, _ = store
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    gt = next(p for p in copy.rglob("*.json") if "ground-truth" in p.name)
    rec = json.loads(gt.read_text())
    rec["subject"]["sha256"] = "0" * 64
    gt.write_text(json.dumps(rec))
    rc, _, err = run_cli("self", "--subject", SUBJECT, "--results", str(copy), "--no-progress", *FAST)
    assert rc != 0 and "made on other data of subject 'astronaut-64px-2s'" in err and str(gt) in err
    assert "Traceback" not in err and json.loads(gt.read_text())["subject"]["sha256"] == "0" * 64
