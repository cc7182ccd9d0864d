"""`lmgs-eval demo --full` (make bench): every stage is run once, as listed, and a failing stage
is reported without stopping the rest. The protocols themselves are replaced by recorders here
(each has its own end-to-end tests); what is checked is the wiring of the benchmark."""

from __future__ import annotations

import argparse

from lmgs_eval.protocols.capacity import DEFAULT_BUDGETS


def test_bench_runs_each_stage_once_and_a_failing_stage_does_not_stop_the_rest(tmp_path, monkeypatch, capsys):
    import lmgs_eval.protocols.capacity as capacity
    import lmgs_eval.protocols.cross as cross_mod
    import lmgs_eval.protocols.self_driven as self_mod
    import lmgs_eval.protocols.stress as stress
    from lmgs_eval.commands import demo, table

    calls = []

    def self_(cfg):
        calls.append(("self", cfg.subject, cfg.methods, cfg.seeds))
        return []

    def cross(cfg):
        calls.append(("cross", cfg.subject, cfg.methods, cfg.seeds))
        return [], (["no cross clips"] if cfg.methods == ("wav2lip",) and cfg.subject == "hopper" else [])

    def stress_(cfg, jobs=1):
        calls.append(("stress", cfg.subject, cfg.methods, jobs))
        raise RuntimeError("worker died")

    def capacity_(cfg, budgets):
        calls.append(("capacity", cfg.subject, tuple(budgets)))

    monkeypatch.setattr(self_mod, "run_self", self_)
    monkeypatch.setattr(cross_mod, "run_cross", cross)
    monkeypatch.setattr(stress, "run_stress", stress_)
    monkeypatch.setattr(capacity, "run_capacity", capacity_)
    monkeypatch.setattr(table, "run", lambda a: calls.append(("table", a.out, a.records)))
    monkeypatch.setattr(demo, "_report", lambda results, out, renders=None, preview_side=256: calls.append(
        ("report", results, out, renders, preview_side)) or out / "index.html")
    args = argparse.Namespace(results=str(tmp_path / "results"), out=str(tmp_path / "tables"), data_root=None, no_progress=True)
    rc = demo.run_full(args)
    out = capsys.readouterr().out
    assert rc == 1  # two stages failed, and the benchmark says so
    assert "failed: hopper / wav2lip: no cross clips" in out and "RuntimeError: worker died" in out
    # the report is made last, from the committed records with this store's renders, and its index printed
    tables = tmp_path / "tables"
    assert calls[-1] == ("report", tables / "records", tables / "report", tmp_path / "results", demo.REPORT_PREVIEW_SIDE)
    assert f"report (open in a browser): {(tables / 'report' / 'index.html').resolve()}" in out
    for subject in demo.FULL_SUBJECTS:
        for m in demo.FULL_METHODS:
            seeds = demo.FULL_SEEDS.get(m, (0,))
            assert calls.count(("self", subject, (m,), seeds)) == 1 and calls.count(("cross", subject, (m,), seeds)) == 1
    for v in demo.FULL_VARIANTS:
        assert calls.count(("self", demo.VARIANT_SUBJECT, (v,), demo.ABLATION_SEEDS.get((demo.VARIANT_SUBJECT, v), (0,)))) == 1
    # Table IV's component rows on astronaut, over the seeds the committed tables hold
    assert calls.count(("self", "astronaut", ("lmgs-no-se",), (0, 1, 2, 3, 4))) == 1
    assert calls.count(("self", "astronaut", ("lmgs-no-lc",), (0, 1, 2))) == 1
    assert calls.count(("self", demo.VARIANT_SUBJECT, ("lmgs-no-gr",), (0, 1, 2))) == 1
    for subject in demo.FULL_SUBJECTS:  # out-of-fold landmarks, SE by θ alone: both subjects, 5 seeds, self only
        for v in ("lmgs-oof", "lmgs-uncapped"):
            assert calls.count(("self", subject, (v,), (0, 1, 2, 3, 4))) == 1
            assert not any(c[0] == "cross" and c[2] == (v,) for c in calls)
    assert ("stress", demo.STRESS_SUBJECT, demo.FULL_STRESS, 2) in calls
    # the stages after the failed stress stage still ran: capacity on both subjects, then the tables
    assert calls[-4:-1] == [("capacity", "astronaut", DEFAULT_BUDGETS), ("capacity", "hopper", (4000, 10000, 16000)),
                            ("table", tmp_path / "tables", tmp_path / "tables" / "records")]
