"""The prose a record's notes carry for people beside its structured facts (``record.run``).

Tables print these sentences, made from the structured fields, never parsed back out of them;
only the migration of version-1 records reads them (:mod:`lmgs_eval.results.migrate`).
"""

from __future__ import annotations

BUDGET_NOTE = "Gaussian budget: "
SE_NOTE = "spatial enhancement selected {pct:.1f}% of face points on average"


def budget_note(density: float, preset_density: float) -> str:
    """The sentence for a run sized by its subject's own Gaussian density (its capacity knee)."""
    return (f"{BUDGET_NOTE}{density:g} per pixel of face area, this subject's capacity knee (lmgs_eval.data.registry."
            f"KNEE_DENSITY), not the quick preset's {preset_density:g}; every method sized by face area takes it on this "
            "subject")


def se_note(fraction: float, theta: float | None) -> str:
    """The sentence for the share of face points Spatial Enhancement selected in a run."""
    return SE_NOTE.format(pct=100 * fraction) + (f" (theta = {theta:g}; the paper reports about 20% at 0.6)"
                                                 if theta is not None else "")
