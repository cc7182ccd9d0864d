"""The command line: its pinned command list, and every command run once as a user types it.

The smoke run uses the tiny bundled subject (64x64, 2 s) and a short schedule; one model is
trained (by ``demo``) and reused by the commands after it, as on a user's machine.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import run_cli
from lmgs_eval import cli
from lmgs_eval.results import load_records

SUBJECT = "astronaut-64px-2s"
FAST = ["--set", "train.static_steps=40", "--set", "train.dynamic_steps=40", "--set", "train.landmark_steps=20",
        "--set", "train.densify_every=20"]
EXPECTED = ("subjects", "ingest", "prepare", "metrics", "score", "methods", "weights", "sync-check", "self", "cross", "run",
            "table", "report", "stress", "capacity", "verify", "bench", "demo")


def command_names(parser) -> tuple[str, ...]:
    sub = next(a for a in parser._actions if a.dest == "command")
    return tuple(sub.choices)


def test_the_command_list_is_pinned():
    assert command_names(cli.build_parser()) == EXPECTED
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), pytest.raises(SystemExit):
        cli.main(["--help"])
    for name in EXPECTED:
        assert f"    {name} " in buf.getvalue() or f"    {name}\n" in buf.getvalue()


def test_a_missing_command_module_is_an_error_not_a_dropped_command(monkeypatch):
    monkeypatch.setitem(cli.COMMANDS, "ghost", "lmgs_eval.commands.ghost")
    with pytest.raises(ModuleNotFoundError, match="lmgs_eval.commands.ghost"):
        cli.build_parser()


def test_a_missing_bench_target_is_an_error(monkeypatch):
    from lmgs_eval.commands import bench

    monkeypatch.setitem(bench.TARGETS, "ghost", "lmgs.ghost_bench")
    with pytest.raises(ModuleNotFoundError, match="lmgs.ghost_bench"):
        cli.build_parser()


@pytest.fixture(scope="module")
def demo_store(tmp_path_factory):
    """``lmgs-eval demo`` on the tiny subject with a short schedule: self, cross A/B and the tables."""
    root = tmp_path_factory.mktemp("smoke")
    res, out_dir = root / "results", root / "tables"
    rc, out, err = run_cli("demo", "--subject", SUBJECT, "--results", str(res), "--out", str(out_dir), "--no-progress",
                           *FAST)
    assert rc == 0, err
    return res, out_dir, out


def test_smoke_demo_self_cross_and_tables(demo_store):
    res, out_dir, out = demo_store
    recs = load_records(res)[0]
    got = {(r.protocol.name, r.protocol.clip, r.method.name) for r in recs}
    assert {("self", "test", "lmgs"), ("cross", "A", "lmgs"), ("cross", "B", "lmgs")} <= got
    assert (out_dir / "table1_self.md").is_file() and (out_dir / "table2_cross.md").is_file()
    assert "demo finished" in out and (res / "report" / "index.html").is_file()  # the demo ends with the report


def test_smoke_run_plan_dry_run_and_report(demo_store, tmp_path):
    res, _, _ = demo_store
    rc, out, err = run_cli("run", str(Path(__file__).resolve().parents[1] / "benchmarks" / "paper.toml"), "--dry-run")
    runs = [ln for ln in out.splitlines() if ln.startswith(("todo ", "done "))]
    assert rc == 0 and len(runs) == 127, out + err  # the committed benchmark's runs, listed, none run
    rc, out, err = run_cli("report", "--results", str(res), "--out", str(tmp_path / "site"))
    assert rc == 0 and (tmp_path / "site" / "index.html").is_file(), err


def test_smoke_informational_commands(demo_store):
    rc, out, err = run_cli("subjects", "--json")
    assert rc == 0, err
    listed = {s["name"]: s for s in json.loads(out)["subjects"]}
    assert listed["astronaut"]["bundled"] and listed["hopper"]["bundled"]
    rc, out, err = run_cli("methods", "--json")
    assert rc == 0 and "lmgs" in out, err
    rc, out, err = run_cli("metrics")
    assert rc == 0 and "psnr" in out.lower(), err
    rc, out, err = run_cli("prepare", "--subject", SUBJECT)
    assert rc == 0 and "frames" in out, err


def test_smoke_self_rerun_is_skipped_and_seeds_device_preset_are_honoured(demo_store):
    res, _, _ = demo_store
    n = len(load_records(res)[0])
    rc, out, err = run_cli("self", "--subject", SUBJECT, "--results", str(res), "--device", "cpu", "--no-progress",
                           *FAST)
    assert rc == 0 and "skipped" in err, err
    assert len(load_records(res)[0]) == n
    rc, out, err = run_cli("self", "--subject", SUBJECT, "--results", str(res), "--device", "banana", "--no-progress",
                           *FAST)
    assert rc == 2 and "banana" in err and "Traceback" not in err
    # two seeds with --force: seed 0 is redone from its cached model, seed 1 is trained
    before = {r.seed: r for r in load_records(res)[0] if r.protocol.name == "self" and r.method.name == "lmgs"}
    rc, out, err = run_cli("self", "--subject", SUBJECT, "--results", str(res), "--seed", "0", "--seed", "1", "--force",
                           "--no-progress", *FAST)
    assert rc == 0, err
    after = {r.seed: r for r in load_records(res)[0] if r.protocol.name == "self" and r.method.name == "lmgs"}
    assert set(after) == {0, 1} and set(before) == {0}
    ck = {k: r.artefacts["checkpoint"].sha256 for k, r in after.items()}
    assert ck[0] == before[0].artefacts["checkpoint"].sha256 and ck[1] != ck[0]  # seed 0 reused, seed 1 new
    assert after[0].cost.train_seconds == pytest.approx(before[0].cost.train_seconds)  # its fit.json
    rc, out, err = run_cli("methods", "--preset", "paper", "--json")
    assert rc == 0, err
    rows = {m["name"]: m for m in json.loads(out)["methods"]}
    assert rows["lmgs"]["config_hash"] != "-" and rows["adnerf"]["config_hash"] == "-"  # adnerf has no paper preset


def test_smoke_table_formats_verify_and_score(demo_store, tmp_path):
    res, _, _ = demo_store
    rc, out, err = run_cli("table", "--results", str(res), "--out", str(tmp_path / "md"), "--format", "md",
                           "--no-charts")
    assert rc == 0, err
    assert {p.suffix for p in (tmp_path / "md").iterdir()} == {".md"}
    rc, out, err = run_cli("verify", str(res))
    assert rc == 0 and "all inputs unchanged" in out, out + err
    render = next(r for r in load_records(res)[0] if r.protocol.name == "self" and r.method.name == "lmgs")
    mp4 = res / render.artefacts["render"].path
    rc, out, err = run_cli("score", "--pred", str(mp4), "--gt", str(mp4), "--metrics", "psnr,ssim", "--json")
    assert rc == 0, err
    got = json.loads(out)["results"]
    assert got["ssim"]["values"]["ssim"] == pytest.approx(1.0)


def test_smoke_stress_one_condition(demo_store):
    res, _, _ = demo_store
    rc, out, err = run_cli("stress", "--subject", SUBJECT, "--results", str(res), "--condition", "silence",
                           "--no-progress", *FAST)
    assert rc == 0, err
    conds = {r.protocol.clip for r in load_records(res)[0] if r.protocol.name == "stress"}
    assert {"clean", "silence"} <= conds


def test_smoke_bench_metrics(demo_store):
    rc, out, err = run_cli("bench", "metrics", "--frames", "2", "--sizes", "64", "--json")
    assert rc == 0, err
    res = json.loads(out)
    assert res["frames"] == 2 and res["threads"] >= 1
    net = res["lpips_network"]
    rows = {r["metric"]: r for r in res["rows"]}
    assert {r["size"] for r in res["rows"]} == {64} and len(rows) == len(res["rows"])
    assert {"psnr", "ssim", f"{net} onnxruntime", f"{net} eager torch (folded)", f"{net} eager torch (reference)",
            "lmd landmarks (dlib, pred+gt)"} <= set(rows)
    assert any(m.startswith("lse (") for m in rows)  # the bundled scorer is installed
    ort_ms = rows[f"{net} onnxruntime"]["ms_per_frame"]
    for name, r in rows.items():
        # one timing t of 2 frames gives both figures: frames/s = 2 / t, ms/frame = 1000 t / 2
        assert r["ms_per_frame"] > 0 and r["frames_per_s"] * r["ms_per_frame"] == pytest.approx(1000.0, rel=1e-9), name
        if "eager" in name:  # the eager time over the ONNX Runtime time of the same network and frames
            assert r["ort_speedup"] == pytest.approx(r["ms_per_frame"] / ort_ms, rel=1e-9), name
        else:
            assert r["ort_speedup"] is None, name
    assert not any(k.startswith("suite_500x512") for k in res)  # extrapolated from 512 px rows only


def test_smoke_bench_metrics_suite():
    rc, out, err = run_cli("bench", "metrics", "--suite", "--frames", "12", "--sizes", "128", "--json")
    assert rc == 0, err
    res = json.loads(out)
    assert res["frames"] == 12 and res["size"] == 128
    timed = {(r["lpips_network"], r["metric"]) for r in res["rows"]}
    for net in res["totals"]:
        assert {(net, m) for m in ("psnr", "ssim", "lmd", "lse", "total")} <= timed
