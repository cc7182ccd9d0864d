"""The results store: schema, typed records, atomic writes, loading with warnings, resume lookup, the DataFrame
view (``verify`` and the committed snapshot: ``test_results_verify.py``).

Also home of the hand-written results store that the table tests use (:func:`fixture_records`, in
the JSON form a test edits; :func:`typed` makes the records the store hands out).
"""

from __future__ import annotations

import json
import multiprocessing
from pathlib import Path

import numpy as np
import pytest

from lmgs_eval import results as R
from lmgs_eval.results.migrate import lmgs_components
from lmgs_eval.errors import UserError

CREATED = "2025-01-01T00:00:00+00:00"
CODE = {"version": "0.1.0", "git_commit": "0" * 40, "dirty": False}
MACHINE = {"cpu": "Test CPU", "threads": 2, "torch": "2.13.0", "cuda_device": None, "platform": "Linux-test"}
SUBJECT = {"name": "astronaut", "bundled": True, "standin": "synthetic head animated from a public-domain photo",
           "frames": 20, "width": 64, "height": 64, "path": None, "sha256": "a" * 64}
ARROWS = {"psnr": True, "lpips": False, "lmd": False, "lse_d": False, "lse_c": True}
UNITS = {"psnr": "dB", "lpips": "", "lmd": "px", "lse_d": "", "lse_c": ""}
BACKENDS = {"psnr": "numpy", "lpips": "stlpips-alex", "lmd": "dlib|gt:dlib",
            "lse_d": "onnxruntime:bundled-sync", "lse_c": "onnxruntime:bundled-sync"}
N_ITEMS = 20


def items(mean: float, spread: float, seed: int, n: int = N_ITEMS) -> list[float]:
    """Per-item values with exactly the given mean (after rounding to 6 digits, close to it)."""
    u = np.random.default_rng(seed).uniform(-1, 1, n)
    return R.compact(mean + spread * (u - u.mean()))


def metric(key: str, per_item: list[float] | None, value: float | None = None, backend: str | None = None,
           standin: str | None = None) -> dict:
    if value is None and per_item is not None:
        value = float(np.mean(per_item))
    return {"value": value, "n_original": N_ITEMS, "n_effective": N_ITEMS if per_item else 0,
            "higher_is_better": ARROWS[key], "unit": UNITS[key], "backend": backend or BACKENDS[key],
            "backend_version": "1", "weights_sha256": None, "flags": [], "per_item": per_item,
            "standin": standin if standin is not None else (
                "ST-LPIPS (shift-tolerant) instead of LPIPS: no AlexNet trunk offline" if key == "lpips" else
                "bundled sync scorer instead of SyncNet v2" if key.startswith("lse") else None)}


def record(name: str, display: str, family: str, seed: int, metrics: dict, *, protocol: str = "self",
           clip: str = "test", config: dict | None = None, variant: str | None = None, cost: dict | None = None,
           control: dict | None = None, status: dict | None = None, description: str | None = None) -> dict:
    method = {"name": name, "display_name": display, "family": family,
              "description": description or f"{display}: reimplemented on the shared renderer, CPU schedule.",
              "standins": [], "variant": variant}
    if control:
        method["control"] = control
    if (name == "lmgs" or name.startswith("lmgs-")) and config and "guidance" in config:
        method["components"] = lmgs_components(config)  # what the lmgs adapter declares for such a config
    rec = R.make_record(method=method, subject=SUBJECT,
                        protocol={"name": protocol, "version": "1", "clip": clip, "split": "test", "n_frames": N_ITEMS},
                        metrics=metrics, seed=seed, config=config or {"name": name}, cost=cost, code=CODE,
                        machine=MACHINE, status=status)
    rec["created"] = CREATED
    return rec


# (key -> (mean, spread)) per method; lmgs is clearly best on image metrics, tied with
# TalkingGaussian on sync (the spread dwarfs the gap).
_SELF = {
    "ernerf": ("ER-NeRF", "NeRF", {"psnr": (27.0, 1.0), "lpips": (0.0864, 0.01), "lmd": (2.86, 0.2),
                                   "lse_d": (8.712, 0.5), "lse_c": (6.088, 0.5)},
               {"fps": 3.2, "train_seconds": 1800.0, "n_gaussians": None, "model_mb": 2.51}),
    "talkinggaussian": ("TalkingGaussian", "3DGS", {"psnr": (32.0, 1.0), "lpips": (0.0407, 0.01), "lmd": (2.81, 0.2),
                                                    "lse_d": (7.160, 0.5), "lse_c": (7.880, 0.5)},
                        {"fps": 20.5, "train_seconds": 900.0, "n_gaussians": 12000, "model_mb": 3.1}),
    "lmgs": ("Ours (lmgs)", "3DGS", {"psnr": (38.0, 1.0), "lpips": (0.0128, 0.003), "lmd": (2.28, 0.1),
                                     "lse_d": (7.150, 0.5), "lse_c": (7.900, 0.5)},
             {"fps": 18.0, "train_seconds": 1200.0, "n_gaussians": 11000, "model_mb": 2.9}),
}
LMGS_CONFIG = {"guidance": {"se": True, "lc": True, "theta": 0.6}, "gr": True}


def _lmgs_config(theta=0.6, se=True, lc=True, gr=True) -> dict:
    return {"guidance": {"se": se, "lc": lc, "theta": theta}, "gr": gr}


def fixture_records() -> list[dict]:
    """A small hand-written store: 3 methods x 2 seeds, Ground Truth, controls, cross, theta, ablation, stress."""
    recs = []
    recs.append(record("gt", "Ground Truth", "ground-truth", 0, {
        "psnr": metric("psnr", None, value=None), "lpips": metric("lpips", [0.0] * N_ITEMS),
        "lmd": metric("lmd", [0.0] * N_ITEMS), "lse_d": metric("lse_d", items(6.672, 0.4, 90)),
        "lse_c": metric("lse_c", items(8.530, 0.4, 91))}))
    for k, (name, (display, family, ms, cost)) in enumerate(_SELF.items()):
        for seed in (0, 1):
            mets = {key: metric(key, items(mean * (1 + 0.002 * seed * (1 if ARROWS[key] else -1)), spread,
                                           100 * k + 10 * j + seed))
                    for j, (key, (mean, spread)) in enumerate(ms.items())}
            cfg = _lmgs_config() if name == "lmgs" else {"name": name}
            recs.append(record(name, display, family, seed, mets, config=cfg,
                               cost={**cost, "fps": cost["fps"] * (1 + 0.02 * seed)}))
    for k, name in enumerate(_SELF):
        for c, clip in enumerate(("A", "B")):
            base = {"ernerf": (9.9, 4.5), "talkinggaussian": (9.6, 4.9), "lmgs": (9.0, 5.7)}[name]
            recs.append(record(name, _SELF[name][0], _SELF[name][1], 0, {
                "lse_d": metric("lse_d", items(base[0] + 0.1 * c, 0.3, 500 + 10 * k + c)),
                "lse_c": metric("lse_c", items(base[1] - 0.1 * c, 0.3, 600 + 10 * k + c))},
                protocol="cross", clip=clip, config=_lmgs_config() if name == "lmgs" else {"name": name}))
    variants = {
        "lmgs-theta0.4": (_lmgs_config(theta=0.4), "theta0.4", (0.0147, 2.41, 7.203, 7.831)),
        "lmgs-theta0.8": (_lmgs_config(theta=0.8), "theta0.8", (0.0138, 2.35, 7.176, 7.856)),
        "lmgs-no-se": (_lmgs_config(se=False), "no-se", (0.0153, 2.45, 7.221, 7.801)),
        "lmgs-no-lc": (_lmgs_config(lc=False), "no-lc", (0.0150, 2.52, 7.256, 7.818)),
        "lmgs-no-gr": (_lmgs_config(gr=False), "no-gr", (0.0131, 2.30, 7.203, 7.862)),
    }
    for k, (name, (cfg, variant, (lp, lmd, ld, lc))) in enumerate(variants.items()):
        recs.append(record(name, f"lmgs ({variant})", "3DGS", 0, {
            "lpips": metric("lpips", items(lp, 0.001, 700 + k)), "lmd": metric("lmd", items(lmd, 0.05, 710 + k)),
            "lse_d": metric("lse_d", items(ld, 0.3, 720 + k)), "lse_c": metric("lse_c", items(lc, 0.3, 730 + k))},
            config=cfg, variant=variant))
    recs.append(record("gt-shift+5", "GT, audio shifted +5 frames", "control", 0, {
        "lse_d": metric("lse_d", items(9.8, 0.4, 800)), "lse_c": metric("lse_c", items(2.1, 0.4, 801))},
        control={"kind": "audio-shift", "targets": ["lse_d", "lse_c"]}))
    recs.append(record("still-frame", "Still frame", "control", 0, {
        "lmd": metric("lmd", items(3.9, 0.3, 810)), "lse_d": metric("lse_d", items(10.5, 0.4, 811)),
        "lse_c": metric("lse_c", items(1.2, 0.4, 812))},
        control={"kind": "still-frame", "targets": ["lmd", "lse_d", "lse_c"]}))
    for k, name in enumerate(("talkinggaussian", "lmgs")):
        for c, (cond, shift) in enumerate((("clean", 0.0), ("noise-10db", -0.8), ("silence", -4.0))):
            recs.append(record(name, _SELF[name][0], _SELF[name][1], 0, {
                "lse_c": metric("lse_c", items(7.5 - 0.3 * k + shift, 0.3, 900 + 10 * k + c)),
                "lmd": metric("lmd", items(2.5 + 0.1 * c, 0.1, 950 + 10 * k + c))},
                protocol="stress", clip=cond, config={"name": name}))
    recs.append(record("talkinggaussian", "TalkingGaussian", "3DGS", 0, {}, protocol="stress", clip="long-300s",
                       config={"name": "talkinggaussian"}, status={"state": "failed", "reason": "out of memory"}))
    return recs


def typed(recs: list[dict]) -> list[R.Record]:
    """Records in their JSON form as the typed records the store hands out."""
    return [R.Record.from_dict(r) for r in recs]


def write_store(root: Path, recs: list[dict] | None = None) -> list[Path]:
    return [R.write_record(root, r) for r in (recs or fixture_records())]


# ----------------------------------------------------------------------------- tests
def test_fixture_records_validate_and_round_trip(tmp_path):
    recs = fixture_records()
    for r in recs:
        assert R.validate(r) == [], r["method"]["name"]
    paths = write_store(tmp_path, recs)
    assert len(set(paths)) == len(recs)  # one file per (method, subject, protocol, clip, seed, config)
    loaded, warnings = R.load_records(tmp_path)
    assert warnings == [] and all(isinstance(r, R.Record) for r in loaded)
    key = lambda r: str(R.record_path("", r))  # noqa: E731
    assert sorted(loaded, key=key) == sorted(typed(recs), key=key)
    # the typed record gives back the JSON it was read from, explicit nulls included ("variant": null)
    written = {p: json.loads(json.dumps(r)) for p, r in zip(paths, recs)}
    assert all(rec.to_dict() == written[p] for p, rec in R.iter_store(tmp_path)[0])
    assert loaded[0].to_dict()["method"]["variant"] is None
    p = R.record_path(tmp_path, typed(recs)[1])
    assert p == tmp_path / "astronaut" / "self" / f"ernerf--test--seed0--{recs[1]['config_hash']}.json"
    assert p == R.run_path(tmp_path, "astronaut", "self", "ernerf", "test", 0, recs[1]["config_hash"])


def test_a_typed_record_is_written_as_the_json_it_came_from(tmp_path):
    """Writing the typed record or its JSON form gives the same file, byte for byte; a changed copy
    (:func:`replace`) keeps the nulls of what it does not change, and is checked when it is made."""
    rec = fixture_records()[3]
    rec["cost"]["others_cpu_share"] = None  # an optional field written as null
    a, b = R.write_record(tmp_path / "a", rec), R.write_record(tmp_path / "b", R.Record.from_dict(rec))
    assert a.read_bytes() == b.read_bytes() and '"others_cpu_share": null' in a.read_text()
    (loaded,) = R.load_records(tmp_path / "a")[0]
    assert loaded.failed is False and loaded.value("psnr") == rec["metrics"]["psnr"]["value"]
    assert loaded.value("jitter") is None
    faster = R.replace(loaded, cost=R.replace(loaded.cost, fps=99.0))
    assert faster.to_dict()["cost"] == {**rec["cost"], "fps": 99.0}
    assert loaded.cost.fps != 99.0  # the record itself is unchanged (frozen)
    with pytest.raises(ValueError, match="n_effective 99 > n_original"):
        R.replace(loaded.metrics["psnr"], n_effective=99)  # no such block is made, so none is written


def test_validate_names_the_field():
    rec = fixture_records()[1]
    rec["metrics"]["psnr"]["value"] = "high"
    rec["method"]["family"] = "diffusion"
    del rec["seed"]
    problems = R.validate(rec)
    assert "record.metrics.psnr.value: expected number|null, got str 'high'" in problems
    assert any(p.startswith("record.method.family: 'diffusion' is not one of") for p in problems)
    assert "record.seed: missing" in problems
    rec = fixture_records()[1]
    rec["metrics"]["psnr"]["value"] = float("nan")
    assert any("psnr.value" in p for p in R.validate(rec))
    rec = fixture_records()[1]
    rec["metrics"]["psnr"]["n_effective"] = 99
    assert any("n_effective 99 > n_original" in p for p in R.validate(rec))


def test_broken_record_is_rejected_on_write_and_nothing_is_written(tmp_path):
    rec = fixture_records()[1]
    rec["artefacts"] = {"renders": {"path": "r.mp4", "sha256": "not-a-hash"}}
    with pytest.raises(UserError, match=r"ernerf/astronaut is invalid: record.artefacts.renders.sha256"):
        R.write_record(tmp_path, rec)
    assert list(tmp_path.rglob("*")) == []


def test_foreign_and_broken_files_are_skipped_with_a_warning(tmp_path):
    write_store(tmp_path)
    (tmp_path / "notes.json").write_text('{"schema": "lmgs-eval/score/1"}')
    (tmp_path / "astronaut" / "truncated.json").write_text('{"schema_version": "1", "meth')
    bad = fixture_records()[2]
    bad["metrics"]["lmd"]["higher_is_better"] = "no"
    (tmp_path / "astronaut" / "bad.json").write_text(json.dumps(bad))
    future = dict(fixture_records()[2], schema_version="99")
    (tmp_path / "future.json").write_text(json.dumps(future))
    (tmp_path / ".x.json.tmp-123").write_text("{")  # a writer's temp file: ignored
    recs, warnings = R.load_records(tmp_path)
    assert len(recs) == len(fixture_records())
    joined = "\n".join(warnings)
    assert len(warnings) == 4
    assert f"{tmp_path / 'notes.json'}: skipped, not a result record" in joined
    assert f"{tmp_path / 'astronaut' / 'truncated.json'}: skipped, not readable JSON" in joined
    assert f"{tmp_path / 'astronaut' / 'bad.json'}: skipped, invalid record: record.metrics.lmd.higher_is_better" in joined
    assert f"{tmp_path / 'future.json'}: skipped, schema_version '99'" in joined
    assert R.load_records(tmp_path / "absent") == ([], [])


def test_find_record_for_resume(tmp_path):
    rec = fixture_records()[3]
    assert R.find_record(tmp_path, "ernerf", "astronaut", "self", "test", 1, rec["config_hash"]) is None
    write_store(tmp_path, [rec])
    got = R.find_record(tmp_path, rec["method"]["name"], "astronaut", "self", "test", rec["seed"], rec["config_hash"])
    assert got == R.Record.from_dict(rec)
    assert R.find_record(tmp_path, rec["method"]["name"], "astronaut", "self", "test", rec["seed"], "other") is None
    assert R.find_record(tmp_path, rec["method"]["name"], "astronaut", "cross", "A", rec["seed"], rec["config_hash"]) is None
    # a record of other data of a subject of the same name is neither reused nor overwritten
    key = (tmp_path, rec["method"]["name"], "astronaut", "self", "test", rec["seed"], rec["config_hash"])
    assert R.find_record(*key, subject_sha="a" * 64) == got
    with pytest.raises(UserError, match=r"made on other data of subject 'astronaut' \(manifest sha256 aaaaaaaaaaaa, now bbbbbbbbbbbb\)"):
        R.find_finished(*key, subject_sha="b" * 64)


def test_interrupted_write_leaves_no_partial_record(tmp_path, monkeypatch):
    import lmgs_eval.paths as paths

    def boom(fd):
        raise RuntimeError("power cut after the bytes, before the rename")

    write_store(tmp_path, fixture_records()[:1])
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    monkeypatch.setattr(paths.os, "fsync", boom)
    with pytest.raises(RuntimeError, match="power cut"):
        R.write_record(tmp_path, fixture_records()[1])
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file()) == \
        sorted(b for b in before if (tmp_path / b).is_file())
    assert R.load_records(tmp_path)[1] == []


def _writer(root: str, which: int) -> None:
    recs = fixture_records()
    for _ in range(15):
        for r in recs[:6]:  # both processes write the same six records
            r["notes"] = [f"writer {which}"]
            R.write_record(root, r)


def test_concurrent_writers_leave_valid_files(tmp_path):
    ctx = multiprocessing.get_context("fork")
    procs = [ctx.Process(target=_writer, args=(str(tmp_path), i)) for i in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
        assert p.exitcode == 0
    recs, warnings = R.load_records(tmp_path)
    assert warnings == [] and len(recs) == 6
    assert {r.notes[0] for r in recs} <= {"writer 0", "writer 1"}
    assert not [p for p in tmp_path.rglob("*") if p.name.startswith(".")]


def test_metric_entries_from_metric_results():
    spec = {"name": "stlpips-alex", "higher_is_better": False, "unit": "", "backend": "onnxruntime", "version": "ST0.0",
            "weights_sha256": "b" * 64, "standin": "ST-LPIPS instead of LPIPS", "per": "frame", "definition": "",
            "reference": ""}
    res = {"name": "stlpips-alex", "available": True, "value": 0.1, "values": {"stlpips": 0.1}, "n_original": 3,
           "n_effective": 2, "flags": ["no-face"], "notes": [], "spec": spec, "per_item": [0.1, None, 0.123456789]}
    e = R.metric_entries(res)["lpips"]
    assert e["backend"] == "stlpips-alex" and e["backend_version"] == "ST0.0"
    assert e["per_item"] == [0.1, None, 0.123457] and e["standin"] == "ST-LPIPS instead of LPIPS"
    lse_spec = dict(spec, name="lse", backend="onnxruntime:bundled-sync", version="1", standin="")
    lse = {"name": "lse", "available": True, "value": 7.0, "values": {"lse_d": 7.0, "lse_c": 8.0, "offset": 1},
           "n_original": 10, "n_effective": 10, "flags": [], "notes": [], "spec": lse_spec, "per_item": [7.0] * 10}
    e = R.metric_entries(lse)
    assert (e["lse_d"]["value"], e["lse_c"]["value"]) == (7.0, 8.0)
    assert e["lse_c"]["higher_is_better"] and not e["lse_d"]["higher_is_better"]
    assert e["lse_d"]["standin"] is None and e["lse_c"]["per_item"] is None
    rec = record("x", "X", "3DGS", 0, {**R.metric_entries(res), **e})
    assert R.validate(rec) == []


def test_helpers(tmp_path):
    f = tmp_path / "a.bin"
    f.write_bytes(b"abc")
    assert R.sha256_file(f) == "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    assert R.config_hash({"b": 1, "a": [1, 2]}) == R.config_hash({"a": [1, 2], "b": 1})
    g = R.git_info()
    assert set(g) == {"version", "git_commit", "dirty"}
    m = R.machine_info()
    assert set(m) == {"cpu", "threads", "torch", "cuda_device", "platform", "cpu_kernels"} and m["threads"] >= 1
    import torch

    # with torch loaded, the kernels' instruction set is the one torch dispatches to
    assert R.machine_info()["cpu_kernels"] == torch.backends.cpu.get_cpu_capability()


def test_input_artefacts_name_the_sync_scorer_that_made_the_lse(tmp_path):
    from lmgs_eval.metrics.sync.scorers import PIXEL_ONNX, WEIGHTS
    from lmgs_eval.metrics.sync.landmark import ONNX_NAME
    from lmgs_eval.results.records import input_artefacts

    for backend, weights in (("onnxruntime:landmark-sync", WEIGHTS / ONNX_NAME),
                             ("onnxruntime:bundled-sync", WEIGHTS / PIXEL_ONNX)):
        got = input_artefacts({"lse_d": {"backend": backend, "value": 1.0}}, tmp_path)
        assert got["weights:sync"] == {"path": str(weights.resolve()), "sha256": R.sha256_file(weights)}
    assert "weights:sync" not in input_artefacts({"lse_d": {"backend": "onnxruntime:landmark-sync", "value": None}},
                                                  tmp_path)


# ----------------------------------------------------------------------------- the DataFrame view
ROOT = Path(__file__).resolve().parents[1]


def test_frame_has_a_row_per_record_and_metric(tmp_path):
    from lmgs_eval.results.dataframe import COLUMNS

    recs = fixture_records()
    paths = write_store(tmp_path, recs)
    (tmp_path / "junk.json").write_text("[]")
    with pytest.warns(UserWarning, match="junk.json: skipped"):
        df = R.frame(tmp_path)
    assert list(df.columns) == list(COLUMNS)
    assert len(df) == sum(len(r["metrics"]) for r in recs)
    per_record = df.groupby("path").size()
    for p, r in zip(paths, recs):  # a failed run without metrics has no row
        assert per_record.get(str(p), 0) == len(r["metrics"]), p
    row = df[(df.method == "lmgs") & (df.protocol == "self") & (df.seed == 1) & (df.metric == "lpips")].iloc[0]
    rec = next(r for r in recs if r["method"]["name"] == "lmgs" and r["protocol"]["name"] == "self" and r["seed"] == 1)
    assert row.value == rec["metrics"]["lpips"]["value"] and row.backend == "stlpips-alex" and row.standin
    assert row.metric_standin.startswith("ST-LPIPS") and row.subject_standin == SUBJECT["standin"]
    assert [row[c] for c in ("subject", "clip", "split", "config_hash", "status")] == ["astronaut", "test", "test",
                                                                                      rec["config_hash"], "ok"]
    assert row.fps == rec["cost"]["fps"] and row.n_gaussians == 11000 and np.isnan(row.ci_low)
    assert (row.commit, row.created, row.cpu, row.threads) == ("0" * 40, CREATED, "Test CPU", 2)
    assert df.value.dtype == "float64" and df.seed.dtype == "int64" and df.variant.isna().sum() > 0
    # from records in memory: the same rows, without their files
    mem = R.frame(typed(recs))
    assert mem.path.isna().all() and len(mem) == len(df)
    assert R.frame(tmp_path / "absent").columns.tolist() == list(COLUMNS) and R.frame([]).empty


def test_frame_pivots_to_the_committed_tables():
    """The committed tables/*.csv are made from tables/records: a pivot of the frame gives their means."""
    import csv

    df = R.frame(ROOT / "tables" / "records")
    items, _ = R.iter_store(ROOT / "tables" / "records")
    assert df.path.nunique() == sum(1 for _, r in items if r.metrics)
    assert df.groupby("path").size().to_dict() == {str(p): len(r.metrics) for p, r in items if r.metrics}
    use = df[(df.status == "ok") & df.variant.isna() & (df.family != "control")]
    self_ = use[use.protocol == "self"]
    means = self_.pivot_table("value", index=["subject", "method"], columns="metric", aggfunc="mean")
    fps = self_.drop_duplicates("path").groupby(["subject", "method"]).fps.mean()
    cross = use[use.protocol == "cross"].pivot_table("value", index=["subject", "method"], columns=["clip", "metric"])
    checked = 0
    for name, cols in (("table1_self", ("psnr", "lpips", "lmd", "lse_d", "lse_c")),
                       ("table2_cross", ("A.lse_d", "A.lse_c", "B.lse_d", "B.lse_c"))):
        with open(ROOT / "tables" / f"{name}.csv", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
        assert rows
        for row in rows:
            key = (row["section"].removesuffix(" (bundled)"), row["method"])
            for col in cols:
                if not row[col]:
                    continue
                got = means.loc[key, col] if name == "table1_self" else cross.loc[key, tuple(col.split("."))]
                assert got == pytest.approx(float(row[col]), rel=1e-12), (name, key, col)
                checked += 1
            if name == "table1_self" and row["cost.fps"]:
                assert fps[key] == pytest.approx(float(row["cost.fps"]), rel=1e-12), key
    assert checked > 100
