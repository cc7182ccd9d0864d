"""Blocks: frozen dataclasses that check their fields when they are made, read from JSON and written back.

A block (:class:`Block`) checks, when it is made, each field's type (a bool is not a number, a
number is finite: JSON has no NaN), the items of an array and the values of an object, the
constraints in a field's metadata (``enum``, ``min_length``, ``pattern``, ``minimum``) and its own
rules tying fields together (:meth:`Block._tied`); a block that does not fit is :class:`Invalid`.
:func:`decode` makes blocks of decoded JSON, naming each misfit from the top down; :func:`json_object`
writes a block back (as ``json.dumps(..., default=json_object)``), and :func:`replace` changes one. The schema's blocks are in
:mod:`lmgs_eval.results.types`.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Union, get_args, get_origin, get_type_hints


class Invalid(ValueError):
    """A block made with fields that do not fit. ``problems``: ``(where, message)`` pairs, ``where`` the
    field below the block (``.value``, ``.flags[2]``, ``.weights_files.alexnet``; empty for a rule of the
    whole block)."""

    def __init__(self, problems: list[tuple[str, str]]):
        self.problems = list(problems)
        super().__init__("; ".join(f"{w.lstrip('.')}: {m}" if w else m for w, m in self.problems))


class Block:
    """A part of a record that checks its fields when it is made (:func:`_check`): a made block is a valid one."""

    def __post_init__(self) -> None:
        problems = _check(type(self), vars(self))
        if problems:
            raise Invalid(problems)

    @classmethod
    def _tied(cls, values: Mapping[str, Any]) -> list[tuple[str, str]]:
        """What the rules tying this block's fields together find wrong in ``values`` (none by default)."""
        return []


# ----------------------------------------------------------------------------- checking
@dataclass(frozen=True)
class _Rule:
    """How one field of a block is read from JSON and checked."""

    name: str
    hint: Any  # the field's type
    optional: bool  # it may be left out of the JSON (it has a default)
    converts: bool  # decoding makes something of its JSON value (a block, a tuple, a copied object)
    kinds: tuple[type, ...]  # the Python types its value may have
    label: str  # the JSON type a misfit names: "number|null"
    items: tuple[type, ...] | None  # the types of an array's items or an object's values (None: not looked into)
    items_label: str
    meta: Mapping[str, Any]


_RULES: dict[type, tuple[_Rule, ...]] = {}


def _rules(cls: type) -> tuple[_Rule, ...]:
    """The rules of a block's fields, in field order (worked out once per class)."""
    if cls not in _RULES:
        hints = get_type_hints(cls)
        out = []
        for f in dataclasses.fields(cls):
            tp = hints[f.name]
            inner = _without_null(tp)
            item = get_args(inner)[0] if get_origin(inner) is tuple else get_args(inner)[1] if get_origin(inner) is dict else None
            out.append(_Rule(f.name, tp, _optional(f), _converts(tp), _kinds(tp), _type_label(tp),
                             None if item in (None, Any) else _kinds(item), "" if item is None else _type_label(item), f.metadata))
        _RULES[cls] = tuple(out)
    return _RULES[cls]


def _without_null(tp: Any) -> Any:
    """``X`` of ``X | None`` (``tp`` itself otherwise)."""
    if get_origin(tp) in (Union, types.UnionType):
        return next(a for a in get_args(tp) if a is not type(None))
    return tp


def _converts(tp: Any) -> bool:
    inner = _without_null(tp)
    return get_origin(inner) in (tuple, dict) or dataclasses.is_dataclass(inner)


def _kinds(tp: Any) -> tuple[type, ...]:
    """The Python types a decoded value of ``tp`` may have (an array is a tuple, an integer-valued number stays an int)."""
    origin = get_origin(tp)
    if origin in (Union, types.UnionType):
        return tuple(k for a in get_args(tp) for k in _kinds(a))
    if tp is Any:
        return (object,)
    if tp is float:
        return (int, float)
    return (origin or tp,)


def _type_label(tp: Any) -> str:
    origin = get_origin(tp)
    if origin in (Union, types.UnionType):
        return "|".join(_type_label(a) for a in get_args(tp))
    if tp is type(None):
        return "null"
    if origin is tuple:
        return "array"
    if origin is dict or dataclasses.is_dataclass(tp):
        return "object"
    return {int: "integer", float: "number", bool: "boolean", str: "string"}.get(tp, "value")


def _check(cls: type, values: Mapping[str, Any], skip: frozenset[str] | set[str] = frozenset()) -> list[tuple[str, str]]:
    """What does not fit in ``values`` (fields by name) as a ``cls``, as :attr:`Invalid.problems`.

    Each field's type (a bool is not a number, a number is finite: JSON has no NaN), the items of an
    array or the values of an object, the constraints in its metadata, then the block's own rules
    (:meth:`Block._tied`). A field in ``skip`` (found wrong inside already) or not in ``values`` is
    passed over.
    """
    out: list[tuple[str, str]] = []
    for r in _rules(cls):
        if r.name in skip or r.name not in values:
            continue
        v = values[r.name]
        todo = [(f".{r.name}", v, r.kinds, r.label)]
        if r.items is not None and isinstance(v, tuple):
            todo += [(f".{r.name}[{i}]", x, r.items, r.items_label) for i, x in enumerate(v)]
        elif r.items is not None and isinstance(v, dict):
            todo += [(f".{r.name}.{k}", x, r.items, r.items_label) for k, x in v.items()]
        for at, x, kinds, label in todo:
            if object in kinds:
                continue
            if (not isinstance(x, kinds) or (isinstance(x, bool) and bool not in kinds)
                    or (isinstance(x, float) and not math.isfinite(x))):
                out.append((at, f"expected {label}, got {type(x).__name__} {x!r:.60}"))
        if v is None:
            continue
        meta = r.meta
        if "enum" in meta and v not in meta["enum"]:
            out.append((f".{r.name}", f"{v!r} is not one of {', '.join(map(str, meta['enum']))}"))
        if isinstance(v, str):
            if len(v) < meta.get("min_length", 0):
                out.append((f".{r.name}", "empty string"))
            if "pattern" in meta and not re.search(meta["pattern"], v):
                out.append((f".{r.name}", f"{v!r:.60} does not match {meta['pattern']}"))
        if isinstance(v, (int, float)) and not isinstance(v, bool) and "minimum" in meta and v < meta["minimum"]:
            out.append((f".{r.name}", f"{v} < {meta['minimum']}"))
    return out + cls._tied(values)


# ----------------------------------------------------------------------------- decoding
def decode(tp: Any, value: Any, where: str, out: list[str]) -> Any:
    """``value`` (decoded JSON) as type ``tp``: an object as its block (which checks itself when made),
    an array as a tuple; each misfit appended to ``out`` as one line naming the field from ``where``.

    A value of the wrong JSON type is handed on as it is: the block it goes into names it.
    """
    if get_origin(tp) in (Union, types.UnionType):
        return None if value is None else decode(_without_null(tp), value, where, out)
    origin = get_origin(tp)
    if origin is tuple and isinstance(value, (list, tuple)):
        item = get_args(tp)[0]
        if not _converts(item):
            return tuple(value)
        return tuple(decode(item, x, f"{where}[{i}]", out) for i, x in enumerate(value))
    if origin is dict and isinstance(value, dict):
        item = get_args(tp)[1]
        if not _converts(item):
            return dict(value)
        return {k: decode(item, v, f"{where}.{k}", out) for k, v in value.items()}
    if not (dataclasses.is_dataclass(tp) and isinstance(value, dict)):
        return value
    kwargs, wrong, missing = {}, set(), False
    for r in _rules(tp):
        if r.name not in value:
            if not r.optional:
                out.append(f"{where}.{r.name}: missing")
                missing = True
            continue
        n = len(out)
        kwargs[r.name] = decode(r.hint, value[r.name], f"{where}.{r.name}", out) if r.converts else value[r.name]
        if len(out) > n:
            wrong.add(r.name)
    try:
        if wrong or missing:  # not made: its other fields are checked all the same
            raise Invalid(_check(tp, kwargs, wrong))
        obj = tp(**kwargs)
    except Invalid as e:
        out.extend(f"{where}{w}: {m}" for w, m in e.problems)
        return None
    nulls = frozenset(r.name for r in _rules(tp) if r.optional and value.get(r.name, 0) is None)
    if nulls:
        object.__setattr__(obj, _NULLS, nulls)  # written back as null (not a field: equality ignores it)
    return obj


_NULLS = "_json_nulls"
"""The attribute that lists the optional fields a decoded object's JSON held as ``null``."""


def _optional(f: dataclasses.Field) -> bool:
    return f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING


def replace(obj: Any, **changes: Any) -> Any:
    """:func:`dataclasses.replace` that keeps which untouched optional fields the JSON held as ``null``."""
    new = dataclasses.replace(obj, **changes)
    nulls = getattr(obj, _NULLS, frozenset()) - changes.keys()
    if nulls:
        object.__setattr__(new, _NULLS, nulls)
    return new


# ----------------------------------------------------------------------------- encoding
def json_object(obj: Any) -> dict[str, Any]:
    """A block as its JSON object, for :func:`json.dumps` (``default=json_object``): its fields, an optional
    one that is None left out unless the JSON it was read from held it as ``null``."""
    if not dataclasses.is_dataclass(obj) or isinstance(obj, type):
        raise TypeError(f"Object of type {type(obj).__name__} is not JSON serializable")
    nulls = getattr(obj, _NULLS, frozenset())
    out = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if v is not None or not _optional(f) or f.name in nulls:
            out[f.name] = v
    return out
