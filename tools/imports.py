"""The import graph of the relight package, by layer, and what breaks the layering.

    .venv/bin/python tools/imports.py

Reads the source with ``ast`` (nothing is imported): every ``import`` and ``from ...
import`` anywhere in a module counts, inside functions too (a lazy import is still a
dependency), and relative imports are resolved against the module's package.  The
package is ``relight_cli/`` with ``commands/`` installed as ``relight_cli.commands`` and
``formats/`` as ``relight_cli.formats`` (pyproject.toml's package-dir).  Importing
``a.b.c`` is counted as a dependency on ``a.b.c`` only, not on the ``__init__`` of its
parent packages.

The layers, bottom to top (a module may import its own layer and those below):

    base       relight_cli (__version__), relight_cli.errors and relight_cli.fileio (the
               I/O base: atomic writes, stdin/stdout, the input/output registry)
    formats    relight_cli.formats.*: file formats (plain arrays, small dataclasses)
    engine     every other relight_cli.* module (relight_cli.provenance among them)
    jobs       relight_cli.jobs.*: whole runs the commands drive
    the CLI, the only layers that may import click:
    cli-tools  relight_cli.cli.* but the group and the man pages: the options and checks
               every command shares (cli.tools) and input resolution (cli.inputs)
    commands   relight_cli.commands.*: one module per subcommand, plus the private
               shared helpers commands/_*.py (which must not import a command)
    cli-group  relight_cli.cli (the click group) and relight_cli.cli.manpage

Prints the graph, one line per module (``module [layer] -> deps``), then the
violations: an import circle (two or more modules), a module importing a layer above
its own (a format importing the engine, say), a command importing another command, a
module below the CLI importing click (at module level or inside a function); and
the short module aliases that read two ways: one alias (``D``, ``EV``: one to three
capitals) naming two modules in different files (``D`` as ``gaussians.dgsm`` here and
``neural.distill`` there), or a file that binds an alias it imports a module as to a
value too (``T`` a module and an array).  Exits 1 if there is any.  ``tests/system/test_tools_imports.py`` runs it on the package.
"""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "relight_cli"
# installed package name -> its folder (pyproject.toml's [tool.setuptools.package-dir])
SOURCES = {
    "relight_cli": ROOT / "relight_cli",
    "relight_cli.commands": ROOT / "commands",
    "relight_cli.formats": ROOT / "formats",
}
LAYERS = ("base", "formats", "engine", "jobs", "cli-tools", "commands", "cli-group")
#: the command-line layers: the only ones whose modules may import click
CLI_LAYERS = ("cli-tools", "commands", "cli-group")
BASE = {"relight_cli", "relight_cli.errors", "relight_cli.fileio"}
CLI_GROUP = {"relight_cli.cli", "relight_cli.cli.manpage"}
#: third-party packages that only the CLI layers may import
CLI_ONLY = ("click",)


def module_files(sources: dict | None = None) -> dict:
    """module name -> (path, is_package) for every .py file of the package."""
    sources = sources or SOURCES
    modules = {}
    for package, folder in sources.items():
        for path in sorted(folder.rglob("*.py")):
            parts = path.relative_to(folder).with_suffix("").parts
            if "__pycache__" in parts:
                continue
            is_package = parts[-1] == "__init__"
            if is_package:
                parts = parts[:-1]
            name = ".".join((package,) + parts)
            owner = max((p for p in sources if name == p or name.startswith(p + ".")), key=len)
            if owner == package:   # else installed from its own folder (package-dir)
                modules[name] = (path, is_package)
    return modules


def _known(name: str, modules) -> str | None:
    """The longest prefix of dotted ``name`` that is a module of the package."""
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        candidate = ".".join(parts[:end])
        if candidate in modules:
            return candidate
    return None


def _from_target(node: ast.ImportFrom, here: str) -> str:
    """The dotted module a ``from ... import`` reads from, relative ones resolved against
    the importing module's package ``here``."""
    if not node.level:
        return node.module or ""
    base = here.split(".")
    if node.level > 1:
        base = base[:-(node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(source: str, module: str, is_package: bool, modules) -> set:
    """The package modules that the module ``module`` (its text ``source``) imports."""
    tree = ast.parse(source)
    here = module if is_package else module.rpartition(".")[0]
    deps = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == PACKAGE or alias.name.startswith(PACKAGE + "."):
                    found = _known(alias.name, modules)
                    if found:
                        deps.add(found)
        elif isinstance(node, ast.ImportFrom):
            target = _from_target(node, here)
            if not (target == PACKAGE or target.startswith(PACKAGE + ".")):
                continue
            for alias in node.names:   # `from pkg import submodule` names a module
                sub = f"{target}.{alias.name}"
                found = sub if sub in modules else _known(target, modules)
                if found:
                    deps.add(found)
    deps.discard(module)
    return deps


def graph(sources: dict | None = None) -> dict:
    """module -> the set of package modules it imports (anywhere in its body)."""
    modules = module_files(sources)
    return {name: imports_of(path.read_text(), name, is_package, modules)
            for name, (path, is_package) in sorted(modules.items())}


def outside_imports(source: str) -> set:
    """The top-level names of the packages outside relight_cli that a module's text
    imports anywhere (``import click``, ``from click import echo`` inside a function:
    ``{"click"}``); relative imports are the package's own and left out."""
    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            found.add(node.module.split(".")[0])
    found.discard(PACKAGE)
    return found


def cli_only_imports(sources: dict | None = None) -> dict:
    """module -> the :data:`CLI_ONLY` packages (click) it imports, for the modules that
    import any."""
    found = {}
    for name, (path, _) in sorted(module_files(sources).items()):
        used = outside_imports(path.read_text()) & set(CLI_ONLY)
        if used:
            found[name] = used
    return found


def layer(module: str) -> str:
    """The layer of a package module (see the module docstring)."""
    if module in BASE:
        return "base"
    if module in CLI_GROUP:
        return "cli-group"
    for name, what in (("formats", "formats"), ("jobs", "jobs"), ("commands", "commands"),
                       ("cli", "cli-tools")):
        package = f"{PACKAGE}.{name}"
        if module == package or module.startswith(package + "."):
            return what
    return "engine"


def is_command(module: str) -> bool:
    """A subcommand module (not the package nor a private shared helper ``_*``)."""
    package = f"{PACKAGE}.commands."
    return module.startswith(package) and not module[len(package):].startswith("_")


def cycles(graph: dict) -> list:
    """The import circles of ``graph``: one list per strongly connected component of two
    or more modules, a closed walk through all of it (``[a, b, ..., a]``, starting at its
    first module in sorted order)."""
    index, low, on_stack, stack, components = {}, {}, set(), [], []

    def strongconnect(node):   # Tarjan, iterative (no recursion limit on deep graphs)
        work = [(node, iter(sorted(graph.get(node, ()))))]
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        while work:
            current, children = work[-1]
            for child in children:
                if child not in graph:
                    continue
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                    break
                if child in on_stack:
                    low[current] = min(low[current], index[child])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[current])
                if low[current] == index[current]:
                    component = set()
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.add(member)
                        if member == current:
                            break
                    if len(component) > 1:
                        components.append(component)

    for node in sorted(graph):
        if node not in index:
            strongconnect(node)
    return sorted((_walk(graph, component) for component in components),
                  key=lambda walk: walk[0])


def _walk(graph: dict, component: set) -> list:
    """A closed walk visiting every module of a strongly connected component."""
    start = min(component)
    walk, unvisited = [start], set(component) - {start}
    while unvisited:
        target = min(unvisited)
        walk += _path(graph, component, walk[-1], target)[1:]
        unvisited -= set(walk)
    walk += _path(graph, component, walk[-1], start)[1:]
    return walk


def _path(graph: dict, component: set, source: str, target: str) -> list:
    """A shortest import path source -> target inside ``component`` (breadth first)."""
    previous, frontier = {source: None}, [source]
    while target not in previous:
        following = []
        for node in frontier:
            for nxt in sorted(graph[node]):
                if nxt in component and nxt not in previous:
                    previous[nxt] = node
                    following.append(nxt)
        frontier = following
    path = [target]
    while path[-1] != source:
        path.append(previous[path[-1]])
    return path[::-1]


def violations(graph: dict, outside: dict | None = None) -> list:
    """Human-readable breaches of the layering of ``graph`` (module -> imported modules);
    ``outside``: module -> the :data:`CLI_ONLY` packages it imports
    (:func:`cli_only_imports`), each one a breach below the CLI."""
    found = [f"import circle: {' -> '.join(walk)}" for walk in cycles(graph)]
    for module, packages in sorted((outside or {}).items()):
        mine = layer(module)
        if mine not in CLI_LAYERS:
            for package in sorted(packages):
                found.append(f"{mine} module {module} imports {package} (only the CLI "
                             f"may: {', '.join(CLI_LAYERS)})")
    for module in sorted(graph):
        mine = layer(module)
        for dep in sorted(graph[module]):
            theirs = layer(dep)
            if LAYERS.index(theirs) > LAYERS.index(mine):
                allowed = ", ".join(LAYERS[:LAYERS.index(mine) + 1])
                found.append(f"{mine} module {module} imports {theirs} module {dep} "
                             f"({mine} may import only {allowed})")
            elif mine == theirs == "commands" and is_command(dep) and \
                    module != f"{PACKAGE}.commands":
                what = "command" if is_command(module) else "shared commands helper"
                found.append(f"{what} {module} imports command {dep} (move what they share "
                             f"below the commands, e.g. relight_cli/cli/inputs.py or a job)")
    return found


SHORT_ALIAS = re.compile(r"^[A-Z][A-Z0-9]{0,2}$")


def module_aliases(source: str, module: str, is_package: bool) -> dict:
    """Short aliases (:data:`SHORT_ALIAS`) a module's text binds to modules: alias -> the
    set of dotted names imported as it (any package: ``torch.nn.functional`` too)."""
    tree = ast.parse(source)
    here = module if is_package else module.rpartition(".")[0]
    found = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            pairs = [(a.name, a.asname) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            target = _from_target(node, here)
            pairs = [(f"{target}.{a.name}", a.asname) for a in node.names]
        else:
            continue
        for name, alias in pairs:
            if alias and SHORT_ALIAS.match(alias):
                found.setdefault(alias, set()).add(name)
    return found


def _bound_values(source: str) -> set:
    """Names a module's text binds to values: assignment and loop targets, arguments."""
    names = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.arg):
            names.add(node.arg)
    return names


def alias_problems(sources: dict | None = None) -> list:
    """Short module aliases that read two ways across the package (see the docstring)."""
    uses, problems = {}, []
    for name, (path, is_package) in sorted(module_files(sources).items()):
        text = path.read_text()
        aliases = module_aliases(text, name, is_package)
        values = _bound_values(text)
        for alias, targets in sorted(aliases.items()):
            for target in targets:
                uses.setdefault(alias, {}).setdefault(target, []).append(name)
            if len(targets) > 1:
                problems.append(f"{name} imports {' and '.join(sorted(targets))} as {alias}")
            if alias in values:
                problems.append(f"{name} binds {alias} to a value and to module "
                                f"{', '.join(sorted(targets))}")
    for alias, targets in sorted(uses.items()):
        if len(targets) > 1:
            where = "; ".join(f"{t} in {', '.join(sorted(set(m)))}" for t, m in sorted(targets.items()))
            problems.append(f"alias {alias} names {len(targets)} modules: {where}")
    return problems


def main() -> int:
    edges = graph()
    for module, deps in edges.items():
        print(f"{module} [{layer(module)}] -> {', '.join(sorted(deps))}".rstrip())
    counts = {name: sum(layer(m) == name for m in edges) for name in LAYERS}
    print(f"\n{len(edges)} modules: "
          + ", ".join(f"{counts[name]} {name}" for name in LAYERS))
    problems = violations(edges, cli_only_imports())
    print(f"{len(problems)} violation{'s' * (len(problems) != 1)}")
    for problem in problems:
        print(f"  {problem}")
    confusing = alias_problems()
    print(f"{len(confusing)} confusing alias{'es' * (len(confusing) != 1)}")
    for problem in confusing:
        print(f"  {problem}")
    return 1 if problems or confusing else 0


if __name__ == "__main__":
    sys.exit(main())
