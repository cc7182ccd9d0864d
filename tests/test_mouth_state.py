"""``guidance.mouth_state``: the deformations read the mouth's opening and width from the landmarks."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from lmgs.checkpoint import load_model, save_model
from lmgs.guidance import mouth_state
from lmgs.model import MOUTH_STATE_MIN_SPREAD
from lmgs.presets import quick
from lmgs.train import fit
from lmgs.types import DrivingAudio
from model_fixtures import synthetic_clip


def _face(gap: float, width: float, eyes: float) -> np.ndarray:
    """68 points with the outer eye corners ``eyes`` apart, the mouth corners ``width`` apart and the
    inner lips' middles ``gap`` apart (every other point at the origin)."""
    p = np.zeros((68, 3))
    p[36], p[45] = [-eyes / 2, 1.0, 0.0], [eyes / 2, 1.0, 0.0]
    p[48], p[54] = [-width / 2, -1.0, 0.0], [width / 2, -1.0, 0.0]
    p[62], p[66] = [0.0, -1.0 + gap / 2, 0.0], [0.0, -1.0 - gap / 2, 0.0]
    return p


def test_the_mouth_state_is_opening_and_width_over_the_eye_distance_whatever_the_pose():
    face = _face(gap=0.5, width=1.0, eyes=2.0)
    np.testing.assert_allclose(mouth_state(torch.tensor(face)).numpy(), [0.25, 0.5], atol=1e-12)
    # moved, turned and seen from three times as far: the same state
    a = 0.7
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    moved = 3.0 * face @ rot.T + [0.3, -2.0, 5.0]
    batch = torch.tensor(np.stack([face, moved]))
    np.testing.assert_allclose(mouth_state(batch).numpy(), [[0.25, 0.5], [0.25, 0.5]], atol=1e-12)
    with pytest.raises(Exception, match="68 landmarks"):
        mouth_state(torch.zeros(20, 3))


def _cfg(**guidance):
    cfg = quick()
    cfg = cfg.replace(train=dataclasses.replace(cfg.train, static_steps=60, dynamic_steps=40, landmark_steps=20,
                                                densify_every=20, checkpoint_every=30))
    return cfg.replace(guidance=dataclasses.replace(cfg.guidance, **guidance))


def test_off_it_leaves_the_config_hash_and_on_it_keeps_the_landmark_keys():
    assert _cfg().hash() == _cfg(mouth_state=False).hash() != _cfg(mouth_state=True).hash()
    # TalkingGaussian's switches (no SE, no LC) with the mouth state: the landmarks are read, so the
    # keys that choose them stay in the config
    def folds(cfg):
        return cfg.replace(train=dataclasses.replace(cfg.train, landmark_folds=5))

    tg = folds(_cfg(se=False, lc=False, mouth_state=True)).to_dict()
    assert tg["guidance"]["mouth_state"] is True and tg["train"]["landmark_folds"] == 5
    assert "landmark_folds" not in folds(_cfg(se=False, lc=False)).to_dict()["train"]


@pytest.fixture(scope="module")
def clip():
    """The synthetic clip with its inner lips (62 / 66) apart by the mouth's opening."""
    c = synthetic_clip()
    lms = c.landmarks3d.copy()
    open_amt = (lms[:, 61, 1] - lms[0, 60, 1]) / -0.03  # the fixture's opening, read back from point 61
    lms[:, 66, 1] = lms[:, 62, 1] - 0.02 - 0.05 * open_amt
    return dataclasses.replace(c, landmarks3d=lms)


def test_a_fitted_model_reads_the_state_normalised_by_its_training_frames(clip, tmp_path):
    cfg = _cfg(mouth_state=True)
    model, _ = fit(clip, cfg, seed=0, progress=False)
    # the centre and spread are those of the training landmarks the model guided itself with
    # (in-sample predictions of the landmark predictor fitted on the clip's landmarks)
    pred = model.predictor.predict(model.audio_windows(clip.audio, len(clip)))
    s = mouth_state(pred)
    np.testing.assert_allclose(model.mouth_state_norm[0].numpy(), s.median(0).values.numpy(), rtol=1e-5)
    np.testing.assert_allclose(model.mouth_state_norm[1].numpy(), s.std(0).clamp_min(MOUTH_STATE_MIN_SPREAD).numpy(),
                               rtol=1e-5)
    assert model.mouth_state_norm[1, 0] > MOUTH_STATE_MIN_SPREAD  # the opening moves on this clip
    assert model.face_deform.exp_total == 1 + 2 and model.mouth_deform.exp_total == 2

    d = DrivingAudio(audio=clip.audio[: 8 * 640], w2c=clip.w2c[:8])
    frames = model.render(d)
    # the state drives the deformation: pushed two spreads open, the same audio renders another head
    pushed = model.mouth_states
    model.mouth_states = lambda lms: None if lms is None else pushed(lms) + torch.tensor([2.0, 0.0])
    assert np.abs(model.render(d).astype(int) - frames).max() > 0
    del model.mouth_states
    save_model(model, tmp_path / "m.pt")
    np.testing.assert_array_equal(load_model(tmp_path / "m.pt", cfg=cfg).render(d), frames)


def test_a_still_mouth_is_not_blown_up():
    model_cfg = _cfg(mouth_state=True)
    from lmgs.gaussians import GaussianSet
    from lmgs.model import LMGSModel

    gs = GaussianSet(torch.zeros(4, 3), torch.full((4, 3), 0.5), 0.01)
    m = LMGSModel(model_cfg, gs, gs, 80, 16, [-1, -1, -1], [1, 1, 1], [50, 24, 24, 48, 48])
    still = torch.tensor(np.stack([_face(0.2 + 1e-6 * k, 1.0, 2.0) for k in range(10)]), dtype=torch.float32)
    m.fit_mouth_state(still)
    assert float(m.mouth_state_norm[1].min()) == pytest.approx(MOUTH_STATE_MIN_SPREAD)
    assert float(m.mouth_states(still).abs().max()) < 1e-3


def test_the_record_names_the_mouth_state():
    from baselines.lmgs_method import LMGSMethod

    plain = LMGSMethod().describe()
    on = LMGSMethod(overrides={"guidance.mouth_state": True}).describe()
    assert plain.display_name == "Ours (lmgs)" and "mouth_state" not in plain.components
    assert on.display_name == "Ours (lmgs, mouth state)" and on.components["mouth_state"] is True
    assert "mouth's opening and width" in on.description and on.config_hash != plain.config_hash
    # TalkingGaussian's switches with the mouth state read landmarks, so the folds are theirs
    tg = LMGSMethod(overrides={"guidance.se": False, "guidance.lc": False, "guidance.mouth_state": True,
                               "train.landmark_folds": 5}).describe()
    assert tg.components["landmark_folds"] == 5 and "out-of-fold" in tg.description
