"""Spatial Enhancement, Landmark Compensation and the deformation network on hand-made cases."""

import math

import pytest
import torch

from lmgs.config import DeformConfig, GuidanceConfig, TriplaneConfig
from lmgs.deform import DeformNet
from lmgs.errors import InputError
from lmgs.guidance import LandmarkCompensation, spatial_enhance


def _unit(deg):
    a = math.radians(deg)
    return [math.cos(a), math.sin(a)]


def test_spatial_enhance_hand_case():
    # keypoints along the x and y axes; points at known angles from them
    g = torch.tensor([[2.0, 0.0], [0.0, 3.0]])
    f = torch.tensor(
        [
            _unit(10),  # cos 10 deg = 0.985 to k0: selected, matches 0
            _unit(80),  # cos 10 deg to k1: selected, matches 1
            _unit(45),  # cos 45 = 0.707 to both: selected (argmax: first of equals or either)
            _unit(-60),  # cos 60 = 0.5 to k0, negative to k1: not selected
            _unit(180),  # opposite of k0: not selected
        ]
    )
    f = f * torch.tensor([[1.0], [2.0], [0.5], [1.0], [4.0]])  # norms must not matter
    r = spatial_enhance(f, g, theta=0.6)
    assert r.selected.tolist() == [True, True, True, False, False]
    assert r.match[:2].tolist() == [0, 1]
    assert r.fraction == pytest.approx(3 / 5)
    torch.testing.assert_close(r.max_similarity[3], torch.tensor(0.5))
    torch.testing.assert_close(r.features[0], f[0] + g[0])
    torch.testing.assert_close(r.features[1], f[1] + g[1])
    torch.testing.assert_close(r.features[3:], f[3:])
    # a stricter threshold keeps only the two close ones
    assert spatial_enhance(f, g, theta=0.8).selected.tolist() == [True, True, False, False, False]
    # a cap on the share selected keeps the most similar: 2 of 5 at 0.4 (similarities 0.985, 0.985, 0.707)
    capped = spatial_enhance(f, g, theta=0.6, max_fraction=0.4)
    assert capped.selected.tolist() == [True, True, False, False, False] and capped.fraction == pytest.approx(0.4)
    torch.testing.assert_close(capped.features[2], f[2])
    # a cap above what θ selects changes nothing; θ stays the floor under any cap
    assert spatial_enhance(f, g, theta=0.6, max_fraction=0.8).selected.tolist() == r.selected.tolist()
    assert spatial_enhance(f, g, theta=0.99, max_fraction=0.8).selected.tolist() == [False] * 5
    assert not spatial_enhance(f, g, theta=-1.0, max_fraction=0.1).selected.any()  # round(0.5) = 0 points


def test_se_cap_defaults_to_the_papers_share_and_hashes_only_where_se_reads_it():
    from lmgs.presets import paper, quick

    cfg = quick()
    assert cfg.guidance.select_fraction == 0.2 and cfg.to_dict()["guidance"]["select_fraction"] == 0.2
    assert paper().guidance.select_fraction == 0.2
    # θ alone (the records before the cap): the option at its neutral value is left out of the dict, so
    # that config hashes as configs made before the option did
    off = cfg.replace(**{"guidance.select_fraction": 0.0})
    assert "select_fraction" not in off.to_dict()["guidance"] and off.hash() != cfg.hash()
    # without SE the cap changes no weight and no hash (lmgs-no-se's, TalkingGaussian's records stay valid)
    no_se = cfg.replace(**{"guidance.se": False})
    assert "select_fraction" not in no_se.to_dict()["guidance"]
    assert no_se.hash() == no_se.replace(**{"guidance.select_fraction": 0.0}).hash()
    with pytest.raises(ValueError, match="select_fraction"):
        cfg.replace(**{"guidance.select_fraction": 1.0})
    # the deformation network passes the cap to Spatial Enhancement
    torch.manual_seed(0)
    xyz, lms, aud = torch.rand(200, 3) * 2 - 1, torch.rand(68, 3) * 2 - 1, torch.randn(16)
    fracs = []
    for q in (0.0, 0.2):
        net = DeformNet(16, DeformConfig(), _small_tri(), GuidanceConfig(theta=-1.0, select_fraction=q))
        fracs.append(net(xyz, aud, lms, blink=0.5).se_fraction)
    assert fracs[0] == 1.0 and fracs[1] == pytest.approx(0.2, abs=0.01)


def test_spatial_enhance_gradients_flow_through_added_features():
    f = torch.tensor([_unit(5), _unit(200)], requires_grad=True)  # the second matches nothing
    g = torch.tensor([[1.0, 0.0], [0.0, 1.0]], requires_grad=True)
    r = spatial_enhance(f, g, 0.6)
    r.features.sum().backward()
    assert torch.equal(f.grad, torch.ones(2, 2))  # identity in f (the selection is not differentiated)
    assert g.grad[0].tolist() == [1.0, 1.0] and g.grad[1].tolist() == [0.0, 0.0]  # only k0 was used


def test_spatial_enhance_backward_is_reproducible_and_exact():
    """Many points pick the same landmark; their gradients must sum to the same bits every time.

    ``g[match]`` with repeated indices sums its backward with parallel atomic adds on the CPU,
    so the keypoints' gradient changed in the last bits from call to call (9 of 10 different
    here before the fix). Checked against a float64 sum written out per keypoint.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        gen = torch.Generator().manual_seed(0)
        f = torch.randn(20000, 32, generator=gen)
        g = torch.randn(68, 32, generator=gen) + 3 * f[:68]
        upstream = torch.randn(20000, 32, generator=gen)
        grads = []
        for _ in range(6):
            gg = g.clone().requires_grad_(True)
            r = spatial_enhance(f, gg, theta=0.3)
            r.features.backward(upstream)
            grads.append(gg.grad)
        for other in grads[1:]:
            assert torch.equal(other, grads[0])
        want = torch.zeros(68, 32, dtype=torch.float64)
        for i in torch.nonzero(r.selected).flatten().tolist():
            want[int(r.match[i])] += upstream[i].double()
        assert 0.2 < r.fraction < 1.0
        torch.testing.assert_close(grads[0].double(), want, rtol=1e-5, atol=1e-4)
    finally:
        torch.set_num_threads(before)


def test_landmark_compensation_starts_at_zero_and_learns():
    torch.manual_seed(0)
    cfg = GuidanceConfig(n_landmarks=68, cond_dim=8, hidden=16)
    lc = LandmarkCompensation(6, cfg)
    F, g = torch.randn(50, 6), torch.randn(68, 6)
    dx, dr, ds, tau = lc(F, g)
    assert dx.shape == (50, 3) and dr.shape == (50, 4) and ds.shape == (50, 3) and tau.shape == (50, 1)
    assert torch.count_nonzero(dx) + torch.count_nonzero(dr) + torch.count_nonzero(ds) == 0
    assert bool(((tau > 0) & (tau < 1)).all())  # sigmoid gate
    # the zero-initialised head still receives a gradient, so one step moves it off zero
    (dx.sum() + dr.sum() + ds.sum()).backward()
    assert lc.offset[-1].weight.grad.abs().sum() > 0
    # the concatenation h = [F || c_lms] computed explicitly gives the same MLP outputs
    with torch.no_grad():
        for p in lc.offset[-1].parameters():
            p.normal_()
        c = lc.psi(g.reshape(-1))
        h = torch.cat([F, c.expand(50, -1)], dim=1)
        expect = lc.offset(h) * torch.sigmoid(lc.tau(h))
        dx, dr, ds, _ = lc(F, g)
        torch.testing.assert_close(torch.cat([dx, dr, ds], 1), expect, rtol=1e-5, atol=1e-6)
    with pytest.raises(InputError):
        lc(F, torch.randn(10, 6))


def _small_tri():
    return TriplaneConfig(n_levels=4, log2_table_size=10, finest_resolution=64)


def test_deform_face_branch_shapes_and_switches():
    torch.manual_seed(0)
    xyz, lms, aud = torch.rand(200, 3) * 2 - 1, torch.rand(68, 3) * 2 - 1, torch.randn(16)
    net = DeformNet(16, DeformConfig(exp_dim=3), _small_tri(), GuidanceConfig())
    with torch.no_grad():
        net.mlp[-1].weight.normal_(0, 0.1)  # a trained-looking last layer (it starts at zero)
    out = net(xyz, aud, lms, blink=0.4, exp=torch.zeros(3))
    assert out.d_xyz.shape == (200, 3) and out.d_rot.shape == (200, 4) and out.d_scale.shape == (200, 3)
    assert 0.0 <= out.se_fraction <= 1.0
    assert out.audio_attention.shape == (200, 16) and bool(((out.audio_attention > 0) & (out.audio_attention < 1)).all())
    # LC's head starts at zero: switching LC off leaves the offsets unchanged at init
    plain = DeformNet(16, DeformConfig(exp_dim=3), _small_tri(), GuidanceConfig(lc=False))
    plain.load_state_dict({k: v for k, v in net.state_dict().items() if not k.startswith("lc.")})
    out2 = plain(xyz, aud, lms, blink=0.4, exp=torch.zeros(3))
    torch.testing.assert_close(out2.d_xyz, out.d_xyz)
    # without SE or LC no landmarks are needed and no fraction is reported
    bare = DeformNet(16, DeformConfig(), _small_tri(), GuidanceConfig(se=False, lc=False))
    assert bare(xyz, aud, blink=0.0).se_fraction is None
    with pytest.raises(InputError):
        net(xyz, aud, None, blink=0.4, exp=torch.zeros(3))
    with pytest.raises(InputError):
        net(xyz, aud, lms, blink=None, exp=torch.zeros(3))


def test_deform_mouth_branch_position_only_and_audio_dependence():
    torch.manual_seed(0)
    net = DeformNet(8, DeformConfig.mouth(), _small_tri(), GuidanceConfig(se=False, lc=False))
    with torch.no_grad():
        for p in net.encoder.parameters():
            p.normal_()
        net.mlp[-1].weight.normal_(0, 0.1)
    xyz = torch.rand(100, 3) * 2 - 1
    a = net(xyz, torch.zeros(8))
    b = net(xyz, torch.ones(8) * 3)
    assert torch.count_nonzero(a.d_rot) == 0 and torch.count_nonzero(a.d_scale) == 0
    assert not torch.allclose(a.d_xyz, b.d_xyz)
    # cached point features give the same result
    f = net.encode_points(xyz)
    torch.testing.assert_close(net(xyz, torch.ones(8) * 3, point_features=f).d_xyz, b.d_xyz)


def test_deform_starts_at_the_static_solution_and_can_bound_the_audio():
    torch.manual_seed(0)
    xyz, lms = torch.rand(300, 3) * 2 - 1, torch.rand(68, 3) * 2 - 1
    out = DeformNet(16, DeformConfig(zero_init=True), _small_tri(), GuidanceConfig())(xyz, torch.randn(16) * 5, lms, blink=0.7)
    # zero-initialised last layer + zero-initialised LC head: no offset at all before training
    assert torch.count_nonzero(out.d_xyz) == 0 and torch.count_nonzero(out.d_rot) == 0 and torch.count_nonzero(out.d_scale) == 0
    old = DeformNet(16, DeformConfig(), _small_tri(), GuidanceConfig())  # the default keeps PyTorch's init
    assert float(old(xyz, torch.randn(16), lms, blink=0.7).d_scale.detach().abs().max()) > 1e-3
    # bound_audio (off by default: training saturates it): a runaway audio feature cannot move
    # the points further than a saturated one, tanh(1e3 v) == tanh(1e6 v) == sign(v) ...
    net = DeformNet(16, DeformConfig(bound_audio=True), _small_tri(), GuidanceConfig())
    with torch.no_grad():
        net.mlp[-1].weight.normal_(0, 0.1)
        old.load_state_dict(net.state_dict())
    v = torch.randn(16)
    big = net(xyz, v * 1e3, lms, blink=0.7)
    torch.testing.assert_close(net(xyz, v * 1e6, lms, blink=0.7).d_xyz, big.d_xyz)
    torch.testing.assert_close(old(xyz, torch.sign(v), lms, blink=0.7).d_xyz, big.d_xyz)
    assert bool(torch.isfinite(big.d_scale).all())
    # ... while without the bound the offsets grow with the feature
    grow = old(xyz, v * 1e3, lms, blink=0.7).d_xyz.abs().max() / old(xyz, v, lms, blink=0.7).d_xyz.abs().max()
    assert float(grow.detach()) > 50


def test_added_options_leave_the_config_hash_as_it_was():
    import dataclasses
    import hashlib
    import json

    from lmgs.config import config_dict
    from lmgs.presets import quick

    cfg = quick()
    d = cfg.to_dict()
    assert "zero_init" not in d["deform_face"] and "bound_audio" not in d["deform_mouth"]
    # at their neutral values the dict is asdict() without them: records made before the options keep their hash
    plain = dataclasses.asdict(cfg)
    for part in ("deform_face", "deform_mouth"):
        del plain[part]["zero_init"], plain[part]["bound_audio"]
    del plain["train"]["normal_reduce"], plain["train"]["landmark_folds"], plain["train"]["landmark_source"]
    del plain["train"]["lip_weights"], plain["guidance"]["mouth_state"]
    del plain["train"]["derived_depth_weight"], plain["train"]["derived_normal_weight"]
    assert d == plain and d["train"]["gr_warmup"] == 400  # a new default unlike the neutral 0: in the dict
    assert d["guidance"]["select_fraction"] == 0.2  # likewise
    assert "gr_warmup" not in cfg.replace(**{"train.gr_warmup": 0}).to_dict()["train"]  # at neutral: left out
    assert cfg.hash() == hashlib.sha256(json.dumps(plain, sort_keys=True, default=str).encode()).hexdigest()[:16]
    on = cfg.replace(**{"deform_face.zero_init": True})
    assert on.to_dict()["deform_face"]["zero_init"] is True and on.hash() != cfg.hash()
    assert config_dict(DeformConfig(bound_audio=True))["bound_audio"] is True
    mean = cfg.replace(**{"train.normal_reduce": "mean"})
    assert mean.to_dict()["train"]["normal_reduce"] == "mean" and mean.hash() != cfg.hash()
    with pytest.raises(ValueError, match="normal_reduce"):
        cfg.replace(**{"train.normal_reduce": "max"})


@pytest.mark.parametrize("cfg,guid", [
    (DeformConfig(exp_dim=3), GuidanceConfig()),  # the face branch: SE (capped) and LC, blink and an expression vector
    (DeformConfig(), GuidanceConfig(select_fraction=0.0, theta=0.2)),  # SE by theta alone, many points selected
    (DeformConfig(attention="softmax", bound_audio=True), GuidanceConfig(lc=False)),
    (DeformConfig(), GuidanceConfig(se=False)),  # LC alone
    (DeformConfig.mouth(), GuidanceConfig(se=False, lc=False)),  # the mouth branch: position only, no expression
    (DeformConfig(), GuidanceConfig(theta=1.1, select_fraction=0.0)),  # SE on, nothing selected
])
@pytest.mark.parametrize("by_mask", [False, True], ids=["rows", "masks"])
def test_prepared_inference_equals_the_forward_pass(cfg, guid, by_mask, monkeypatch):
    """forward_prepared (first layers of f computed once per clip) against forward, every switch, with
    the selection applied to the selected rows alone (the CPU's way) and to every row by masks (a GPU's)."""
    import lmgs.deform

    monkeypatch.setattr(lmgs.deform, "select_by_mask", lambda device: by_mask)
    torch.manual_seed(1)
    net = DeformNet(16, cfg, _small_tri(), guid)
    with torch.no_grad():  # trained-looking heads (the last layers start at zero)
        for p in net.parameters():
            p.add_(torch.randn_like(p) * 0.2)
    xyz = torch.rand(300, 3) * 2 - 1
    prep = net.prepare(xyz)
    for t in range(3):
        lms, aud = torch.rand(68, 3) * 2 - 1, torch.randn(16) * 2
        kw = {"blink": 0.1 + 0.3 * t} if cfg.blink else {}
        if cfg.exp_dim:
            kw["exp"] = torch.randn(cfg.exp_dim)
        with torch.no_grad():
            want = net(xyz, aud, lms if (guid.se or guid.lc) else None, **kw)
        got = net.forward_prepared(prep, aud, lms if (guid.se or guid.lc) else None, **kw)
        for a, b in ((got.d_xyz, want.d_xyz), (got.d_rot, want.d_rot), (got.d_scale, want.d_scale),
                     (got.audio_attention, want.audio_attention)):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
        assert (got.se_fraction is None) == (want.se_fraction is None) == (not guid.se)
        if guid.se:
            assert float(got.se_fraction) == float(want.se_fraction)
        assert float(want.d_xyz.abs().max()) > 1e-4  # the offsets are not trivially zero
    if guid.se and guid.theta > 1:
        assert float(got.se_fraction) == 0.0
