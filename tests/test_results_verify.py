"""The results store's ``lmgs-eval verify`` (re-hashing what records name) and the committed snapshot of
records (``lmgs-eval table --records``) that a fresh store resumes from."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

from lmgs_eval import results as R
from test_results import fixture_records, typed, write_store


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

    ours = Path(lmgs_eval.__file__).resolve().parent / "metrics" / "sync" / "weights" / "bundled_sync.onnx"
    elsewhere = tmp_path / "gone" / "clone" / "lmgs_eval" / "metrics" / "sync" / "weights" / "bundled_sync.onnx"
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
    key = lambda r: str(R.record_path("", r))  # noqa: E731
    assert sorted(R.load_records(snap)[0], key=key) == sorted(typed(recs), key=key)

    # A fresh machine's empty store: every run of the snapshot is found, so it is not redone.
    fresh = tmp_path / "fresh"
    assert R.copy_records(snap, fresh) == (len(recs), [])
    for r in typed(recs):
        got = R.find_record(fresh, r.method.name, r.subject.name, r.protocol.name, r.protocol.clip, r.seed,
                            r.config_hash)
        assert got == r
    # A record already in the store is kept, not overwritten by the snapshot's.
    second = typed(recs)[1]
    R.write_record(fresh, R.replace(second, notes=("made here",)))
    assert R.copy_records(snap, fresh) == (0, [])
    assert json.loads(R.record_path(fresh, second).read_text())["notes"] == ["made here"]

    # A snapshot replaces the folder whole: a record no longer in the store leaves it.
    R.record_path(tmp_path / "results", second).unlink()
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
