"""The learned half's modules form a layered graph: no import circle in relight_cli.neural,
counting imports inside functions (a lazy import is still a dependency), and the leaves
(scores, weights, config, geometry, losses) import nothing of it."""

from __future__ import annotations

import ast
from pathlib import Path

from conftest import ROOT

PACKAGE = ROOT / "relight_cli" / "neural"
LEAVES = {"scores", "weights", "config", "geometry", "losses", "model_config"}


def neural_imports() -> dict:
    """module → the relight_cli.neural modules it imports (anywhere in its body)."""
    modules = {p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__"}
    graph = {}
    for name in modules:
        tree = ast.parse((PACKAGE / f"{name}.py").read_text())
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                if node.level == 1 and node.module:
                    deps.add(node.module.split(".")[0])
                elif node.level == 1:
                    deps.update(a.name for a in node.names)
                elif (node.module or "").startswith("relight_cli.neural"):
                    parts = node.module.split(".")
                    deps.update([parts[2]] if len(parts) > 2 else [a.name for a in node.names])
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith("relight_cli.neural."):
                        deps.add(a.name.split(".")[2])
        graph[name] = {d for d in deps if d in modules and d != name}
    return graph


def cycle(graph: dict) -> list:
    """One import circle of ``graph`` (a list of modules) or []."""
    state, stack = {}, []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        state[node] = 2
        stack.pop()
        return []
    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return []


def test_neural_has_no_import_circle():
    graph = neural_imports()
    assert {"checkpoints", "scores", "ceiling", "evaluate", "train"} <= set(graph)
    assert cycle(graph) == [], " → ".join(cycle(graph))


def test_leaves_import_nothing_of_neural():
    """Leaves import no other neural module, except the configurations' schema
    (model_config, itself importing none) that config re-exports beside its presets."""
    graph = neural_imports()
    assert graph["model_config"] == set()
    for leaf in LEAVES:
        assert graph[leaf] <= ({"model_config"} if leaf == "config" else set()), \
            (leaf, graph[leaf])


def test_the_circle_finder_finds_one():
    """The check can fail: a graph with a lazy back edge is reported."""
    assert cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert cycle({"a": {"b"}, "b": set()}) == []


def test_one_loader_per_checkpoint_kind():
    """Every checkpoint kind the format defines has exactly one loader, in the registry."""
    from relight_cli.formats.checkpoint import KINDS
    from relight_cli.neural.registry import MODELS
    assert sorted(spec.kind for spec in MODELS.values()) == sorted(KINDS)
    definitions = [p for p in PACKAGE.glob("*.py")
                   if "def model_from_checkpoint" in p.read_text()
                   or "def student_from_checkpoint" in p.read_text()]
    assert definitions == [], definitions
