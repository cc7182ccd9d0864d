"""Which records a run makes, known before it runs: how resume finds it done, and what a failure records.

A run's keys are the store look-ups its protocol makes itself (method, protocol, clip, seed,
config hash): the self-driven run one, the cross-driven run one per driving clip, the stress
run one per condition, the capacity run one per budget. They are made on the driver, with
the methods built as the protocols build them, so a run is skipped exactly when the protocol
would skip all of its work.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lmgs.fileio import sha256_file
from lmgs_eval import results as store
from lmgs_eval.plans.execute import run_config
from lmgs_eval.plans.runs import Run
from lmgs_eval.results.records import RunId, build_record, stored


@dataclass(frozen=True)
class Key:
    """One record a run makes, and the method that makes it (for a failed record)."""

    method: str
    protocol: str
    clip: str
    seed: int
    config_hash: str
    split: str
    info: object  # baselines.protocol.MethodInfo

    def of(self, subject) -> RunId:
        """The run of this key on ``subject``."""
        return RunId(subject, self.info, self.seed, self.protocol, self.clip, self.config_hash)


class Identities:
    """The keys of runs, with each subject read once (a bundled one built on first use, under its lock)."""

    def __init__(self, results: Path, data_root: str | None = None):
        self.results = Path(results)
        self.data_root = data_root
        self._subjects: dict[str, object] = {}
        self._areas: dict[str, float] = {}

    def subject(self, name: str):
        from lmgs_eval.data.registry import find_subject

        if name not in self._subjects:
            self._subjects[name] = find_subject(name, self.data_root, progress=False)
        return self._subjects[name]

    def keys(self, run: Run) -> list[Key]:
        from lmgs_eval.runner import build_method

        subject = self.subject(run.subject)
        cfg = run_config(run, self.results)
        if run.protocol == "capacity":
            return self._capacity_keys(run, cfg, subject)
        info = build_method(cfg, run.method, subject).describe()
        if run.protocol == "self":
            return [Key(info.name, "self", "test", run.seed, info.config_hash, "test", info)]
        if run.protocol == "cross":
            if run.method.startswith("external:"):
                return []
            if run.clips:
                names = _user_clip_names(run.clips)
            else:
                from lmgs_eval.protocols.cross import bundled_cross_clips

                names = [(c.name, c.source) for c in bundled_cross_clips(subject)]
            return [Key(info.name, "cross", n, run.seed, info.config_hash, src, info) for n, src in names]
        if run.protocol == "stress":
            from lmgs_eval.protocols.perturb import SR, make_conditions
            from lmgs_eval.protocols.perturb import VERSION as PERTURB_VERSION
            from lmgs_eval.protocols.stress import _selected

            half = np.zeros(SR // 2, np.float32)
            other = half if (Path(subject.root) / "cross" / "A" / "aud.wav").exists() else None
            conds = _selected(make_conditions(half, seed=0, other_voice=other, long_seconds=run.long_seconds),
                              run.conditions)
            ch = f"{info.config_hash}-stress{PERTURB_VERSION}"
            return [Key(info.name, "stress", c.name, run.seed, ch, c.description, info) for c in conds]
        raise ValueError(f"unknown protocol {run.protocol!r}")

    def _capacity_keys(self, run: Run, cfg, subject) -> list[Key]:
        from lmgs.init import face_area_px
        from lmgs_eval.convert import subject_to_clip
        from lmgs_eval.protocols.capacity import DEFAULT_BUDGETS, budget_overrides
        from lmgs_eval.runner import build_method

        if run.subject not in self._areas:
            self._areas[run.subject] = face_area_px(subject_to_clip(subject, subject.train_ids))
        out = []
        for n, over in budget_overrides(cfg, subject, self._areas[run.subject], run.budgets or DEFAULT_BUDGETS).items():
            info = build_method(cfg, "lmgs", subject, overrides=over).describe()
            out.append(Key(info.name, "capacity", f"budget-{n}", run.seed, info.config_hash, "test", info))
        return out

    def finished(self, run: Run, key: Key) -> bool:
        """The store holds this key's record, and it is not a failed one (a failure is retried)."""
        return stored(self.results, key.of(self.subject(run.subject)), finished=True) is not None

    def known_records(self, run: Run) -> dict[str, str]:
        """The store's records of the run's subject but failed ones (relative path -> JSON text): what the worker resumes from."""
        folder = store.subject_dir(self.results, self.subject(run.subject).name)
        if not folder.is_dir():
            return {}
        out = {}
        for p in sorted(folder.rglob("*.json")):
            if any(s.startswith(".") for s in p.relative_to(folder).parts):
                continue
            text = p.read_text(encoding="utf-8")
            try:
                status = store.migrate(json.loads(text)).get("status") or {}
            except (ValueError, AttributeError):
                continue
            if status.get("state") != "failed":  # a failed run is redone: the protocol must not find it (some take any record as done)
                out[p.relative_to(self.results).as_posix()] = text
        return out

    def write_failed(self, run: Run, key: Key, reason: str) -> store.Record:
        """Record ``key`` as failed with ``reason`` (never over a finished record: callers check first)."""
        rec = build_record(key.of(self.subject(run.subject)), split=key.split, n_frames=0, metrics={}, cost={}, artefacts={},
                           status={"state": "failed", "reason": reason[:500] or "failed"})
        store.write_record(self.results, rec)
        return rec


def _user_clip_names(paths) -> list[tuple[str, str]]:
    """``(clip, split)`` of each user audio file as the cross protocol names it: the file's stem and the
    start of its sha256, and its absolute path (the same audio under two names is one clip; a file
    that is not there makes no record)."""
    out: dict[str, tuple[str, str]] = {}
    for c in paths:
        path = Path(c).resolve()
        if not path.is_file():
            continue
        sha = sha256_file(path)
        out.setdefault(sha, (f"{path.stem}-{sha[:12]}", str(path)))
    return list(out.values())
