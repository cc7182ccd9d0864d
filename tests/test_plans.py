"""Benchmark plans: the TOML schema's one-line errors, expansion into runs, and the serial executor's
retries, failed records and resume (a driver stopped mid-plan and started again does not redo runs)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from conftest import run_cli

from lmgs_eval.errors import UserError
from lmgs_eval.plans import expand, load_plan, make_executor, plan_from_dict, run_plan
from lmgs_eval.results import load_records

import plan_toys

SUBJECT = "astronaut-64px-2s"
REPO = Path(__file__).resolve().parents[1]


def _write(tmp_path, text: str) -> Path:
    p = tmp_path / "plan.toml"
    p.write_text(text)
    return p


GOOD = '[[stage]]\nprotocols = ["self"]\nsubjects = ["astronaut"]\nmethods = ["lmgs"]\n'


@pytest.mark.parametrize("text, words", [
    ("name = 3\n" + GOOD, "plan.toml: name: expected a string, got 3"),
    ("seeds = [0]\n" + GOOD, "plan.toml: unknown key 'seeds' (known: "),
    ("name = 'x'\n", "plan.toml: stage: expected one or more [[stage]] tables"),
    (GOOD + "seed = [1]\n", "plan.toml: stage 1: unknown key 'seed' (known: "),
    (GOOD + "seeds = [0, -1]\n", "plan.toml: stage 1: seeds: expected a list of non-negative integers"),
    (GOOD + "seeds = [1, 1]\n", "stage 1: seeds: [1, 1] repeats a seed"),
    (GOOD.replace('"self"', '"selff"'), "stage 1: protocols: unknown protocol 'selff' (known: self, cross, stress, capacity)"),
    (GOOD.replace('methods = ["lmgs"]\n', ""), "stage 1: methods: missing"),
    (GOOD + "cpus = 0\n", "stage 1: cpus: expected an integer >= 1, got 0"),
    (GOOD + "budgets = [100]\n", "stage 1: budgets: applies to the capacity protocol, which this stage does not run"),
    (GOOD + "set = 3\n", "stage 1: set: expected a table of KEY = VALUE"),
    ('[[stage]]\nprotocols = ["capacity"]\nsubjects = ["a"]\nmethods = ["wav2lip"]\n',
     "stage 1: methods: the capacity protocol runs lmgs only, got wav2lip"),
    ("[[stage]\n", "plan.toml: not a valid TOML file"),
])
def test_a_bad_plan_is_one_line_naming_the_key(tmp_path, text, words):
    with pytest.raises(UserError) as e:
        load_plan(_write(tmp_path, text))
    assert words in str(e.value) and "\n" not in str(e.value)


def test_the_run_command_refuses_a_bad_plan_before_any_work(tmp_path):
    plan = _write(tmp_path, GOOD + "seeds = 'all'\n")
    rc, out, err = run_cli("run", str(plan), "--results", str(tmp_path / "res"))
    assert rc == 2 and "error: " in err and "stage 1: seeds: expected a list" in err and "Traceback" not in err
    assert not (tmp_path / "res").exists()
    rc, _, err = run_cli("run", str(tmp_path / "none.toml"))
    assert rc == 2 and "none.toml: no such plan file" in err
    # a method or an override the registry refuses stops the plan before its first run
    for stage, words in (('methods = ["nope"]', "unknown method 'nope'"),
                         ('methods = ["lmgs"]\nset = { "train.nope" = 1 }', "--set train.nope: TrainConfig has no field 'nope'")):
        plan = _write(tmp_path, f'[[stage]]\nprotocols = ["self"]\nsubjects = ["{SUBJECT}"]\n{stage}\n')
        rc, _, err = run_cli("run", str(plan), "--results", str(tmp_path / "res"))
        assert rc == 2 and words in err and "Traceback" not in err
        assert not (tmp_path / "res").exists()


def test_without_ray_the_ray_executor_is_one_line_saying_what_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails as when it is not installed
    with pytest.raises(UserError, match=r"pip install '\.\[cluster\]'"):
        make_executor("ray")
    rc, _, err = run_cli("run", str(_write(tmp_path, GOOD)), "--executor", "ray", "--results", str(tmp_path / "res"))
    assert rc == 2 and "--executor ray needs Ray" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "res").exists()
    with pytest.raises(UserError, match="--max-parallel 2: the serial executor runs one at a time"):
        make_executor("serial", max_parallel=2)


def test_expansion_crosses_every_axis_once_and_chains_runs_of_one_model():
    plan = plan_from_dict({"cpus": 2, "set": {"train": {"static_steps": 40}}, "stage": [
        {"protocols": ["self", "cross"], "subjects": ["a", "b"], "methods": ["lmgs", "wav2lip"], "seeds": [0, 1]},
        {"protocols": ["self"], "subjects": ["a"], "methods": ["lmgs"], "seeds": [1, 2], "set": {"gr": False}},
        {"protocols": ["capacity"], "subjects": ["a"], "budgets": [500]},
        {"protocols": ["self"], "subjects": ["a"], "methods": ["lmgs"], "seeds": [0]},  # listed before: kept once
    ]})
    runs = expand(plan)
    assert len(runs) == 2 * 2 * 2 * 2 + 2 + 1
    assert len({r.id for r in runs}) == len(runs)
    by = {(r.protocol, r.subject, r.method, r.seed, tuple(sorted(r.overrides))): r for r in runs}
    first = by[("self", "a", "lmgs", 0, ("train.static_steps",))]
    assert first.after == () and first.cpus == 2 and first.overrides == {"train.static_steps": 40}
    # cross reloads the model its self run trained; every self run of a subject follows the first one
    assert by[("cross", "a", "lmgs", 0, ("train.static_steps",))].after == (first.id,)
    assert by[("self", "a", "wav2lip", 1, ("train.static_steps",))].after == (first.id,)
    # other overrides: another model, so only the subject's first self run comes before it
    gr = by[("self", "a", "lmgs", 1, ("gr", "train.static_steps"))]
    assert gr.overrides == {"train.static_steps": 40, "gr": False} and gr.after == (first.id,)
    # capacity's default budget is lmgs's own model: after the last run that trains it
    cap = by[("capacity", "a", "lmgs", 0, ("train.static_steps",))]
    assert cap.budgets == (500,) and cap.after == (by[("cross", "a", "lmgs", 0, ("train.static_steps",))].id,)
    # every dependency is a run listed earlier (runs never wait on a later one)
    pos = {r.id: i for i, r in enumerate(runs)}
    assert all(pos[d] < pos[r.id] for r in runs for d in r.after)


def test_the_committed_benchmark_plan_holds_the_paper_runs():
    """benchmarks/paper.toml: Table I (10 methods x 2 subjects, self + cross; 5 seeds for lmgs and
    TalkingGaussian), the out-of-fold and uncapped rows, Tables III-IV's variants, stress and capacity,
    and the 512 px section."""
    runs = expand(load_plan(REPO / "benchmarks" / "paper.toml"))
    got = {(r.protocol, r.subject, r.method, r.seed) for r in runs}
    methods = ("lmgs", "talkinggaussian", "degstalk", "gaussiantalker", "wav2lip", "ip_lap", "ernerf", "radnerf", "adnerf",
               "geneface")
    for subject in ("astronaut", "hopper"):
        for m in methods:
            for seed in ((0, 1, 2, 3, 4) if m in ("lmgs", "talkinggaussian") else (0,)):
                assert {("self", subject, m, seed), ("cross", subject, m, seed)} <= got
        for v in ("lmgs-oof", "lmgs-uncapped"):
            assert {("self", subject, v, s) for s in range(5)} <= got and ("cross", subject, v, 0) not in got
    seeds = {("astronaut", "lmgs-no-se"): 5, ("astronaut", "lmgs-no-lc"): 3, ("astronaut", "lmgs-no-gr"): 5,
             ("hopper", "lmgs-no-se"): 3, ("hopper", "lmgs-no-gr"): 3}
    for v in ("lmgs-no-se", "lmgs-no-lc", "lmgs-no-gr", "lmgs-no-ae", "lmgs-theta0.4", "lmgs-theta0.8", "lmgs-base",
              "lmgs-gr-paper"):
        for subject in ("astronaut", "hopper"):
            n = seeds.get((subject, v), 1 if subject == "hopper" else 0)
            assert {s for p, su, m, s in got if (p, su, m) == ("self", subject, v)} == set(range(n))
    assert {(m, s) for p, su, m, s in got if p == "stress"} == {(m, 0) for m in ("lmgs", "talkinggaussian",
                                                                                    "gaussiantalker", "degstalk")}
    cap = {r.subject: r.budgets for r in runs if r.protocol == "capacity"}
    assert cap == {"astronaut": None, "hopper": (4000, 10000, 16000), "astronaut-512px-60s": (3000, 6000, 12000)}
    big = {(p, m, s) for p, su, m, s in got if su == "astronaut-512px-60s" and p != "capacity"}
    assert big == {("self", m, 0) for m in ("lmgs", "talkinggaussian", "degstalk")}  # 512 px: self only
    assert len(runs) == 40 + 32 + 20 + 6 + 6 + 10 + 3 + 4 + 2 + 3 + 1
    assert {r.cpus for r in runs} == {2} and {r.preset for r in runs} == {"quick"}


def _toy_plan(marks: Path, seeds=(0,), retries=1, **opts) -> dict:
    return {"name": "toy", "imports": ["plan_toys"], "retries": retries, "stage": [
        {"protocols": ["cross"], "subjects": [SUBJECT], "methods": ["plan-toy"], "seeds": list(seeds),
         "set": {"marks": str(marks), **opts}}]}


def _quiet(msg):
    pass


def test_a_failing_run_is_retried_then_recorded_as_failed_and_retried_on_the_next_start(tmp_path):
    res, marks = tmp_path / "res", tmp_path / "marks"
    # fails once, then succeeds on its retry
    s = run_plan(plan_from_dict(_toy_plan(marks / "a", fail_times=1)), make_executor("serial"), res, progress=_quiet)
    assert s.failed == [] and len(s.done) == 1 and len(plan_toys.fits(marks / "a", 0)) == 2
    recs, _ = load_records(res)
    assert sorted(r.protocol.clip for r in recs) == ["A", "B"] and not any(r.failed for r in recs)
    assert all((res / r.artefacts["render"].path).is_file() for r in recs)
    # fails on both tries: each record it would have made is a failed record with the message
    plan = plan_from_dict(_toy_plan(marks / "b", fail_times=2))
    s = run_plan(plan, make_executor("serial"), res, progress=_quiet)
    assert len(s.failed) == 1 and "RuntimeError: toy failure 2" in s.failed[0]
    failed = [r for r in load_records(res)[0] if r.failed]
    assert sorted(r.protocol.clip for r in failed) == ["A", "B"]
    assert all(r.status.reason == "RuntimeError: toy failure 2" for r in failed)
    # the next start retries it (a failed record is not a finished run); the third fit succeeds
    s = run_plan(plan, make_executor("serial"), res, progress=_quiet)
    assert s.failed == [] and s.skipped == 0 and len(plan_toys.fits(marks / "b", 0)) == 3
    assert not any(r.failed for r in load_records(res)[0])


def test_a_stopped_driver_resumes_without_redoing_finished_runs(tmp_path):
    res, marks = tmp_path / "res", tmp_path / "marks"
    plan = plan_from_dict(_toy_plan(marks, seeds=(0, 1, 2), interrupt_seed=1))
    with pytest.raises(KeyboardInterrupt):
        run_plan(plan, make_executor("serial"), res, progress=_quiet)
    recs, _ = load_records(res)
    assert sorted((r.seed, r.protocol.clip) for r in recs) == [(0, "A"), (0, "B")]  # seed 1 left nothing
    before = {p: p.read_bytes() for p in res.rglob("*.json")}
    lines = []
    s = run_plan(plan, make_executor("serial"), res, progress=lines.append)
    assert s.skipped == 1 and len(s.done) == 2 and s.failed == []
    assert "3 runs, 1 already in" in lines[0] and "2 to do" in lines[0]
    assert [len(plan_toys.fits(marks, seed)) for seed in (0, 1, 2)] == [1, 2, 1]  # seed 0 was not fitted again
    assert all(p.read_bytes() == b for p, b in before.items())  # its records untouched
    recs, _ = load_records(res)
    assert sorted((r.seed, r.protocol.clip) for r in recs) == [(s, c) for s in (0, 1, 2) for c in "AB"]
    # a third start finds everything in the store and runs nothing
    s = run_plan(plan, make_executor("serial"), res, progress=_quiet)
    assert s.skipped == 3 and s.done == [] and [len(plan_toys.fits(marks, seed)) for seed in (0, 1, 2)] == [1, 2, 1]


def test_the_run_command_runs_a_plan_file_and_a_dry_run_lists_what_is_done(tmp_path):
    plan = tmp_path / "toy.toml"
    plan.write_text(f'name = "toy"\nimports = ["plan_toys"]\n[[stage]]\nprotocols = ["cross"]\nsubjects = ["{SUBJECT}"]\n'
                    f'methods = ["plan-toy"]\nseeds = [0, 1]\nset = {{ marks = "{tmp_path / "marks"}" }}\n')
    res = tmp_path / "res"
    rc, out, err = run_cli("run", str(plan), "--results", str(res))
    assert rc == 0, err
    assert "plan: 2 runs, 0 already in the store, 2 done, 0 failed" in out
    assert "[plan] 2/2 finished (2 ok, 0 failed)" in err
    rc, out, _ = run_cli("run", str(plan), "--results", str(res), "--dry-run")
    assert rc == 0 and out.count("done  cross astronaut-64px-2s / plan-toy seed") == 2
    recs = [json.loads(p.read_text()) for p in res.rglob("*.json")]
    assert len(recs) == 4 and {r["method"]["name"] for r in recs} == {"plan-toy"}


def test_a_dry_run_builds_no_subject(tmp_path):
    """A bundled subject not built yet is listed as to do, and left unbuilt (building one takes minutes)."""
    plan = tmp_path / "toy.toml"
    plan.write_text('name = "toy"\n[[stage]]\nprotocols = ["self"]\nsubjects = ["hopper-64px-3s"]\nmethods = ["lmgs"]\n')
    root = tmp_path / "data"
    rc, out, err = run_cli("run", str(plan), "--results", str(tmp_path / "res"), "--data-root", str(root), "--dry-run")
    assert rc == 0, err
    assert out.startswith("todo  self hopper-64px-3s / lmgs seed 0  (subject not built yet at ")
    assert not (root / "hopper-64px-3s").exists()


def test_a_stress_run_is_found_done_by_the_records_of_its_conditions(tmp_path):
    """The keys a stress run is looked up by (its conditions, the stress config hash) are those it writes."""
    res = tmp_path / "res"
    plan = plan_from_dict({"name": "stress", "imports": ["plan_toys"], "stage": [
        {"protocols": ["stress"], "subjects": [SUBJECT], "methods": ["plan-toy"], "conditions": ["silence"],
         "long_seconds": 2, "set": {"marks": str(tmp_path / "marks")}}]})
    s = run_plan(plan, make_executor("serial"), res, progress=_quiet)
    assert s.failed == [] and len(s.done) == 1
    recs, _ = load_records(res)
    assert sorted(r.protocol.clip for r in recs) == ["clean", "silence"]
    s = run_plan(plan, make_executor("serial"), res, progress=_quiet)
    assert s.skipped == 1 and s.done == [] and len(plan_toys.fits(tmp_path / "marks", 0)) == 1


def test_the_time_left_counts_each_run_at_its_protocols_mean():
    from lmgs_eval.plans.driver import _eta

    took = {"self": [100.0, 200.0], "cross": [10.0]}
    # self 150 + cross 10 + stress at the mean of every finished run (310 / 3), over 2 slots
    assert _eta(["self", "cross", "stress"], took, 2) == pytest.approx((150 + 10 + 310 / 3) / 2)
    assert _eta(["cross"], took, 4) == pytest.approx(10.0)  # one run left occupies one slot
    assert _eta([], took, 2) == 0.0 and _eta(["self"], {}, 2) == 0.0
