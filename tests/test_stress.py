"""The stability suite on a tiny bundled subject: every condition runs, broken methods are
recorded as failed without stopping the suite, and the stress metrics match hand-computed cases."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from baselines import protocol as methods
from lmgs_eval.errors import UserError
from baselines.protocol import MethodInfo
from lmgs_eval.protocols.perturb import make_conditions
from lmgs_eval.runner import RunConfig
from lmgs_eval.results import load_records, validate
from lmgs_eval.protocols.stress import check_output, jitter_result, run_stress, silence_open_result

SUBJECT = "astronaut-64px-2s"


class _Toy:
    """A cheap method: the background with a bar whose height follows the audio energy."""

    mode = "ok"

    def __init__(self, preset: str = "quick", **_):
        self.name = f"toy-{self.mode}"

    def describe(self):
        return MethodInfo(self.name, self.name, "2D", f"test method ({self.mode})", config={"mode": self.mode},
                          config_hash=f"toy{self.mode}")

    def fit(self, clip, *, seed, workdir, progress=True):
        assert len(clip) == clip.frames.shape[0]  # as the baselines' fit does (len of a lazily loaded clip too)
        self.shape = clip.frames.shape[1:]

    def render(self, driving):
        n = driving.n_frames
        a = driving.audio[: n * 640].reshape(n, 640)
        rms = np.sqrt((a.astype(np.float64) ** 2).mean(axis=1))
        if self.mode == "raise" and rms.max() == 0 and n > 3:  # (3: the warm-up render)
            raise ValueError("cannot handle silence")
        if self.mode == "nan" and n > 1000:
            return np.full((n, *self.shape), np.nan, np.float32)
        if self.mode == "frozen":
            return np.repeat(driving.backgrounds[:1], n, axis=0)
        out = driving.backgrounds.copy()
        for t in range(n):
            out[t, 40:40 + int(min(20, 200 * rms[t])), 28:36] = 0
        return out

    def cost(self):
        return {"n_params": 0, "model_mb": 0.0}


class ToyOk(_Toy):  # module-level: a worker process of jobs > 1 receives the class by reference
    mode = "ok"


class ToyRaise(_Toy):
    mode = "raise"


def _register(monkeypatch, mode):
    cls = type(f"Toy{mode}", (_Toy,), {"mode": mode})
    monkeypatch.setitem(methods._REGISTRY, f"toy-{mode}", cls)
    return f"toy-{mode}"


def test_every_condition_runs_and_broken_methods_are_recorded_as_failed(monkeypatch, tmp_path):
    names = [_register(monkeypatch, m) for m in ("ok", "raise", "nan", "frozen")]
    cfg = RunConfig(subject=SUBJECT, methods=tuple(names), results=tmp_path, progress=False)
    records, messages = run_stress(cfg, long_seconds=60.0)
    assert messages == []
    recs, warnings = load_records(tmp_path)
    assert warnings == [] and len(recs) == len(records)
    for r in recs:
        assert validate(r) == [], validate(r)
    by = {(r.method.name, r.protocol.clip): r for r in recs}
    conds = {c.name for c in make_conditions(np.ones(16000, np.float32), other_voice=np.ones(8000, np.float32), long_seconds=60.0)}
    for name in names:
        assert {c for (m, c) in by if m == name} == conds  # the suite went on after every failure
    failed = {k: r.status.reason for k, r in by.items() if r.failed}
    assert not any(m == "toy-ok" for m, _ in failed)
    assert failed[("toy-raise", "silence")].startswith("crash: ValueError: cannot handle silence")
    assert [c for (m, c) in failed if m == "toy-raise"] == ["silence"]
    assert "non-finite" in failed[("toy-nan", "long-1min")]
    assert [c for (m, c) in failed if m == "toy-nan"] == ["long-1min"]
    assert failed[("toy-frozen", "clean")].startswith("frozen output")
    assert ("toy-frozen", "silence") not in failed  # a still mouth on silence is right
    # the stressed inputs went through the user-file path: 44.1 kHz and stereo become 16 kHz mono
    assert by[("toy-ok", "rate-44k")].protocol.n_frames == by[("toy-ok", "clean")].protocol.n_frames
    assert any("resampled from 44100" in n for n in by[("toy-ok", "rate-44k")].notes)
    assert any("channels mixed to mono" in n for n in by[("toy-ok", "stereo")].notes)
    assert by[("toy-ok", "long-1min")].protocol.n_frames == 1500
    # the clean clip is timed like the self protocol (median of 3 renders), a perturbed one once
    assert by[("toy-ok", "clean")].cost.render_repeats == 3
    assert {r.cost.render_repeats for (m, c), r in by.items() if m == "toy-ok" and c != "clean"} == {1}
    # resume: a second run redoes only the failed conditions
    records2, _ = run_stress(RunConfig(subject=SUBJECT, methods=("toy-ok",), results=tmp_path, progress=False), long_seconds=60.0)
    assert records2 == []
    # the stability table and heat-map come from these records
    from lmgs_eval.report import tables

    md = tables.table_stability(recs, "jitter").markdown() if any("jitter" in r.metrics for r in recs) else \
        tables.table_stability(recs, "lse_c").markdown()
    assert "failed" in md
    # the suite's cost beside it: the wall time of each method's stress runs
    t = tables.table_stability(recs, "lse_c")
    for row in t.sections[0].rows:
        want = sum(r.cost.wall_seconds for r in row.records) / 60
        assert row.cells["suite_min"].text == f"{want:.1f}"


def test_jitter_and_silence_opening_by_hand():
    lms = np.zeros((5, 68, 2))
    lms[:, 48:68, 1] = np.array([0, 0, 1, 0, 0])[:, None]  # one frame jumps 1 px
    r = jitter_result(lms)
    # accelerations at t=1,2,3: 1, -2, 1 -> mean |.| = 4/3
    assert r.value == pytest.approx(4 / 3) and r.n_effective == 3
    lms[:, 66, 1] = 3.0
    lms[:, 62, 1] = 1.0
    s = silence_open_result(lms, ((0.0, 0.08),), fps=25.0)  # frame centres 0.02, 0.06
    assert s.n_original == 2 and s.value == pytest.approx(2.0)
    assert silence_open_result(lms, ()) is None
    lms[2] = np.nan
    assert jitter_result(lms).n_effective == 0 and jitter_result(lms).value is None


def test_check_output_names_the_failure():
    audio = np.random.default_rng(0).standard_normal(3 * 640).astype(np.float32)
    ok = np.random.default_rng(1).integers(0, 255, (3, 8, 8, 3), dtype=np.uint8)
    assert check_output(ok, 3, audio) is None
    assert "frozen" in check_output(np.repeat(ok[:1], 3, axis=0), 3, audio)
    assert check_output(np.repeat(ok[:1], 3, axis=0), 3, np.zeros_like(audio)) is None
    assert "shape" in check_output(ok[:2], 3, audio)


def test_stress_lse_of_uint8_frames_equals_lse_of_float_frames(monkeypatch):
    """The stress suite scores uint8 renders without a float copy, reading the landmarks its own tracker
    found instead of tracking again; same numbers as the float path that tracks the face itself, and a
    long clip (here: longer than a patched 10-frame limit) detects faces every 5th frame."""
    import cv2
    from skimage import data

    from lmgs_eval.metrics.config import SuiteConfig
    from lmgs_eval.metrics.landmarks import DlibBackend
    from lmgs_eval.metrics.metric_suite import MetricSuite
    from lmgs_eval.protocols import stress

    face = cv2.resize(data.astronaut(), (256, 256), interpolation=cv2.INTER_AREA)
    frames = np.stack([np.roll(face, (i % 3, (i // 2) % 3), axis=(0, 1)) for i in range(24)]).astype(np.uint8)
    t = np.arange(24 * 640) / 16000
    audio = (0.3 * np.sin(2 * np.pi * 180 * t) * (0.6 + 0.4 * np.sin(2 * np.pi * 3 * t))).astype(np.float32)
    want = MetricSuite().lse(frames.astype(np.float32) / 255.0, audio)
    assert want.available
    lms = DlibBackend().landmarks(frames)  # the stress suite's tracker, as run_stress builds it
    got = stress.lse_u8(MetricSuite(), frames, audio, lms)
    assert got.values == want.values and got.flags == want.flags
    monkeypatch.setattr(stress, "LONG_CLIP_FRAMES", 10)
    long_got = stress.lse_u8(MetricSuite(), frames, audio, lms)
    long_want = MetricSuite().lse(frames.astype(np.float32) / 255.0, audio, detect_every=5)
    assert long_got.values == long_want.values
    assert any("every 5th frame" in n for n in long_got.notes)
    # the run's --sync choice travels with its suite (stress workers are other processes)
    assert stress.lse_u8(MetricSuite(SuiteConfig(sync="pixel")), frames, audio, lms).spec.backend == "onnxruntime:bundled-sync"


def test_jobs_run_the_suites_in_worker_processes_with_the_same_results(monkeypatch, tmp_path):
    monkeypatch.setitem(methods._REGISTRY, "toy-ok", ToyOk)
    monkeypatch.setitem(methods._REGISTRY, "toy-raise", ToyRaise)
    conds = ("silence", "noise-snr10")
    cfg = RunConfig(subject=SUBJECT, methods=("toy-ok", "toy-raise"), progress=False)
    serial, _ = run_stress(dataclasses.replace(cfg, results=tmp_path / "serial"), conds, long_seconds=60.0)
    # with jobs > 1 the workers build the context (subject, conditions, landmarks); the parent only checks names
    import lmgs_eval.protocols.stress as stress_mod

    monkeypatch.setattr(stress_mod, "_context", lambda *a, **k: pytest.fail("the parent built the stress context"))
    with pytest.raises(UserError, match="unknown condition.*gargle"):
        run_stress(cfg, ("silence", "gargle"), jobs=2)
    par, messages = run_stress(dataclasses.replace(cfg, results=tmp_path / "jobs"), conds, long_seconds=60.0, jobs=2)
    assert messages == []
    key = [(r.method.name, r.protocol.clip) for r in serial]
    assert [(r.method.name, r.protocol.clip) for r in par] == key and len(key) == 6
    for a, b in zip(serial, par):
        assert {k: v.value for k, v in a.metrics.items()} == {k: v.value for k, v in b.metrics.items()}
        assert a.status == b.status
        assert any("--jobs 2" in n and "contended" in n for n in b.notes)
        assert not any("--jobs" in n for n in a.notes)
    assert par[4].status.reason.startswith("crash: ValueError: cannot handle silence")  # toy-raise / silence
    recs, warnings = load_records(tmp_path / "jobs")
    assert warnings == [] and len(recs) == 6 and all(validate(r) == [] for r in recs)
    with pytest.raises(UserError, match="--jobs"):
        run_stress(cfg, conds, jobs=0)


class ToySized(_Toy):  # sized by face area, like the lmgs backbone family
    mode = "sized"

    def __init__(self, preset: str = "quick", budget_density=None, **_):
        super().__init__(preset)
        self.budget_density = budget_density


def test_a_method_registered_at_run_time_keeps_its_scene_budget_flag_in_a_worker(monkeypatch):
    import pickle
    import types

    from lmgs_eval.protocols import stress as stress_mod

    monkeypatch.setitem(methods._REGISTRY, "toy-sized", ToySized)
    monkeypatch.setattr(methods, "_SCENE_BUDGET", methods._SCENE_BUDGET | {"toy-sized"})
    shipped = pickle.loads(pickle.dumps(stress_mod._ship(("toy-sized", "lmgs"))))  # as the pool sends it
    assert shipped["lmgs"] is None  # a built-in is registered (flag and all) by the worker's import
    # a fresh worker process: the run-time method is neither registered nor flagged there
    monkeypatch.delitem(methods._REGISTRY, "toy-sized")
    monkeypatch.setattr(methods, "_SCENE_BUDGET", methods._SCENE_BUDGET - {"toy-sized"})
    stress_mod._adopt(shipped)
    knee = types.SimpleNamespace(budget_density=0.55)
    assert methods.create_method("toy-sized", subject=knee).budget_density == 0.55  # as a serial run
    assert methods.create_method("toy-sized", subject=knee, budget_density=0.3).budget_density == 0.3


class ToyCached(_Toy):  # a method whose model is already trained: fit() does not read the clip
    mode = "cached"

    def fit(self, clip, *, seed, workdir, progress=True):
        self.shape = (64, 64, 3)


def test_the_training_clip_is_loaded_only_when_a_method_reads_it(monkeypatch, tmp_path):
    import lmgs_eval.protocols.stress as M

    loads = []
    real = M.subject_to_clip
    monkeypatch.setattr(M, "subject_to_clip", lambda subject, ids, **kw: loads.append(len(ids)) or real(subject, ids, **kw))
    monkeypatch.setitem(methods._REGISTRY, "toy-cached", ToyCached)
    monkeypatch.setitem(methods._REGISTRY, "toy-ok", ToyOk)
    cfg = RunConfig(subject=SUBJECT, methods=("toy-cached",), results=tmp_path, progress=False)
    recs, _ = run_stress(cfg, ("silence",), long_seconds=60.0)
    n_test = recs[0].protocol.n_frames
    assert len(recs) == 2 and loads == [n_test]  # the test clip only
    run_stress(dataclasses.replace(cfg, methods=("toy-ok",)), ("silence",), long_seconds=60.0)
    assert len(loads) == 3 and loads[2] > n_test  # the toy that fits reads the training clip
