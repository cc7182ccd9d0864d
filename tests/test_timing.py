"""What is recorded beside every FPS about the host: contention (cost.others_cpu_share) and speed (cost.host_slowdown)."""

from __future__ import annotations

import inspect
import os
import subprocess
import sys
import time

import pytest
import torch

from lmgs_eval.hosttime import HostSpeed, OthersCPU, host_cpu_seconds, probe_ms

needs_proc = pytest.mark.skipif(host_cpu_seconds() is None, reason="needs /proc/stat (Linux)")


def _spin(seconds: float) -> None:
    t = time.perf_counter()
    while time.perf_counter() - t < seconds:
        pass


def _proc_cpu_seconds(stat: str) -> float:
    """utime + stime of a ``/proc/<pid>/stat`` line (fields 14 and 15, counted after the command name)."""
    f = stat.rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def _self_cpu() -> float:
    with open("/proc/self/stat", encoding="ascii") as f:
        return _proc_cpu_seconds(f.read())


def _spin_cpu(seconds: float) -> None:
    """Burn ``seconds`` of this process's CPU time (however long a busy host makes it take)."""
    t = time.process_time()
    while time.process_time() - t < seconds:
        pass


_CHILD = f"""
import os, time
{inspect.getsource(_proc_cpu_seconds)}
t = time.process_time()
while time.process_time() - t < {{spin}}:
    pass
print(_proc_cpu_seconds(open("/proc/self/stat").read()))
"""


def test_others_cpu_share_is_host_busy_less_this_process_over_host_total(monkeypatch):
    """The accounting on given readings: ``share = (d busy - d own) / d total``, clamped into [0, 1]."""
    from lmgs_eval import hosttime

    def share(host, own):
        """The span's share when the host's (busy, total) and this process's CPU seconds read these in turn."""
        it_h, it_o = iter(host), iter(own)
        monkeypatch.setattr(hosttime, "host_cpu_seconds", lambda: next(it_h))
        monkeypatch.setattr(hosttime, "own_cpu_seconds", lambda: next(it_o))
        with OthersCPU() as span:
            pass
        return span.share

    # a 2-core host over 1 s (2 CPU-seconds): another process keeps one core, this one uses 0.2 s
    assert share([(100.0, 500.0), (101.2, 502.0)], [3.0, 3.2]) == pytest.approx(0.5)
    # only this process worked: nothing was taken by others
    assert share([(100.0, 500.0), (101.0, 502.0)], [3.0, 4.0]) == pytest.approx(0.0)
    # both: 0.3 s others of 4 CPU-seconds
    assert share([(10.0, 40.0), (11.1, 44.0)], [1.0, 1.8]) == pytest.approx(0.075)
    # tick granularity can make this process's time exceed the host's busy time: 0, not negative
    assert share([(10.0, 40.0), (10.0, 40.02)], [1.0, 1.01]) == 0.0
    # no /proc/stat, or a clock that did not advance: no share
    assert share([None, None], [0.0, 1.0]) is None
    assert share([(10.0, 40.0), (10.5, 40.0)], [0.0, 0.1]) is None


def test_host_cpu_seconds_reads_the_cpu_line_of_proc_stat(monkeypatch):
    """busy = user + nice + system + irq + softirq + steal, total adds idle and iowait; guest time,
    already inside user, is not added again (ticks of SC_CLK_TCK)."""
    import io

    from lmgs_eval import hosttime

    line = "cpu  100 20 30 400 50 0 10 5 70 9\ncpu0 1 2 3 4 5 6 7 8 9 10\n"
    monkeypatch.setattr(hosttime, "open", lambda *a, **k: io.StringIO(line), raising=False)
    hz = os.sysconf("SC_CLK_TCK")
    busy, total = hosttime.host_cpu_seconds()
    assert total == pytest.approx(615 / hz) and busy == pytest.approx(165 / hz)
    monkeypatch.setattr(hosttime, "open", lambda *a, **k: io.StringIO("intr 1 2 3\n"), raising=False)
    assert hosttime.host_cpu_seconds() is None


@needs_proc
def test_others_cpu_counts_a_child_process_and_not_this_one():
    """Measured against CPU times read from ``/proc/<pid>/stat``: a child's CPU time is counted as
    others', this process's own is not. The readings bracket the span, so the bounds hold however
    busy the rest of the host is (its load only adds to others' share)."""
    spin, tol = 0.4, 0.08  # s; /proc/stat and per-process times are both sampled in clock ticks
    h0, own0 = host_cpu_seconds(), _self_cpu()
    with OthersCPU() as mine:
        _spin_cpu(spin)
    h1, own1 = host_cpu_seconds(), _self_cpu()
    own = own1 - own0
    assert own >= spin - 0.02 and 0.0 <= mine.share <= 1.0
    # others' seconds in the span are at most the host's busy seconds less this process's own
    assert mine.share * (h1[1] - h0[1]) <= (h1[0] - h0[0]) - own + tol

    h0 = host_cpu_seconds()
    with OthersCPU() as theirs:  # this process waits while the child burns its CPU
        out = subprocess.run([sys.executable, "-c", _CHILD.format(spin=spin)], capture_output=True, text=True,
                             check=True).stdout
    h1 = host_cpu_seconds()
    child = float(out)
    assert child >= spin - 0.02 and 0.0 <= theirs.share <= 1.0
    assert theirs.share * (h1[1] - h0[1]) >= child - tol


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


def test_probe_times_exactly_its_fixed_workload(monkeypatch):
    """The clock is read once before and once after the 40 chained matmul + tanh steps, and the
    span is returned in milliseconds (a fake clock advancing 0.25 s per read: 250 ms)."""
    from lmgs_eval import hosttime

    events, real_tanh = [], torch.tanh
    clock = iter([10.0, 10.25])

    def perf_counter():
        events.append("clock")
        return next(clock)

    def tanh(x):
        events.append(("tanh", tuple(x.shape)))
        return real_tanh(x)

    monkeypatch.setattr(hosttime.time, "perf_counter", perf_counter)
    monkeypatch.setattr(torch, "tanh", tanh)
    assert probe_ms() == pytest.approx(250.0)
    assert events == ["clock"] + [("tanh", (256, 256))] * 40 + ["clock"]


def test_training_records_the_contention_and_a_reused_checkpoint_keeps_it(tmp_path, monkeypatch):
    import json
    from types import SimpleNamespace

    from lmgs_eval import runner as protocols
    from lmgs_eval.results.records import RunId

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
    run = RunId(subject, Toy().describe(), 0)
    first = protocols.fit_method(Toy(), None, run, progress=False)
    share = first["train_others_cpu_share"]
    assert not first["reused_checkpoint"] and (share is None or 0 <= share <= 1)
    if host_cpu_seconds() is not None:
        assert share is not None
    fit_json = tmp_path / "cache" / "lmgs" / "models" / "s" / "toy" / "abc-seed0" / "fit.json"
    saved = json.loads(fit_json.read_text())
    assert saved["train_others_cpu_share"] == share and saved["train_seconds"] == first["train_seconds"]
    again = protocols.fit_method(Toy(), None, run, progress=False)
    assert again["reused_checkpoint"]
    assert (again["train_seconds"], again["train_others_cpu_share"]) == (first["train_seconds"], share)
    # the training's peak memory goes with the reused checkpoint into the record's cost (the higher one)
    assert again["train_peak_mb"] == saved["peak_mb"] > 0

    class Cost:
        def cost(self):
            return {}

    fit_json.write_text(json.dumps({**saved, "peak_mb": 1e6}))  # a training that peaked far above this process
    reused = protocols.fit_method(Toy(), None, run, progress=False)
    assert protocols.cost_block(Cost(), reused, {})["peak_mb"] == 1e6
    assert protocols.cost_block(Cost(), first, {})["peak_mb"] < 1e6  # trained here: this process's own peak
