"""Typed records, and the committed store of version-1 records read through the migration.

Most committed ``tables/records`` were written by schema version 1 (SE share and subject budget in
prose notes, no ``method.components``; the 512 px section by the current version). They must load as version 2, agree with what today's lmgs
adapter declares for the same config, and make the committed tables again byte for byte.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from baselines.lmgs_method import LMGSMethod
from lmgs_eval.report.tables import all_tables
from lmgs_eval.results import SCHEMA_VERSION, Record, budget_note, iter_store, migrate, validate

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / "tables" / "records"


@pytest.fixture(scope="module")
def committed():
    items, warnings = iter_store(COMMITTED)
    assert warnings == [] and len(items) > 200
    return items


def test_the_committed_version_1_records_load_as_the_current_schema(committed):
    raw = [json.loads(p.read_text())["schema_version"] for p, _ in committed]
    # most were written by version 1 (the migration is what is exercised here); later runs by the current one
    assert set(raw) <= {"1", SCHEMA_VERSION} and raw.count("1") > 200
    for path, rec in committed:
        assert rec.schema_version == SCHEMA_VERSION and validate(rec) == [], path
        migrated = migrate(json.loads(path.read_text()))
        assert rec.to_dict() == json.loads(json.dumps(migrated)), path  # the typed form loses nothing
        assert rec.method.name == migrated["method"]["name"] and rec.seed == migrated["seed"]


def test_migrated_components_are_what_the_lmgs_adapter_declares(committed):
    """The components a version-1 record's config implies equal the adapter's for the same config hash."""
    checked = set()
    for path, rec in committed:
        name = rec.method.name
        if not (name == "lmgs" or name.startswith("lmgs-")) or rec.protocol.name != "self":
            continue
        method = LMGSMethod(name, budget_density=rec.run.budget.density if rec.run and rec.run.budget else None)
        info = method.describe()
        if info.config_hash != rec.config_hash:
            continue  # a config of an older code version: nothing today declares it
        assert rec.method.components == info.components, path
        checked.add(name)
    # the full model and its Table IV switches are all covered
    assert {"lmgs", "lmgs-no-se", "lmgs-no-lc", "lmgs-no-gr", "lmgs-uncapped", "lmgs-oof"} <= checked


def test_prose_facts_become_fields_and_print_as_before(committed):
    se = [(p, r) for p, r in committed if r.run and r.run.se_fraction is not None]
    budget = [(p, r) for p, r in committed if r.run and r.run.budget]
    assert se and budget
    for path, rec in se:
        raw = json.loads(path.read_text())
        note = next(n for n in raw["notes"] if n.startswith("spatial enhancement selected"))
        assert note.startswith(f"spatial enhancement selected {100 * rec.run.se_fraction:.1f}%")
    for path, rec in budget:
        b = rec.run.budget
        assert budget_note(b.density, b.preset_density) in json.loads(path.read_text())["notes"], path


def test_a_current_record_is_left_as_it_is_and_a_wrong_type_is_named():
    rec = {"schema_version": SCHEMA_VERSION, "notes": ["Gaussian budget: 0.5 per pixel of face area"]}
    assert migrate(rec) is rec
    problems = validate({"schema_version": "2", "seed": "0"})
    assert "record.seed: expected integer, got str '0'" in problems and "record.method: missing" in problems


def test_the_committed_tables_are_made_again_byte_for_byte(committed):
    """Every table under tables/ is a pure function of tables/records."""
    tables = all_tables([r for _, r in committed])
    assert len(tables) >= 5
    made = set()
    for t in tables:
        for ext, text in (("md", t.markdown()), ("tex", t.latex()), ("csv", t.csv())):
            path = ROOT / "tables" / f"{t.name}.{ext}"
            assert path.is_file(), f"{path} is made from tables/records but not committed"
            assert path.read_text(encoding="utf-8") == text, path
            made.add(path.name)
    # and no committed table is left over that the records no longer make
    on_disk = {p.name for p in (ROOT / "tables").iterdir() if p.suffix in (".md", ".tex", ".csv")} - {"README.md"}
    assert on_disk == made, sorted(on_disk ^ made)


def test_a_metric_entry_carries_each_weights_file_and_old_entries_still_read(tmp_path):
    """``weights_files`` (LPIPS alex: the trunk and the heads, path and sha256) beside ``weights_sha256``: optional,
    so the committed records (without it) read and re-encode as they were (the test above)."""
    import torch

    from conftest import random_alexnet_state
    from lmgs_eval.metrics import lpips as L
    from lmgs_eval.results.records import input_artefacts, metrics_block
    from test_results import record

    if L.lpips_heads_path() is None:
        pytest.skip("lpips wheel not installed")
    ck = tmp_path / L.ALEXNET_CKPT
    torch.save(random_alexnet_state(), ck)
    m = L.LPIPS("lpips-alex", alexnet=ck, use_onnx=False)
    frames = torch.rand(2, 40, 40, 3).numpy()
    block = metrics_block({"lpips": m.compute(m.update(frames, frames[::-1].copy()))})
    assert list(block) == ["lpips_custom"]
    rec = record("lmgs", "Ours", "3DGS", 0, block)
    assert validate(rec) == []
    typed = Record.from_dict(rec)
    trunk = typed.metrics["lpips_custom"].weights_files["alexnet"]
    assert trunk.path == str(ck.resolve()) and trunk.sha256 == L.sha256_file(ck)
    assert typed.to_dict()["metrics"] == json.loads(json.dumps(rec["metrics"]))
    # lmgs-eval verify re-hashes the files the number was made with (the trunk given, not the hub cache's)
    arts = input_artefacts(block, tmp_path)
    assert arts["weights:alexnet"] == {"path": str(ck.resolve()), "sha256": trunk.sha256}
    assert arts["weights:lpips_heads"]["sha256"] == L.LPIPS_HEADS_SHA256
    bad = json.loads(json.dumps(rec))
    bad["metrics"]["lpips_custom"]["weights_files"]["alexnet"]["sha256"] = "7be5be79"
    assert validate(bad) == ["record.metrics.lpips_custom.weights_files.alexnet.sha256: '7be5be79' does not match "
                             "^[0-9a-f]{64}$"]
