"""Follow each argument of an ``lmgs-eval`` command through the code, as a reader following it would.

Usage (every argument given on the command line, so that each is an object of its own)::

    python docs/code-map/walk_args.py self --subject astronaut-64px-2s --method lmgs --preset quick \\
        --seed 7919 --results /tmp/walk --device cpu --set train.dynamic_steps=40 --sync landmark --no-progress --force

``WALK_VERBOSE=1`` lists the stops. The command runs under a tracer. An argument's value is the
object argparse made from the command line (generation 0). A *stop* is a distinct project function
(``lmgs``, ``baselines``, ``lmgs_eval``) called with the value (by identity) as an argument other
than ``self``, or with an object holding the value as an attribute the function's code reads off
that parameter (``args.subject``, ``cfg.sync``). What a stop that received one argument's
generation-0 value and no other argument returns (an object: not None, a bool, a number or a str)
is that argument resolved and carries it on (generation 1: the Subject ``--subject`` resolves to,
the scorers ``--sync`` resolves to); generation-1 receivers are stops, their returns are not
followed further. A value made from several arguments (a method built from the run config) is not
followed: it resolves none of them.

*modules*: the distinct modules among the stops. *climbs*: in the order the stops are first
reached, a step from a module of a lower layer to one of a higher layer (lmgs 0 < baselines 1 <
data, metrics, errors, paths 2 < results 3 < runner, convert, hosttime 4 < protocols, plans,
report 5 < commands, cli 6). Booleans (``--force``, ``--no-progress``) are not followed: True is
one object everywhere.
"""

from __future__ import annotations

import argparse
import dis
import os
import sys
import threading

RANK = [("lmgs_eval.commands", 6), ("lmgs_eval.cli", 6), ("lmgs_eval.__main__", 6), ("lmgs_eval.protocols", 5),
        ("lmgs_eval.plans", 5), ("lmgs_eval.report", 5), ("lmgs_eval.runner", 4), ("lmgs_eval.convert", 4),
        ("lmgs_eval.hosttime", 4), ("lmgs_eval.results", 3), ("lmgs_eval", 2), ("baselines", 1), ("lmgs", 0)]
SCALAR = (type(None), bool, int, float, str, bytes)

taint: dict[int, tuple[object, dict[str, int]]] = {}  # id -> (the object, {argument: generation})
stops: dict[str, list[tuple[str, str]]] = {}  # argument -> [(module, function)] in first-reach order
_attrs: dict = {}


def rank(module: str) -> int | None:
    for prefix, r in RANK:
        if module == prefix or module.startswith(prefix + "."):
            return r
    return None


def attrs_read(code, name: str) -> set[str]:
    """The attributes ``code`` reads off its local ``name`` (``name.attr``)."""
    if code not in _attrs:
        reads: dict[str, set[str]] = {}
        ins = list(dis.get_instructions(code))
        for a, b in zip(ins, ins[1:]):
            if a.opname.startswith("LOAD_FAST") and b.opname in ("LOAD_ATTR", "LOAD_METHOD") and isinstance(a.argval, str):
                reads.setdefault(a.argval, set()).add(b.argval)
        _attrs[code] = reads
    return _attrs[code].get(name, set())


def carried(x, code, name: str) -> dict[str, int]:
    """The arguments ``x`` (the function's parameter ``name``) carries: itself, or an attribute of it that
    ``code`` reads (``name.attr``)."""
    out: dict[str, int] = {}
    t = taint.get(id(x))
    if t is not None and t[0] is x:
        out.update(t[1])
    d = getattr(x, "__dict__", None)
    if isinstance(d, dict) and not isinstance(x, type):
        for a in attrs_read(code, name) & d.keys():
            t = taint.get(id(d[a]))
            if t is not None and t[0] is d[a]:
                for name, g in t[1].items():
                    out[name] = min(g, out.get(name, 9))
    return out


_parse = argparse.ArgumentParser.parse_args


def parse_args(self, *a, **k):
    ns = _parse(self, *a, **k)
    if not taint:  # the command's own arguments (the first parse)
        for name, v in vars(ns).items():
            if not isinstance(v, (type(None), bool)):
                for x in ([v, *v] if isinstance(v, list) else [v]):
                    taint[id(x)] = (x, {name: 0})
    return ns


def tracer(frame, event, arg):
    if event != "call" or not taint or rank(frame.f_globals.get("__name__", "")) is None:
        return None
    code = frame.f_code
    if code.co_filename.startswith("<"):
        return None  # generated code (a dataclass's __init__): the holder's readers are the stops
    hits: dict[str, int] = {}
    for n in code.co_varnames[: code.co_argcount + code.co_kwonlyargcount]:
        x = frame.f_locals.get(n)
        if n in ("self", "cls") or x is None or isinstance(x, bool):
            continue  # a method called on the object is not a step of following it
        for name, g in carried(x, code, n).items():
            hits[name] = min(g, hits.get(name, 9))
    if not hits:
        return None
    key = (frame.f_globals["__name__"], code.co_qualname)
    for name in hits:
        if key not in stops.setdefault(name, []):
            stops[name].append(key)
    carry = {n: 1 for n, g in hits.items() if g == 0} if len(hits) == 1 else {}
    if not carry:  # a value made from several arguments (a method from the run config) resolves none of them
        return None

    def on_return(fr, ev, value):
        if ev == "return" and not isinstance(value, SCALAR):
            old = taint.get(id(value))
            names = dict(old[1]) if old is not None and old[0] is value else {}
            for n, g in carry.items():
                names.setdefault(n, g)
            taint[id(value)] = (value, names)
        return on_return

    return on_return


def main() -> None:
    argparse.ArgumentParser.parse_args = parse_args
    sys.argv = ["lmgs-eval", *sys.argv[1:]]
    sys.settrace(tracer)
    threading.settrace(tracer)
    try:
        from lmgs_eval.cli import main as cli

        rc = cli()
    except SystemExit as e:
        rc = e.code
    sys.settrace(None)
    total_stops = total_climbs = 0
    modules: set[str] = set()
    for name, seen in sorted(stops.items()):
        mods = {m for m, _ in seen}
        modules |= mods
        climbs = sum(1 for (a, _), (b, _) in zip(seen, seen[1:]) if rank(b) > rank(a))
        total_stops += len(seen)
        total_climbs += climbs
        print(f"--{name}: {len(seen)} stops, {len(mods)} modules, {climbs} climbs")
        if os.environ.get("WALK_VERBOSE"):
            for m, f in seen:
                print(f"      {rank(m)} {m}:{f}")
    print(f"TOTAL: {total_stops} stops in {len(modules)} modules, {total_climbs} climbs (rc={rc})")


if __name__ == "__main__":
    main()
