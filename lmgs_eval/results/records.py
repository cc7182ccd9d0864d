"""A run's record assembled from what the protocols hand over: method, subject, metrics, cost, artefacts.

A run is named once, by a :class:`RunId` (the method's info on a subject, under a protocol and
clip, with a seed), and handed down: the store key of its record, where its model is cached and
its renders go come from it. The sections follow the schema (:mod:`lmgs_eval.results.schema`);
here are the toolkit's sources of each: the subject's identity (its manifest's sha256), the
inputs a number depends on (ground truth and metric weights, re-hashed by ``lmgs-eval verify``),
and the store look-up that makes a run resumable.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lmgs.presets import TrainConfig
from lmgs.fileio import sha256_file
from lmgs_eval.metrics import lpips as L
from lmgs_eval.metrics.sync.scorers import weights_file as sync_weights_file
from lmgs_eval.metrics.landmarks import dlib_model_path
from lmgs_eval.paths import cache_root
from lmgs_eval.results.provenance import EMPTY_COST, git_info, machine_info, metric_entries, now_iso
from lmgs_eval.results.notes import budget_note, se_note
from lmgs_eval.results.store import find_finished, find_record, to_record
from lmgs_eval.results.types import SCHEMA_VERSION, Record

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


@dataclass(frozen=True)
class RunId:
    """What one record is of: a method (its info) on a subject, under a protocol and clip, with a seed.

    Made once per run and handed down; the store key of its record, its model's folder and its
    render's name all come from it. ``config_hash``: in place of the method's in the store key (a
    protocol that adds to the identity of a run, e.g. the stress suite's perturbation set); the
    model's folder keeps the method's own.
    """

    subject: Any  # lmgs_eval.data.Subject
    info: Any  # baselines.protocol.MethodInfo
    seed: int = 0
    protocol: str = "self"
    clip: str = "test"
    config_hash: str | None = None

    @property
    def label(self) -> str:
        """``<method> seed <N>``, as the log names the run."""
        return f"{self.info.name} seed {self.seed}"

    @property
    def model_dir(self) -> Path:
        """The model cache's folder of this method, config and seed on this subject."""
        return cache_root() / "models" / self.subject.name / self.info.name / f"{self.info.config_hash}-seed{self.seed}"

    @property
    def renders(self) -> str:
        """The store's folder (relative) of the subject's renders."""
        return f"renders/{self.subject.name}"

    @property
    def stem(self) -> str:
        """``<method>-<config hash[:8]>-seed<N>``: the file name of the run's render, distinct per config.

        Without the hash a re-run under a changed config overwrote the render an older record
        still points to (and hashes); the record then failed ``lmgs-eval verify``.
        """
        return f"{self.info.name.replace(':', '_')}-{self.info.config_hash[:8]}-seed{self.seed}"


def stored(root, run: RunId, *, finished: bool = False) -> Record | None:
    """The store's record of ``run`` on its subject's data, or None.

    ``finished``: a failed run counts as not done (it is retried). A record made on other data
    of a subject of the same name is a UserError (:func:`lmgs_eval.results.find_record`).
    """
    find = find_finished if finished else find_record
    return find(root, run.info.name, run.subject.name, run.protocol, run.clip, run.seed,
                run.config_hash or run.info.config_hash, manifest_sha(run.subject.root))


def manifest_sha(folder) -> str | None:
    """sha256 of a subject folder's ``manifest.json`` (None without one): which data a record was made on."""
    p = Path(folder) / "manifest.json"
    return _sha_cached(p) if p.exists() else None


_SHA_CACHE: dict[tuple[str, int, int], str] = {}


def _sha_cached(path: Path) -> str:
    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _SHA_CACHE:
        _SHA_CACHE[key] = sha256_file(path)
    return _SHA_CACHE[key]


def input_artefacts(metrics: dict, folder) -> dict:
    """The inputs a record's numbers depend on, for ``lmgs-eval verify``: the ground truth of the
    subject in ``folder`` (its manifest, or its transforms files) and the weights files of the metrics used."""
    files: dict[str, Path | None] = {}
    root = Path(folder)
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


def build_record(run: RunId, *, split: str, n_frames: int, metrics: dict, cost: dict, artefacts: dict,
                 notes: list[str] | None = None, control: dict | None = None, se_fraction: float | None = None,
                 status: dict | None = None) -> Record:
    """The typed record of ``run`` (schema in :mod:`lmgs_eval.results`).

    ``notes``: default the subject's (what reading it repaired). The run's facts come with a note
    each: ``se_fraction`` (the share of face points Spatial Enhancement selected, as measured) and
    the subject's own Gaussian budget, when the method was sized by it. ``status``: ``{state,
    reason}`` of a failed run. A record that does not validate is a
    :class:`~lmgs_eval.errors.UserError` naming the fields.
    """
    info, subject = run.info, run.subject
    method = {"name": info.name, "display_name": info.display_name, "family": info.family,
              "description": info.description, "standins": list(info.standins)}
    if control is not None:
        method["control"] = control
    if getattr(info, "variant", None) is not None:
        method["variant"] = info.variant
    if getattr(info, "components", None):
        method["components"] = dict(info.components)
    facts, notes = {}, list(subject.notes if notes is None else notes)
    if se_fraction is not None:
        facts["se_fraction"] = float(se_fraction)
        notes.append(se_note(facts["se_fraction"], (info.components or {}).get("theta")))
    density = getattr(subject, "budget_density", None)  # the subject's own knee, where the method took it
    if density is not None and _config_value(info.config, "budget_density") == density:
        facts["budget"] = {"density": float(density), "preset_density": float(TrainConfig.budget_density)}
        notes.append(budget_note(facts["budget"]["density"], facts["budget"]["preset_density"]))
    rec = {"schema_version": SCHEMA_VERSION, "method": method,
           "subject": {"name": subject.name, "bundled": subject.bundled, "frames": subject.n_frames,
                       "width": subject.width, "height": subject.height, "path": str(subject.root),
                       "standin": subject.meta.get("standin") if subject.bundled else None,
                       "sha256": manifest_sha(subject.root)},
           "protocol": {"name": run.protocol, "version": PROTOCOL_VERSIONS[run.protocol], "clip": run.clip, "split": split,
                        "n_frames": int(n_frames)},
           "metrics": metrics, "cost": {**EMPTY_COST, **cost}, "config": dict(info.config),
           "config_hash": run.config_hash or info.config_hash, "seed": int(run.seed), "code": git_info(),
           "machine": machine_info(), "artefacts": {**input_artefacts(metrics, subject.root), **artefacts},
           "created": now_iso(), "notes": notes}
    if status is not None:
        rec["status"] = status
    if facts:
        rec["run"] = facts
    return to_record(rec)
