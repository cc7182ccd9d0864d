"""The layers import one way: lmgs <- method adapters <- toolkit (data, metrics <- results <- runner,
protocols, report) <- CLI, and no module imports itself back through others. Every import statement
counts, at module level or inside a function, and so does a module named by a string to
``importlib.import_module`` or ``__import__``."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("lmgs", "baselines", "lmgs_eval")

# module prefix -> prefixes it must never import (a prefix matches the module and its submodules)
TOOLKIT_ABOVE_DATA = ("lmgs_eval.convert", "lmgs_eval.hosttime", "lmgs_eval.runner", "lmgs_eval.protocols",
                      "lmgs_eval.results", "lmgs_eval.report", "lmgs_eval.commands", "lmgs_eval.cli")
RULES: dict[str, tuple[str, ...]] = {
    "lmgs": ("lmgs_eval", "baselines"),
    # the adapters never import the toolkit: what they need of it comes in as hooks (baselines.protocol)
    "baselines": ("lmgs_eval",),
    "lmgs_eval.data": ("baselines", "lmgs_eval.metrics") + TOOLKIT_ABOVE_DATA,
    "lmgs_eval.metrics": ("baselines",) + TOOLKIT_ABOVE_DATA,
    "lmgs_eval.errors": ("baselines",) + TOOLKIT_ABOVE_DATA,
    "lmgs_eval.paths": ("baselines",) + TOOLKIT_ABOVE_DATA,
    "lmgs_eval.hooks": ("baselines",) + TOOLKIT_ABOVE_DATA,  # lent to the adapters: below what runs them
    "lmgs_eval.results": ("baselines", "lmgs_eval.convert", "lmgs_eval.hosttime", "lmgs_eval.runner", "lmgs_eval.protocols",
                          "lmgs_eval.report", "lmgs_eval.commands", "lmgs_eval.cli"),
    "lmgs_eval.report": ("baselines", "lmgs_eval.runner", "lmgs_eval.protocols", "lmgs_eval.commands", "lmgs_eval.cli"),
    "lmgs_eval.hosttime": ("baselines", "lmgs_eval.runner", "lmgs_eval.protocols", "lmgs_eval.report",
                           "lmgs_eval.commands", "lmgs_eval.cli"),
    "lmgs_eval.convert": ("baselines", "lmgs_eval.runner", "lmgs_eval.protocols", "lmgs_eval.report",
                          "lmgs_eval.commands", "lmgs_eval.cli"),
    "lmgs_eval.runner": ("lmgs_eval.protocols", "lmgs_eval.report", "lmgs_eval.commands", "lmgs_eval.cli"),
    "lmgs_eval.protocols": ("lmgs_eval.report", "lmgs_eval.commands", "lmgs_eval.cli"),
    "lmgs_eval.plans": ("lmgs_eval.report", "lmgs_eval.commands", "lmgs_eval.cli"),
}


def _matches(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _from_base(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    """The module a ``from X import ...`` statement in ``module`` imports from (relative imports resolved)."""
    if not node.level:
        return node.module or ""
    base = module.split(".")
    base = base if is_package else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(source: str, module: str, is_package: bool) -> set[str]:
    """Every module an import statement of ``source`` names (relative imports resolved)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            name = _from_base(node, module, is_package)
            out.add(name)
            out |= {f"{name}.{a.name}" for a in node.names}  # ``from pkg import submodule``
        elif isinstance(node, ast.Call) and _imports_by_name(node.func) and node.args \
                and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
            out.add(node.args[0].value)  # importlib.import_module("pkg.mod"), __import__("pkg")
    return out


def _imports_by_name(func: ast.expr) -> bool:
    return (isinstance(func, ast.Attribute) and func.attr == "import_module") or \
        (isinstance(func, ast.Name) and func.id in ("import_module", "__import__"))


def violations(graph: dict[str, set[str]]) -> list[str]:
    """``module imports target`` for every import that a rule of :data:`RULES` forbids (most specific rule wins)."""
    bad = []
    for module, targets in sorted(graph.items()):
        rules = [p for p in RULES if _matches(module, p)]
        if not rules:
            continue
        forbidden = RULES[max(rules, key=len)]
        for t in sorted(targets):
            if any(_matches(t, f) for f in forbidden):
                bad.append(f"{module} imports {t}")
    return bad


def dependencies_of(source: str, module: str, is_package: bool, modules: set[str]) -> set[str]:
    """The project ``modules`` whose code must run for ``source``'s imports: an imported module and the
    packages above it (their ``__init__``), except the packages ``module`` itself is inside (Python has
    begun those before it runs). ``from pkg import name`` depends on ``pkg.name`` where that is a
    module, else on ``pkg``'s ``__init__`` (which defines the name), also from inside ``pkg``."""
    out: set[str] = set()

    def add(target: str, own_package_too: bool = False) -> None:
        parts = target.split(".")
        for i in range(1, len(parts) + 1):
            p = ".".join(parts[:i])
            if p in modules and (not module.startswith(p + ".") or (own_package_too and p == target)):
                out.add(p)

    for name in imports_of(source, module, is_package):
        if name in modules:
            add(name)
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            pkg = _from_base(node, module, is_package)
            if any(f"{pkg}.{a.name}" not in modules for a in node.names):
                add(pkg, own_package_too=True)
    out.discard(module)
    return out


def cycles(deps: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of a dependency graph (:func:`dependencies_of`): each strongly connected group of two
    or more modules, sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found = []

    def visit(v: str) -> None:  # Tarjan's algorithm
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(deps[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for v in sorted(deps):
        if v not in index:
            visit(v)
    return sorted(found)


def _sources() -> dict[str, tuple[str, bool]]:
    return {module_name(p): (p.read_text(encoding="utf-8"), p.name == "__init__.py")
            for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}


def project_graph() -> dict[str, set[str]]:
    return {mod: imports_of(src, mod, is_pkg) for mod, (src, is_pkg) in _sources().items()}


def project_dependencies() -> dict[str, set[str]]:
    sources = _sources()
    return {mod: dependencies_of(src, mod, is_pkg, set(sources)) for mod, (src, is_pkg) in sources.items()}


def test_the_layers_import_one_way():
    graph = project_graph()
    assert {"lmgs", "baselines.protocol", "lmgs_eval.runner", "lmgs_eval.cli"} <= set(graph)
    assert violations(graph) == []


def test_an_upward_import_is_caught():
    """The checker itself: an adapter importing a protocol, the model library importing the toolkit,
    a metric importing the results store, and a relative import climbing into the runner are each found."""
    graph = {
        "baselines.gaussian": imports_of("from lmgs_eval.protocols.self_driven import run_self", "baselines.gaussian", False),
        "lmgs.train": imports_of("def f():\n    import lmgs_eval.results\n", "lmgs.train", False),
        "lmgs_eval.metrics.sync": imports_of("from lmgs_eval import results", "lmgs_eval.metrics.sync", False),
        "lmgs_eval.report.tables": imports_of("from ..runner import log", "lmgs_eval.report.tables", False),
        "baselines.protocol": imports_of("from lmgs_eval.data import io", "baselines.protocol", False),
        "baselines.external": imports_of("def f():\n    from lmgs_eval.data.frames import FrameFile\n", "baselines.external",
                                         False),
        "baselines.twod": imports_of("import importlib\nsync = importlib.import_module('lmgs_eval.metrics.sync')\n",
                                     "baselines.twod", False),
    }
    assert violations(graph) == [
        "baselines.external imports lmgs_eval.data.frames",
        "baselines.external imports lmgs_eval.data.frames.FrameFile",
        "baselines.gaussian imports lmgs_eval.protocols.self_driven",
        "baselines.gaussian imports lmgs_eval.protocols.self_driven.run_self",
        "baselines.protocol imports lmgs_eval.data",
        "baselines.protocol imports lmgs_eval.data.io",
        "baselines.twod imports lmgs_eval.metrics.sync",
        "lmgs.train imports lmgs_eval.results",
        "lmgs_eval.metrics.sync imports lmgs_eval.results",
        "lmgs_eval.report.tables imports lmgs_eval.runner",
        "lmgs_eval.report.tables imports lmgs_eval.runner.log",
    ]


def test_no_import_circles():
    assert cycles(project_dependencies()) == []


def test_a_circle_is_caught():
    """The checker itself: two modules importing each other (one inside a function), a package whose
    ``__init__`` re-exports a submodule that takes a name from the package back, and a string import."""
    mods = {"p", "p.a", "p.b", "q", "q.x", "q.y", "r"}
    src = {
        "p": ("", True),
        "p.a": ("from p import b", False),
        "p.b": ("def f():\n    from . import a\n", False),
        "q": ("from q.x import thing", True),
        "q.x": ("from q import other", False),  # ``other`` is defined in q's __init__: q.x needs q to have run
        "q.y": ("from q import x", False),  # a submodule: q.y only needs q.x (q has begun before q.y runs)
        "r": ("import importlib\nimportlib.import_module('p.a')", False),
    }
    deps = {m: dependencies_of(s, m, pkg, mods) for m, (s, pkg) in src.items()}
    assert deps["q.y"] == {"q.x"} and deps["r"] == {"p", "p.a"}
    assert cycles(deps) == [["p.a", "p.b"], ["q", "q.x"]]
