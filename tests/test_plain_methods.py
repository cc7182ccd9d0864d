"""Every registered method trains and renders on a plain processed folder.

The tiny bundled subject (astronaut, 64x64, 2 s) is stripped to what the field's preprocessing
leaves (``complete.PLAIN_LAYOUT``: no 3D landmarks, no depth / normal maps, no manifest);
``read_subject`` derives what the methods need. Each method is fitted on a short schedule,
renders the test split from its audio and is scored and recorded by the toolkit's runner, as
``lmgs-eval self`` runs it. ``external:NAME`` is left out: it trains nothing.

Floors, measured on this subject's 5 test frames with these schedules (seed 0): full-frame
PSNR 28.2-32.5 dB over the methods (adnerf lowest), 22.8-27.6 dB inside the head mask; what
garbage scores: the torso on the plate without a head 15.8 (head 9.3), a grey head 19.4
(12.9), the true head moved 4 px 18.0 (13.3), the true frames blurred by a 2 px Gaussian
20.8 (19.7).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from baselines.protocol import EXTERNAL_PREFIX, list_methods

SUBJECT = "astronaut-64px-2s"
METHODS = [m for m in list_methods() if not m.startswith(EXTERNAL_PREFIX)]
PSNR_FLOOR, HEAD_PSNR_FLOOR = 25.0, 19.0
# Short schedules: the baselines' ``tiny`` preset; lmgs and its variants have none (quick, cut down).
LMGS_FAST = {"train.static_steps": 40, "train.dynamic_steps": 40, "train.landmark_steps": 20, "train.densify_every": 20}


def _psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean per-frame PSNR (dB) of uint8 videos, over ``mask`` ``[T, H, W]`` when given (written out here)."""
    d = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    mse = d.mean(axis=(1, 2, 3)) if mask is None else np.array([d[i][mask[i]].mean() for i in range(len(d))])
    return float(np.mean(10 * np.log10(255.0**2 / np.maximum(mse, 1e-12))))


def _options(name: str) -> dict:
    from baselines.lmgs_method import VARIANTS

    return {"preset": "quick", "overrides": LMGS_FAST} if name in VARIANTS else {"preset": "tiny"}


def _feature_file(name: str) -> str | None:
    """The precomputed audio-feature file of the layout a method's front end reads (lmgs-ds: aud_ds.npy)."""
    from baselines.protocol import create_method
    from lmgs_eval.data.layout import _FEATURE_FILES

    audio = create_method(name, **_options(name)).describe().config.get("audio")
    return _FEATURE_FILES.get(audio.get("frontend")) if isinstance(audio, dict) else None


pytestmark = pytest.mark.usefixtures("one_thread")  # 64x64 frames: one thread (conftest.one_thread)


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """The stripped folder, read; its clips; and a copy with DeepSpeech features (the field's optional aud_ds.npy)."""
    from lmgs_eval.convert import driving_from_clip, subject_to_clip
    from lmgs_eval.data.complete import PLAIN_LAYOUT, strip_to_plain
    from lmgs_eval.data.layout import read_subject
    from lmgs_eval.data.registry import resolve_subject_dir

    full = resolve_subject_dir(SUBJECT, progress=False)
    root = strip_to_plain(full, tmp_path_factory.mktemp("plain") / "astronaut-plain")
    assert sorted(p.name for p in root.iterdir()) == sorted(PLAIN_LAYOUT)
    assert {p.suffix for p in (root / "ori_imgs").iterdir()} == {".jpg", ".lms"}
    subject = read_subject(root)
    train = subject_to_clip(subject, subject.train_ids)
    test = subject_to_clip(subject, subject.test_ids)
    return {"full": full, "root": root, "subject": subject, "train": train, "test": test,
            "driving": driving_from_clip(test)}


def _with_features(plain: dict, fname: str, tmp_path) -> dict:
    """The plain folder plus stand-in features in ``fname`` (the bundled subjects have none; their values do not matter here)."""
    import shutil

    from lmgs_eval.convert import driving_from_clip, subject_to_clip
    from lmgs_eval.data.layout import read_subject

    root = tmp_path / plain["root"].name
    shutil.copytree(plain["root"], root)
    n = plain["subject"].n_frames
    np.save(root / fname, np.random.default_rng(0).normal(size=(n, 16, 29)).astype(np.float32))
    s = read_subject(root)
    train, test = subject_to_clip(s, s.train_ids), subject_to_clip(s, s.test_ids)
    return {**plain, "root": root, "subject": s, "train": train, "test": test,
            "driving": driving_from_clip(test)}


def test_the_plain_folder_is_read_with_derived_geometry(plain):
    """The derived geometry against the full folder's own (the generator's true 3D landmarks,
    depth and normals). Measured (seed 0): the lifted landmarks reproject onto the 2D track to
    1e-6 px, their shape (centred) lies 8-9 % of the jaw width from the truth's; the depth prior
    covers 99.8 % of the true depth map at a 5.3 % median error, its normals 13.6 deg off."""
    from lmgs_eval.data.layout import read_subject

    s, full = plain["subject"], read_subject(plain["full"])
    assert s.describe()["geometry_derived"] and s.has_geometry and not full.describe()["geometry_derived"]
    assert plain["train"].landmarks3d is not None and plain["train"].depth is not None
    for i in range(s.n_frames):  # 3D landmarks on the camera rays of the 2D ones
        w2c = s.camera(i).world_to_camera.numpy().astype(np.float64)
        pc = s.landmarks3d[i] @ w2c[:3, :3].T + w2c[:3, 3]
        uv = np.stack([s.focal * pc[:, 0] / pc[:, 2] + s.cx, s.focal * pc[:, 1] / pc[:, 2] + s.cy], 1)
        np.testing.assert_allclose(uv, s.landmarks[i], atol=1e-3)
    for i in (0, s.n_frames - 1):
        got, true = s.landmarks3d[i], full.landmarks3d[i]
        jaw = np.linalg.norm(true[16] - true[0])
        shape_err = np.linalg.norm((got - got.mean(0)) - (true - true.mean(0)), axis=1).mean()
        assert shape_err < 0.15 * jaw, (i, shape_err / jaw)
        d, d_true = s.depth(i), full.depth(i)
        both = (d > 0) & (d_true > 0)
        assert both.sum() > 0.95 * (d_true > 0).sum(), i
        assert np.median(np.abs(d[both] - d_true[both]) / d_true[both]) < 0.08, i
        n, n_true = s.normal(i)[both], full.normal(i)[both]
        np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-3)
        cos = (n * n_true).sum(-1) / np.linalg.norm(n_true, axis=-1)
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))).mean() < 20.0, i


def test_a_geometry_term_weighs_the_plain_folders_derived_priors_as_derived(plain):
    """The ellipsoid ray-cast for a plain folder is a derived prior; the bundled folder's maps are the
    rendered head. lmgs and DEGSTalk (the methods with a geometry term) weigh the first by their
    derived-prior weights; on the bundled folder their configs, and hashes, are those built without a
    subject; TalkingGaussian (no geometry term) is the same on both; a run's own ``--set`` wins."""
    from baselines.lmgs_method import DERIVED_PRIORS
    from lmgs_eval.convert import subject_to_clip
    from lmgs_eval.data.layout import read_subject
    from lmgs_eval.runner import RunConfig, build_method

    full = read_subject(plain["full"])
    assert plain["subject"].priors_derived and plain["train"].priors_derived
    assert not full.priors_derived and not subject_to_clip(full, full.train_ids[:2]).priors_derived
    want = {k.removeprefix("train."): v for k, v in DERIVED_PRIORS.items()}
    for name in ("lmgs", "degstalk"):
        alone, on_full, on_plain = (build_method(RunConfig(), name, s) for s in (None, full, plain["subject"]))
        assert on_full.describe().config_hash == alone.describe().config_hash
        got = on_plain.describe().config["train"]
        assert {k: got.get(k) for k in want} == want, name
        assert on_plain.describe().config_hash != on_full.describe().config_hash
        assert "derived priors" not in on_full.describe().description
        assert "priors derived from the tracking" in on_plain.describe().description
    tg = {build_method(RunConfig(), "talkinggaussian", s).describe().config_hash for s in (full, plain["subject"])}
    assert len(tg) == 1
    mine = build_method(RunConfig(method_options={"overrides": {"train.derived_normal_weight": 1.0}}), "lmgs", plain["subject"])
    assert "derived_normal_weight" not in mine.describe().config["train"]


def test_recorded_footage_reads_the_generic_mouth_and_the_bundled_subjects_their_own(plain):
    """A plain folder is recorded footage: lmgs (and its variants with SE or LC) read the generic lip model's
    mouth, fine-tuned, with the mouth state and out-of-fold training landmarks; GeneFace and IP_LAP the same
    mouth. On the bundled folder, or built without a subject, every config is the per-subject predictor's,
    hash included; a variant without SE and LC, and methods that read no predicted landmarks, are the same on
    both; a run's own --set wins; a bundled subject trained on in a folder's place stays bundled."""
    from baselines.lmgs_method import ON_FOOTAGE
    from lmgs_eval.data.layout import read_subject
    from lmgs_eval.runner import RunConfig, build_method

    full = read_subject(plain["full"])
    assert full.bundled and not plain["subject"].bundled

    def config(name, subject, **opts):
        return build_method(RunConfig(**opts), name, subject).describe()

    want = {"mouth_state": True, "landmark_source": "generic-tuned", "landmark_folds": 5}
    assert {k.split(".")[1]: v for k, v in ON_FOOTAGE.items()} == want
    for name in ("lmgs", "lmgs-no-se", "lmgs-no-lc"):
        alone, on_full, on_plain = config(name, None), config(name, full), config(name, plain["subject"])
        assert on_full.config_hash == alone.config_hash
        got = on_plain.config
        assert (got["guidance"]["mouth_state"], got["train"]["landmark_source"], got["train"]["landmark_folds"]) == (
            True, "generic-tuned", 5), name
        assert on_full.config["train"].get("landmark_source", "subject") == "subject"
        assert not on_full.config["guidance"].get("mouth_state", False)
        assert on_plain.components["mouth_state"] and "generic lip model" in " ".join(on_plain.standins), name
    assert "generic mouth, tuned, mouth state" in config("lmgs", plain["subject"]).display_name
    for name in ("lmgs-base", "talkinggaussian", "wav2lip", "ernerf"):  # nothing reads a predicted mouth
        assert config(name, full).config == config(name, plain["subject"]).config, name
    for name in ("geneface", "ip_lap"):
        assert config(name, full).config.get("landmark_source", "subject") == "subject"
        assert config(name, plain["subject"]).config["landmark_source"] == "generic-tuned"
        assert config(name, plain["subject"]).display_name.endswith("(generic mouth, tuned)")
        assert "generic" not in config(name, full).display_name
    mine = config("lmgs", plain["subject"], method_options={"overrides": {"train.landmark_source": "subject"}})
    assert mine.config["train"].get("landmark_source", "subject") == "subject" and mine.config["guidance"]["mouth_state"]
    ours = config("geneface", plain["subject"], method_options={"overrides": {"landmark_source": "subject"}})
    assert ours.config.get("landmark_source", "subject") == "subject"
    # the end-to-end benches build every folder's method from the bundled subject, the folder's priors aside
    from baselines.protocol import create_method

    on_bundled = create_method("lmgs", subject=full, priors_from=plain["subject"]).describe()
    assert on_bundled.config["train"].get("landmark_source", "subject") == "subject"


def test_methods_lists_the_configs_a_subject_gets(plain):
    """``lmgs-eval methods --subject`` gives each method's hash as the protocols build it for that subject."""
    from conftest import run_cli
    from lmgs_eval.data.layout import read_subject
    from lmgs_eval.runner import RunConfig, build_method

    got = {}
    for folder in (plain["root"], plain["full"]):
        rc, out, err = run_cli("methods", "--subject", str(folder), "--json")
        assert rc == 0, err
        got[folder] = {m["name"]: m["config_hash"] for m in json.loads(out)["methods"]}
    for name in ("lmgs", "geneface", "degstalk", "talkinggaussian"):
        for folder, s in ((plain["root"], plain["subject"]), (plain["full"], read_subject(plain["full"]))):
            assert got[folder][name] == build_method(RunConfig(), name, s).describe().config_hash, (name, folder)
    assert got[plain["root"]]["lmgs"] != got[plain["full"]]["lmgs"]
    assert got[plain["root"]]["talkinggaussian"] == got[plain["full"]]["talkinggaussian"]
    rc, out, err = run_cli("methods", "--subject", str(plain["root"] / "nowhere"))
    assert rc == 2 and "nowhere" in err and "Traceback" not in err



@pytest.mark.parametrize("name", METHODS)
def test_every_method_trains_and_renders_on_a_plain_folder(name, plain, tmp_path):
    from lmgs.errors import InputError
    from lmgs_eval.results.records import RunId
    from lmgs_eval.runner import RunConfig, build_method, fit_render_score

    feature = _feature_file(name)
    if feature is not None:
        # the exact plain layout has no precomputed features: a one-line refusal that names the file
        method = build_method(RunConfig(), name, plain["subject"], **_options(name))
        with pytest.raises(InputError, match=feature):
            method.fit(plain["train"], seed=0, workdir=tmp_path / "refused", progress=False)
        plain = _with_features(plain, feature, tmp_path)
    s, test = plain["subject"], plain["test"]
    cfg = RunConfig(subject=str(plain["root"]), results=tmp_path / "results", progress=False)
    method = build_method(cfg, name, s, **_options(name))
    rec = fit_render_score(cfg, method, RunId(s, method.describe()), plain["train"], plain["driving"], test.frames,
                           f"renders/{name}.mp4", workdir=tmp_path / "model")

    frames = method.render(plain["driving"])
    assert frames.shape == test.frames.shape and frames.dtype == np.uint8
    got, head = _psnr(frames, test.frames), _psnr(frames, test.frames, test.head_masks)
    assert got > PSNR_FLOOR, f"{name}: {got:.2f} dB"
    assert head > HEAD_PSNR_FLOOR, f"{name}: {head:.2f} dB inside the head"
    assert rec.metrics["psnr"].value == pytest.approx(got, abs=0.5)  # the run scored these frames

    # the record says what was derived, and where it is
    derived = [n for n in rec.notes if "derived 3D landmarks" in n]
    assert len(derived) == 1 and "depth / normal priors" in derived[0] and str(plain["root"]) in derived[0]
    cache = derived[0].split("cached at ")[1].split(" (")[0]
    assert (Path(cache) / "lms3d.npy").is_file()
    assert rec.subject.path == str(plain["root"]) and rec.subject.sha256 is None  # no manifest



def test_bench_stripped_prints_the_full_and_the_stripped_run_side_by_side(tmp_path):
    """``lmgs-eval bench stripped`` on the tiny subject with a short schedule: two records of one config."""
    import json

    from conftest import run_cli
    from lmgs_eval.commands.bench import _in_all
    from lmgs_eval.results import load_records

    sets = [a for k, v in LMGS_FAST.items() for a in ("--set", f"{k}={v}")]
    rc, out, err = run_cli("bench", "stripped", "--size", "64", "--seconds", "2", *sets, "--results", str(tmp_path / "res"),
                           "--json")
    assert rc == 0, err
    got = json.loads(out)
    rows = {r["figure"]: r for r in got["rows"]}
    psnr = rows["PSNR dB"]
    assert psnr["full"] > PSNR_FLOOR and psnr["stripped"] > PSNR_FLOOR
    assert psnr["stripped - full"] == pytest.approx(psnr["stripped"] - psnr["full"])
    assert rows["LPIPS"]["full"] is not None and rows["LPIPS"]["stripped"] is not None
    assert rows["LMD px"]["full"] is None and "no face" in rows["LMD px"]["note"]  # dlib finds no face at 64 px
    assert rows["folder MB"]["stripped"] < rows["folder MB"]["full"]  # no depth / normal maps, no video
    assert rows["train, s"]["full"] > 0 and rows["train, s"]["stripped"] > 0
    assert "derived 3D landmarks" in got["derived"]
    stripped_root = got["stripped"].split(" (")[0]
    assert not Path(stripped_root).exists()  # the copy is temporary

    recs = sorted(load_records(tmp_path / "res")[0], key=lambda r: r.subject.name)
    assert [r.subject.name for r in recs] == [SUBJECT, f"{SUBJECT}-plain"]
    # one config, but for the derived priors of the stripped copy, which lmgs's geometry term weighs as such
    assert recs[0].config_hash != recs[1].config_hash and recs[0].seed == recs[1].seed == 0
    full_train, plain_train = (dict(r.config["train"]) for r in recs)
    assert "derived_normal_weight" not in full_train and plain_train.pop("derived_normal_weight") == 0.0
    assert full_train == plain_train
    assert f"{recs[0].config_hash} (full)" in got["method"] and f"{recs[1].config_hash} (stripped)" in got["method"]
    assert not any("derived" in n for n in recs[0].notes) and any("derived 3D landmarks" in n for n in recs[1].notes)
    assert recs[1].metrics["psnr"].value == pytest.approx(psnr["stripped"])
    assert not _in_all("stripped") and _in_all("raster")  # `bench all` stays a speed benchmark


# ----------------------------------------------------------------------------- against the full folder
LARGER = "astronaut-128px-4s"
# How much lower a method may score on the plain copy than on the full folder, by family.
# Measured (seed 0, these schedules, 10 test frames): the 3DGS methods lose 2.6-3.8 dB (lmgs
# 32.92 -> 29.64, GaussianTalker 33.42 -> 29.64, DEGSTalk 32.36 -> 29.78): they place their
# first Gaussians on the depth prior, and the derived face sits 3.6 cm behind the generator's
# (placed where the truth is, lmgs gets 31.87). The NeRF methods move -0.2..+1.2 dB, the 2D
# ones 0..-0.1.
GAP_DB = {"3DGS": 5.0, "NeRF": 1.0, "2D": 1.0}


def _load(root: Path) -> dict:
    from lmgs_eval.convert import driving_from_clip, subject_to_clip
    from lmgs_eval.data.layout import read_subject

    s = read_subject(root)
    test = subject_to_clip(s, s.test_ids)
    return {"root": root, "subject": s, "train": subject_to_clip(s, s.train_ids), "test": test,
            "driving": driving_from_clip(test)}


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    from lmgs_eval.data.complete import strip_to_plain
    from lmgs_eval.data.registry import resolve_subject_dir

    full = resolve_subject_dir(LARGER, progress=False)
    plain = strip_to_plain(full, tmp_path_factory.mktemp("plain-larger") / f"{LARGER}-plain")
    return {"full": _load(full), "plain": _load(plain)}


@pytest.mark.slow
@pytest.mark.parametrize("name", METHODS)
def test_every_method_on_a_plain_folder_scores_near_the_full_folder(name, both, tmp_path):
    """Each method, same schedule and seed, on the 128 px subject and on its plain copy: the derived
    geometry costs little against the generator's own."""
    from baselines.protocol import create_method

    got = {}
    for kind, d in both.items():
        feature = _feature_file(name)
        if feature is not None:  # stand-in features in both folders (the bundled subjects have none)
            import shutil

            root = tmp_path / kind / d["root"].name
            shutil.copytree(d["root"], root)
            np.save(root / feature, np.random.default_rng(0).normal(size=(d["subject"].n_frames, 16, 29)).astype(np.float32))
            d = _load(root)
        m = create_method(name, subject=both["full"]["subject"], **_options(name))
        m.fit(d["train"], seed=0, workdir=tmp_path / kind, progress=False)
        frames = m.render(d["driving"])
        assert frames.shape == d["test"].frames.shape and frames.dtype == np.uint8
        got[kind] = _psnr(frames, d["test"].frames), _psnr(frames, d["test"].frames, d["test"].head_masks)
    print(f"{name}: full {got['full'][0]:.2f} dB (head {got['full'][1]:.2f}), plain {got['plain'][0]:.2f} (head {got['plain'][1]:.2f})")
    assert got["plain"][0] > PSNR_FLOOR and got["plain"][1] > HEAD_PSNR_FLOOR
    assert got["plain"][0] > got["full"][0] - GAP_DB[m.describe().family]
