"""The reference model end to end on a tiny synthetic clip made with a known Gaussian scene."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from lmgs.errors import InputError
from lmgs.presets import config_from_dict, quick
from lmgs.checkpoint import load_model, save_model
from lmgs.train import TrainingDiverged, fit
from lmgs.types import DrivingAudio
from model_fixtures import synthetic_clip


def _tiny_cfg(**changes):
    cfg = quick()
    cfg = cfg.replace(train=dataclasses.replace(cfg.train, static_steps=60, dynamic_steps=40, landmark_steps=20, densify_every=20,
                                                checkpoint_every=30))
    return cfg.replace(**changes) if changes else cfg


@pytest.fixture(scope="module")
def clip():
    return synthetic_clip()


@pytest.fixture(scope="module")
def trained(clip):
    return fit(clip, _tiny_cfg(), seed=0, progress=False)


def _psnr(a, b):
    return float(np.mean([10 * np.log10(1 / np.mean((a[i] / 255.0 - b[i] / 255.0) ** 2)) for i in range(len(a))]))


def test_fit_reconstructs_training_frames(clip, trained):
    model, report = trained
    frames = model.render(DrivingAudio(audio=clip.audio, w2c=clip.w2c))
    assert frames.shape == clip.frames.shape and frames.dtype == np.uint8
    # The mean background alone scores about 14 dB on this clip; a fitted head far more.
    bg_only = np.broadcast_to(clip.backgrounds[0], clip.frames.shape)
    assert _psnr(bg_only, clip.frames) < 18
    assert _psnr(frames, clip.frames) > 28
    assert report.n_gaussians <= report.budget + 64 and report.steps == 100


def test_save_load_renders_identically(tmp_path, clip, trained):
    model, _ = trained
    save_model(model, tmp_path / "m.pt")
    again = load_model(tmp_path / "m.pt", cfg=model.cfg)
    d = DrivingAudio(audio=clip.audio[: 10 * 640], w2c=clip.w2c[:10])
    np.testing.assert_array_equal(model.render(d), again.render(d))


def test_checkpoint_errors_name_the_file(tmp_path, trained):
    model, _ = trained
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="bad.pt"):
        load_model(bad)
    save_model(model, tmp_path / "m.pt")
    other = model.cfg.replace(**{"guidance.theta": 0.4})
    with pytest.raises(InputError, match="config"):
        load_model(tmp_path / "m.pt", cfg=other)
    with pytest.raises(InputError, match="not found"):
        load_model(tmp_path / "missing.pt")


def _psnr_u8(a, b):
    return _psnr(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("seconds", [0.05, 0.2, 3.0])
def test_any_audio_length_and_silence(trained, clip, seconds):
    # Silence of any length still draws the fitted head: every frame is close to what the
    # training audio renders from the same camera and to that camera's ground truth
    # (black or garbage frames, e.g. from non-finite features, score far below).
    model, _ = trained
    n = max(1, int(seconds * 25))
    silence = np.zeros(int(seconds * 16000), np.float32)
    w2c = np.tile(clip.w2c[0], (n, 1, 1))
    out = model.render(DrivingAudio(audio=silence, w2c=w2c))
    assert out.shape == (n, *clip.frames.shape[1:]) and out.dtype == np.uint8
    voiced = model.render(DrivingAudio(audio=clip.audio[:640], w2c=clip.w2c[:1]))
    assert _psnr_u8(out, np.repeat(voiced, n, 0)) > 35
    assert _psnr_u8(out, np.repeat(clip.frames[:1], n, 0)) > 25


def test_clipped_audio_renders_the_fitted_head(trained, clip):
    # Gain x50, hard-clipped at +-1: the front end clips floats beyond [-1, 1] itself, so the
    # clipped and the unclipped loud waveform give the same features (exactly), and those
    # features stay finite although they lie far outside the training range.
    from lmgs.audio.features import waveform_features

    model, _ = trained
    loud = np.clip(clip.audio * 50, -1, 1)
    kind = model.cfg.audio.frontend
    np.testing.assert_array_equal(waveform_features(clip.audio * 50, kind), waveform_features(loud, kind))
    assert np.isfinite(waveform_features(loud, kind)).all()
    out = model.render(DrivingAudio(audio=loud, w2c=clip.w2c))
    ref = model.render(DrivingAudio(audio=clip.audio, w2c=clip.w2c))
    assert out.shape == ref.shape == clip.frames.shape
    # How far the saturated features move the head is extrapolation, and it varies with the
    # weights the toy model trains to, which the float rounding of the host's instruction set
    # sets: the clipped render lies 36.3 dB from the unclipped one on an AVX-512 host and
    # 26.3 dB on an AVX2-only one (AMD EPYC Zen 3); against the ground truth 25.3 dB there,
    # loud white noise 23.1 dB, the unclipped audio 33.7 dB. What must hold on any host: it is
    # still the fitted head (the background alone scores under 18 dB, a blank or exploded
    # render far less).
    assert _psnr_u8(out, clip.frames) > 22


def _alter_loss_after(monkeypatch, n: int, change):
    """From the (n+1)-th training step on, the photometric loss goes through ``change``."""
    import lmgs.train as tr

    real = tr.losses.CoveredPhotometric.__call__
    calls = {"n": 0}

    def altered(self, *args):
        calls["n"] += 1
        out = real(self, *args)
        return change(out) if calls["n"] > n else out

    monkeypatch.setattr(tr.losses.CoveredPhotometric, "__call__", altered)


def test_non_finite_loss_stops_with_message(clip, monkeypatch, tmp_path):
    _alter_loss_after(monkeypatch, 45, lambda x: x * float("nan"))
    with pytest.raises(TrainingDiverged, match=r"non-finite at step 45.*checkpoint.*curve up to it is .*curve.png"):
        fit(clip, _tiny_cfg(), seed=0, progress=False, workdir=tmp_path)
    assert (tmp_path / "checkpoint.pt").exists()  # the last good one (step 30) is kept
    assert (tmp_path / "curve.csv").read_text().splitlines()[-1].startswith("45,static,nan")


def test_collapse_guard_hand_cases():
    from lmgs.train import CollapseGuard

    g = CollapseGuard(window=4, factor=3.0)
    assert [g.update(x, "static") for x in (0.5, 0.4, 0.3, 0.2)] == [None, None, None, None]  # falling: fine
    assert g.best == pytest.approx(0.35)
    assert g.update(2.0, "static") is None  # one spike: (0.4 + 0.3 + 0.2 + 2.0) / 4 = 0.725 < 3 x 0.35
    assert g.update(2.0, "static") == pytest.approx((0.3 + 0.2 + 2.0 + 2.0) / 4 / 0.35)  # a plateau: 3.2x
    # a new stage starts its own reference: its higher loss level is not a collapse
    assert [g.update(x, "dynamic") for x in (5.0, 5.0, 5.0, 5.0, 5.1)] == [None] * 5


def test_collapse_stops_with_message(clip, monkeypatch, tmp_path):
    # a finite loss that jumps and stays (as the 16,000-Gaussian hopper run's did) stops the run
    _alter_loss_after(monkeypatch, 88, lambda x: x + 5.0)
    with pytest.raises(TrainingDiverged, match=r"collapsed at step 8[89] \(dynamic stage\).*checkpoint \(step 60\)"
                                               r".*training curve up to it is .*curve.png"):
        fit(clip, _tiny_cfg(), seed=0, progress=False, workdir=tmp_path)
    import csv

    rows = list(csv.DictReader((tmp_path / "curve.csv").open()))  # the curve up to the stop, for a look
    assert int(rows[-1]["step"]) in (88, 89) and rows[-1]["stage"] == "dynamic" and float(rows[-1]["loss"]) > 5
    assert (tmp_path / "curve.png").exists()


def test_resume_after_interruption(clip, monkeypatch, tmp_path):
    import lmgs.train as tr

    real = tr.losses.CoveredPhotometric.__call__
    calls = {"n": 0}

    def interrupt(self, *args):
        calls["n"] += 1
        if calls["n"] == 50:
            raise KeyboardInterrupt
        return real(self, *args)

    monkeypatch.setattr(tr.losses.CoveredPhotometric, "__call__", interrupt)
    with pytest.raises(KeyboardInterrupt):
        fit(clip, _tiny_cfg(), seed=0, progress=False, workdir=tmp_path)
    monkeypatch.setattr(tr.losses.CoveredPhotometric, "__call__", real)
    model, report = fit(clip, _tiny_cfg(), seed=0, progress=False, workdir=tmp_path)
    assert report.resumed_from == 30 and report.steps == 70
    # the time is the whole training's: the interrupted run's up to its checkpoint, then this one's
    import csv

    secs = [float(r["seconds"]) for r in csv.DictReader(open(tmp_path / "curve.csv"))]
    assert report.prior_seconds > 0 and report.seconds > report.prior_seconds
    assert secs == sorted(secs) and secs[-1] <= report.seconds
    assert (tmp_path / "curve.csv").exists() and (tmp_path / "curve.png").exists()
    assert not (tmp_path / "checkpoint.pt").exists()


def test_same_seed_same_model(clip, trained):
    model, _ = trained
    again, _ = fit(clip, _tiny_cfg(), seed=0, progress=False)
    torch.testing.assert_close(again.face.means, model.face.means, rtol=0, atol=0)


def test_ablation_switches_are_configs(clip):
    cfg = _tiny_cfg(**{"guidance.se": False, "guidance.lc": False, "gr": False})
    model, report = fit(clip, cfg, seed=0, progress=False)
    assert model.predictor is None and np.isnan(report.se_fraction)
    assert model.face_deform.lc is None
    assert config_from_dict(cfg.to_dict()) == cfg and cfg.hash() != _tiny_cfg().hash()


def test_a_config_rebuilt_from_its_dict_is_the_same_config():
    """What a checkpoint or record holds rebuilds the config it came from, the options added after
    records existed included: left out of the dict at their neutral value, they must come back at
    it, not at a newer default (an uncapped model loaded from the cache would render capped)."""
    from lmgs.presets import paper

    for cfg in (quick(), paper(), _tiny_cfg(),
                quick().replace(**{"guidance.select_fraction": 0.0}),  # SE uncapped: the cap's neutral, not its default
                quick().replace(**{"train.gr_warmup": 0}),
                quick().replace(**{"guidance.se": False}),
                quick().replace(**{"guidance.mouth_state": True, "train.landmark_folds": 5,
                                   "train.landmark_source": "generic-tuned"})):
        again = config_from_dict(cfg.to_dict())
        assert again == cfg and again.hash() == cfg.hash()
    assert "select_fraction" not in quick().replace(**{"guidance.select_fraction": 0.0}).to_dict()["guidance"]


def test_ds_front_end_drives_the_model_from_the_subjects_features(clip):
    """The paper's "Replacing Audio Net with DS" row: the model reads aud_ds.npy, not the waveform."""
    cfg = _tiny_cfg(**{"audio.frontend": "ds"})
    with pytest.raises(InputError, match="'ds' needs precomputed features"):
        fit(clip, cfg, seed=0, progress=False)
    rng = np.random.default_rng(1)
    ds = rng.normal(size=(len(clip.frames), 16, 29)).astype(np.float32)
    model, _ = fit(dataclasses.replace(clip, audio_features={"ds": ds}), cfg, seed=0, progress=False)
    w2c = model.train_w2c.numpy()
    same = model.render(DrivingAudio(audio=clip.audio, w2c=w2c, audio_features={"ds": ds}))
    quiet = model.render(DrivingAudio(audio=np.zeros_like(clip.audio), w2c=w2c, audio_features={"ds": ds}))
    other = model.render(DrivingAudio(audio=clip.audio, w2c=w2c, audio_features={"ds": ds[::-1].copy()}))
    assert np.array_equal(same, quiet)  # the waveform is not what drives it
    assert np.abs(same.astype(int) - other).max() > 0  # the DS features are
    with pytest.raises(InputError, match="precomputed 'ds' audio features"):
        model.render(DrivingAudio(audio=clip.audio, w2c=w2c))


def test_without_audio_encoder_the_window_is_averaged(clip):
    """The paper's "w/o Audio Encoder" row: no convolutions, a mean over the window and one linear layer."""
    model, _ = fit(clip, _tiny_cfg(**{"audio.use_encoder": False}), seed=0, progress=False)
    enc = model.audio_net.encoder
    assert not any(isinstance(m, torch.nn.Conv1d) for m in enc.modules())
    # the encoder is exactly "standardise, mean over the window, one linear layer"
    x = torch.randn(5, enc.window, enc.in_channels)
    want = enc.proj(((x - enc.mean) / enc.std).mean(dim=1))
    torch.testing.assert_close(enc(x), want)
    assert not torch.equal(enc.std, torch.ones_like(enc.std))  # the standardisation was fitted
    # and the model it drives still reconstructs its training frames (the background alone: < 18 dB)
    out = model.render(DrivingAudio(audio=clip.audio, w2c=model.train_w2c.numpy()))
    assert out.shape == clip.frames.shape and _psnr_u8(out, clip.frames) > 26


def _spy_on_geometry_weights(monkeypatch) -> list:
    """A list that gathers the Geometry Regularizer's ``(lambda_d, lambda_n)`` of every training step."""
    import lmgs.train as tr

    seen = []
    real = tr.losses.geometry

    def spy(depth, normal, alpha, ref_d, ref_n, lambda_d, lambda_n, reduce, **kw):
        seen.append((lambda_d, lambda_n))
        return real(depth, normal, alpha, ref_d, ref_n, lambda_d, lambda_n, reduce, **kw)

    monkeypatch.setattr(tr.losses, "geometry", spy)
    return seen


def test_gr_warmup_ramps_the_geometry_weights_in_and_leaves_the_hash_when_off(clip, monkeypatch):
    assert clip.depth is not None and clip.normal is not None
    assert quick().train.gr_warmup == 400 and quick().to_dict()["train"]["gr_warmup"] == 400  # the default ramps
    base = _tiny_cfg(**{"train.gr_warmup": 0})
    warm = base.replace(train=dataclasses.replace(base.train, gr_warmup=4))
    assert "gr_warmup" not in base.to_dict()["train"] and warm.hash() != base.hash()  # 0 hashes as before the option
    seen = _spy_on_geometry_weights(monkeypatch)
    fit(clip, warm, seed=0, progress=False)
    lam = base.train.lambda_normal
    assert len(seen) == base.train.dynamic_steps  # only in the dynamic stage
    assert [n for _, n in seen[:5]] == pytest.approx([lam / 4, lam / 2, 3 * lam / 4, lam, lam])
    assert all(d == pytest.approx(n) for d, n in seen)  # lambda_depth == lambda_normal == 1e-4
    seen.clear()
    fit(clip, base, seed=0, progress=False)
    assert {n for _, n in seen} == {lam}  # off: full weight from the first dynamic step, as before


def test_derived_priors_are_weighed_by_their_own_weights_and_measured_ones_are_not(clip, monkeypatch):
    base = _tiny_cfg(**{"train.gr_warmup": 0})
    weighed = base.replace(**{"train.derived_depth_weight": 0.5, "train.derived_normal_weight": 0.0})
    # at 1 (before the options) the hash is as before; without the regularizer the weights change nothing
    assert "derived_normal_weight" not in base.to_dict()["train"] and weighed.hash() != base.hash()
    assert weighed.replace(gr=False).hash() == base.replace(gr=False).hash()
    assert config_from_dict(weighed.to_dict()) == weighed
    seen = _spy_on_geometry_weights(monkeypatch)
    lam_d, lam_n = base.train.lambda_depth, base.train.lambda_normal
    assert not clip.priors_derived
    fit(clip, weighed, seed=0, progress=False)  # measured priors: the full weights
    assert set(seen) == {(lam_d, lam_n)}
    seen.clear()
    fit(dataclasses.replace(clip, priors_derived=True), weighed, seed=0, progress=False)
    assert seen and all(d == pytest.approx(lam_d / 2) and n == 0.0 for d, n in seen)


def test_training_landmarks_are_out_of_fold_and_the_folds_hash(clip, monkeypatch):
    import lmgs.landmarks as lm
    import lmgs.train as tr

    # off by default (in-sample training landmarks), and then the hash is that of before the option
    assert quick().train.landmark_folds == 0 and "landmark_folds" not in quick().to_dict()["train"]
    on = _tiny_cfg(**{"train.landmark_folds": 5})
    assert on.to_dict()["train"]["landmark_folds"] == 5 and on.hash() != _tiny_cfg().hash()
    # without SE and LC nothing reads landmarks: the folds leave TalkingGaussian's hash alone
    tg = _tiny_cfg(**{"guidance.se": False, "guidance.lc": False, "gr": False})
    assert tg.hash() == tg.replace(**{"train.landmark_folds": 0}).hash()
    with pytest.raises(ValueError, match="landmark_folds"):
        _tiny_cfg(**{"train.landmark_folds": 1})

    calls, fed = [], []
    real = lm.cross_fit_landmarks

    def spy(feats, targets, *, folds, steps, seed):
        out = real(feats, targets, folds=folds, steps=steps, seed=seed)
        calls.append((folds, out.clone()))
        return out

    real_render = tr.LMGSModel.render_frame

    def render_spy(self, w2c, bg, *, dynamic=True, landmarks=None, **kw):
        if landmarks is not None:
            fed.append(landmarks.detach().clone())
        return real_render(self, w2c, bg, dynamic=dynamic, landmarks=landmarks, **kw)

    monkeypatch.setattr(lm, "cross_fit_landmarks", spy)
    monkeypatch.setattr(tr.LMGSModel, "render_frame", render_spy)
    cfg = _tiny_cfg(**{"train.landmark_folds": 3})
    model, _ = fit(clip, cfg, seed=0, progress=False)
    assert [f for f, _ in calls] == [3]  # 24 frames: 3 blocks of 8
    oof = calls[0][1]
    assert len(fed) == cfg.train.dynamic_steps  # only the dynamic stage reads landmarks
    assert all(any(torch.equal(x, o) for o in oof) for x in fed)  # the out-of-fold sets, not the predictor's own
    from lmgs.audio import compute_features

    feats = compute_features(clip.audio, 16000, cfg.audio, n_frames=len(clip))
    in_sample = model.predictor.predict(feats)
    assert not any(torch.allclose(fed[0], p) for p in in_sample)
    calls.clear()
    said = []
    fit(clip, on, seed=0, progress=False, log=said.append)  # 5 folds asked, 24 frames: capped at 3 blocks of 8
    assert [f for f, _ in calls] == [3] and any("3-fold out-of-fold" in s for s in said)
    calls.clear()
    said.clear()
    fit(synthetic_clip(n=12), on, seed=0, progress=False, log=said.append)
    assert calls == [] and any("in-sample (12 frames are too few for 5 folds)" in s for s in said)
    said.clear()
    fit(synthetic_clip(n=12), _tiny_cfg(), seed=0, progress=False, log=said.append)  # the default: in-sample
    assert calls == [] and any("training landmarks in-sample" in s and "too few" not in s for s in said)
