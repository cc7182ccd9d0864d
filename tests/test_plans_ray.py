"""A plan on a local two-node Ray cluster (``ray.cluster_utils.Cluster``): its records equal the serial
executor's record by record (cost, machine and time fields aside), its runs spread over both nodes,
and a run whose worker process is killed is retried, then recorded as failed when it dies every time.

One test: starting the cluster takes about 10 s of the suite's budget."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

import plan_toys
from lmgs_eval.plans import make_executor, plan_from_dict, run_plan
from lmgs_eval.results import load_records

ray = pytest.importorskip("ray")

SUBJECT = "astronaut-64px-2s"
FAST = {"train.static_steps": 20, "train.dynamic_steps": 20, "train.landmark_steps": 10, "train.densify_every": 20}
# Fields that say what a run cost and where and when it ran; a checkpoint stores its training time,
# so its file (path under each node's cache, and hash) is one of them.
VARYING = ("cost", "machine", "created")


def _comparable(rec: dict) -> dict:
    rec = {k: v for k, v in rec.items() if k not in VARYING}
    rec["artefacts"] = {k: v for k, v in rec["artefacts"].items() if k != "checkpoint"}
    return rec


def _quiet(msg):
    pass


def test_a_plan_on_a_two_node_ray_cluster_records_what_the_serial_executor_records(tmp_path, monkeypatch):
    from ray.cluster_utils import Cluster

    marks = tmp_path / "marks"
    plan = plan_from_dict({"name": "ray", "cpus": 1, "imports": ["plan_toys"], "stage": [
        {"protocols": ["self"], "subjects": [SUBJECT], "methods": ["lmgs"], "set": FAST},
        {"protocols": ["self", "cross"], "subjects": [SUBJECT], "methods": ["plan-toy"], "seeds": [0, 1],
         "set": {"marks": str(marks)}}]})
    # each executor trains its own models (a cache of its own), from the same subject folder
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache-serial"))
    serial = run_plan(plan, make_executor("serial"), tmp_path / "serial", progress=_quiet)
    assert serial.failed == [] and len(serial.done) == 5

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache-ray"))
    tests_dir = str(Path(__file__).resolve().parent)  # the workers import plan_toys as the plan says
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (tests_dir, os.environ.get("PYTHONPATH")) if p))
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    try:
        cluster.add_node(num_cpus=1)
        lines = []
        executor = make_executor("ray", cluster.address)
        assert executor.slots == 2
        on_ray = run_plan(plan, executor, tmp_path / "ray", progress=lines.append)
        assert on_ray.failed == [] and len(on_ray.done) == 5
        assert len(set(on_ray.nodes.values())) == 2  # the runs ran on both nodes
        assert any("2 in flight" in ln or "1 in flight" in ln for ln in lines[1:]) and "about" in lines[1]

        a = {p.relative_to(tmp_path / "serial"): json.loads(p.read_text()) for p in (tmp_path / "serial").rglob("*.json")}
        b = {p.relative_to(tmp_path / "ray"): json.loads(p.read_text()) for p in (tmp_path / "ray").rglob("*.json")}
        assert sorted(a) == sorted(b) and len(a) == 1 + 1 + 6 + 1 + 2 * 3  # GT, plate, controls, lmgs, toy self + A + B
        for path in a:
            assert _comparable(a[path]) == _comparable(b[path]), path
        lm = next(path for path in a if path.name.startswith("lmgs--"))
        assert a[lm]["metrics"]["psnr"]["value"] == b[lm]["metrics"]["psnr"]["value"] is not None
        # trained twice, once in each cache
        ck = b[lm]["artefacts"]["checkpoint"]["path"]
        assert ck.startswith(str(tmp_path / "cache-ray")) and Path(ck).is_file()
        assert a[lm]["artefacts"]["checkpoint"]["path"].startswith(str(tmp_path / "cache-serial"))

        # A worker killed mid-run (SIGKILL in fit) is retried in a new process; killed on every try, the
        # run is recorded as failed with the message, and a run beside it is not disturbed.
        killed = plan_from_dict({"name": "killed", "cpus": 1, "imports": ["plan_toys"], "retries": 1, "stage": [
            {"protocols": ["cross"], "subjects": [SUBJECT], "methods": ["plan-toy"], "seeds": [0],
             "set": {"marks": str(tmp_path / "k1"), "kill_times": 1}},
            {"protocols": ["cross"], "subjects": [SUBJECT], "methods": ["plan-toy"], "seeds": [0],
             "set": {"marks": str(tmp_path / "k2"), "kill_times": 5}}]})
        s = run_plan(killed, make_executor("ray", cluster.address), tmp_path / "killed", progress=_quiet)
        assert len(s.done) == 1 and len(s.failed) == 1
        once, always = plan_toys.fits(tmp_path / "k1", 0), plan_toys.fits(tmp_path / "k2", 0)
        assert len(once) == 2 and once[0] != once[1]  # the retry ran in another process
        assert len(always) == 2  # retries = 1: two tries, then given up
        recs, _ = load_records(tmp_path / "killed")
        ok = [r for r in recs if not r.failed]
        failed = [r for r in recs if r.failed]
        assert sorted(r.protocol.clip for r in ok) == ["A", "B"] and {r.config["kill_times"] for r in ok} == {1}
        assert sorted(r.protocol.clip for r in failed) == ["A", "B"]
        assert all("died" in r.status.reason.lower() or "crash" in r.status.reason.lower() for r in failed), \
            failed[0].status.reason
    finally:
        ray.shutdown()
        cluster.shutdown()
