"""The nine baseline adapters on the tiny synthetic clip (48x48, 24 frames) with the ``tiny`` budget."""

from __future__ import annotations

import numpy as np
import pytest

from lmgs.errors import InputError
from lmgs.types import DrivingAudio
from baselines.protocol import MethodInfo, TalkingHead, create_method, list_methods
from model_fixtures import synthetic_clip

GS = ("talkinggaussian", "degstalk", "gaussiantalker")
NERF = ("adnerf", "radnerf", "ernerf", "geneface")
TWO_D = ("wav2lip", "ip_lap")
ALL = GS + NERF + TWO_D
FAMILY = {**{m: "3DGS" for m in GS}, **{m: "NeRF" for m in NERF}, **{m: "2D" for m in TWO_D}}
# A much shorter schedule for the determinism checks (two fits per method).
SHORT = {**{m: {"static_steps": 10, "dynamic_steps": 10, "densify_every": 5} for m in GS},
         **{m: {"steps": 15, "landmark_steps": 10} for m in NERF + TWO_D}}


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Mean per-frame PSNR (dB) of uint8 videos, written out here (not the toolkit's metric)."""
    mse = ((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean(axis=(1, 2, 3)) / 255.0**2
    return float(np.mean(10 * np.log10(1.0 / np.maximum(mse, 1e-12))))


pytestmark = pytest.mark.usefixtures("one_thread")  # 48x48 frames: one thread (conftest.one_thread)


@pytest.fixture(scope="module")
def clip():
    return synthetic_clip()


@pytest.fixture(scope="module")
def fitted(clip, tmp_path_factory):
    cache: dict[str, tuple] = {}

    def get(name):
        if name not in cache:
            wd = tmp_path_factory.mktemp(name)
            m = create_method(name, preset="tiny")
            m.fit(clip, seed=0, workdir=wd, progress=False)
            cache[name] = (m, wd)
        return cache[name]

    return get


def _self_driving(clip) -> DrivingAudio:
    return DrivingAudio(audio=clip.audio, w2c=clip.w2c, backgrounds=np.repeat(clip.backgrounds, len(clip), 0), blink=clip.blink)


def test_all_nine_are_registered():
    names = list_methods()
    for m in ALL:
        assert m in names


def test_methods_command_lists_every_method_with_its_config_hash():
    import json

    from conftest import run_cli

    code, out, _ = run_cli("methods", "--json")
    assert code == 0
    rows = {r["name"]: r for r in json.loads(out)["methods"]}
    assert list(rows) == list_methods()  # the --method help points here
    for name in (*ALL, "lmgs", "lmgs-no-se"):
        info = create_method(name, preset="quick").describe()
        assert (rows[name]["family"], rows[name]["config_hash"]) == (info.family, info.config_hash)
    assert rows["lmgs-no-se"]["variant"] and not rows["lmgs"]["variant"]
    # The DS row reads the subject's own DeepSpeech features: no front-end stand-in to name.
    ours, ds = create_method("lmgs").describe(), create_method("lmgs-ds").describe()
    assert any("log-mel" in s for s in ours.standins) and not any("front end" in s for s in ds.standins)
    assert any("GeneFace" in s for s in ds.standins) and "audio front end ds" in ds.display_name


@pytest.mark.parametrize("name", ALL)
def test_protocol_describe_and_cost(name, fitted, clip):
    m, wd = fitted(name)
    assert isinstance(m, TalkingHead)
    info = m.describe()
    assert isinstance(info, MethodInfo) and info.name == name and info.family == FAMILY[name]
    assert "Simplified" in info.description or "simplified" in info.description
    assert len(info.config_hash) == 16 and info.config
    c = m.cost()
    # against the checkpoint the fit saved: its state holds the parameters and the buffers; the
    # parameters are what is counted, at 4 bytes each; a 3DGS method's Gaussians are the rows of
    # its means there (one set, or the face's and the mouth's)
    import torch

    ck = torch.load(wd / "model.pt", map_location="cpu", weights_only=False)
    buffers = {k for k, _ in m.model.named_buffers()}
    saved = sum(v.numel() for k, v in ck["state"].items() if k not in buffers)
    assert saved > 0 and c["n_params"] == saved
    assert c["model_mb"] == pytest.approx(saved * 4 / 2**20, rel=1e-12)
    if name in GS:
        means = [v for k, v in ck["state"].items() if k.split(".")[-1] == "means"]
        assert means and all(v.shape[1:] == (3,) for v in means)
        assert c["n_gaussians"] == sum(v.shape[0] for v in means) > 0
    else:
        assert c["n_gaussians"] is None
    # and an adapter that reloads that checkpoint reports the same
    again = create_method(name, preset="tiny")
    again.fit(clip, seed=0, workdir=wd, progress=False)
    assert {k: again.cost()[k] for k in ("n_params", "n_gaussians", "model_mb")} == {
        k: c[k] for k in ("n_params", "n_gaussians", "model_mb")}


@pytest.mark.parametrize("name", GS + NERF)
def test_reconstructs_training_frames_better_than_background(name, fitted, clip):
    m, _ = fitted(name)
    out = m.render(_self_driving(clip))
    assert out.shape == clip.frames.shape and out.dtype == np.uint8
    bg_only = np.broadcast_to(clip.backgrounds[0], clip.frames.shape)
    assert _psnr(bg_only, clip.frames) < 13  # the background alone: about 11.9 dB
    assert _psnr(out, clip.frames) > 24


@pytest.mark.parametrize("name", TWO_D)
def test_2d_mouth_follows_audio(name, fitted, clip):
    """From one fixed source frame, the edited mouth is nearer the true frames than the source itself."""
    m, _ = fitted(name)
    n = len(clip)
    out = m.render(DrivingAudio(audio=clip.audio, w2c=np.repeat(clip.w2c[:1], n, 0)))
    assert out.shape == clip.frames.shape and out.dtype == np.uint8
    gt = clip.frames.astype(np.float64)
    moving = gt.std(axis=0).mean(-1) > 8  # pixels that change over the clip (mouth, head turn)
    err_out = np.abs(out.astype(np.float64) - gt)[:, moving].mean()
    err_src = np.abs(np.repeat(clip.frames[:1], n, 0).astype(np.float64) - gt)[:, moving].mean()
    assert err_out < 0.85 * err_src


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("seconds", [0.0, 0.1, 1.0])
def test_silence_and_short_clips(name, fitted, clip, seconds):
    # Silence of any length renders the fitted head from the first training camera: close to
    # that camera's ground-truth frame (measured 24-39 dB; the background alone scores about 14,
    # a blank or broken frame far below), and still: with nothing said and the camera fixed,
    # consecutive frames differ by under half a grey level on average (measured 0-0.39).
    m, _ = fitted(name)
    n = int(seconds * 25)
    out = m.render(DrivingAudio(audio=np.zeros(int(seconds * 16000), np.float32),
                                w2c=np.repeat(clip.w2c[:1], n, 0)))
    assert out.shape == (n, clip.height, clip.width, 3) and out.dtype == np.uint8
    if n == 0:
        return
    gt0 = np.repeat(clip.frames[:1], n, 0)
    assert _psnr(out, gt0) > 22
    if n > 1:
        assert np.abs(np.diff(out.astype(np.int16), axis=0)).mean() < 0.5


@pytest.mark.parametrize("name", ALL)
def test_checkpoint_is_reused(name, fitted, clip):
    m, wd = fitted(name)
    assert (wd / "model.pt").exists()
    again = create_method(name, preset="tiny")
    again.fit(clip, seed=123, workdir=wd, progress=False)  # loads; a new seed would train differently
    d = DrivingAudio(audio=clip.audio[: 6 * 640], w2c=clip.w2c[:6])
    np.testing.assert_array_equal(m.render(d), again.render(d))


def test_checkpoint_of_another_config_is_refused(fitted, clip):
    _, wd = fitted("adnerf")
    other = create_method("adnerf", preset="tiny", hidden=16)
    with pytest.raises(InputError, match="model.pt"):
        other.fit(clip, seed=0, workdir=wd, progress=False)


@pytest.mark.parametrize("name", ALL)
def test_deterministic_with_seed(name, clip, tmp_path):
    d = DrivingAudio(audio=clip.audio[: 8 * 640], w2c=clip.w2c[:8])
    renders = []
    for k, seed in enumerate((0, 0, 1)):
        m = create_method(name, preset="tiny", **SHORT[name])
        m.fit(clip, seed=seed, workdir=tmp_path / str(k), progress=False)
        renders.append(m.render(d))
    np.testing.assert_array_equal(renders[0], renders[1])
    assert not np.array_equal(renders[0], renders[2])


@pytest.mark.slow
@pytest.mark.parametrize("name", ALL)
def test_long_audio(name, fitted, clip):
    m, _ = fitted(name)
    t = np.arange(20 * 16000) / 16000
    out = m.render(DrivingAudio(audio=(0.2 * np.sin(2 * np.pi * 200 * t)).astype(np.float32)))
    assert out.shape == (500, clip.height, clip.width, 3) and out.dtype == np.uint8


def test_gaussiantalker_config_hash_follows_its_budget_and_shared_schedule():
    # the Gaussian budget and the lmgs schedule values it trains with are part of its config:
    # a cached model trained with another budget is never reused under the same hash
    from lmgs.presets import quick

    base = create_method("gaussiantalker", preset="quick")
    cfg = base.describe().config
    assert cfg["budget_density"] == quick().train.budget_density
    assert cfg["shared_lmgs_train"]["lr_means"] == quick().train.lr_means
    other = create_method("gaussiantalker", preset="quick", budget_density=0.12)
    assert other.describe().config_hash != base.describe().config_hash


def test_degstalk_geometry_term_is_the_toolkits_lmgs_form():
    """DEGSTalk keeps a geometry term, in the same form as the toolkit's lmgs (not the preset's summed one)."""
    degs, full = create_method("degstalk").cfg, create_method("lmgs").cfg
    assert degs.gr and not degs.guidance.se and not degs.guidance.lc
    for field in ("normal_reduce", "lambda_normal", "lambda_depth", "gr_warmup"):
        assert getattr(degs.train, field) == getattr(full.train, field), field
    assert (degs.train.normal_reduce, degs.train.lambda_normal) == ("mean", 0.05)


@pytest.mark.parametrize("name", ["talkinggaussian", "degstalk"])
def test_lmgs_configured_baselines_train_with_their_budget_density(name):
    # a budget override reaches the lmgs training config (and so the hash), not only the budget record
    from lmgs.presets import quick

    base = create_method(name, preset="quick")
    assert base.cfg.train.budget_density == quick().train.budget_density
    other = create_method(name, preset="quick", budget_density=0.12)
    assert other.cfg.train.budget_density == 0.12
    assert other.describe().config_hash != base.describe().config_hash


@pytest.mark.parametrize("name,field,value", [("talkinggaussian", "budget_density", 0.2), ("gaussiantalker", "budget_density", 0.2),
                                              ("ernerf", "steps", 10), ("wav2lip", "steps", 10)])
def test_the_clis_set_reaches_a_baselines_schedule_and_an_unknown_key_is_one_line(name, field, value):
    # `lmgs-eval self --method NAME --set KEY=VALUE` hands the method overrides={KEY: VALUE} (it raised a TypeError)
    from types import SimpleNamespace

    from lmgs.errors import InputError
    from lmgs_eval.commands._common import parse_overrides

    want = create_method(name, preset="quick", **{field: value}).describe()
    assert want.config_hash != create_method(name, preset="quick").describe().config_hash
    for key in (field, f"train.{field}"):
        assert create_method(name, preset="quick", **parse_overrides([f"{key}={value}"])).describe().config_hash == \
            want.config_hash, key
    if field == "budget_density":  # --set wins over a subject's knee density
        knee = SimpleNamespace(budget_density=0.55)
        assert create_method(name, subject=knee, preset="quick", **parse_overrides([f"train.{field}={value}"])) \
            .describe().config_hash == want.config_hash
    with pytest.raises(InputError, match=f"method '{name}' has no setting 'nope'; its settings: .*{field}"):
        create_method(name, preset="quick", **parse_overrides(["nope=1"]))


def test_a_subject_knee_density_reaches_every_method_sized_by_face_area_and_no_other():
    """Every method whose config has a budget density is registered as sized by face area (so a
    subject's knee cannot miss one of them), takes the subject's density, and an explicit one wins."""
    from types import SimpleNamespace

    from baselines.protocol import list_methods, scene_budget_methods
    from lmgs_eval.results.records import _config_value

    knee = SimpleNamespace(budget_density=0.55)
    sized = set(scene_budget_methods())
    assert {"lmgs", "lmgs-base", "talkinggaussian", "degstalk", "gaussiantalker"} <= sized
    for name in (n for n in list_methods() if not n.startswith("external:")):
        plain = create_method(name, preset="quick").describe()
        on_subject = create_method(name, subject=knee, preset="quick").describe()
        if _config_value(plain.config, "budget_density") is None:
            assert name not in sized and on_subject.config_hash == plain.config_hash, name
            continue
        assert name in sized, f"{name} sizes by face area but is not registered scene_budget=True"
        assert _config_value(on_subject.config, "budget_density") == 0.55, name
        assert on_subject.config_hash != plain.config_hash, name
    # an explicit density (CLI --set, capacity's budgets) wins over the subject's
    assert create_method("talkinggaussian", subject=knee, budget_density=0.2).cfg.train.budget_density == 0.2
    lm = create_method("lmgs", subject=knee, overrides={"train.budget_density": 0.3})
    assert lm.cfg.train.budget_density == 0.3
    assert create_method("lmgs", subject=SimpleNamespace(budget_density=None)).describe().config_hash == \
        create_method("lmgs").describe().config_hash


@pytest.mark.parametrize("name", ["geneface", "ip_lap"])
def test_landmark_methods_take_the_generic_mouth(name, fitted, clip, tmp_path):
    """``landmark_source=generic``: the method's predicted mouth (48-67) is the generic lip model's, retargeted to the
    subject; the default's config (and every record's hash) is unchanged; the checkpoint keeps the retargeting."""
    import torch

    from baselines.common import audio_windows

    base, _ = fitted(name)
    assert "landmark_source" not in base.config()
    m = create_method(name, preset="tiny", landmark_source="generic")
    assert m.config_hash() != base.config_hash()
    assert any("generic lip model" in s for s in m.describe().standins)
    m.fit(clip, seed=0, workdir=tmp_path, progress=False)
    lips = m.model.lips
    assert lips is not None and base.model.lips is None
    windows = audio_windows(clip.audio, len(clip))
    with torch.no_grad():
        subject = base.model.predictor.predict(windows).numpy()
    want = lips.predict(windows.numpy())
    if name == "ip_lap":
        got = m._audio(m.model, windows)
        np.testing.assert_allclose(got[:, 48:68], want, atol=1e-6)
        with torch.no_grad():
            np.testing.assert_allclose(got[:, :48], m.model.predictor.predict(windows).numpy()[:, :48], atol=1e-6)
    assert not np.allclose(want, subject[:, 48:68], atol=1e-4)  # a different mouth than the subject predictor's
    d = DrivingAudio(audio=clip.audio[: 6 * 640], w2c=clip.w2c[:6])
    again = create_method(name, preset="tiny", landmark_source="generic")
    again.fit(clip, seed=5, workdir=tmp_path, progress=False)  # loads the checkpoint, the retargeting with it
    np.testing.assert_array_equal(m.render(d), again.render(d))


def test_geneface_coefficients_of_its_own_prediction_are_its_coefficients(fitted, clip):
    """The generic mouth reaches GeneFace's NeRF as the coefficients of the edited landmarks in the predictor's basis;
    with the predictor's own landmarks that is the predictor's own condition (on every component the NeRF reads)."""
    import torch

    from baselines.common import audio_windows
    from baselines.nerf.methods import _landmark_coefficients

    m, _ = fitted("geneface")
    p = m.model.predictor
    w = audio_windows(clip.audio, len(clip))
    mask = m.model.coef_mask.numpy() > 0  # the components the NeRF reads (the others have no spread in training)
    assert mask.any()
    with torch.no_grad():
        np.testing.assert_allclose(_landmark_coefficients(p, p.predict(w)).numpy()[:, mask], p.coefficients(w).numpy()[:, mask],
                                   atol=1e-4)


@pytest.mark.parametrize("name", ["adnerf", "wav2lip", "talkinggaussian"])
def test_a_method_without_landmarks_refuses_a_landmark_source(name):
    # the NeRF and 2D budgets carry the key for GeneFace and IP_LAP; the Gaussian baselines' schedules have no such key
    why = "has no setting 'landmark_source'" if name in GS else "reads no audio-predicted landmarks"
    with pytest.raises(InputError, match=f"method '{name}' {why}"):
        create_method(name, preset="tiny", landmark_source="generic")
    with pytest.raises(InputError, match="landmark_source=nope: not one of subject, generic, generic-tuned"):
        create_method("ip_lap", preset="tiny", landmark_source="nope")
