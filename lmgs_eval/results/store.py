"""The results store on disk: one JSON file per run, written atomically, read back validated.

What goes in and what comes out is the typed :class:`~lmgs_eval.results.types.Record`; its JSON
form (:meth:`~lmgs_eval.results.types.Record.to_dict`) is what the files hold.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from lmgs.fileio import atomic_write, sha256_file
from lmgs_eval.errors import UserError
from lmgs_eval.paths import atomic_dir
from lmgs_eval.results.migrate import migrate
from lmgs_eval.results.schema import READ_VERSIONS, check
from lmgs_eval.results.types import Record, json_object


def _slug(s: str) -> str:
    slug = re.sub(r"[^A-Za-z0-9._+-]+", "_", s).strip("._") or "x"
    if slug != s:  # keep distinct names distinct after cleaning ("a:b" vs "a_b")
        slug += "-" + hashlib.sha256(s.encode()).hexdigest()[:6]
    return slug


def subject_dir(root: str | os.PathLike, subject: str) -> Path:
    """The folder of store ``root`` holding a subject's records (one sub-folder per protocol)."""
    return Path(root) / _slug(subject)


def run_path(root: str | os.PathLike, subject: str, protocol: str, method: str, clip: str, seed: int,
             config_hash: str) -> Path:
    """Stable file of a run: ``root/<subject>/<protocol>/<method>--<clip>--seed<N>--<config_hash>.json``
    (the subject's folder is :func:`subject_dir`)."""
    name = f"{_slug(method)}--{_slug(clip)}--seed{int(seed)}--{_slug(config_hash)}.json"
    return Path(root) / _slug(subject) / _slug(protocol) / name


def record_path(root: str | os.PathLike, record: Record) -> Path:
    """The file of ``record`` in store ``root`` (:func:`run_path` of its :attr:`~Record.key`)."""
    return run_path(root, *record.key)


def to_record(data: Mapping[str, Any]) -> Record:
    """A record's JSON form as the typed record; :class:`UserError` naming each field that does not fit."""
    rec, problems = check(data)
    if problems:
        who = (f"{data.get('method', {}).get('name', '?')}/{data.get('subject', {}).get('name', '?')}"
               if isinstance(data, Mapping) else "?")
        raise UserError(f"result record {who} is invalid: {'; '.join(problems[:5])}"
                        + (f" (+{len(problems) - 5} more)" if len(problems) > 5 else ""))
    return rec


def write_record(root: str | os.PathLike, record: Record | Mapping[str, Any]) -> Path:
    """Write a record (typed, or its JSON form) atomically (temp file + rename); returns its path.

    A typed record was checked when it was made; a JSON form is checked here, and one that does
    not validate writes nothing and raises :class:`UserError`. Two writers at once never leave a
    partial file: each writes its own temporary file and the rename is atomic (the last one wins
    for the same record).
    """
    rec = record if isinstance(record, Record) else to_record(record)
    path = record_path(root, rec)
    atomic_write(path, json.dumps(record, default=json_object, indent=1, sort_keys=True, allow_nan=False,
                                  ensure_ascii=False) + "\n")
    return path


def iter_store(root: str | os.PathLike) -> tuple[list[tuple[Path, Record]], list[str]]:
    """Every valid record of a store with its file, and a warning per skipped file.

    Files are read in sorted order; hidden files and folders (temporary files of writers in
    progress) are ignored. A file that is not JSON, not a record of this schema (foreign),
    of another schema version or invalid is skipped with a warning naming it.
    """
    root = Path(root)
    if not root.exists():
        return [], []
    if not root.is_dir():
        raise UserError(f"{root}: results store is not a folder")
    out: list[tuple[Path, Record]] = []
    warnings: list[str] = []
    for path in sorted(root.rglob("*.json")):
        if any(part.startswith(".") for part in path.relative_to(root).parts):
            continue
        try:
            rec = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            warnings.append(f"{path}: skipped, not readable JSON ({exc})")
            continue
        if not isinstance(rec, dict) or "schema_version" not in rec:
            warnings.append(f"{path}: skipped, not a result record (no schema_version)")
            continue
        if rec["schema_version"] not in READ_VERSIONS:
            warnings.append(f"{path}: skipped, schema_version {rec['schema_version']!r} (this code reads "
                            f"{', '.join(map(repr, READ_VERSIONS))})")
            continue
        typed, problems = check(migrate(rec))
        if problems:
            warnings.append(f"{path}: skipped, invalid record: {'; '.join(problems[:3])}")
            continue
        out.append((path, typed))
    return out, warnings


def load_records(root: str | os.PathLike) -> tuple[list[Record], list[str]]:
    """All valid records under ``root`` and a warning (naming the file) per skipped file."""
    items, warnings = iter_store(root)
    return [r for _, r in items], warnings


def copy_records(src: str | os.PathLike, dst: str | os.PathLike) -> tuple[int, list[str]]:
    """Copy into store ``dst`` every valid record of store ``src`` that ``dst`` does not hold.

    Only the JSON records travel: renders and checkpoints stay where they were made, while
    tables, charts and resume (:func:`find_record`) work from the record alone. The copies
    are listed in ``dst``'s :data:`IMPORTED_FILE`, so ``lmgs-eval verify`` does not call
    their absent renders and checkpoints missing. A record already in ``dst`` (same subject,
    protocol, method, clip, seed and config hash) is kept as it is. Returns the number
    copied and a warning per skipped file of ``src``.
    """
    items, warnings = iter_store(src)
    copied = []
    for _, rec in items:
        if not record_path(dst, rec).is_file():
            copied.append(write_record(dst, rec).relative_to(dst).as_posix())
    if copied:
        atomic_write(Path(dst) / IMPORTED_FILE, json.dumps(
            {"records": sorted(imported_records(dst) | set(copied))}, indent=1) + "\n")
    return len(copied), warnings


IMPORTED_FILE = ".imported.json"
"""Ledger of a store's records copied from elsewhere by :func:`copy_records` (hidden: not a record)."""


MADE_ELSEWHERE = ("render", "checkpoint", "driving_audio")
"""Artefact roles that stay on the machine that made a record (ground truth and weights travel)."""


def imported_records(root: str | os.PathLike) -> set[str]:
    """Paths (relative to the store) of the records :func:`copy_records` brought into ``root``."""
    try:
        return set(json.loads((Path(root) / IMPORTED_FILE).read_text(encoding="utf-8"))["records"])
    except (OSError, ValueError, KeyError, TypeError):
        return set()


def snapshot_records(records: Iterable[Record], dst: str | os.PathLike) -> Path:
    """Write exactly ``records`` as a store at ``dst``, replacing what was there, atomically.

    This is how the committed ``tables/records/`` is made: the records a set of tables was
    generated from, so ``lmgs-eval table --results tables/records`` makes the same tables
    again on any machine and ``make bench`` can resume from them.
    """
    with atomic_dir(Path(dst)) as tmp:
        for rec in records:
            write_record(tmp, rec)
    return Path(dst)


def se_fraction(rec: Record) -> float | None:
    """The share of face points Spatial Enhancement selected in this run (0..1); None if not recorded."""
    return rec.run.se_fraction if rec.run is not None else None


def find_finished(root: str | os.PathLike, method: str, subject: str, protocol: str, clip: str, seed: int,
                  config_hash: str, subject_sha: str | None = None) -> Record | None:
    """:func:`find_record`, but a failed run counts as not done: it is retried (the failure may have been fixed)."""
    rec = find_record(root, method, subject, protocol, clip, seed, config_hash, subject_sha)
    return None if rec is None or rec.failed else rec


def find_record(root: str | os.PathLike, method: str, subject: str, protocol: str, clip: str, seed: int,
                config_hash: str, subject_sha: str | None = None) -> Record | None:
    """The stored record for this run, or None (so an interrupted run can resume).

    Only a valid record whose fields match is returned; a failed run (``status.state ==
    "failed"``) is returned too, and the caller decides whether to retry it. With
    ``subject_sha`` (the subject's manifest hash), a record made on other data of a subject of
    the same name (re-generated, re-processed) is a :class:`UserError`: it is neither reused
    as if it were of this data nor overwritten.
    """
    path = run_path(root, subject, protocol, method, clip, seed, config_hash)
    if not path.is_file():
        return None
    try:
        rec = check(migrate(json.loads(path.read_text(encoding="utf-8"))))[0]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if rec is None:
        return None
    if rec.key != (subject, protocol, method, clip, seed, config_hash):
        return None
    made_on = rec.subject.sha256
    if subject_sha and made_on and made_on != subject_sha:
        raise UserError(f"{path}: made on other data of subject '{subject}' (manifest sha256 {made_on[:12]}, now "
                        f"{subject_sha[:12]}); move the old records out of the store, or use another --results")
    return rec


def resolve_artefact(root: str | os.PathLike, path: str) -> Path:
    """An artefact's file: absolute paths as is, relative ones under the store root."""
    p = Path(path).expanduser()
    return p if p.is_absolute() else Path(root) / p


def check_artefacts(root: str | os.PathLike, record: Record, imported: bool = False) -> tuple[list[str], int]:
    """Re-hash a record's artefacts: one line per artefact that changed or went missing, and how many were checked.

    ``imported``: the record was copied from another machine (:func:`copy_records`), so its
    render and checkpoint being absent here is expected, not a problem, and they are not
    counted as checked; present ones, and every other artefact (ground truth, metric
    weights), are checked as usual.
    """
    out = []
    checked = 0
    for role, a in sorted(record.artefacts.items()):
        p = resolve_artefact(root, a.path)
        if imported and role in MADE_ELSEWHERE and not p.is_file():
            continue
        checked += 1
        if not p.is_file():
            p = package_file(p) or p
        if not p.is_file():
            out.append(f"{role} {p}: missing")
            continue
        now = sha256_file(p)
        if now != a.sha256:
            out.append(f"{role} {p}: changed (recorded sha256 {a.sha256[:12]}, now {now[:12]})")
    return out, checked


def package_file(path: Path) -> Path | None:
    """The file of this ``lmgs_eval`` checkout at the place ``path`` had in the checkout it was
    recorded from (the bundled metric weights: a record made in another clone or worktree names
    that one's absolute path); None when ``path`` is not inside an ``lmgs_eval`` folder or this
    checkout lacks the file. The caller still compares the sha256, so a different file is caught.
    """
    parts = Path(path).parts
    if "lmgs_eval" not in parts:
        return None
    i = len(parts) - 1 - parts[::-1].index("lmgs_eval")
    here = Path(__file__).resolve().parents[1].joinpath(*parts[i + 1:])
    return here if here.is_file() else None
