"""Which sync scorer an LSE uses: ``--sync {auto,mesh,landmark,pixel,syncnet-v2}``.

* ``syncnet-v2``: the official SyncNet weights, once imported (``lmgs-eval weights
  import-syncnet``); the only scorer whose LSE compares with papers.
* ``mesh``: the bundled mesh scorer (``mesh-sync``, :mod:`~lmgs_eval.metrics.sync.mesh`), the mouth
  of the dense face mesh in the canonical face frame against MFCC, adapted on real speakers'
  recordings; its leave-one-speaker-out figures on real footage are in ``mesh_sync.json``.
* ``landmark``: the bundled landmark scorer (:mod:`~lmgs_eval.metrics.sync.landmark`),
  mouth-landmark trajectories against MFCC; identity cannot reach it.
* ``pixel``: the bundled pixel scorer (``bundled-sync``), a small SyncNet on 48x48 mouth
  crops, trained on the two bundled faces.
* ``auto`` (default): ``syncnet-v2`` when imported; else the bundled scorers in turn: ``mesh``,
  ``landmark``, ``pixel`` when the mesh scorer's manifest records that it met its acceptance
  leave one speaker out (:func:`mesh_is_default`), otherwise ``landmark``, ``pixel``. On a clip
  where a scorer fails its self-check (:mod:`~lmgs_eval.metrics.sync.check`) the next one is
  tried, and the first that passes is kept; if none passes, the first available result stays,
  marked untrusted. The record names the scorer used and, for a fallback, why.

The choice travels in the metric suite's config (:class:`~lmgs_eval.metrics.config.SuiteConfig`,
``--sync`` on the command line): the suite resolves it once into :class:`SyncScorers`, which the
LSE metric is built with; a worker process given the config resolves the same choice.
"""

from __future__ import annotations

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.config import SYNC_CHOICES as CHOICES
from lmgs_eval.metrics.sync import scorers


def check_choice(name: str) -> str:
    """``name`` if it is one of :data:`CHOICES`.

    Raises:
        UserError: an unknown name.
    """
    if name not in CHOICES:
        raise UserError(f"--sync {name!r}: unknown sync scorer; choose one of {', '.join(CHOICES)}")
    return name


def official_imported() -> bool:
    return scorers.present("syncnet-v2")


def mesh_is_default() -> bool:
    """Whether ``auto`` tries the mesh scorer first: its weights are here and its manifest records that it met
    its acceptance leave one speaker out on real footage (``"loso": {"meets_acceptance": true}`` in
    ``mesh_sync.json``). Reads the manifest only; no network is loaded."""
    if not scorers.present("mesh"):
        return False
    loso = (scorers.mesh_manifest() or {}).get("loso")
    return isinstance(loso, dict) and loso.get("meets_acceptance") is True


def candidates(name: str = "auto") -> list[str]:
    """Scorers to try in order for a choice (``auto`` may fall back from one to the next)."""
    if check_choice(name) != "auto":
        return [name]
    if official_imported():
        return ["syncnet-v2"]
    return ["mesh", "landmark", "pixel"] if mesh_is_default() else ["landmark", "pixel"]


class SyncScorers:
    """The scorers of one ``--sync`` choice, in the order LSE tries them (:func:`candidates`), resolved
    when made; each one is loaded the first time it is tried and kept (with its reason when it is not here).

    Iterating gives ``(scorer, "")`` or ``(None, reason)`` per candidate. It pickles as its choice:
    a worker process resolves and loads its own.
    """

    def __init__(self, choice: str = "auto"):
        self.choice = check_choice(choice or "auto")
        self.names = tuple(candidates(self.choice))
        self._got: dict[str, tuple[object | None, str]] = {}

    def __iter__(self):
        for name in self.names:
            if name not in self._got:
                self._got[name] = scorers.load(name)
            yield self._got[name]

    def __reduce__(self):
        return SyncScorers, (self.choice,)


def _mesh_figures() -> str:
    """``mesh_sync.json``'s leave-one-speaker-out count (``" (N/M clips pass)"``), or nothing when it records none."""
    loso = (scorers.mesh_manifest() or {}).get("loso")
    if isinstance(loso, dict) and isinstance(loso.get("passes"), int) and isinstance(loso.get("clips"), int):
        return f": {loso['passes']}/{loso['clips']} clips pass"
    return ""


def status(choice: str = "auto") -> tuple[bool, str]:
    """Which scorer ``choice`` scores with here and why (for ``lmgs-eval metrics``), without loading a network."""
    if check_choice(choice) != "auto":
        ok = scorers.present(choice)
        return ok, f"--sync {choice}" + ("" if ok else " (weights not present)")
    if scorers.present("syncnet-v2"):
        return True, f"default syncnet-v2: the official SyncNet weights are imported ({scorers.syncnet_manifest_path()})"
    not_imported = ("the official SyncNet weights are not imported "
                    "(lmgs-eval weights import-syncnet syncnet_v2.model)")
    if mesh_is_default():
        return True, (f"default mesh-sync (stand-in): {not_imported}; the mesh scorer reads the mouth of the dense face "
                      "mesh in the canonical face frame and is adapted on real speakers (leave-one-speaker-out figures "
                      f"on real footage in mesh_sync.json{_mesh_figures()}); per clip, the landmark and then the pixel "
                      "scorer is used where only it passes the self-check")
    if scorers.present("landmark"):
        why = ("default landmark-sync (stand-in): " + not_imported + "; the landmark scorer reads only mouth-landmark "
               "motion, so it does not depend on who is talking (held-out figures in landmark_sync.json); "
               "per clip, the pixel scorer is used where only it passes the self-check")
        if scorers.present("mesh"):
            recorded = isinstance((scorers.mesh_manifest() or {}).get("loso"), dict)
            why += ("; mesh-sync is here (--sync mesh) but not the default: its leave-one-speaker-out figures on real "
                    "footage " + (f"(mesh_sync.json{_mesh_figures()}) do not meet its acceptance" if recorded
                                  else "are not recorded in mesh_sync.json"))
        return True, why
    if scorers.present("pixel"):
        return True, "default bundled-sync pixel scorer (stand-in): no official or landmark weights here"
    return False, "no sync scorer: import syncnet_v2.model with `lmgs-eval weights import-syncnet`"
