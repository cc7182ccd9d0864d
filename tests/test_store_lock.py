"""The model cache under concurrent and failed runs: one training per model, no empty folders, usual file modes."""

from __future__ import annotations

import os
import threading
from pathlib import Path
from types import SimpleNamespace

import pytest

from lmgs_eval.paths import cache_root
from lmgs_eval.results.records import RunId
from lmgs_eval.runner import fit_method


class FakeMethod:
    """Trains (writes model.pt) unless the folder already has a model; counts trainings. A training
    holds until ``release`` is set (by the test, when a second run is seen waiting on the claim)."""

    trainings = 0
    started = threading.Event()  # set once a training is under way (the claim is held)
    release = threading.Event()
    events: list[str] = []

    def __init__(self, fail: Exception | None = None, save_first: bool = False):
        self.fail, self.save_first = fail, save_first

    def describe(self):
        return SimpleNamespace(name="fake", config_hash="0123456789abcdef")

    def fit(self, clip, *, seed, workdir, progress):
        if (workdir / "model.pt").exists():
            type(self).events.append("model found")
            return
        if self.save_first:
            (workdir / "checkpoint.pt").write_bytes(b"half a training")
        if self.fail is not None:
            raise self.fail
        type(self).started.set()
        assert type(self).release.wait(60), "the second run never waited on the claim"
        type(self).trainings += 1
        (workdir / "model.pt").write_bytes(b"weights")
        type(self).events.append("trained")


def subject(tmp_path: Path):
    return SimpleNamespace(name="tiny", root=tmp_path)  # no manifest.json: the data marker is not written


def run_of(subj, seed: int) -> RunId:
    return RunId(subj, FakeMethod().describe(), seed)


def test_a_second_run_of_the_same_model_waits_and_reuses(tmp_path, capsys, monkeypatch):
    """In order: the first run claims the model and trains; the second says it waits and blocks
    on the claim; only then does the first finish; the second reloads what the first trained.
    Each step waits for the one before it (no timing window)."""
    from lmgs_eval import runner

    FakeMethod.trainings = 0
    FakeMethod.started.clear()
    FakeMethod.release.clear()
    FakeMethod.events = events = []
    subj = subject(tmp_path)
    out: dict[int, dict] = {}
    say = runner.log

    def log(msg):
        say(msg)
        if "waiting for it to finish" in msg:
            events.append("second waits")
            FakeMethod.release.set()  # the first may finish now: the second is already queued on the lock

    monkeypatch.setattr(runner, "log", log)

    def run(k):
        out[k] = fit_method(FakeMethod(), None, run_of(subj, 0), False)

    first = threading.Thread(target=run, args=(0,))
    first.start()
    assert FakeMethod.started.wait(60)  # the first holds the claim and trains
    events.append("first trains")
    run(1)
    first.join(60)
    assert not first.is_alive()
    assert events == ["first trains", "second waits", "trained", "model found"]
    assert FakeMethod.trainings == 1
    assert out[0]["reused_checkpoint"] is False and out[1]["reused_checkpoint"] is True
    assert out[1]["train_seconds"] == out[0]["train_seconds"]  # from the first run's fit.json
    err = capsys.readouterr().err
    assert f"pid {os.getpid()}" in err and "waiting for it to finish" in err and "fake seed 0 on tiny" in err


def test_a_failed_fit_leaves_no_empty_model_folder(tmp_path):
    subj = subject(tmp_path)
    models = cache_root() / "models"
    before = sorted(models.rglob("*")) if models.exists() else []
    with pytest.raises(ValueError):
        fit_method(FakeMethod(fail=ValueError("bad")), None, run_of(subj, 7), False)
    assert not run_of(subj, 7).model_dir.exists()
    assert (sorted(models.rglob("*")) if models.exists() else []) == before
    # a fit that saved a checkpoint before failing keeps it (the next run resumes from it)
    with pytest.raises(KeyboardInterrupt):
        fit_method(FakeMethod(fail=KeyboardInterrupt(), save_first=True), None, run_of(subj, 8), False)
    assert (run_of(subj, 8).model_dir / "checkpoint.pt").is_file()


def test_saved_models_have_the_usual_file_mode(tmp_path):
    from baselines.common import atomic_save

    atomic_save({"w": 1}, tmp_path / "model.pt")
    (tmp_path / "other.txt").write_text("x")  # what open() makes under this umask
    assert (tmp_path / "model.pt").stat().st_mode & 0o777 == (tmp_path / "other.txt").stat().st_mode & 0o777
