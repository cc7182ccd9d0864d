"""The lip model's weights files (lmgs.lips_weights): the shipped ones and their sha256, other files named by
theirs, their provenance, the config key that names them, and the guard against scoring a clip they were
adapted on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from lmgs import lips, lips_weights
from lmgs.errors import InputError
from lmgs.fileio import sha256_file

FOOTAGE = Path(__file__).resolve().parents[1] / ".." / "shared" / "footage"


@pytest.mark.parametrize("name", sorted(lips_weights.WEIGHTS))
def test_shipped_weights_match_their_sha256(name):
    path = lips_weights.FOLDER / name
    assert path.stat().st_size < 4 << 20  # a few MB at most
    assert sha256_file(path) == lips_weights.WEIGHTS[name][1]
    model = lips.load(name)
    assert model.template.abs().sum() > 0  # the canonical face travels with the weights


def test_altered_weights_are_refused(tmp_path, monkeypatch):
    bad = tmp_path / "lips_generic.pt"
    bad.write_bytes((lips_weights.FOLDER / "lips_generic.pt").read_bytes()[:-8] + b"\0" * 8)
    monkeypatch.setattr(lips_weights, "FOLDER", tmp_path)
    with pytest.raises(InputError, match="altered"):
        lips.load("lips_generic.pt")


def _weights_file(tmp_path, clips=(), held=()) -> Path:
    """A lip model's weights file (the shipped one, perturbed) with its provenance beside it."""
    model = lips.load()
    with torch.no_grad():
        model.head.bias.add_(0.01)
    path = tmp_path / "held" / "lips_generic.pt"
    path.parent.mkdir(parents=True, exist_ok=True)
    lips.save(model, path)
    lips_weights.write_provenance(path, list(clips), held_out=list(held))
    return path


def test_shipped_provenance_names_what_each_file_was_adapted_on():
    """The pretrained file saw no real recording; the shipped model names each real clip it was adapted on by its
    video file's sha256 (what the toolkit's guard compares)."""
    assert lips_weights.adapted_on("lips_generated.pt") == []
    seen = lips_weights.adapted_on(lips_weights.DEFAULT)
    assert seen and all(len(c["sha256"]) == 64 and c["frames"] > 0 and c["clip"] for c in seen)
    assert len({c["sha256"] for c in seen}) == len(seen)
    if FOOTAGE.is_dir():  # where the development footage is, the recorded sha256 are its files'
        have = {p.stem: sha256_file(p) for p in FOOTAGE.glob("*.mp4")}
        assert all(have.get(c["clip"]) == c["sha256"] for c in seen)


def test_a_weights_file_is_named_by_its_sha256_and_checked_on_reload(tmp_path):
    """A retargeting on a weights file keeps the file's sha256; the checkpoint's state reloads the same mouth, and
    a file changed since is refused in one line."""
    path = _weights_file(tmp_path, clips=[{"clip": "a", "sha256": "0" * 64, "frames": 10}], held=["b"])
    rng = np.random.default_rng(3)
    tpl = lips.load().template.numpy().astype(np.float64)
    world = np.repeat(tpl[None], 20, 0) * 2.0
    world[:, lips.MOUTH, 1] += 0.003 * rng.standard_normal((20, 20))
    feats = rng.standard_normal((20, lips.WINDOW, lips.IN_CHANNELS)).astype(np.float32)
    ret = lips.retarget_for("generic", rng.standard_normal(20 * 640).astype(np.float32), 20, world, weights=str(path))
    state = ret.to_state()
    assert state["name"] == str(path) and state["sha256"] == sha256_file(path) != lips_weights.WEIGHTS[lips_weights.DEFAULT][1]
    assert ret.describe()["weights_sha256"] == sha256_file(path)
    np.testing.assert_allclose(lips.RetargetedLips.from_state(state).predict(feats), ret.predict(feats), atol=1e-6)
    shipped = lips.retarget_for("generic", rng.standard_normal(20 * 640).astype(np.float32), 20, world)
    assert np.abs(shipped.model.predict(feats) - ret.model.predict(feats)).max() > 1e-4  # the file's weights are used
    assert "b held out" in lips_weights.describe_weights(path) and lips_weights.adapted_on(path)[0]["clip"] == "a"
    path.write_bytes(path.read_bytes()[:-8] + b"\0" * 8)
    with pytest.raises(InputError, match="not the one there now"):
        lips.RetargetedLips.from_state(state)


def test_lip_weights_key():
    """``train.lip_weights`` is left out of the config (and hash) at the shipped model, names the weights in the
    record's stand-ins otherwise, and is refused in one line where it names nothing or nothing reads it."""
    from baselines.protocol import create_method
    from lmgs.presets import quick

    base = quick().replace(**{"train.landmark_source": "generic"})
    assert "lip_weights" not in base.to_dict()["train"]
    other = base.replace(**{"train.lip_weights": "lips_generated.pt"})
    assert other.hash() != base.hash()
    info = create_method("lmgs", preset="quick", overrides={"train.landmark_source": "generic",
                                                             "train.lip_weights": "lips_generated.pt"}).describe()
    assert any("pretrained on the bundled generator's clips" in s for s in info.standins)
    with pytest.raises(InputError, match=r"^--set train.lip_weights: /nowhere/x.pt: no such lip model file"):
        create_method("lmgs", preset="quick", overrides={"train.landmark_source": "generic",
                                                          "train.lip_weights": "/nowhere/x.pt"})
    with pytest.raises(InputError, match="read only with --set train.landmark_source=generic"):
        create_method("lmgs", preset="quick", overrides={"train.lip_weights": "lips_generated.pt"})
    with pytest.raises(InputError, match=r"^--set lip_weights: /nowhere/x.pt: no such lip model file"):
        create_method("ip_lap", preset="tiny", landmark_source="generic", lip_weights="/nowhere/x.pt")
    assert create_method("geneface", preset="tiny", landmark_source="generic",
                         lip_weights="lips_generated.pt").lip_weights() == "lips_generated.pt"


def _ingested(tmp_path, sha: str):
    """A subject as the toolkit sees one, whose manifest names the video it was made from by ``sha``."""
    import json
    from types import SimpleNamespace

    root = tmp_path / "subj"
    root.mkdir(parents=True)
    (root / "manifest.json").write_text(json.dumps({"input": {"video": "v.mp4", "sha256": sha}, "audio": {"sha256": None}}))
    return SimpleNamespace(name="subj", root=root)


@pytest.mark.parametrize("method,opts", [("lmgs", {"overrides": {"train.landmark_source": "generic"}}),
                                         ("ip_lap", {"preset": "tiny", "landmark_source": "generic"})])
def test_a_clip_the_lip_model_was_adapted_on_is_not_scored(tmp_path, method, opts):
    """Scoring a method that reads the lip model on a clip that model was adapted on would score it on its own
    training data: the toolkit refuses in one line naming the way out, and takes weights made without the clip."""
    from baselines.protocol import create_method
    from lmgs_eval.errors import UserError
    from lmgs_eval.runner import check_lips_held_out

    seen = "ab" * 32
    subject = _ingested(tmp_path, seen)
    opts = {"preset": "quick", **opts}
    key = "train.lip_weights" if method == "lmgs" else "lip_weights"

    def build(weights):
        o = dict(opts)
        if method == "lmgs":
            o["overrides"] = {**o["overrides"], key: weights}
        else:
            o[key] = weights
        return create_method(method, **o)

    bad = _weights_file(tmp_path / "bad", clips=[{"clip": "talk", "sha256": seen, "frames": 50}])
    with pytest.raises(UserError, match=r"was adapted on this very clip \(talk\).*--hold-out talk"):
        check_lips_held_out(build(str(bad)), subject)
    if method == "ip_lap":  # every protocol builds its methods so: the run stops before anything is trained
        from lmgs_eval.runner import RunConfig, build_method

        with pytest.raises(UserError, match="adapted on this very clip"):
            build_method(RunConfig(), method, subject, preset="tiny", landmark_source="generic", lip_weights=str(bad))
    good = _weights_file(tmp_path / "good", clips=[{"clip": "other", "sha256": "cd" * 32, "frames": 50}], held=["talk"])
    check_lips_held_out(build(str(good)), subject)
    plain = create_method(method, preset=opts["preset"])  # the per-subject predictor reads no lip model
    check_lips_held_out(plain, subject)
    if FOOTAGE.is_dir() and (FOOTAGE / "anchor_de_20s.mp4").is_file():  # the shipped model saw the footage
        with pytest.raises(UserError, match="anchor_de_20s"):
            check_lips_held_out(build(lips_weights.DEFAULT), _ingested(tmp_path / "a", sha256_file(FOOTAGE / "anchor_de_20s.mp4")))


@pytest.mark.parametrize("method,key,preset", [("lmgs", "train.landmark_source", "quick"),
                                               ("geneface", "landmark_source", "tiny")])
def test_footage_the_shipped_lip_model_saw_stops_by_default(tmp_path, method, key, preset):
    """On recorded footage the shipped lip model is read by default, so a subject ingested from a clip it was
    adapted on stops as the run is built, in one line naming both ways out; the per-subject predictor runs."""
    from lmgs.lips_weights import DEFAULT, adapted_on
    from lmgs_eval.errors import UserError
    from lmgs_eval.runner import RunConfig, build_method

    seen = adapted_on(DEFAULT)[0]
    subject = _ingested(tmp_path, seen["sha256"])
    subject.bundled = False
    with pytest.raises(UserError, match=rf"\({seen['clip']}\).*--hold-out.*landmark_source=subject"):
        build_method(RunConfig(preset=preset), method, subject)
    mine = build_method(RunConfig(preset=preset, method_options={"overrides": {key: "subject"}}), method, subject)
    assert mine.lip_weights() is None
    subject.bundled = True  # a bundled subject reads its per-subject predictor: nothing to refuse
    assert build_method(RunConfig(preset=preset), method, subject).lip_weights() is None


def test_shipped_provenance_is_what_the_script_writes(tmp_path):
    """The committed ``provenance.json`` is byte for byte what ``scripts/train_lip_model.py`` writes for the clips it
    lists (so a re-run can be compared with ``cmp``)."""
    import json

    doc = json.loads((lips_weights.FOLDER / lips_weights.PROVENANCE).read_text())
    assert doc["lips_generated.pt"]["adapted_on"] == [] and len(doc["lips_generic.pt"]["adapted_on"]) == 11
    lips_weights.write_shipped_provenance(tmp_path, doc["lips_generic.pt"]["adapted_on"])
    assert (tmp_path / lips_weights.PROVENANCE).read_bytes() == (lips_weights.FOLDER / lips_weights.PROVENANCE).read_bytes()
