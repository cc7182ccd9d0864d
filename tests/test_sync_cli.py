"""``--sync`` on every command that scores, ``lmgs-eval weights`` and ``metrics`` naming the default scorer."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lmgs_eval.cli import build_parser
from lmgs_eval.metrics.config import SuiteConfig
from lmgs_eval.metrics.metric_suite import MetricSuite
from lmgs_eval.metrics.sync import scorers, select
from tests.conftest import run_cli

SCORING = ("score", "self", "cross", "stress")


def _args(cmd: str, *extra: str) -> list[str]:
    return [cmd, *(["--pred", "x.mp4"] if cmd == "score" else []), *extra]


@pytest.fixture(autouse=True)
def _auto_without_official(monkeypatch, tmp_path):
    # other test modules import a random-weight SyncNet into the session's cache; these tests are about
    # the machine without the official weights
    monkeypatch.setattr(scorers, "syncnet_manifest_path", lambda: tmp_path / "weights" / "syncnet_v2.json")


@pytest.mark.parametrize("cmd", SCORING)
def test_every_scoring_command_takes_each_sync_choice(cmd):
    parser = build_parser()
    assert parser.parse_args(_args(cmd)).sync == "auto"
    for choice in ("auto", "landmark", "pixel", "syncnet-v2"):
        assert parser.parse_args(_args(cmd, "--sync", choice)).sync == choice


@pytest.mark.parametrize("cmd", SCORING)
def test_bad_sync_value_is_one_line_and_exit_2(cmd):
    rc, out, err = run_cli(*_args(cmd, "--sync", "wav2lip"))
    assert rc == 2 and out == ""
    assert "--sync" in err and "invalid choice: 'wav2lip'" in err and "Traceback" not in err


def test_an_unknown_sync_choice_is_refused_when_the_suite_is_made():
    from lmgs_eval.errors import UserError

    with pytest.raises(UserError, match="--sync 'foo'"):
        MetricSuite(SuiteConfig(sync="foo"))


def test_auto_is_the_landmark_scorer_without_official_weights():
    assert not scorers.syncnet_manifest_path().is_file()
    assert select.candidates("auto") == ["landmark", "pixel"]
    assert select.candidates("pixel") == ["pixel"]
    ok, why = select.status()
    assert ok and why.startswith("default landmark-sync") and "import-syncnet" in why


def test_selection_reaches_lse_and_auto_falls_back_when_a_scorer_cannot_run():
    rng = np.random.default_rng(0)
    crops = rng.uniform(0, 255, (60, 224, 224, 3)).astype(np.float32)
    audio = rng.standard_normal(60 * 640).astype(np.float32) * 0.1
    r = MetricSuite(SuiteConfig(sync="landmark")).lse(None, audio, crops=crops)  # crops alone carry no landmarks
    assert not r.available and "landmark" in r.reason
    r = MetricSuite(SuiteConfig(sync="auto")).lse(None, audio, crops=crops)  # so auto scores with the pixel scorer
    assert r.available and r.spec.backend == "onnxruntime:bundled-sync"
    assert any(n.startswith("auto: onnxruntime:landmark-sync was unavailable") for n in r.notes)
    assert r.values["trusted"] is False  # random crops: the pixel scorer's number is kept, marked untrusted


def test_weights_prints_the_cache_and_metrics_names_the_default():
    rc, out, _ = run_cli("weights")
    assert rc == 0
    assert f"weights cache: {scorers.syncnet_manifest_path().parent}" in out
    assert "landmark-sync" in out and "not imported" in out
    rc, out, _ = run_cli("metrics", "--json")
    row = {r["name"]: r for r in json.loads(out)}["lse"]
    assert row["available"] and row["detail"].startswith("default landmark-sync") and "not imported" in row["detail"]


def test_score_prints_one_line_when_lse_is_not_trusted(tmp_path):
    """A still face with speech: the scorer's LSE-C is that of its own still-face control, so it is not trusted."""
    from lmgs_eval.data.bundled import synthesize_clip
    from lmgs_eval.data.video import write_video

    clip = synthesize_clip("astronaut", "Seven bright lamps were lit.", "espeak:en-us+f4", size=160, seed=5)
    n = len(clip.frames)
    assert n >= 2 * 21 + 6
    write_video(tmp_path / "still.mp4", np.repeat(clip.frames[:1], n, 0), 25, clip.audio)
    rc, out, err = run_cli("score", "--pred", str(tmp_path / "still.mp4"), "--metrics", "lse")
    assert rc == 0, err
    assert "NOT trusted" in out
    lines = [ln for ln in err.splitlines() if "not trusted" in ln]
    assert len(lines) == 1 and "lmgs-eval weights import-syncnet" in lines[0]


def test_sync_check_finds_injected_delays_on_an_in_sync_clip(tmp_path):
    """``sync-check`` on a held-out generated clip written as mp4 (held-out voice and texts)."""
    from lmgs_eval.data.bundled import synthesize_clip
    from lmgs_eval.data.bundled.generator import load_corpus
    from lmgs_eval.data.video import write_video
    from tests.conftest import write_pcm_wav

    corpus = load_corpus()
    clip = synthesize_clip("hopper", " ".join(corpus["cross-a"][2:4]), "espeak:en-us+f4", size=192, seed=11)
    other = synthesize_clip("astronaut", " ".join(corpus["cross-b"][:2]), "espeak:en-gb-x-rp+f4", size=64, seed=12)
    write_video(tmp_path / "clip.mp4", clip.frames, 25, clip.audio)
    write_pcm_wav(tmp_path / "other.wav", other.audio, 16000)
    rc, out, err = run_cli("sync-check", str(tmp_path / "clip.mp4"), "--other-audio", str(tmp_path / "other.wav"), "--json")
    assert rc == 0, err
    res = json.loads(out)
    assert res["backend"] == "onnxruntime:landmark-sync"
    assert res["own"]["offset"] == 0 and res["own"]["trusted"] is True
    assert {int(k): v for k, v in res["shifts"].items()} == {-10: 10, -5: 5, 5: -5, 10: -10}
    assert res["own_above_every_other"] is True
