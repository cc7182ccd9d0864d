"""LSE's self-check: does the scorer separate this clip's own sync from null controls made of the same clip?

A sync scorer that has never seen a face like this one can return any LSE-C and an
arbitrary offset without failing. So every LSE also scores controls built from the clip
itself, which cost no extra pass of the network (the embeddings are reused):

* **other audio of the same clip**: the audio embeddings rolled cyclically by ``r``
  windows, for up to :data:`N_ROLLS` values of ``r`` spread over ``[MIN_ROLL, N - MIN_ROLL]``,
  so the true alignment lies beyond the ±15-frame offset search plus the 5-frame window:
  the same face and the same voice, out of sync by construction;
* **a still face**: the first video window of the clip held for every window (the
  embedding of one window, repeated) against the real audio: whatever LSE-C this gives
  comes from the audio side alone.

.. math::
    \\mathrm{separation} = \\frac{C - \\mu_0}{\\max(\\sigma_0,\\ 0.1\\,\\mu_0,\\ 10^{-6})}

where ``C`` is the clip's LSE-C and ``mu_0``, ``sigma_0`` the mean and standard deviation of
the rolled-audio controls' LSE-C. The LSE is **trusted** when separation >= :data:`MIN_SEPARATION`,
``C`` is above every rolled control, and ``C >= STILL_RATIO x`` the still-face LSE-C; on
footage known to be in sync (ground truth, ``reference=True``) the offset must also be
within ±1 frame. A clip shorter than ``2 * MIN_ROLL + 5`` frames is not checked
(``trusted`` None). On a method's output, an untrusted LSE means the clip is out of sync *or*
the scorer cannot read this face; the ground truth's check tells the two apart.
"""

from __future__ import annotations

import numpy as np

from lmgs_eval.metrics.sync.maths import VSHIFT, lse_from_embeddings

MIN_ROLL = VSHIFT + 5 + 1  # windows: beyond the offset search and the window's own span
N_ROLLS = 16
MIN_SEPARATION = 3.0
STILL_RATIO = 2.0
UNTRUSTED_HINT = ("the sync scorer does not separate this clip's own audio from audio taken elsewhere in the clip: "
                  "its LSE-D/LSE-C/offset are not evidence of lip sync here (the clip is out of sync, or the scorer "
                  "cannot read this face); for LSE comparable with papers import the official SyncNet weights: "
                  "lmgs-eval weights import-syncnet syncnet_v2.model; on a real face, --sync mesh reads the dense face "
                  "mesh and was adapted on real speakers (a stand-in too; its figures: docs/metrics.md)")


def rolls(n: int) -> list[int]:
    """The cyclic audio shifts (in windows) of the other-audio controls for ``n`` windows; empty when too short."""
    if n < 2 * MIN_ROLL + 1:
        return []
    return sorted({int(round(r)) for r in np.linspace(MIN_ROLL, n - MIN_ROLL, N_ROLLS)})


def self_check(v_emb: np.ndarray, a_emb: np.ndarray, v_still: np.ndarray, lse_c: float, offset: int,
               reference: bool = False) -> tuple[dict, list[str]]:
    """Separation and trust of one LSE from its embeddings; ``(values, flags)``.

    Args:
        v_emb, a_emb: ``[N, D]`` per-window embeddings the LSE was computed from.
        v_still: ``[D]`` embedding of the still-face window.
        lse_c, offset: the clip's LSE-C and AV offset.
        reference: the footage is known to be in sync (then ``|offset| <= 1`` is required too).

    Returns:
        values ``separation``, ``trusted`` (bool, or None when the clip is too short),
        ``null_lse_c`` (mean over the rolled-audio controls), ``null_lse_c_max``,
        ``still_lse_c``; and the flags explaining a failed check.
    """
    n = len(v_emb)
    still_c = lse_from_embeddings(np.repeat(np.asarray(v_still)[None], n, 0), a_emb)["lse_c"]
    rs = rolls(n)
    if not rs:
        return ({"separation": None, "trusted": None, "null_lse_c": None, "null_lse_c_max": None, "still_lse_c": still_c},
                [f"self_check_skipped: {n} windows, the other-audio controls need at least {2 * MIN_ROLL + 1}"])
    null = np.array([lse_from_embeddings(v_emb, np.roll(a_emb, -r, axis=0))["lse_c"] for r in rs])
    mu, sd = float(null.mean()), float(null.std())
    sep = (float(lse_c) - mu) / max(sd, 0.1 * abs(mu), 1e-6)
    why = []
    if sep < MIN_SEPARATION:
        why.append(f"separation {sep:.2f} < {MIN_SEPARATION:g}")
    if lse_c <= null.max():
        why.append(f"LSE-C {lse_c:.3f} not above every other-audio control (max {null.max():.3f})")
    if lse_c < STILL_RATIO * still_c:
        why.append(f"LSE-C {lse_c:.3f} < {STILL_RATIO:g} x the still face's {still_c:.3f}")
    if reference and abs(int(offset)) > 1:
        why.append(f"offset {int(offset)} on footage in sync (must be 0 +- 1)")
    values = {"separation": sep, "trusted": not why, "null_lse_c": mu, "null_lse_c_max": float(null.max()),
              "still_lse_c": float(still_c)}
    return values, ([f"untrusted_sync: {'; '.join(why)}"] if why else [])
