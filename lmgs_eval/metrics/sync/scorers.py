"""The sync scorers and their weights: where each one's files are, loading them, checking their sha256.

Four scorers, by their ``--sync`` names (their records name them by the scorer's own name):

* ``syncnet-v2`` (``syncnet-v2``): the official SyncNet, imported by ``lmgs-eval weights
  import-syncnet`` into the cache (:func:`syncnet_manifest_path`, the ONNX graph and its sha256);
* ``mesh`` (``mesh-sync``): the bundled mesh scorer (:mod:`~lmgs_eval.metrics.sync.mesh`: the dense face
  mesh's mouth against MFCC, adapted on real speakers), ``weights/mesh_sync.{onnx,json}``;
* ``landmark`` (``landmark-sync``): the bundled landmark scorer, ``weights/landmark_sync.{onnx,json}``;
* ``pixel`` (``bundled-sync``): the bundled pixel scorer, ``weights/bundled_sync.{onnx,json}``.

A file whose sha256 is not its manifest's, or an imported graph holding NaN or Inf, is an error,
never a silent score. :func:`load` keeps a loaded scorer for the process.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.sync import mesh
from lmgs_eval.metrics.sync.landmark import JSON_NAME, ONNX_NAME, LandmarkScorer
from lmgs_eval.metrics.sync.pixel import SyncScorer

WEIGHTS = Path(__file__).resolve().parent / "weights"  # the bundled scorers' ONNX graphs and manifests
PIXEL_ONNX, PIXEL_JSON = "bundled_sync.onnx", "bundled_sync.json"


def syncnet_manifest_path() -> Path:
    """The manifest ``lmgs-eval weights import-syncnet`` writes (present once the official weights are imported)."""
    from lmgs_eval.paths import cache_root

    return cache_root() / "weights" / "syncnet_v2.json"


def _check_sha(p: Path, j: Path, want: str | None) -> str:
    from lmgs.fileio import sha256_file

    sha = sha256_file(p)
    if want and sha != want:
        raise UserError(f"{p}: sha256 {sha[:12]}... does not match {j} (corrupt or replaced weights)")
    return sha


def find_scorer(prefer: str | None = None) -> tuple[SyncScorer | None, str]:
    """The official SyncNet if imported, else the bundled pixel scorer; ``(None, reason)`` if neither.

    ``prefer``: ``syncnet-v2`` or ``bundled-sync`` alone.
    """
    from lmgs.fileio import sha256_file
    from lmgs_eval.metrics.ort import load_session, nonfinite_weights

    reasons = []
    if prefer in (None, "syncnet-v2"):
        mp = syncnet_manifest_path()
        if mp.is_file():
            m = json.loads(mp.read_text())
            p = Path(m["onnx"])
            if not p.is_file():
                reasons.append(f"syncnet-v2: {p} listed in {mp} is missing (re-run lmgs-eval weights import-syncnet)")
            else:
                sha = sha256_file(p)
                if sha != m.get("onnx_sha256"):
                    raise UserError(f"{p}: sha256 {sha[:12]}... does not match {mp}; re-run lmgs-eval weights import-syncnet")
                bad = nonfinite_weights(p)
                if bad:
                    raise UserError(f"{p} (imported from {m.get('source')}): weights {bad[0]!r}"
                                    + (f" and {len(bad) - 1} more" if len(bad) > 1 else "") + " hold NaN or Inf; "
                                    "import a sound syncnet_v2.model with lmgs-eval weights import-syncnet")
                return SyncScorer("syncnet-v2", load_session(p), m["source_sha256"], tuple(m["input_hw"]),
                                  m.get("region", "full"), m.get("pixel", "bgr_0_255"), source=str(m.get("source", p))), ""
        else:
            reasons.append("syncnet-v2 not imported (lmgs-eval weights import-syncnet syncnet_v2.model)")
    if prefer in (None, "bundled-sync"):
        p, j = WEIGHTS / PIXEL_ONNX, WEIGHTS / PIXEL_JSON
        if p.is_file() and j.is_file():
            m = json.loads(j.read_text())
            sha = _check_sha(p, j, m.get("sha256"))
            return SyncScorer("bundled-sync", load_session(p), sha, tuple(m.get("input_hw", (48, 96))),
                              m.get("region", "lower_half"), m.get("pixel", "bgr_0_1"), source=str(p),
                              standin="bundled-sync is trained by this project on synthetic clips; its LSE values are "
                                      "not comparable with SyncNet LSE in papers"), ""
        reasons.append(f"bundled-sync weights not present ({p.name} + {j.name} in {WEIGHTS})")
    return None, "; ".join(reasons)


def _load_points_scorer(cls, files: tuple[str, str], context: int, folder: Path | None):
    """A scorer of mouth points (``cls``: :class:`LandmarkScorer` or :class:`~mesh.MeshScorer`) from its ONNX
    graph and manifest ``files`` in ``folder`` (default the shipped ones), or ``(None, reason)``; ``context``
    when the manifest gives none."""
    from lmgs_eval.metrics.ort import load_session

    folder = Path(folder if folder is not None else WEIGHTS)
    onnx_name, json_name = files
    p, j = folder / onnx_name, folder / json_name
    if not (p.is_file() and j.is_file()):
        return None, f"{cls.name} weights not present ({onnx_name} + {json_name} in {folder})"
    m = json.loads(j.read_text())
    sha = _check_sha(p, j, m.get("sha256"))
    return cls(load_session(p), sha, int(m.get("context", context)), int(m.get("highpass", 0))), ""


def load_landmark(folder: Path | None = None) -> tuple[LandmarkScorer | None, str]:
    """The landmark scorer of ``folder`` (default the shipped one), or ``(None, reason)``.

    Raises:
        UserError: the ONNX file does not match the sha256 in its manifest.
    """
    return _load_points_scorer(LandmarkScorer, (ONNX_NAME, JSON_NAME), 5, folder)


def load_mesh(folder: Path | None = None) -> tuple[mesh.MeshScorer | None, str]:
    """The mesh scorer of ``folder`` (default the shipped one), or ``(None, reason)``.

    Raises:
        UserError: the ONNX file does not match the sha256 in its manifest.
    """
    return _load_points_scorer(mesh.MeshScorer, (mesh.ONNX_NAME, mesh.JSON_NAME), 15, folder)


def mesh_manifest(folder: Path | None = None) -> dict | None:
    """The mesh scorer's manifest (``mesh_sync.json``), or None when it is not here or not readable JSON."""
    j = Path(folder if folder is not None else WEIGHTS) / mesh.JSON_NAME
    try:
        m = json.loads(j.read_text())
    except (OSError, ValueError):
        return None
    return m if isinstance(m, dict) else None


@dataclass(frozen=True)
class Entry:
    """One scorer of the ``--sync`` choices: its record name, its weights files, its loader."""

    record_name: str  # the scorer's name in records (``onnxruntime:<record_name>``)
    files: Callable[[], tuple[Path, ...]]  # what must be here; the first one's path and mtime key the process cache
    graph: Callable[[], Path | None]  # the ONNX file the scores depend on (None: not here)
    load: Callable[[], tuple[object | None, str]]


def _syncnet_graph() -> Path | None:
    mp = syncnet_manifest_path()
    return Path(json.loads(mp.read_text())["onnx"]) if mp.is_file() else None


SCORERS: dict[str, Entry] = {
    "syncnet-v2": Entry("syncnet-v2", lambda: (syncnet_manifest_path(),), _syncnet_graph, lambda: find_scorer("syncnet-v2")),
    "mesh": Entry("mesh-sync", lambda: (WEIGHTS / mesh.ONNX_NAME, WEIGHTS / mesh.JSON_NAME),
                  lambda: WEIGHTS / mesh.ONNX_NAME, load_mesh),
    "landmark": Entry("landmark-sync", lambda: (WEIGHTS / ONNX_NAME, WEIGHTS / JSON_NAME), lambda: WEIGHTS / ONNX_NAME,
                      load_landmark),
    "pixel": Entry("bundled-sync", lambda: (WEIGHTS / PIXEL_ONNX, WEIGHTS / PIXEL_JSON), lambda: WEIGHTS / PIXEL_ONNX,
                   lambda: find_scorer("bundled-sync")),
}
_loaded: dict[str, tuple[object, str]] = {}


def entry(name: str) -> Entry:
    try:
        return SCORERS[name]
    except KeyError:
        raise UserError(f"sync scorer {name!r}: unknown; choose one of {', '.join(SCORERS)}") from None


def present(name: str) -> bool:
    """Whether the weights of scorer ``name`` are here (without loading them)."""
    return all(p.is_file() for p in entry(name).files())


def load(name: str) -> tuple[object | None, str]:
    """``(scorer, "")`` for ``mesh``, ``landmark``, ``pixel`` or ``syncnet-v2``, or ``(None, reason)``.

    A loaded scorer is kept for the process under its file's path and modification time (so a
    later import or retraining is seen); a missing one is looked for again next time.
    """
    e = entry(name)
    where = e.files()[0]
    key = f"{name}|{where}|{where.stat().st_mtime_ns if where.is_file() else 0}"
    if key in _loaded:
        return _loaded[key]
    got = e.load()
    if got[0] is not None:
        _loaded[key] = got
    return got


def weights_file(record_name: str) -> Path | None:
    """The weights file a record's LSE was computed with, from the scorer name in its backend
    (``onnxruntime:landmark-sync`` or ``landmark-sync``); None when unknown or no longer here."""
    name = record_name.rsplit(":", 1)[-1]
    e = next((e for e in SCORERS.values() if e.record_name == name), None)
    return None if e is None else e.graph()
