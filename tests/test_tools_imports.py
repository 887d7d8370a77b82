"""tools/imports.py: the package's import graph keeps its layers (formats below the engine,
no command importing another, no import circle), and the checker finds each breach when
one is planted (in a fake graph, and in a small package it parses)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys

import pytest

from conftest import ROOT


@pytest.fixture(scope="module")
def tool():
    spec = importlib.util.spec_from_file_location("tools_imports", ROOT / "tools" / "imports.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def real(tool):
    return tool.graph()


def test_the_package_keeps_its_layers(tool, real):
    assert tool.violations(real) == [], "\n".join(tool.violations(real))
    layers = {m: tool.layer(m) for m in real}
    assert layers["relight_cli.formats.dgsm_exr"] == "formats"
    assert layers["relight_cli.gaussians.dgsm"] == "engine"
    assert layers["relight_cli.jobs.relight_hand"] == "jobs"
    assert layers["relight_cli.commands.relight"] == "commands"
    assert layers["relight_cli.cli"] == "cli"
    assert layers["relight_cli.errors"] == "base"
    assert {"formats", "engine", "jobs", "commands", "cli", "base"} == set(layers.values())


def test_the_graph_counts_lazy_relative_and_aliased_imports(real):
    # formats/keypoints.py imports .leap inside read_keypoints (relative, in a function)
    assert "relight_cli.formats.leap" in real["relight_cli.formats.keypoints"]
    # jobs/relight_gaussians.py: `from relight_cli.gaussians import dgsm as D` names a module
    assert "relight_cli.gaussians.dgsm" in real["relight_cli.jobs.relight_gaussians"]
    # `from . import __version__` is the package itself
    assert "relight_cli" in real["relight_cli.provenance"]
    assert all(m not in deps for m, deps in real.items())


def test_the_moved_pieces_stay_below(real):
    """What issue 22 moved: formats import no engine module, commands no command."""
    assert "relight_cli.preview" not in real["relight_cli.formats.image"]
    assert not {d for d in real["relight_cli.formats.dgsm_exr"] if d.startswith("relight_cli.gaussians")}
    assert "relight_cli.hand.model" not in real["relight_cli.formats.leap"]
    assert "relight_cli.inputs" in real["relight_cli.commands.relight"]


def test_planted_breaches_are_reported(tool, real):
    """The checker can fail: each kind of breach added to the real graph is reported."""
    plants = {
        ("relight_cli.formats.image", "relight_cli.preview"): "formats module relight_cli.formats.image imports engine module relight_cli.preview",
        ("relight_cli.formats.leap", "relight_cli.hand.model"): "formats module relight_cli.formats.leap imports engine",
        ("relight_cli.formats.camera", "relight_cli.commands.camera"): "imports commands module",
        ("relight_cli.errors", "relight_cli.formats.exr"): "base module relight_cli.errors imports formats",
        ("relight_cli.hand.model", "relight_cli.jobs.relight_hand"): "engine module relight_cli.hand.model imports jobs",
        ("relight_cli.commands.relight", "relight_cli.commands.dgsm_build"): "command relight_cli.commands.relight imports command relight_cli.commands.dgsm_build",
        ("relight_cli.commands._learned", "relight_cli.commands.distill"): "shared commands helper relight_cli.commands._learned imports command",
        ("relight_cli.sh", "relight_cli.gaussians.probe"): "import circle: ",
    }
    for (module, dep), expected in plants.items():
        sabotaged = {m: set(d) for m, d in real.items()}
        sabotaged[module].add(dep)
        found = tool.violations(sabotaged)
        assert any(expected in v for v in found), (module, dep, found)


def test_circles_are_found_whole(tool):
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": {"b"}, "e": {"a"}, "f": set()}
    assert tool.cycles(graph) == [["a", "b", "c", "d", "b", "c", "a"]]
    assert tool.cycles({"a": {"b"}, "b": set()}) == []
    two = {"x": {"y"}, "y": {"x"}, "p": {"q"}, "q": {"p"}}
    assert tool.cycles(two) == [["p", "q", "p"], ["x", "y", "x"]]


def test_allowed_imports_are_not_reported(tool):
    graph = {
        "relight_cli.formats.a": {"relight_cli.formats.b", "relight_cli.errors",
                                  "relight_cli.provenance"},
        "relight_cli.formats.b": set(),
        "relight_cli.errors": set(),
        "relight_cli.provenance": {"relight_cli", "relight_cli.errors"},
        "relight_cli": set(),
        "relight_cli.inputs": {"relight_cli.formats.a"},
        "relight_cli.commands.one": {"relight_cli.commands._shared", "relight_cli.inputs"},
        "relight_cli.commands._shared": {"relight_cli.inputs"},
        "relight_cli.cli": {"relight_cli.commands.one"},
    }
    assert tool.violations(graph) == []


def test_a_planted_package_is_parsed_and_refused(tool, tmp_path):
    """A small package on disk: a lazy relative import closing a circle and a format
    importing the engine inside a function are both found by parsing."""
    engine, formats, commands = tmp_path / "relight_cli", tmp_path / "formats", tmp_path / "commands"
    for folder in (engine, engine / "hand", formats, commands):
        folder.mkdir()
        (folder / "__init__.py").write_text("")
    (engine / "hand" / "model.py").write_text("from .poses import POSES\n")
    (engine / "hand" / "poses.py").write_text("def f():\n    from . import model\n")
    (formats / "leap.py").write_text("def names():\n"
                                     "    from relight_cli.hand.model import JOINT_NAMES\n")
    (commands / "run.py").write_text("from ._helper import x\nimport relight_cli.commands.other\n")
    (commands / "_helper.py").write_text("x = 1\n")
    (commands / "other.py").write_text("")
    graph = tool.graph({"relight_cli": engine, "relight_cli.commands": commands,
                        "relight_cli.formats": formats})
    assert graph["relight_cli.hand.poses"] == {"relight_cli.hand.model"}
    assert graph["relight_cli.formats.leap"] == {"relight_cli.hand.model"}
    found = tool.violations(graph)
    assert found == [
        "import circle: relight_cli.hand.model -> relight_cli.hand.poses -> relight_cli.hand.model",
        "command relight_cli.commands.run imports command relight_cli.commands.other (move what "
        "they share into the engine, e.g. relight_cli/inputs.py)",
        "formats module relight_cli.formats.leap imports engine module relight_cli.hand.model "
        "(formats may import only base, formats)",
    ], found


def test_the_script_prints_the_graph_and_exits_0():
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "imports.py")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr
    lines = r.stdout.splitlines()
    assert "relight_cli.formats.image [formats] -> relight_cli.errors, relight_cli.formats.exr, " \
           "relight_cli.provenance" in lines
    assert "0 violations" in lines and lines[-1] == "0 confusing aliases"


def test_short_aliases_read_one_way(tool, tmp_path):
    """A short module alias names one module across the package, and never a value in
    the file that imports it; a planted package with both breaches is reported."""
    assert tool.alias_problems() == [], "\n".join(tool.alias_problems())
    engine, formats, commands = tmp_path / "relight_cli", tmp_path / "formats", tmp_path / "commands"
    for folder in (engine, formats, commands):
        folder.mkdir()
        (folder / "__init__.py").write_text("")
    (engine / "dgsm.py").write_text("")
    (engine / "distill.py").write_text("")
    (commands / "a.py").write_text("from relight_cli import dgsm as D\n")
    (commands / "b.py").write_text("def f():\n    from relight_cli import distill as D\n"
                                   "    T = 1\n    from relight_cli import dgsm as T\n")
    found = tool.alias_problems({"relight_cli": engine, "relight_cli.commands": commands,
                                 "relight_cli.formats": formats})
    assert found == [
        "relight_cli.commands.b binds T to a value and to module relight_cli.dgsm",
        "alias D names 2 modules: relight_cli.dgsm in relight_cli.commands.a; "
        "relight_cli.distill in relight_cli.commands.b",
    ], found
