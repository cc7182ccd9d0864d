"""The layers import one way: lmgs <- method adapters <- toolkit (data, metrics <- results <- runner,
protocols, report) <- CLI. Every import statement counts, at module level or inside a function."""

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
    # the adapters read subjects' files through the data layer at most
    "baselines": TOOLKIT_ABOVE_DATA + ("lmgs_eval.metrics",),
    "baselines.protocol": ("lmgs_eval",),
    "lmgs_eval.data": ("baselines", "lmgs_eval.metrics") + TOOLKIT_ABOVE_DATA,
    "lmgs_eval.metrics": ("baselines",) + TOOLKIT_ABOVE_DATA,
    "lmgs_eval.errors": ("baselines",) + TOOLKIT_ABOVE_DATA,
    "lmgs_eval.paths": ("baselines",) + TOOLKIT_ABOVE_DATA,
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


def imports_of(source: str, module: str, is_package: bool) -> set[str]:
    """Every module an import statement of ``source`` names (relative imports resolved)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base if is_package else base[:-1]
                base = base[: len(base) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.add(name)
            out |= {f"{name}.{a.name}" for a in node.names}  # ``from pkg import submodule``
    return out


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


def project_graph() -> dict[str, set[str]]:
    graph = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            mod = module_name(path)
            graph[mod] = imports_of(path.read_text(encoding="utf-8"), mod, path.name == "__init__.py")
    return graph


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
        "baselines.external": imports_of("from lmgs_eval.data import io", "baselines.external", False),  # allowed
    }
    assert violations(graph) == [
        "baselines.gaussian imports lmgs_eval.protocols.self_driven",
        "baselines.gaussian imports lmgs_eval.protocols.self_driven.run_self",
        "baselines.protocol imports lmgs_eval.data",
        "baselines.protocol imports lmgs_eval.data.io",
        "lmgs.train imports lmgs_eval.results",
        "lmgs_eval.metrics.sync imports lmgs_eval.results",
        "lmgs_eval.report.tables imports lmgs_eval.runner",
        "lmgs_eval.report.tables imports lmgs_eval.runner.log",
    ]
