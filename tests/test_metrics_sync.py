"""SyncNet import -> ONNX == the syncnet_python network; our LSE == syncnet_python's evaluate().

The outside reference is the code of the ``syncnet-python`` package (joonson/syncnet_python
for modern Python; install it with ``pip install --no-deps syncnet-python==0.2.3``): its
``SyncNetModel.S`` and ``SyncNetInstance.evaluate`` are loaded from their files. The official
weights are not on this machine, so a random state dict in the official layout is used; the
official demo numbers (offset 3, min dist 5.353, confidence 10.021) cannot be reproduced here.
"""

from __future__ import annotations

import importlib.util
import json
import types
import wave
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.sync import maths, nets, pixel, scorers, scoring


def _pkg_dir():
    spec = importlib.util.find_spec("syncnet_python")
    return None if spec is None else Path(list(spec.submodule_search_locations)[0])


def _load_file(name, path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


needs_pkg = pytest.mark.skipif(_pkg_dir() is None, reason="syncnet-python (reference code) not installed")


@pytest.fixture(autouse=True)
def _imported_syncnet_removed():
    """An imported official scorer is kept in the test session's cache, where every later scoring test
    (in whatever order the test processes take the files) would pick it: each test here removes it."""
    yield
    scorers.syncnet_manifest_path().unlink(missing_ok=True)


@pytest.fixture(scope="module")
def reference_net(tmp_path_factory):
    model = _load_file("ref_syncnet_model", _pkg_dir() / "SyncNetModel.py")
    torch.manual_seed(0)
    net = model.S(num_layers_in_fc_layers=1024)
    for m in net.modules():  # random BN statistics, so eval-mode BN is not the identity
        if isinstance(m, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d, torch.nn.BatchNorm3d)):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.1, 0.1)
    net.eval()
    path = tmp_path_factory.mktemp("sn") / "syncnet_v2.model"
    torch.save(net.state_dict(), path)
    return net, path


def _clip(n=20, seed=0):
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.uniform(0, 255, (224, 224, 3)).astype(np.float32), (0, 0), 4)
    crops = np.stack([np.clip(base + 30 * np.sin(i / 2.0) + rng.normal(0, 5, base.shape), 0, 255) for i in range(n)])
    t = np.arange(n * 640) / 16000
    audio = 0.3 * np.sin(2 * np.pi * 180 * t) * (0.6 + 0.4 * np.sin(2 * np.pi * 3 * t)) + 0.02 * rng.normal(size=t.size)
    return crops.astype(np.uint8), np.clip(audio, -1, 1)


@needs_pkg
def test_imported_onnx_equals_reference_network(reference_net):
    net, path = reference_net
    m = nets.import_syncnet(path)
    scorer, why = scorers.find_scorer("syncnet-v2")
    assert scorer is not None, why
    assert m["source_sha256"] == scorer.sha256
    g = torch.Generator().manual_seed(1)
    a = torch.randn(3, 1, 13, 20, generator=g) * 10
    v = torch.rand(3, 3, 5, 224, 224, generator=g) * 255
    with torch.no_grad():
        ra, rv = net.forward_aud(a), net.forward_lip(v)
    oa, ov = scorer.embed(a.numpy(), v.numpy())
    for ours, ref in ((oa, ra.numpy()), (ov, rv.numpy())):
        assert np.abs(ours - ref).max() <= 1e-4 * max(1.0, np.abs(ref).max())


@needs_pkg
def test_lse_equals_syncnet_python_evaluate(reference_net, tmp_path):
    net, path = reference_net
    nets.import_syncnet(path)
    crops, audio = _clip()
    work = tmp_path / "tmp"
    work.mkdir()
    for i, c in enumerate(crops):  # syncnet_python reads its crops as jpgs from tmp_dir
        cv2.imwrite(str(work / f"{i + 1:06d}.jpg"), c)
    pcm = np.clip(np.rint(audio * 32767), -32768, 32767).astype("<i2")
    with wave.open(str(work / "audio.wav"), "wb") as w:
        w.setnchannels(1), w.setsampwidth(2), w.setframerate(16000), w.writeframes(pcm.tobytes())
    inst = _load_file("ref_syncnet_instance", _pkg_dir() / "SyncNetInstance.py")
    ref = inst.SyncNetInstance(net, device="cpu")
    offset, conf, minval = ref.evaluate(types.SimpleNamespace(tmp_dir=str(work), batch_size=20, vshift=15))

    from lmgs_eval.data.audio import load_audio

    a16, _ = load_audio(work / "audio.wav")
    read = np.stack([cv2.imread(str(work / f"{i + 1:06d}.jpg")) for i in range(len(crops))]).astype(np.float32)
    scorer, _ = scorers.find_scorer("syncnet-v2")
    r = scoring.lse(None, a16, crops=read, scorer=scorer)
    assert r.available and r.values["offset"] == offset
    assert r.values["lse_d"] == pytest.approx(minval, rel=1e-4)
    assert r.values["lse_c"] == pytest.approx(conf, rel=1e-3, abs=1e-4)
    assert r.n_effective == len(crops) - 5 and r.per_item.shape == (len(crops) - 5,)


def test_lse_from_embeddings_hand_case():
    # audio embeddings = video embeddings shifted by 2 windows: the best offset is found
    rng = np.random.default_rng(0)
    v = rng.normal(size=(12, 4))
    a = np.concatenate([np.zeros((2, 4)), v[:-2]])  # a_{i} = v_{i-2}
    r = maths.lse_from_embeddings(v, a, vshift=3)
    k = int(np.argmin(r["mdist"]))
    assert k == 5 and r["offset"] == -2
    assert r["lse_c"] == pytest.approx(np.median(r["mdist"]) - r["mdist"].min())


def test_windows_follow_syncnet_indexing():
    crops = np.arange(12)[:, None, None, None] * np.ones((12, 4, 4, 3))
    mf = np.arange(13 * 60, dtype=float).reshape(13, 60)
    v, a = maths.windows(crops, mf, n_samples=10 * 640 + 100)  # min_length 10 -> 5 windows
    assert v.shape == (5, 3, 5, 4, 4) and a.shape == (5, 1, 13, 20)
    assert v[3, 0, :, 0, 0].tolist() == [3, 4, 5, 6, 7]
    np.testing.assert_array_equal(a[2, 0], mf[:, 8:28])


def _no_weights(monkeypatch, tmp_path):
    monkeypatch.setattr(scorers, "syncnet_manifest_path", lambda: tmp_path / "none.json")
    monkeypatch.setattr(scorers, "WEIGHTS", tmp_path / "weights")


def test_no_weights_is_unavailable_with_reason(monkeypatch, tmp_path):
    from lmgs_eval.metrics.metric_suite import MetricSuite

    _no_weights(monkeypatch, tmp_path)
    crops, audio = _clip(8)
    r = MetricSuite().lse(None, audio, crops=crops)
    assert not r.available and r.value is None and "no SyncNet weights" in r.reason


def _bundled(monkeypatch, tmp_path):
    _no_weights(monkeypatch, tmp_path)
    _, B = nets.nets()
    torch.manual_seed(0)
    nets.export_bundled(B(), tmp_path / "weights", {"recipe": "test", "seed": 0})
    scorer, why = scorers.find_scorer()
    assert scorer is not None and scorer.name == "bundled-sync", why
    return scorer


def test_bundled_scorer_loads_runs_and_flags_silence(monkeypatch, tmp_path):
    scorer = _bundled(monkeypatch, tmp_path)
    crops, audio = _clip(12)
    crops[:, :112] = 128  # a still upper face: what moves is in the lower half, the half this scorer reads
    r = scoring.lse(None, audio, crops=crops.astype(np.float32), scorer=scorer)
    assert r.available and "bundled" in r.spec.standin
    # the same numbers from the torch network the ONNX file was exported from, on inputs shaped
    # here (the lower half of each 224 crop, area-resized to 96x48, 0..1) and syncnet_python's
    # windows and distances (test_lse_equals_syncnet_python_evaluate holds those to its code)
    _, B = nets.nets()
    torch.manual_seed(0)
    net = B().eval()  # the weights _bundled exported
    x = np.stack([cv2.resize(c[112:].astype(np.float32), (96, 48), interpolation=cv2.INTER_AREA) for c in crops]) / 255
    vw, aw = maths.windows(x, maths.mfcc_13(audio), len(audio))
    with torch.no_grad():
        a_emb, v_emb = (t.numpy() for t in net(torch.from_numpy(aw), torch.from_numpy(vw.astype(np.float32))))
    want = maths.lse_from_embeddings(v_emb, a_emb)
    assert r.values["offset"] == want["offset"] and r.n_effective == len(vw) == len(crops) - 5
    assert r.values["lse_d"] == pytest.approx(want["lse_d"], rel=1e-4)
    assert r.values["lse_c"] == pytest.approx(want["lse_c"], rel=1e-3, abs=1e-5)
    np.testing.assert_allclose(r.per_item, want["per_window"], rtol=1e-4)
    assert not any("silent" in f for f in r.flags)
    r = scoring.lse(None, np.zeros_like(audio), crops=crops.astype(np.float32), scorer=scorer)
    assert any(f.startswith("silent_audio") for f in r.flags)
    r = scoring.lse(None, None, crops=crops.astype(np.float32), scorer=scorer, audio_reason="clip.mp4 has no audio track")
    assert not r.available and "no audio track" in r.reason


def test_bundled_corrupt_weights_clear_error(monkeypatch, tmp_path):
    _bundled(monkeypatch, tmp_path)
    p = tmp_path / "weights" / "bundled_sync.onnx"
    p.write_bytes(p.read_bytes()[:-10] + b"0123456789")
    with pytest.raises(UserError, match="does not match"):
        scorers.find_scorer()


def test_import_rejects_bad_files(tmp_path):
    bad = tmp_path / "syncnet_v2.model"
    bad.write_bytes(b"\x00garbage")
    with pytest.raises(UserError, match="not a readable SyncNet state dict"):
        nets.import_syncnet(bad)
    torch.save({"netcnnaud.0.weight": torch.zeros(64, 1, 3, 3)}, bad)
    with pytest.raises(UserError, match="missing"):
        nets.import_syncnet(bad)


def test_score_video_without_audio_reports_lse_unavailable(monkeypatch, tmp_path):
    from lmgs_eval.data.video import write_video
    from lmgs_eval.metrics.suite import score

    scorer = _bundled(monkeypatch, tmp_path)
    assert scorer is not None
    frames = np.random.default_rng(0).random((8, 64, 64, 3)).astype(np.float32)
    write_video(tmp_path / "v.mp4", frames, 25)
    rec = score(tmp_path / "v.mp4", metrics=["lse"])
    assert rec["results"]["lse"]["available"] is False
    assert "no audio track" in rec["results"]["lse"]["reason"]
    json.dumps(rec)


def test_batched_window_embedding_equals_all_windows():
    # lse() builds video windows a batch at a time from each frame prepared once; the
    # embeddings must equal those of every window built up front (syncnet_python's way)
    class _Session:  # embeds a window as its per-frame means, audio as its first 4 values
        def run(self, names, feeds):
            a, v = feeds["audio"], feeds["video"]
            return [a.reshape(a.shape[0], -1)[:, :4], v.mean(axis=(1, 3, 4))]

    sc = pixel.SyncScorer("fake", _Session(), "0" * 64, (4, 6), "full", "bgr_0_255")
    rng = np.random.default_rng(0)
    frames = rng.uniform(0, 255, (23, 4, 6, 3)).astype(np.float32)
    mf = rng.normal(size=(13, 120))
    v, a = maths.windows(frames, mf, n_samples=23 * 640)
    ref_a, ref_v = sc.embed(a, v)
    got_a, got_v = sc.embed_frames(a, frames, batch=5)
    np.testing.assert_array_equal(got_a, ref_a)
    np.testing.assert_array_equal(got_v, ref_v)
    assert got_v.shape == (18, 5)


def test_too_short_clip_is_unavailable_not_a_crash():
    class _Session:
        def run(self, names, feeds):
            raise AssertionError("nothing to embed")

    sc = pixel.SyncScorer("fake", _Session(), "0" * 64, (224, 224), "full", "bgr_0_255")
    crops = np.zeros((4, 224, 224, 3), np.float32)
    r = scoring.lse(None, np.zeros(4 * 640, np.float32) + 0.1, scorer=sc, crops=crops)
    assert r.value is None and "too short" in " ".join(r.notes + r.flags + [str(getattr(r, "reason", ""))])
