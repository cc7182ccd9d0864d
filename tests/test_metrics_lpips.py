"""LPIPS / ST-LPIPS: ONNX == torch, folded == unfolded, the stlpips and lpips packages as outside references;
LPIPS alex named official only for torchvision's published trunk (by its sha256), lpips-alex-custom otherwise."""

from __future__ import annotations

import importlib
import sys
import types
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from skimage import data

from conftest import random_alexnet_state
from lmgs_eval.errors import UserError
from lmgs_eval.metrics import lpips as L
from lmgs_eval.metrics.ort import load_torch_state

pytestmark = pytest.mark.skipif(L.stlpips_weights_path() is None, reason="stlpips-pytorch not installed")


@pytest.fixture(scope="module")
def st_metric():
    return L.LPIPS("stlpips-alex", batch=3)


def _face(size=96):
    img = data.astronaut()[40:296, 120:376].astype(np.float32) / 255.0
    return cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)


def test_folded_conv_equals_unfolded_on_even_and_odd_sizes():
    folded, _ = L.build_stlpips_torch(fold=True)
    plain, _ = L.build_stlpips_torch(fold=False)
    g = torch.Generator().manual_seed(0)
    for h, w in [(64, 64), (65, 67), (70, 71)]:
        x = torch.rand(2, 3, h, w, generator=g)
        with torch.no_grad():
            a, b = folded.trunk(x)[0], plain.trunk(x)[0]
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)


def test_onnx_equals_torch(st_metric):
    plain, _ = L.build_stlpips_torch(fold=False)
    rng = np.random.default_rng(0)
    for h, w in [(64, 64), (67, 65)]:  # dynamic height/width, both parities
        p = rng.random((3, h, w, 3)).astype(np.float32)
        g = rng.random((3, h, w, 3)).astype(np.float32)
        ours = st_metric.distances(p, g)
        with torch.no_grad():
            ref = plain(torch.from_numpy(p.transpose(0, 3, 1, 2).copy()), torch.from_numpy(g.transpose(0, 3, 1, 2).copy()))
        np.testing.assert_allclose(ours, ref.numpy(), atol=1e-5)


def test_zero_on_identical_and_monotone_in_noise_and_blur(st_metric):
    img = _face()
    rng = np.random.default_rng(0)
    noise = rng.normal(0, 1, img.shape).astype(np.float32)
    noisy = np.stack([np.clip(img + s * noise, 0, 1) for s in (0.02, 0.05, 0.1, 0.2)])
    d = st_metric.distances(noisy, np.repeat(img[None], 4, 0))
    assert np.all(np.diff(d) > 0), d
    blurred = np.stack([cv2.GaussianBlur(img, (0, 0), s) for s in (0.7, 1.5, 3.0)])
    d = st_metric.distances(blurred, np.repeat(img[None], 3, 0))
    assert np.all(np.diff(d) > 0), d
    assert st_metric.distances(img[None], img[None])[0] == pytest.approx(0.0, abs=1e-7)


def _package_stlpips():
    """The stlpips package's own network, imported with torchvision/IPython/torchsummary stubbed (test only)."""
    stubs = {n: types.ModuleType(n) for n in ("torchvision", "torchvision.models", "IPython", "torchsummary")}
    stubs["IPython"].embed = lambda *a, **k: None
    stubs["torchsummary"].summary = lambda *a, **k: None
    stubs["torchvision"].models = stubs["torchvision.models"]
    saved = {k: sys.modules.get(k) for k in stubs}
    sys.modules.update(stubs)
    try:
        mod = importlib.import_module("stlpips_pytorch.stlpips")
        return mod.LPIPS(net="alex", variant="shift_tolerant", verbose=False)
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
        for k in [k for k in sys.modules if k.startswith("stlpips_pytorch")]:
            sys.modules.pop(k)


def test_port_matches_stlpips_package(st_metric):
    ref = _package_stlpips()
    img = _face(80)
    rng = np.random.default_rng(3)
    p = np.clip(img + rng.normal(0, 0.08, img.shape), 0, 1).astype(np.float32)
    tp = torch.from_numpy(p.transpose(2, 0, 1)[None].copy())
    tg = torch.from_numpy(img.transpose(2, 0, 1)[None].copy())
    with torch.no_grad():
        expect = float(ref(tp, tg, normalize=True).ravel()[0])
    assert st_metric.distances(p[None], img[None])[0] == pytest.approx(expect, rel=1e-5, abs=1e-7)


def _random_alexnet(path):
    torch.save(random_alexnet_state(), path)


needs_heads = pytest.mark.skipif(L.lpips_heads_path() is None, reason="lpips wheel not installed")


def _as_official(monkeypatch, ck):
    """Take ``ck`` for torchvision's published trunk: the known prefix becomes its sha256's (no real
    file can be made to hash to 7be5be79...)."""
    monkeypatch.setattr(L, "ALEXNET_SHA256_PREFIX", L.sha256_file(ck)[:8])


@needs_heads
def test_official_lpips_alex_onnx_equals_torch_with_random_trunk(tmp_path, monkeypatch):
    ck = tmp_path / L.ALEXNET_CKPT
    _random_alexnet(ck)
    _as_official(monkeypatch, ck)
    m = L.LPIPS("lpips-alex", alexnet=ck)
    assert m.spec.name == "lpips-alex" and not m.spec.standin and len(m.spec.weights_sha256) == 64
    heads = load_torch_state(L.lpips_heads_path(), "heads")
    torch.testing.assert_close(m.backend.net.lins[2].weight.reshape(-1), heads["lin2.model.1.weight"].reshape(-1))
    rng = np.random.default_rng(0)
    p = rng.random((2, 70, 66, 3)).astype(np.float32)
    g = rng.random((2, 70, 66, 3)).astype(np.float32)
    with torch.no_grad():
        ref = m.backend.net(torch.from_numpy(p.transpose(0, 3, 1, 2).copy()), torch.from_numpy(g.transpose(0, 3, 1, 2).copy()))
    np.testing.assert_allclose(m.distances(p, g), ref.numpy(), atol=1e-5)
    assert m.distances(g, g) == pytest.approx([0.0, 0.0], abs=1e-7)


def _package_lpips_alex(trunk_sd):
    """The lpips package's own v0.1 alex network (its heads from the wheel) on the trunk ``trunk_sd``,
    imported with a torchvision stand-in that builds torchvision's AlexNet ``features`` (test only)."""
    from torch import nn

    def alexnet(pretrained=False, **kw):
        m = nn.Module()
        m.features = nn.Sequential(
            nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(384, 256, 3, padding=1),
            nn.ReLU(inplace=True), nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2))
        m.features.load_state_dict({k[len("features."):]: v for k, v in trunk_sd.items() if k.startswith("features.")})
        return m

    stubs = {n: types.ModuleType(n) for n in ("torchvision", "torchvision.models")}
    stubs["torchvision.models"].alexnet = alexnet
    stubs["torchvision"].models = stubs["torchvision.models"]
    saved = {k: sys.modules.get(k) for k in stubs}
    sys.modules.update(stubs)
    try:
        mod = importlib.import_module("lpips")
        return mod.LPIPS(net="alex", version="0.1", verbose=False).eval()
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
        for k in [k for k in sys.modules if k == "lpips" or k.startswith("lpips.")]:
            sys.modules.pop(k)


@needs_heads
def test_official_path_matches_the_lpips_package(tmp_path, monkeypatch):
    ck = tmp_path / L.ALEXNET_CKPT
    _random_alexnet(ck)
    _as_official(monkeypatch, ck)
    m = L.LPIPS("lpips-alex", alexnet=ck)
    assert m.spec.name == "lpips-alex"
    ref = _package_lpips_alex(load_torch_state(ck, "trunk"))
    img = _face(80)
    rng = np.random.default_rng(5)
    p = np.stack([np.clip(img + rng.normal(0, s, img.shape), 0, 1) for s in (0.02, 0.1)]).astype(np.float32)
    g = np.repeat(img[None], 2, 0)
    with torch.no_grad():
        expect = ref(torch.from_numpy(p.transpose(0, 3, 1, 2).copy()), torch.from_numpy(g.transpose(0, 3, 1, 2).copy()),
                     normalize=True).reshape(-1).double().numpy()
        eager = m.backend.net(torch.from_numpy(p.transpose(0, 3, 1, 2).copy()),
                              torch.from_numpy(g.transpose(0, 3, 1, 2).copy())).double().numpy()
    assert np.all(expect > 0)
    np.testing.assert_allclose(eager, expect, rtol=1e-6, atol=1e-9)  # equal here (same ops, same order)
    np.testing.assert_allclose(m.distances(p, g), expect, rtol=1e-5, atol=1e-8)  # the ONNX graph: ~1e-9 here


@needs_heads
def test_a_random_trunk_named_as_torchvisions_scores_as_custom(tmp_path):
    from lmgs_eval.results.provenance import metric_entries

    ck = tmp_path / L.ALEXNET_CKPT
    _random_alexnet(ck)
    sha = L.sha256_file(ck)
    assert not sha.startswith(L.ALEXNET_SHA256_PREFIX)
    m = L.LPIPS("lpips-alex", alexnet=ck)  # asked for the official one, by its file name
    assert m.spec.name == "lpips-alex-custom" and "not torchvision's published" in m.spec.standin
    assert "not comparable with published LPIPS" in m.spec.standin
    files = m.spec.files()
    assert files["alexnet"] == {"path": str(ck.resolve()), "sha256": sha}
    assert files["lpips_heads"]["sha256"] == L.LPIPS_HEADS_SHA256
    assert m.spec.weights_sha256 == L.AlexWeights(ck, sha, L.lpips_heads_path(), L.LPIPS_HEADS_SHA256).sha256
    frames = np.random.default_rng(1).random((2, 40, 40, 3)).astype(np.float32)
    entries = metric_entries(m.compute(m.update(frames, frames[::-1].copy())).to_dict())
    assert set(entries) == {"lpips_custom"}  # never under the official key
    e = entries["lpips_custom"]
    assert e["backend"] == f"lpips-alex-custom({sha[:8]})" and e["standin"] == m.spec.standin
    assert e["weights_files"]["alexnet"] == {"path": str(ck.resolve()), "sha256": sha}
    assert e["weights_sha256"] == m.spec.weights_sha256


@needs_heads
def test_the_label_is_decided_by_the_sha256_prefix(tmp_path, monkeypatch):
    ck = tmp_path / "some-trunk.pth"  # the file's name plays no part
    _random_alexnet(ck)
    sha = L.sha256_file(ck)
    assert L.is_official_alexnet("7be5be79" + "0" * 56) and not L.is_official_alexnet(sha)
    assert L.alex_weights(ck).name == "lpips-alex-custom"
    monkeypatch.setattr(L, "sha256_file", lambda p: ("7be5be79" + sha[8:]) if p == ck else L.hashlib.sha256(
        Path(p).read_bytes()).hexdigest())
    w = L.alex_weights(ck)
    assert w.official and w.name == "lpips-alex" and w.trunk_sha256.startswith("7be5be79")
    b = L.resolve_lpips("lpips-alex", alexnet=ck, use_onnx=False)
    assert b.spec.name == "lpips-alex" and not b.spec.standin and b.spec.files()["alexnet"]["sha256"] == w.trunk_sha256
    # and from the torch hub cache, with nothing asked for
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "hub-home"))
    hub = tmp_path / "hub-home" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    (hub / L.ALEXNET_CKPT).write_bytes(ck.read_bytes())
    assert L.resolve_lpips(None, use_onnx=False).spec.name == "lpips-alex-custom"  # its real sha256 is not 7be5be79


@needs_heads
def test_heads_other_than_the_published_v0_1_file_are_refused(tmp_path):
    ck = tmp_path / L.ALEXNET_CKPT
    _random_alexnet(ck)
    heads = tmp_path / "alex.pth"
    sd = load_torch_state(L.lpips_heads_path(), "heads")
    torch.save({k: v * 2 for k, v in sd.items()}, heads)
    with pytest.raises(UserError, match="is not the lpips v0.1 alex heads'") as e:
        L.build_lpips_alex_torch(ck, heads)
    assert str(heads) in str(e.value) and "\n" not in str(e.value)


@needs_heads
@pytest.mark.parametrize("edit, words", [
    (lambda sd: sd.update({"features.3.weight": torch.zeros(192, 64, 3, 3)}),
     ["features.3.weight: expected shape (192, 64, 5, 5), got (192, 64, 3, 3)"]),
    (lambda sd: sd.update({"features.10.bias": torch.zeros(128)}), ["features.10.bias: expected shape (256,), got (128,)"]),
    (lambda sd: sd.pop("features.0.weight"), ["not torchvision's alexnet layout: missing 'features.0.weight'"]),
    (lambda sd: sd.update({"module.features.0.weight": sd.pop("features.0.weight")}),
     ["missing 'features.0.weight'; unexpected 'module.features.0.weight'"]),
])
def test_a_checkpoint_not_in_torchvisions_layout_is_one_line(tmp_path, edit, words):
    ck = tmp_path / "trunk.pth"
    _random_alexnet(ck)
    sd = torch.load(ck)
    edit(sd)
    torch.save(sd, ck)
    with pytest.raises(UserError) as e:
        L.LPIPS("lpips-alex", alexnet=ck)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(str(ck)), msg
    for w in words:
        assert w in msg, msg
    assert "c2." not in msg and "c1." not in msg  # torchvision's key, not the port's layer name


def test_default_is_labelled_standin_without_trunk(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    monkeypatch.setattr(L.Path, "home", lambda: tmp_path)
    b = L.resolve_lpips(None, use_onnx=False)
    assert b.spec.name == "stlpips-alex" and "NOT the LPIPS" in b.spec.standin


def test_corrupt_weights_and_onnx_give_clear_errors(tmp_path):
    bad = tmp_path / L.ALEXNET_CKPT
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(UserError, match="not a readable AlexNet checkpoint"):
        L.LPIPS("lpips-alex", alexnet=bad)
    from lmgs_eval.metrics.ort import load_session

    junk = tmp_path / "x.onnx"
    junk.write_bytes(b"garbage")
    with pytest.raises(UserError, match="not a loadable ONNX graph"):
        load_session(junk)


def test_small_frames_rejected(st_metric):
    x = np.zeros((1, 16, 16, 3), np.float32)
    with pytest.raises(UserError, match="at least 32x32"):
        st_metric.distances(x, x)
