"""LPIPS / ST-LPIPS: ONNX == torch, folded == unfolded, the stlpips package as outside reference."""

from __future__ import annotations

import importlib
import sys
import types

import cv2
import numpy as np
import pytest
import torch
from skimage import data

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
    """A random state dict in torchvision's alexnet key layout (the real trunk is not on this machine)."""
    g = torch.Generator().manual_seed(0)
    shapes = {"features.0": (64, 3, 11, 11), "features.3": (192, 64, 5, 5), "features.6": (384, 192, 3, 3),
              "features.8": (256, 384, 3, 3), "features.10": (256, 256, 3, 3)}
    sd = {}
    for k, s in shapes.items():
        fan = s[1] * s[2] * s[3]
        sd[f"{k}.weight"] = torch.randn(s, generator=g) * (2.0 / fan) ** 0.5
        sd[f"{k}.bias"] = torch.zeros(s[0])
    sd["classifier.1.weight"] = torch.zeros(4, 4)  # extra keys are ignored, as in torchvision's checkpoint
    torch.save(sd, path)


@pytest.mark.skipif(L.lpips_heads_path() is None, reason="lpips wheel not installed")
def test_official_lpips_alex_onnx_equals_torch_with_random_trunk(tmp_path):
    ck = tmp_path / L.ALEXNET_CKPT
    _random_alexnet(ck)
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
