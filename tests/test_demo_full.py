"""`lmgs-eval demo --full` (make bench): the committed plan (benchmarks/paper.toml) through the plan
runner, then the tables; a failed run is reported and makes the exit code 1. The plan runner is
replaced by a recorder here (its own tests run plans); what is checked is the wiring of the benchmark."""

from __future__ import annotations

import argparse
from pathlib import Path

import lmgs_eval.plans as plans
from lmgs_eval.plans import Summary, expand, load_plan

REPO = Path(__file__).resolve().parents[1]


def test_bench_runs_the_committed_plan_then_the_tables(tmp_path, monkeypatch, capsys):
    from lmgs_eval.commands import demo, table

    calls = []

    def run_plan(plan, executor, results, **_):
        calls.append(("plan", plan, executor.name, Path(results)))
        return Summary(total=len(expand(plan)), skipped=3, done=["a"], failed=["stress hopper / degstalk seed 0: worker died"])

    monkeypatch.setattr(plans, "run_plan", run_plan)
    monkeypatch.setattr(table, "run", lambda a: calls.append(("table", a.out, a.records)))
    monkeypatch.setattr(demo, "_report", lambda results, out, renders=None, preview_side=256: calls.append(
        ("report", results, out, renders, preview_side)) or out / "index.html")
    monkeypatch.chdir(REPO)  # make bench runs from the repository root: the plan's default path is relative to it
    args = argparse.Namespace(results=str(tmp_path / "results"), out=str(tmp_path / "tables"), data_root=None, no_progress=True,
                              plan=demo.PAPER_PLAN, executor="serial", address=None, max_parallel=None)
    rc = demo.run_full(args)
    out = capsys.readouterr().out
    assert rc == 1 and "failed: stress hopper / degstalk seed 0: worker died" in out
    assert "plan: 127 runs, 3 already in the store, 1 done, 1 failed" in out
    (_, plan, executor, results), tab, rep = calls
    assert plan == load_plan("benchmarks/paper.toml") and executor == "serial" and results == tmp_path / "results"
    assert tab == ("table", tmp_path / "tables", tmp_path / "tables" / "records")
    # the report is made last, from the committed records with this store's renders, and its index printed
    tables = tmp_path / "tables"
    assert rep == ("report", tables / "records", tables / "report", tmp_path / "results", demo.REPORT_PREVIEW_SIDE)
    assert f"report (open in a browser): {(tables / 'report' / 'index.html').resolve()}" in out
