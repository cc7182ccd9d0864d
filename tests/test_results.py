"""The results store: schema, atomic writes, loading with warnings, resume lookup, ``verify``.

Also home of the hand-written results store that the table tests use (:func:`fixture_records`).
"""

from __future__ import annotations

import json
import multiprocessing
import os
import sys
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
    assert warnings == []
    key = lambda r: str(R.record_path("", r))  # noqa: E731
    assert sorted(loaded, key=key) == sorted(json.loads(json.dumps(recs)), key=key)
    p = R.record_path(tmp_path, recs[1])
    assert p == tmp_path / "astronaut" / "self" / f"ernerf--test--seed0--{recs[1]['config_hash']}.json"


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
    assert got == rec
    assert R.find_record(tmp_path, rec["method"]["name"], "astronaut", "self", "test", rec["seed"], "other") is None
    assert R.find_record(tmp_path, rec["method"]["name"], "astronaut", "cross", "A", rec["seed"], rec["config_hash"]) is None
    # a record of other data of a subject of the same name is neither reused nor overwritten
    key = (tmp_path, rec["method"]["name"], "astronaut", "self", "test", rec["seed"], rec["config_hash"])
    assert R.find_record(*key, subject_sha="a" * 64) == rec
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
    assert {r["notes"][0] for r in recs} <= {"writer 0", "writer 1"}
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


# ----------------------------------------------------------------------------- verify
def cli_main(argv: list[str]) -> int:
    """Run one of this module's commands as ``lmgs-eval`` would (parse, run, UserError -> 2)."""
    import argparse
    import importlib

    from lmgs.errors import InputError

    mod = importlib.import_module(f"lmgs_eval.commands.{argv[0]}")
    parser = argparse.ArgumentParser(prog=f"lmgs-eval {argv[0]}")
    mod.add_arguments(parser)
    try:
        return mod.run(parser.parse_args(argv[1:]))
    except InputError as exc:
        print(f"lmgs-eval {argv[0]}: error: {exc}", file=sys.stderr)
        return 2


def _store_with_artefacts(root: Path) -> list[dict]:
    (root / "renders").mkdir(parents=True)
    (root / "renders" / "lmgs.mp4").write_bytes(b"frames of lmgs")
    weights = root / "w" / "sync.onnx"
    weights.parent.mkdir()
    weights.write_bytes(b"weights")
    recs = fixture_records()[:4]
    recs[3]["artefacts"] = {
        "renders": {"path": "renders/lmgs.mp4", "sha256": R.sha256_file(root / "renders" / "lmgs.mp4")},
        "weights:lse": {"path": str(weights), "sha256": R.sha256_file(weights)},
    }
    write_store(root, recs)
    return recs


def test_verify_passes_an_intact_store(tmp_path, capsys):
    _store_with_artefacts(tmp_path)
    assert cli_main(["verify", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "4 records, 2 artefacts checked: all inputs unchanged" in out


def test_verify_catches_changed_render_and_missing_weights(tmp_path, capsys):
    _store_with_artefacts(tmp_path)
    (tmp_path / "renders" / "lmgs.mp4").write_bytes(b"frames of something else")
    os.unlink(tmp_path / "w" / "sync.onnx")
    assert cli_main(["verify", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    assert f"renders {tmp_path / 'renders' / 'lmgs.mp4'}: changed" in out
    assert f"weights:lse {tmp_path / 'w' / 'sync.onnx'}: missing" in out
    assert "1 of 4 records" in out


def test_verify_finds_the_bundled_weights_of_a_record_made_in_another_checkout(tmp_path, capsys):
    """A record made in another clone names that clone's weights; verify hashes this clone's file
    at the same place in the package (same bytes: unchanged; other bytes: changed)."""
    import lmgs_eval

    ours = Path(lmgs_eval.__file__).resolve().parent / "metrics" / "weights" / "bundled_sync.onnx"
    elsewhere = tmp_path / "gone" / "clone" / "lmgs_eval" / "metrics" / "weights" / "bundled_sync.onnx"
    recs = fixture_records()[:1]
    recs[0]["artefacts"] = {"weights:sync": {"path": str(elsewhere), "sha256": R.sha256_file(ours)}}
    write_store(tmp_path / "a", recs)
    assert cli_main(["verify", str(tmp_path / "a")]) == 0
    assert "1 artefacts checked: all inputs unchanged" in capsys.readouterr().out
    recs[0]["artefacts"]["weights:sync"]["sha256"] = "0" * 64
    write_store(tmp_path / "b", recs)
    assert cli_main(["verify", str(tmp_path / "b")]) == 1
    assert f"weights:sync {ours}: changed (recorded sha256 000000000000" in capsys.readouterr().out
    recs[0]["artefacts"]["weights:sync"]["path"] = str(tmp_path / "gone" / "lmgs_eval" / "no-such.onnx")
    write_store(tmp_path / "c", recs)
    assert cli_main(["verify", str(tmp_path / "c")]) == 1
    assert "no-such.onnx: missing" in capsys.readouterr().out


def test_verify_of_a_missing_store_is_a_user_error(tmp_path, capsys):
    assert cli_main(["verify", str(tmp_path / "nope")]) == 2
    assert "nope" in capsys.readouterr().err


# ----------------------------------------------------------------------------- committed records
def test_records_snapshot_makes_the_same_tables_and_lets_a_fresh_store_resume(tmp_path, capsys):
    """``table --records``: the snapshot regenerates byte-identical tables; importing it resumes."""
    recs = fixture_records()
    write_store(tmp_path / "results", recs)
    snap = tmp_path / "tables" / "records"
    assert cli_main(["table", "--results", str(tmp_path / "results"), "--out", str(tmp_path / "tables"),
                     "--records", str(snap), "--no-charts"]) == 0
    assert cli_main(["table", "--results", str(snap), "--out", str(tmp_path / "again"), "--no-charts"]) == 0
    made = sorted(p.name for p in (tmp_path / "tables").glob("*.*"))
    assert made and made == sorted(p.name for p in (tmp_path / "again").glob("*.*"))
    for name in made:
        assert (tmp_path / "tables" / name).read_bytes() == (tmp_path / "again" / name).read_bytes(), name
    assert sorted(R.load_records(snap)[0], key=R.config_hash) == sorted(recs, key=R.config_hash)

    # A fresh machine's empty store: every run of the snapshot is found, so it is not redone.
    fresh = tmp_path / "fresh"
    assert R.copy_records(snap, fresh) == (len(recs), [])
    for r in recs:
        got = R.find_record(fresh, r["method"]["name"], r["subject"]["name"], r["protocol"]["name"],
                            r["protocol"]["clip"], r["seed"], r["config_hash"])
        assert got == r
    # A record already in the store is kept, not overwritten by the snapshot's.
    mine = json.loads(R.record_path(fresh, recs[1]).read_text())
    mine["notes"] = ["made here"]
    R.write_record(fresh, mine)
    assert R.copy_records(snap, fresh) == (0, [])
    assert json.loads(R.record_path(fresh, recs[1]).read_text())["notes"] == ["made here"]

    # A snapshot replaces the folder whole: a record no longer in the store leaves it.
    R.record_path(tmp_path / "results", recs[1]).unlink()
    assert cli_main(["table", "--results", str(tmp_path / "results"), "--out", str(tmp_path / "tables"),
                     "--records", str(snap), "--no-charts"]) == 0
    assert len(R.load_records(snap)[0]) == len(recs) - 1


@pytest.mark.parametrize("where", ["same", "inside", "parent"])
def test_records_folder_overlapping_the_store_is_refused(tmp_path, capsys, where):
    store = tmp_path / "store"
    write_store(store)
    target = {"same": store, "inside": store / "tables" / "records", "parent": tmp_path}[where]
    assert cli_main(["table", "--results", str(store), "--out", str(tmp_path / "t"), "--records", str(target),
                     "--no-charts"]) == 2
    err = capsys.readouterr().err
    assert "overlaps the results store" in err and str(target) in err
    assert len(R.load_records(store)[0]) == len(fixture_records())  # nothing was replaced


def test_verify_of_imported_records_excuses_only_their_renders_and_checkpoints(tmp_path, capsys):
    """Records copied from another machine: renders/checkpoints stay there; weights are still checked."""
    made = tmp_path / "made"
    (made / "renders").mkdir(parents=True)
    (made / "renders" / "a.mp4").write_bytes(b"frames")
    weights = tmp_path / "w.onnx"
    weights.write_bytes(b"weights")
    recs = fixture_records()[:3]
    for r in recs:
        r["artefacts"] = {"render": {"path": "renders/a.mp4", "sha256": R.sha256_file(made / "renders" / "a.mp4")},
                          "checkpoint": {"path": str(tmp_path / "gone" / "model.pt"), "sha256": "0" * 64},
                          "weights:sync": {"path": str(weights), "sha256": R.sha256_file(weights)}}
    write_store(made, recs)
    here = tmp_path / "here"
    assert R.copy_records(made, here)[0] == 3
    assert len(R.imported_records(here)) == 3 and R.load_records(here)[1] == []  # the ledger is not a record
    assert cli_main(["verify", str(here)]) == 0
    out = capsys.readouterr().out
    assert "3 records were imported" in out and "3 records, 3 artefacts checked: all inputs unchanged" in out

    # a record made here with its render missing is still a problem
    own = fixture_records()[5]
    own["artefacts"] = {"render": {"path": "renders/b.mp4", "sha256": "1" * 64}}
    R.write_record(here, own)
    weights.write_bytes(b"other weights")  # and a weights file that changed is caught on imported records too
    assert cli_main(["verify", str(here)]) == 1
    out = capsys.readouterr().out
    assert f"render {here / 'renders' / 'b.mp4'}: missing" in out
    assert out.count(f"weights:sync {weights}: changed") == 3
    assert "4 of 4 records" in out


def test_input_artefacts_name_the_sync_scorer_that_made_the_lse(tmp_path):
    from types import SimpleNamespace

    from lmgs_eval.metrics import sync_landmark
    from lmgs_eval.results.records import input_artefacts

    subject = SimpleNamespace(root=tmp_path)
    for backend, weights in (("onnxruntime:landmark-sync", sync_landmark.WEIGHTS / sync_landmark.ONNX_NAME),
                             ("onnxruntime:bundled-sync", sync_landmark.WEIGHTS / "bundled_sync.onnx")):
        got = input_artefacts({"lse_d": {"backend": backend, "value": 1.0}}, subject)
        assert got["weights:sync"] == {"path": str(weights.resolve()), "sha256": R.sha256_file(weights)}
    assert "weights:sync" not in input_artefacts({"lse_d": {"backend": "onnxruntime:landmark-sync", "value": None}},
                                                  subject)
