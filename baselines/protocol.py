"""The talking-head protocol every method implements, and the registry of method names.

This module is the bottom of the adapter layer: it imports nothing of the toolkit, so an
adapter (and the reference model behind it) never depends on protocols, metrics or results.
A method is any object with ``fit`` / ``render`` / ``describe`` / ``cost``
(:class:`TalkingHead`, a structural ``typing.Protocol``), built by a factory registered
under a name with :func:`register` (or, for a family of names ``PREFIX + NAME`` such as
``external:ernerf``, with :func:`register_prefix`). The adapters' modules are listed in
:data:`baselines.ADAPTERS`; :func:`create_method` imports them on first use.

What only the toolkit can do (read a video, a differentiable sync loss from its scorer) reaches an
adapter as a *hook*: a callable the toolkit passes to :func:`create_method` in ``hooks``; a factory
takes the hooks it names in its ``hooks`` attribute, as keyword arguments.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from baselines import ADAPTERS
from lmgs.errors import InputError
from lmgs.types import DrivingAudio, TrainingClip


@dataclass(frozen=True)
class MethodInfo:
    """What a method says about itself; goes into every result and the tables' footnotes.

    Attributes:
        name: registry name (``lmgs``, ``talkinggaussian``, ``external:ernerf``...).
        display_name: as printed in tables.
        family: ``3DGS``, ``NeRF``, ``2D``, ``external`` or ``ground-truth``.
        description: what was kept from the original method and what was simplified.
        standins: components replaced because the original cannot be had here.
        config: the full configuration (JSON-able).
        config_hash: a short hash of ``config``; a trained model is reused when it matches.
        variant: an ablation / sweep variant of a base method (rows of Tables III-IV, not I).
        components: the method's switchable parts and their settings, as the method declares them
            (lmgs: ``se``, ``lc``, ``gr``, ``theta``, ``se_cap``...); tables label ablation rows
            from these, never from config keys. None for a method without such parts.
    """

    name: str
    display_name: str
    family: str
    description: str
    standins: tuple[str, ...] = ()
    config: dict = field(default_factory=dict)
    config_hash: str = ""
    variant: str | None = None
    components: dict[str, Any] | None = None


@runtime_checkable
class TalkingHead(Protocol):
    """fit / render / describe: the whole contract between the toolkit and a method."""

    def fit(self, clip: TrainingClip, *, seed: int, workdir: Path, progress: bool = True) -> None:
        """Train on ``clip`` (the subject's training split); checkpoints go under ``workdir``."""

    def render(self, driving: DrivingAudio) -> np.ndarray:
        """Frames ``[T, H, W, 3]`` uint8 driven by ``driving`` (audio in, frames out)."""

    def describe(self) -> MethodInfo:
        """Name, family, what was simplified, config and its hash."""

    def cost(self) -> dict[str, Any]:
        """Size figures: ``n_params``, ``n_gaussians`` (or None), ``model_mb``."""


_REGISTRY: dict[str, Callable[..., TalkingHead]] = {}
_PREFIXED: dict[str, Callable[..., TalkingHead]] = {}  # prefix -> factory taking the NAME after it
# Methods whose Gaussian count is ``budget_density`` x face area (the lmgs backbone family):
# they take a subject's own knee density, all alike, so a comparison between them stays fair.
_SCENE_BUDGET: set[str] = set()
_ABLATIONS: set[str] = set()  # a method's ablation rows (lmgs-no-se, ...): not methods of the field of their own
# Methods with a geometry term on depth / normal priors: told whether a subject's priors are derived
_PRIOR_READERS: set[str] = set()
_LIP_READERS: set[str] = set()  # methods reading audio-predicted landmarks: told whether a subject is recorded footage
EXTERNAL_PREFIX = "external:"


def register(name: str, *, scene_budget: bool = False, ablation: bool = False, reads_priors: bool = False,
             lip_model: bool = False) -> Callable:
    """Decorator registering a method factory under ``name`` (duplicates are rejected).

    ``scene_budget``: the factory takes ``budget_density`` (Gaussians per face pixel), which
    :func:`create_method` sets from a subject that has its own (``subject.budget_density``).
    ``ablation``: an ablation row of another method (left out of :func:`field_methods`).
    ``reads_priors``: the factory takes ``priors_derived``, which :func:`create_method` sets for a
    subject whose depth / normal priors are derived from the tracking (``subject.priors_derived``).
    ``lip_model``: the factory takes ``footage``, which :func:`create_method` sets for a subject of
    recorded footage (one the bundled generator did not make: ``subject.bundled`` false); such a method
    reads the generic lip model's mouth there by default.
    """

    def deco(factory):
        if name in _REGISTRY:
            raise ValueError(f"method '{name}' registered twice")
        _REGISTRY[name] = factory
        if scene_budget:
            _SCENE_BUDGET.add(name)
        if ablation:
            _ABLATIONS.add(name)
        if reads_priors:
            _PRIOR_READERS.add(name)
        if lip_model:
            _LIP_READERS.add(name)
        return factory

    return deco


def register_prefix(prefix: str) -> Callable:
    """Decorator registering a factory for every name ``prefix + NAME``; it takes ``NAME`` first."""

    def deco(factory):
        if prefix in _PREFIXED:
            raise ValueError(f"method prefix '{prefix}' registered twice")
        _PREFIXED[prefix] = factory
        return factory

    return deco


def registration(name: str) -> tuple[Callable[..., TalkingHead], bool] | None:
    """``(factory, scene_budget)`` of a registered method (after loading the adapters), or None."""
    load_adapters()
    return (_REGISTRY[name], name in _SCENE_BUDGET) if name in _REGISTRY else None


def is_registered(name: str) -> bool:
    return name in _REGISTRY


def load_adapters() -> None:
    """Import every module of :data:`baselines.ADAPTERS` (importing one registers its methods)."""
    for mod in ADAPTERS:
        importlib.import_module(mod)


def list_methods() -> list[str]:
    load_adapters()
    return sorted(_REGISTRY) + [f"{prefix}NAME" for prefix in sorted(_PREFIXED)]


def field_methods() -> list[str]:
    """The methods of the field: every registered method but the ablation rows (``--method all``)."""
    load_adapters()
    return sorted(n for n in _REGISTRY if n not in _ABLATIONS)


def create_method(name: str, subject: Any = None, hooks: dict[str, Callable] | None = None, priors_from: Any = None,
                  **options) -> TalkingHead:
    """Build a method by name; ``external:NAME`` scores renders made by any other code.

    With ``subject`` (anything with a ``budget_density`` attribute, e.g. the toolkit's
    ``Subject``), a method sized by face area (``register(..., scene_budget=True)``) takes the
    subject's knee density when it has one and ``options`` set none; the density is in the
    method's config, so its hash, and the records and model cache, follow it. A method with a
    geometry term (``reads_priors=True``) is told when the subject's priors are derived
    (``subject.priors_derived``, or ``priors_from``'s where the method trains on another folder of the
    same footage) and weighs them in its config the same way. A method that reads audio-predicted landmarks
    (``lip_model=True``) is told when ``subject`` is recorded footage (``subject.bundled`` false; a folder
    trained on in its place, ``priors_from``, does not change it). ``hooks``: the
    toolkit's callables by name; the factory gets those its ``hooks`` attribute names.
    """
    load_adapters()
    for prefix, factory in _PREFIXED.items():
        if name.startswith(prefix):
            return factory(name.removeprefix(prefix), **_hooks_for(factory, hooks), **options)
    if name not in _REGISTRY:
        raise InputError(f"unknown method '{name}'; known: {', '.join(list_methods())}")
    density = getattr(subject, "budget_density", None)
    if density is not None and name in _SCENE_BUDGET:
        options.setdefault("budget_density", density)
    if name in _PRIOR_READERS and getattr(subject if priors_from is None else priors_from, "priors_derived", False):
        options.setdefault("priors_derived", True)
    if name in _LIP_READERS and subject is not None and not getattr(subject, "bundled", True):
        options.setdefault("footage", True)
    return _REGISTRY[name](**_hooks_for(_REGISTRY[name], hooks), **options)


def _hooks_for(factory, hooks: dict[str, Callable] | None) -> dict[str, Callable]:
    """The ``hooks`` that ``factory`` names (its ``hooks`` attribute; a hook not given is left out)."""
    return {k: hooks[k] for k in getattr(factory, "hooks", ()) if hooks and k in hooks}


def scene_budget_methods() -> list[str]:
    """The registered methods that size their Gaussians by face area (and take a subject's knee)."""
    load_adapters()
    return sorted(_SCENE_BUDGET)
