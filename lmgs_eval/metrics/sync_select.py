"""Which sync scorer an LSE uses: ``--sync {auto,landmark,pixel,syncnet-v2}``.

* ``syncnet-v2``: the official SyncNet weights, once imported (``lmgs-eval weights
  import-syncnet``); the only scorer whose LSE compares with papers.
* ``landmark``: the bundled landmark scorer (:mod:`sync_landmark`), mouth-landmark
  trajectories against MFCC; identity cannot reach it.
* ``pixel``: the bundled pixel scorer (``bundled-sync``), a small SyncNet on 48x48 mouth
  crops, trained on the two bundled faces.
* ``auto`` (default): ``syncnet-v2`` when imported; else ``landmark``, and on a clip where the
  landmark scorer fails its self-check (:mod:`sync_check`) the pixel scorer is tried and kept
  only if it passes; otherwise the first available result stays, marked untrusted. The record names
  the scorer used and, for a fallback, why.

The choice is process-wide (:func:`set_backend`, set by the CLI) so protocol code that calls
``sync.lse`` without a scorer follows the flag.
"""

from __future__ import annotations

from lmgs_eval.errors import UserError

CHOICES = ("auto", "landmark", "pixel", "syncnet-v2")
_state = {"backend": "auto"}
_loaded: dict[str, tuple[object | None, str]] = {}


def set_backend(name: str | None) -> None:
    """Select the scorer for every later ``sync.lse(..., scorer=None)`` of this process.

    Raises:
        UserError: an unknown name.
    """
    name = name or "auto"
    if name not in CHOICES:
        raise UserError(f"--sync {name!r}: unknown sync scorer; choose one of {', '.join(CHOICES)}")
    _state["backend"] = name


def get_backend() -> str:
    return _state["backend"]


def load(name: str):
    """``(scorer, "")`` for ``landmark``, ``pixel`` or ``syncnet-v2``, or ``(None, reason)``.

    A loaded scorer is kept for the process under its file's path and modification time (so a
    later import or retraining is seen); a missing one is looked for again next time.
    """
    from lmgs_eval.metrics import sync, sync_landmark

    if name not in CHOICES[1:]:
        raise UserError(f"sync scorer {name!r}: unknown; choose one of {', '.join(CHOICES[1:])}")
    where = {"landmark": sync_landmark.WEIGHTS / sync_landmark.ONNX_NAME, "pixel": sync.BUNDLED_DIR / "bundled_sync.onnx",
             "syncnet-v2": sync.syncnet_manifest_path()}[name]
    key = f"{name}|{where}|{where.stat().st_mtime_ns if where.is_file() else 0}"
    if key in _loaded:
        return _loaded[key]
    if name == "landmark":
        got = sync_landmark.load()
    else:
        got = sync.find_scorer("bundled-sync" if name == "pixel" else "syncnet-v2")
    if got[0] is not None:
        _loaded[key] = got
    return got


def official_imported() -> bool:
    from lmgs_eval.metrics.sync import syncnet_manifest_path

    return syncnet_manifest_path().is_file()


def candidates(name: str | None = None) -> list[str]:
    """Scorers to try in order for a selection (``auto`` may fall back from the first to the second)."""
    name = name or get_backend()
    if name != "auto":
        return [name]
    return ["syncnet-v2"] if official_imported() else ["landmark", "pixel"]


def status() -> tuple[bool, str]:
    """Which scorer ``lse`` uses here and why (for ``lmgs-eval metrics``), without loading a network."""
    from lmgs_eval.metrics.sync import BUNDLED_DIR, syncnet_manifest_path
    from lmgs_eval.metrics.sync_landmark import JSON_NAME, ONNX_NAME, WEIGHTS

    sel = get_backend()
    have = {"syncnet-v2": syncnet_manifest_path().is_file(),
            "landmark": (WEIGHTS / ONNX_NAME).is_file() and (WEIGHTS / JSON_NAME).is_file(),
            "pixel": (BUNDLED_DIR / "bundled_sync.onnx").is_file() and (BUNDLED_DIR / "bundled_sync.json").is_file()}
    if sel != "auto":
        return have[sel], f"--sync {sel}" + ("" if have[sel] else " (weights not present)")
    if have["syncnet-v2"]:
        return True, f"default syncnet-v2: the official SyncNet weights are imported ({syncnet_manifest_path()})"
    if have["landmark"]:
        return True, ("default landmark-sync (stand-in): the official SyncNet weights are not imported "
                      "(lmgs-eval weights import-syncnet syncnet_v2.model); the landmark scorer reads only mouth-landmark "
                      "motion, so it does not depend on who is talking (held-out figures in landmark_sync.json); "
                      "per clip, the pixel scorer is used where only it passes the self-check")
    if have["pixel"]:
        return True, "default bundled-sync pixel scorer (stand-in): no official or landmark weights here"
    return False, "no sync scorer: import syncnet_v2.model with `lmgs-eval weights import-syncnet`"
