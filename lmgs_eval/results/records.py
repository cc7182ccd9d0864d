"""A run's record assembled from what the protocols hand over: method, subject, metrics, cost, artefacts.

The sections follow the schema (:mod:`lmgs_eval.results.schema`); here are the toolkit's
sources of each: the subject's identity (its manifest's sha256), the inputs a number depends on
(ground truth and metric weights, re-hashed by ``lmgs-eval verify``), and the store look-up
that makes a run resumable.
"""

from __future__ import annotations

from pathlib import Path

from lmgs.presets import TrainConfig
from lmgs.fileio import sha256_file
from lmgs_eval.metrics import lpips as L
from lmgs_eval.metrics.sync.scorers import weights_file as sync_weights_file
from lmgs_eval.metrics.landmarks import dlib_model_path
from lmgs_eval.results.provenance import make_record, metric_entries
from lmgs_eval.results.notes import budget_note
from lmgs_eval.results.store import find_finished, find_record, to_record
from lmgs_eval.results.types import Record

PROTOCOL_VERSIONS = {"self": "1", "cross": "1", "stress": "1", "calibration": "1", "capacity": "1"}


def metrics_block(results: dict) -> dict:
    """MetricResults as the results file's ``metrics`` mapping (canonical keys, backends named)."""
    block = {}
    for r in results.values():
        block.update(metric_entries(r.to_dict()))
    return block


def _config_value(config, key: str):
    """The first ``key`` in a nested config dict (depth first), or None."""
    if isinstance(config, dict):
        if key in config:
            return config[key]
        for v in config.values():
            found = _config_value(v, key)
            if found is not None:
                return found
    return None


def subject_budget(info, subject) -> dict | None:
    """``run.budget`` of a method sized by the subject's own knee density (None when it was not)."""
    d = getattr(subject, "budget_density", None)
    if d is None or _config_value(info.config, "budget_density") != d:
        return None
    return {"density": float(d), "preset_density": float(TrainConfig.budget_density)}


def subject_block(subject) -> dict:
    return {
        "name": subject.name,
        "bundled": subject.bundled,
        "standin": subject.meta.get("standin") if subject.bundled else None,
        "frames": subject.n_frames,
        "width": subject.width,
        "height": subject.height,
        "path": str(subject.root),
        "sha256": subject_sha(subject),
    }


def stored(root, subject, method: str, protocol: str, clip: str, seed: int, config_hash: str, *,
           finished: bool = False) -> Record | None:
    """The store's record of this run on this subject's data, or None.

    ``finished``: a failed run counts as not done (it is retried). A record made on other data
    of a subject of the same name is a UserError (:func:`lmgs_eval.results.find_record`).
    """
    find = find_finished if finished else find_record
    return find(root, method, subject.name, protocol, clip, seed, config_hash, subject_sha(subject))


def subject_sha(subject) -> str | None:
    """sha256 of the subject's ``manifest.json`` (None without one): which data a record was made on."""
    p = subject.root / "manifest.json"
    return _sha_cached(p) if p.exists() else None


_SHA_CACHE: dict[tuple[str, int, int], str] = {}


def _sha_cached(path: Path) -> str:
    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _SHA_CACHE:
        _SHA_CACHE[key] = sha256_file(path)
    return _SHA_CACHE[key]


def input_artefacts(metrics: dict, subject) -> dict:
    """The inputs a record's numbers depend on, for ``lmgs-eval verify``: the subject's ground
    truth (its manifest, or its transforms files) and the weights files of the metrics used."""
    files: dict[str, Path | None] = {}
    root = Path(subject.root)
    if (root / "manifest.json").is_file():
        files["ground_truth"] = root / "manifest.json"
    else:
        for name in ("transforms_train.json", "transforms_val.json"):
            files[f"ground_truth:{name}"] = root / name
    for key in ("lpips", "lpips_custom"):
        entry = metrics.get(key) or {}
        if entry.get("weights_files"):  # the files the number was made with, as the metric recorded them
            for role, f in entry["weights_files"].items():
                files[f"weights:{role}"] = Path(f["path"])
        elif entry.get("backend") == "stlpips-alex":
            files["weights:stlpips"] = L.stlpips_weights_path()
        elif entry.get("backend") == "lpips-alex":
            files["weights:lpips_heads"] = L.lpips_heads_path()
            files["weights:alexnet"] = L.find_alexnet()
    if (metrics.get("lse_d") or {}).get("value") is not None:  # the scorer the record's backend names
        files["weights:sync"] = sync_weights_file((metrics.get("lse_d") or {}).get("backend") or "")
    if (metrics.get("lmd") or {}).get("value") is not None:
        files["weights:dlib"] = dlib_model_path()
    return {k: {"path": str(p.resolve()), "sha256": _sha_cached(p)} for k, p in files.items() if p is not None and p.is_file()}


def build_record(*, info, subject, protocol: str, clip: str, split: str, n_frames: int, seed: int, metrics: dict,
                 cost: dict, artefacts: dict, notes: list[str], control: dict | None = None,
                 run: dict | None = None, status: dict | None = None, config_hash: str | None = None) -> Record:
    """One run's typed record (schema in :mod:`lmgs_eval.results`); ``run``: its structured facts.

    ``status``: ``{state, reason}`` of a failed run; ``config_hash``: in place of the method's (a
    protocol that adds to the identity of a run, e.g. the stress suite's perturbation set). A record
    that does not validate is a :class:`~lmgs_eval.errors.UserError` naming the fields.
    """
    method = {"name": info.name, "display_name": info.display_name, "family": info.family,
              "description": info.description, "standins": list(info.standins)}
    if control is not None:
        method["control"] = control
    if getattr(info, "variant", None) is not None:
        method["variant"] = info.variant
    if getattr(info, "components", None):
        method["components"] = dict(info.components)
    run = dict(run or {})
    budget = subject_budget(info, subject)
    if budget is not None:
        run["budget"] = budget
        notes = [*notes, budget_note(budget["density"], budget["preset_density"])]
    return to_record(make_record(run=run or None,
        method=method,
        subject=subject_block(subject),
        protocol={"name": protocol, "version": PROTOCOL_VERSIONS[protocol], "clip": clip, "split": split, "n_frames": int(n_frames)},
        metrics=metrics, seed=seed, config=info.config, config_hash_=config_hash or info.config_hash, cost=cost,
        artefacts={**input_artefacts(metrics, subject), **artefacts}, notes=notes, status=status,
    ))
