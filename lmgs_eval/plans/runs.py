"""A plan expanded into runs: one (protocol, subject, method, seed, options) each, independent but for order.

Two runs that train the same model (same subject, method, seed, preset and overrides; the
capacity protocol's default budget is lmgs's own config) are chained in plan order: the later
one reloads the earlier one's checkpoint instead of training it a second time at once on the
same node. Every self-driven run of a subject follows that subject's first one, which scores
the ground truth, the plate reference and the calibration controls once.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from typing import Any

from lmgs_eval.plans.schema import Plan


@dataclass(frozen=True)
class Run:
    """One unit of work, small enough to pickle to a worker; runs the protocol function on one method and seed."""

    protocol: str
    subject: str
    method: str
    seed: int
    preset: str = "quick"
    overrides: dict[str, Any] = field(default_factory=dict)
    device: str | None = None
    cpus: int = 1
    gpus: float = 0
    retries: int = 1
    clips: tuple[str, ...] = ()
    conditions: tuple[str, ...] = ()
    max_minutes: float = 15.0
    long_seconds: float = 300.0
    budgets: tuple[int, ...] | None = None
    data_root: str | None = None
    imports: tuple[str, ...] = ()
    after: tuple[str, ...] = ()  # ids of the runs this one waits for

    @property
    def options_tag(self) -> str:
        """A short digest of what else than (protocol, subject, method, seed) sets the run apart."""
        opts = {"preset": self.preset, "set": self.overrides, "device": self.device, "clips": self.clips,
                "conditions": self.conditions, "max_minutes": self.max_minutes, "long_seconds": self.long_seconds,
                "budgets": self.budgets}
        return hashlib.sha256(json.dumps(opts, sort_keys=True, default=str).encode()).hexdigest()[:8]

    @property
    def id(self) -> str:
        return f"{self.protocol}/{self.subject}/{self.method}/seed{self.seed}/{self.options_tag}"

    @property
    def label(self) -> str:
        extra = "" if not self.overrides else f" ({len(self.overrides)} --set)"
        return f"{self.protocol} {self.subject} / {self.method} seed {self.seed}{extra}"

    @property
    def model_key(self) -> str:
        """Runs with the same key train (or reload) the same model."""
        return json.dumps([self.subject, self.method, self.seed, self.preset, self.overrides, self.device],
                          sort_keys=True, default=str)


def expand(plan: Plan) -> list[Run]:
    """Every run of the plan, in plan order, each once (a run listed twice is kept where it comes first)."""
    runs: dict[str, Run] = {}
    for st in plan.stages:
        for subject in st.subjects:
            for method in st.methods:
                for seed in st.seeds:
                    for protocol in st.protocols:
                        r = Run(protocol=protocol, subject=subject, method=method, seed=seed, preset=st.preset,
                                overrides=dict(st.overrides), device=st.device, cpus=st.cpus, gpus=st.gpus,
                                retries=st.retries, clips=st.clips if protocol == "cross" else (),
                                conditions=st.conditions if protocol == "stress" else (),
                                max_minutes=st.max_minutes if protocol == "stress" else 15.0,
                                long_seconds=st.long_seconds if protocol == "stress" else 300.0,
                                budgets=st.budgets if protocol == "capacity" else None,
                                data_root=plan.data_root, imports=plan.imports)
                        runs.setdefault(r.id, r)
    return _ordered(list(runs.values()))


def _ordered(runs: list[Run]) -> list[Run]:
    last_by_model: dict[str, str] = {}
    first_self: dict[str, str] = {}
    out = []
    for r in runs:
        after = []
        if r.model_key in last_by_model:
            after.append(last_by_model[r.model_key])
        if r.protocol == "self":
            if r.subject in first_self:
                after.append(first_self[r.subject])
            else:
                first_self[r.subject] = r.id
        r = Run(**{**r.__dict__, "after": tuple(dict.fromkeys(after))})
        last_by_model[r.model_key] = r.id
        out.append(r)
    return out
