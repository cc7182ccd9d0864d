"""Bad input to the scoring commands (``score``, ``sync-check``, ``weights import-syncnet``): exit code 2, one line
naming the file or flag, nothing written; and scoring reads a high-resolution clip without holding it.

The rule for a metric that cannot be computed: reported as unavailable with its reason while the
others are scored; an error (one line, exit 2) when none of the metrics asked for can be.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from conftest import one_line_error, run_cli, write_pcm_wav
from test_bad_inputs import world as _world  # noqa: F401  (a results store and the cache, both to stay unchanged)


@pytest.fixture
def world(_world):
    """:func:`test_bad_inputs.world`, after this process has loaded an ONNX Runtime session once (onnxruntime
    makes its own folder under the cache then: not a file of the commands)."""
    from lmgs_eval.metrics.sync.scorers import load

    load("landmark")
    return _world


def _tone(seconds: float, sr: int = 16000) -> np.ndarray:
    t = np.arange(int(seconds * sr)) / sr
    return 0.3 * np.sin(2 * np.pi * 220 * t) * (0.6 + 0.4 * np.sin(2 * np.pi * 3 * t))


def _video(path: Path, n: int = 12, size: int = 64, audio: bool = True) -> Path:
    """A short faceless 25 fps clip (noise), with a tone as its audio track unless ``audio`` is False."""
    from lmgs_eval.data.video import write_video

    frames = np.random.default_rng(0).integers(0, 256, (n, size, size, 3), dtype=np.uint8)
    write_video(path, frames, 25, _tone(n / 25) if audio else None, 16000)
    return path


def _empty_wav(path: Path) -> Path:
    write_pcm_wav(path, np.zeros(0), 16000)
    return path


# ----------------------------------------------------------------------------- empty and short audio
def test_an_empty_wav_as_the_audio_of_score_and_sync_check(world):
    tmp, res, snap = world
    v = _video(tmp / "v.mp4", audio=False)
    empty = _empty_wav(tmp / "empty.wav")
    before = snap()
    rc, out, err = run_cli("score", "--pred", str(v), "--audio", str(empty), "--metrics", "lse")
    one_line_error(rc, out, err, str(empty), "holds no samples")
    rc, out, err = run_cli("sync-check", str(v), "--audio", str(empty))
    one_line_error(rc, out, err, str(empty), "holds no samples")
    assert out == "" and snap() == before


def test_audio_too_short_for_one_lse_window_names_its_length_and_the_minimum(world):
    tmp, res, snap = world
    v = _video(tmp / "v.mp4", audio=False)
    short = tmp / "short.wav"
    write_pcm_wav(short, _tone(0.1), 16000)
    before = snap()
    for argv in (["score", "--pred", str(v), "--audio", str(short), "--metrics", "lse"],
                 ["sync-check", str(v), "--audio", str(short)]):
        rc, out, err = run_cli(*argv)
        one_line_error(rc, out, err, str(short), "0.10 s", "at least 0.24 s")
    assert snap() == before


def test_lse_on_audio_shorter_than_a_window_is_unavailable_not_an_index_error():
    from lmgs_eval.metrics.metric_suite import MetricSuite

    crops = np.zeros((8, 224, 224, 3), np.uint8)
    for n in (0, 100, 3000):
        r = MetricSuite().lse(None, np.zeros(n, np.float32), crops=crops)
        assert not r.available and "too short" in r.reason


# ----------------------------------------------------------------------------- the other-speech control
@pytest.mark.parametrize("kind, words", [
    ("empty", ["holds no samples"]),
    ("short", ["--other-audio", "0.50 s", "at least 2.00 s"]),
    ("silent", ["--other-audio", "silent"]),
])
def test_sync_check_other_audio_that_cannot_be_a_control(world, kind, words):
    tmp, res, snap = world
    v = _video(tmp / "v.mp4", n=100)
    other = tmp / f"{kind}.wav"
    write_pcm_wav(other, {"empty": np.zeros(0), "short": _tone(0.5), "silent": np.zeros(3 * 16000)}[kind], 16000)
    before = snap()
    rc, out, err = run_cli("sync-check", str(v), "--other-audio", str(other))
    one_line_error(rc, out, err, str(other), *words)
    assert out == "" and snap() == before


# ----------------------------------------------------------------------------- a metric asked for and unavailable
def test_lse_alone_on_a_video_without_audio_is_an_error(world):
    tmp, res, snap = world
    v = _video(tmp / "v.mp4", audio=False)
    before = snap()
    for extra in ([], ["--json"]):
        rc, out, err = run_cli("score", "--pred", str(v), "--metrics", "lse", *extra)
        one_line_error(rc, out, err, str(v), "nothing could be scored", "lse unavailable", "no audio track")
        assert out == ""
    rc, out, err = run_cli("score", "--pred", str(v))  # no --gt: LSE is all there is to score
    one_line_error(rc, out, err, "no audio track")
    assert snap() == before


def test_lse_unavailable_beside_other_metrics_is_reported_and_the_others_scored(world):
    tmp, res, snap = world
    v = _video(tmp / "v.mp4", audio=False)
    rc, out, err = run_cli("score", "--pred", str(v), "--gt", str(v), "--metrics", "psnr,lse")
    assert rc == 0, err
    assert "psnr" in out and "lse" in out and "unavailable: " in out and "no audio track" in out
    rc, out, err = run_cli("score", "--pred", str(v), "--gt", str(v), "--metrics", "psnr,lse", "--json")
    rec = json.loads(out)
    assert rec["results"]["psnr"]["available"] and rec["results"]["psnr"]["value"] == 100.0
    assert not rec["results"]["lse"]["available"] and "no audio track" in rec["results"]["lse"]["reason"]


def test_sync_check_on_a_faceless_video_is_an_error(world):
    tmp, res, snap = world
    v = _video(tmp / "noise.mp4", n=30)
    before = snap()
    rc, out, err = run_cli("sync-check", str(v))
    one_line_error(rc, out, err, str(v), "LSE unavailable", "no face")
    rc, out, err = run_cli("score", "--pred", str(v), "--metrics", "lse")
    one_line_error(rc, out, err, str(v), "lse unavailable", "no face")
    assert snap() == before


def test_the_rule_is_in_score_help():
    from lmgs_eval.cli import build_parser

    sub = next(a for a in build_parser()._actions if getattr(a, "choices", None) and "score" in a.choices)
    text = " ".join(sub.choices["score"].format_help().split())
    assert "reported as unavailable" in text and "exit code 2" in text
    metrics_help = next(a.help for a in sub.choices["score"]._actions if "--metrics" in a.option_strings)
    assert "unavailable" in metrics_help and "exit code 2" in metrics_help


def test_protocol_rows_give_the_reason_of_an_unavailable_metric(capsys):
    from lmgs_eval.commands._common import print_rows
    from test_results import metric, record, typed

    why = "unavailable: no audio"
    rec = record("lmgs", "lmgs", "3DGS", 0, {
        "psnr": metric("psnr", None, value=30.0), "lse_d": dict(metric("lse_d", None), flags=[why]),
        "lse_c": dict(metric("lse_c", None), flags=[why])})
    print_rows(typed([rec]))
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "unavailable" in ln]
    assert lines == ["  lmgs/test seed 0: lse unavailable: no audio"]


# ----------------------------------------------------------------------------- SyncNet weights holding NaN
def _syncnet_state(bad: str | None = None) -> dict:
    import torch

    from lmgs_eval.metrics.sync.nets import nets

    torch.manual_seed(0)
    sd = nets()[0]().state_dict()
    if bad:
        sd[bad] = torch.full_like(sd[bad], float("nan"))
    return sd


@pytest.mark.parametrize("bad", ["netcnnaud.0.weight", "netfclip.3.bias"])
def test_import_syncnet_refuses_nan_weights(world, bad):
    import torch

    tmp, res, snap = world
    ck = tmp / "syncnet_v2.model"
    torch.save(_syncnet_state(bad), ck)
    before = snap()
    rc, out, err = run_cli("weights", "import-syncnet", str(ck))
    one_line_error(rc, out, err, str(ck), repr(bad), "NaN or Inf")
    assert snap() == before


def test_nan_weights_found_on_load_are_refused(world, monkeypatch):
    """An imported graph that holds NaN (imported by an older version, or damaged since) is refused when loaded."""
    import torch

    from lmgs.fileio import sha256_file
    from lmgs_eval.metrics.sync import nets, scorers

    tmp, res, snap = world
    S, _ = nets.nets()
    net = S()
    net.load_state_dict(_syncnet_state("netcnnlip.0.weight"))
    onnx_path = tmp / "nan.onnx"
    nets._export_sync(net, onnx_path, (224, 224))
    manifest = tmp / "weights" / "syncnet_v2.json"
    manifest.parent.mkdir()
    manifest.write_text(json.dumps({"name": "syncnet-v2", "source": str(tmp / "syncnet_v2.model"), "source_sha256": "0" * 64,
                                    "onnx": str(onnx_path), "onnx_sha256": sha256_file(onnx_path),
                                    "input_hw": [224, 224], "region": "full", "pixel": "bgr_0_255"}))
    monkeypatch.setattr(scorers, "syncnet_manifest_path", lambda: manifest)
    v = _video(tmp / "v.mp4", n=30)
    rc, out, err = run_cli("score", "--pred", str(v), "--metrics", "lse")
    one_line_error(rc, out, err, str(onnx_path), "NaN or Inf", "import-syncnet")


def test_non_finite_embeddings_are_an_error_not_a_trusted_null():
    from lmgs_eval.errors import UserError
    from lmgs_eval.metrics.suite import format_record
    from lmgs_eval.metrics.sync.pixel import SyncScorer
    from lmgs_eval.metrics.sync.scoring import lse

    class _NaN:
        def run(self, names, feeds):
            n = len(feeds["audio"])
            return [np.full((n, 8), np.nan, np.float32), np.full((n, 8), np.nan, np.float32)]

    sc = SyncScorer("fake", _NaN(), "ab" * 32, (224, 224), "full", "bgr_0_255", source="fake.onnx")
    with pytest.raises(UserError, match=r"fake \(fake.onnx\): non-finite audio and video and still-face embeddings"):
        lse(None, _tone(2.0).astype(np.float32), scorer=sc, crops=np.zeros((50, 224, 224, 3), np.uint8))
    # a record whose self-check has no separation still prints
    rec = {"pred": "p", "gt": None, "n_frames": 50, "fps": 25.0, "flags": [], "results": {"lse": {
        "available": True, "spec": {"higher_is_better": False, "backend": "x"}, "values": {
            "lse_d": None, "separation": None, "trusted": False}, "n_effective": 45, "n_original": 45, "flags": []}}}
    assert "separation n/a, NOT trusted" in format_record(rec)


# ----------------------------------------------------------------------------- streaming: memory of a large clip
PROBE = textwrap.dedent("""
    import json, resource, sys
    from lmgs_eval.cli import main
    from lmgs_eval.metrics.landmarks import DlibBackend
    from lmgs_eval.metrics.sync.scorers import load

    DlibBackend(); load("landmark")  # models loaded before the baseline: only the clip's share is measured
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    rc = main(sys.argv[1:])
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"rc": rc, "growth_mb": (peak - base) / 1024}), file=sys.stderr)
""")


def _growth_mb(*argv: str) -> tuple[int, float, str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                        os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True, text=True, env=env, timeout=900)
    last = json.loads(r.stderr.strip().splitlines()[-1])
    return last["rc"], last["growth_mb"], r.stderr


FRAME_MB = 1080 * 1920 * 3 / 2**20  # one 1080x1920 frame as uint8 (as float32, four times that)


@pytest.fixture(scope="module")
def portrait_clips(tmp_path_factory):
    """Generated 1080x1920 clips (a phone's portrait video) of 2 s and 6 s (50 and 150 frames), made when first asked for."""
    from lmgs_eval.commands._bench_score_memory import portrait_clip

    tmp, made = tmp_path_factory.mktemp("portrait"), {}

    def get(name: str) -> Path:
        if name not in made:
            made[name] = portrait_clip(tmp / f"{name}.mp4", seconds={"short": 2.0, "long": 6.0}[name])
        return made[name]

    return get


@pytest.mark.slow
def test_score_holds_a_few_frames_of_a_1080x1920_clip_whatever_its_length(portrait_clips):
    """Peak memory of ``score`` on 1080x1920 clips does not grow with the clip's length (its paired metrics
    hold a few frames of both clips as float, whatever the length)."""
    grown = {}
    for name in ("short", "long"):
        clip = portrait_clips(name)
        rc, grown[name], err = _growth_mb("score", "--pred", str(clip), "--gt", str(clip), "--metrics", "psnr", "--json")
        assert rc == 0, err
    assert grown["long"] < 150 * FRAME_MB * 2 / 2, grown  # half of both clips as uint8 (they were held as float32 too)
    assert grown["long"] - grown["short"] < 100 * FRAME_MB / 4, grown  # 100 frames more: (almost) nothing more held


def test_sync_check_of_a_1080x1920_clip_does_not_hold_its_frames(portrait_clips):
    """Peak memory of ``sync-check`` on a 6 s 1080x1920 clip: far below its frames (the face is found and
    cropped as the clip decodes)."""
    rc, growth, err = _growth_mb("sync-check", str(portrait_clips("long")), "--sync", "landmark", "--json")
    assert rc == 0, err
    assert growth < 150 * FRAME_MB / 4, (growth, err)  # the old reader held all 150 frames, as uint8 and float32
