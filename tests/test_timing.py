"""What is recorded beside every FPS about the host: contention (cost.others_cpu_share) and speed (cost.host_slowdown)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from lmgs_eval.hosttime import HostSpeed, OthersCPU, host_cpu_seconds, probe_ms

needs_proc = pytest.mark.skipif(host_cpu_seconds() is None, reason="needs /proc/stat (Linux)")


def _spin(seconds: float) -> None:
    t = time.perf_counter()
    while time.perf_counter() - t < seconds:
        pass


@needs_proc
def test_others_cpu_share_counts_other_processes_and_not_this_one():
    ncpu = os.cpu_count() or 1
    with OthersCPU() as idle:
        time.sleep(0.5)
    if idle.share is not None and idle.share > 0.15:
        pytest.skip(f"the host is busy ({idle.share:.0%} of its CPU taken by others): contention cannot be measured against it")
    with OthersCPU() as own:
        _spin(1.0)  # only this process is busy
    child = subprocess.Popen([sys.executable, "-c",
                              "import time\nt = time.perf_counter()\nwhile time.perf_counter() - t < 1.8: pass"])
    try:
        time.sleep(0.3)  # let it start
        with OthersCPU() as other:
            time.sleep(1.0)  # this process idles while the other one keeps a core busy
    finally:
        child.wait()
    assert own.share is not None and other.share is not None and 0 <= own.share <= 1 and 0 <= other.share <= 1
    assert other.share > 0.7 / ncpu  # one core of the host (about 0.5 on 2 cores)
    assert other.share - own.share > 0.5 / ncpu  # this process's own work is not contention


class _Probe:
    """A probe that returns given milliseconds in turn (the host speed is simulated, not timed)."""

    def __init__(self, *ms):
        self.ms, self.k = list(ms), 0

    def __call__(self):
        self.k += 1
        return self.ms[(self.k - 1) % len(self.ms)]


def test_host_slowdown_is_against_the_fastest_probe_this_machine_recorded(tmp_path):
    import json

    ledger = tmp_path / "host_probe.json"
    # a quiet span: warm-up, 3 probes before, 3 after; median 30 ms both sides
    with HostSpeed(ledger, probe=_Probe(99, 30, 31, 29, 30, 30, 31)) as quiet:
        pass
    assert quiet.before == 30 and quiet.after == 30 and quiet.slowdown == pytest.approx(1.0)
    book = json.loads(ledger.read_text())
    (entry,) = book.values()
    assert entry == {"best_ms": 30.0, "n": 1}
    # a later span on a slowed host: medians 75 and 90 -> 3x slower than the best recorded
    with HostSpeed(ledger, probe=_Probe(200, 70, 75, 80, 90, 95, 85)) as slow:
        pass
    assert (slow.before, slow.after, slow.best) == (75, 90, 30.0)
    assert slow.slowdown == pytest.approx(3.0)
    assert slow.cost() == {"host_probe_ms": [75, 90], "host_probe_best_ms": 30.0, "host_slowdown": pytest.approx(3.0)}
    assert json.loads(ledger.read_text())[next(iter(book))] == {"best_ms": 30.0, "n": 2}
    # a faster host later lowers the best: its own slowdown is 1
    with HostSpeed(ledger, probe=_Probe(0, 20, 20, 20)) as fast:
        pass
    assert fast.slowdown == pytest.approx(1.0) and json.loads(ledger.read_text())[next(iter(book))]["best_ms"] == 20


def test_host_speed_survives_a_corrupt_ledger_and_keeps_none_when_asked(tmp_path):
    ledger = tmp_path / "host_probe.json"
    ledger.write_text("{not json")
    with HostSpeed(ledger, probe=_Probe(40)) as h:
        pass
    assert h.slowdown == pytest.approx(1.0) and "best_ms" in ledger.read_text()
    with HostSpeed(None, probe=_Probe(1, 10, 10, 10, 20, 20, 20)) as h:
        pass
    assert h.slowdown == pytest.approx(2.0)  # no ledger: against the faster of its own two sides


def test_probe_is_a_real_workload():
    ms = [probe_ms() for _ in range(3)]
    assert all(m > 0 for m in ms)


def test_training_records_the_contention_and_a_reused_checkpoint_keeps_it(tmp_path, monkeypatch):
    import json
    from types import SimpleNamespace

    from lmgs_eval import runner as protocols

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))

    class Toy:
        def describe(self):
            return SimpleNamespace(name="toy", config_hash="abc")

        def fit(self, clip, *, seed, workdir, progress):
            workdir.mkdir(parents=True, exist_ok=True)
            if not (workdir / "model.pt").exists():
                _spin(0.3)
                (workdir / "model.pt").write_bytes(b"x")

    subject = SimpleNamespace(name="s", bundled=False, meta={}, root=tmp_path / "subject")  # no manifest: not checked
    first = protocols.fit_method(Toy(), None, subject, 0, progress=False)
    share = first["train_others_cpu_share"]
    assert not first["reused_checkpoint"] and (share is None or 0 <= share <= 1)
    if host_cpu_seconds() is not None:
        assert share is not None
    fit_json = tmp_path / "cache" / "lmgs" / "models" / "s" / "toy" / "abc-seed0" / "fit.json"
    saved = json.loads(fit_json.read_text())
    assert saved["train_others_cpu_share"] == share and saved["train_seconds"] == first["train_seconds"]
    again = protocols.fit_method(Toy(), None, subject, 0, progress=False)
    assert again["reused_checkpoint"]
    assert (again["train_seconds"], again["train_others_cpu_share"]) == (first["train_seconds"], share)
    # the training's peak memory goes with the reused checkpoint into the record's cost (the higher one)
    assert again["train_peak_mb"] == saved["peak_mb"] > 0

    class Cost:
        def cost(self):
            return {}

    fit_json.write_text(json.dumps({**saved, "peak_mb": 1e6}))  # a training that peaked far above this process
    reused = protocols.fit_method(Toy(), None, subject, 0, progress=False)
    assert protocols.cost_block(Cost(), reused, {})["peak_mb"] == 1e6
    assert protocols.cost_block(Cost(), first, {})["peak_mb"] < 1e6  # trained here: this process's own peak
