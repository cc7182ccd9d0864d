"""The training step's device-side data and its read-back-free pieces, against the plain ways.

On a GPU the training step keeps its data on the device (:mod:`lmgs.clipdata`) and computes without
reading values back (masked sums, ``torch.where``, fused optimisers). The CPU keeps the plain ways;
these tests hold the GPU's ways equal to them, on the CPU where they can be forced, and on CUDA where
it is there (skipped without it).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from model_fixtures import synthetic_clip

import lmgs.clipdata as cd
from lmgs.device import choose_device
from lmgs.errors import InputError
from lmgs.presets import quick
from lmgs.render import rasterize
from lmgs.strategy import accumulate, initialize_state
from lmgs.types import Camera

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def _clip_with_masks():
    clip = synthetic_clip(n=10, size=32)
    masks = np.zeros((10, 32, 32), bool)
    for t in range(10):
        if t % 3:
            masks[t, 18 + t % 4 : 22 + t % 4, 10 : 12 + t] = True
    return dataclasses.replace(clip, mouth_masks=masks)


def test_clip_tensors_on_the_device_equal_the_per_step_copies(monkeypatch):
    clip = _clip_with_masks()
    host = cd.ClipTensors(clip, torch.device("cpu"))
    assert not host.resident  # the CPU reads each frame from the arrays
    monkeypatch.setattr(cd, "fits_on_device", lambda clip, dev: True)
    resident = cd.ClipTensors(clip, torch.device("cpu"))
    assert resident.resident
    for i in range(len(clip)):
        for name in ("frame", "background", "depth", "normal", "blink", "index"):
            a, b = getattr(host, name)(i), getattr(resident, name)(i)
            assert a.dtype == b.dtype and torch.equal(a, b), (name, i)
        px = resident.mouth_pixels(i)
        want = torch.from_numpy(clip.mouth_masks[i])
        if not want.any():
            assert px is None and host.mouth_pixels(i) is None
            continue
        image = torch.rand(32, 32)
        # the same pixels in the order boolean selection takes them: the same mean, bit for bit
        assert torch.equal(image.reshape(-1)[px], image[want])
    assert float(host.frame(3).max()) <= 1.0 and torch.equal(host.frame(3), torch.from_numpy(clip.frames[3]).float() / 255.0)
    assert torch.equal(host.normal(2), torch.from_numpy(clip.normal[2].astype(np.float32) / 127.0))


def test_clip_tensors_stay_on_the_host_when_the_device_is_too_small():
    clip = _clip_with_masks()
    assert not cd.fits_on_device(clip, torch.device("cpu"))
    assert cd._nbytes(clip) > clip.frames.nbytes


def test_accumulate_adds_where_visible_as_indexing_did():
    g = torch.Generator().manual_seed(0)
    n = 50
    state = initialize_state(n)
    state["grad2d"] += torch.rand(n, generator=g)
    state["count"] += 2.0
    want_g, want_c = state["grad2d"].clone(), state["count"].clone()
    means2d = torch.rand(n, 2, generator=g, requires_grad=True)
    (means2d * torch.randn(n, 2, generator=g)).sum().backward()
    visible = torch.rand(n, generator=g) > 0.4
    grad = means2d.grad.clone()
    grad[:, 0] *= 64 / 2.0
    grad[:, 1] *= 48 / 2.0
    want_g[visible] += grad.norm(dim=-1)[visible]
    want_c[visible] += 1
    accumulate(state, means2d, visible, 64, 48)
    assert torch.equal(state["grad2d"], want_g) and torch.equal(state["count"], want_c)


def _scene(n=30):
    g = torch.Generator().manual_seed(1)
    means = torch.randn(n, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, 1.0])
    quats = torch.randn(n, 4, generator=g)
    return [means, quats, torch.full((n, 3), -3.0), torch.zeros(n), torch.rand(n, 3, generator=g)]


def test_rasterize_without_the_value_check_still_checks_shapes():
    params = _scene()
    cam = Camera(torch.eye(4), 40.0, 40.0, 16.0, 16.0, 32, 32)
    params[3] = params[3].clone()
    params[3][4] = float("nan")
    with pytest.raises(InputError, match="opacity_logits has 1 non-finite"):
        rasterize(*params, cam)
    rasterize(*params, cam, check_values=False)  # asked not to look at the values: no error
    with pytest.raises(InputError, match="quats must have shape"):
        rasterize(params[0], params[1][:5], *params[2:], cam, check_values=False)


def test_optimisers_keep_torchs_default_on_the_cpu():
    from lmgs.gaussians import GaussianSet
    from lmgs.optim import gaussian_adam, network_adamw

    gs = GaussianSet(torch.rand(5, 3), torch.rand(5, 3), 0.01)
    assert gaussian_adam([gs], quick().train).defaults["fused"] is None
    assert network_adamw([torch.nn.Linear(3, 2)], 1e-3).defaults["fused"] is None


def _tiny(clip):
    cfg = quick()
    return cfg.replace(train=dataclasses.replace(cfg.train, static_steps=40, dynamic_steps=30, landmark_steps=20,
                                                 densify_every=20, checkpoint_every=1000, budget_density=8.0))


@cuda
def test_training_on_cuda_tracks_the_cpu():  # pragma: no cover - CUDA only
    """The same tiny fit on both devices: the first loss equal, the end within a seed's spread, the
    CUDA model's renders (masks, chunked copies) equal to the same model's on the CPU."""
    from lmgs.train import fit
    from lmgs.types import DrivingAudio

    clip = _clip_with_masks()
    cfg = _tiny(clip)
    m_cpu, r_cpu = fit(clip, cfg, seed=0, progress=False, device="cpu")
    m_gpu, r_gpu = fit(clip, cfg, seed=0, progress=False, device=choose_device("cuda"))
    assert r_gpu.curve[0]["loss"] == pytest.approx(r_cpu.curve[0]["loss"], rel=1e-4)
    assert abs(r_gpu.final_psnr - r_cpu.final_psnr) < 2.0
    assert abs(r_gpu.se_fraction - r_cpu.se_fraction) < 0.05
    driving = DrivingAudio(audio=clip.audio, w2c=clip.w2c, backgrounds=clip.backgrounds.repeat(len(clip), 0)
                           if clip.backgrounds.shape[0] == 1 else clip.backgrounds, blink=clip.blink)
    t_gpu, t_cpu = {}, {}
    on_gpu = m_gpu.render(driving, timings=t_gpu)
    on_cpu = m_gpu.to("cpu").render(driving, timings=t_cpu)
    assert np.abs(on_gpu.astype(int) - on_cpu.astype(int)).max() <= 2
    assert t_gpu["se_fraction"] == pytest.approx(t_cpu["se_fraction"], abs=1e-6)


@cuda
def test_optimisers_are_fused_on_cuda():  # pragma: no cover - CUDA only
    from lmgs.gaussians import GaussianSet
    from lmgs.optim import gaussian_adam, network_adamw

    dev = choose_device("cuda")  # (the test is skipped without CUDA)
    gs = GaussianSet(torch.rand(5, 3, device=dev), torch.rand(5, 3, device=dev), 0.01)
    assert gaussian_adam([gs], quick().train).defaults["fused"] is True
    assert network_adamw([torch.nn.Linear(3, 2).to(dev)], 1e-3).defaults["fused"] is True


def test_a_model_with_a_non_finite_parameter_is_named_before_rendering_on_a_gpu():
    """On a GPU ``render`` checks the parameters once for the clip instead of in every rasterizer call."""
    from lmgs.train import fit

    clip = _clip_with_masks()
    model, _ = fit(clip, _tiny(clip).replace(**{"train.static_steps": 5, "train.dynamic_steps": 5}), seed=0,
                   progress=False)
    model._check_finite()  # a trained model passes
    with torch.no_grad():
        model.face_deform.mlp[0].weight[0, 1] = float("inf")
    with pytest.raises(InputError, match=r"face_deform\.mlp\.0\.weight holds 1 non-finite"):
        model._check_finite()
