"""tools/imports.py: the package's import graph keeps its layers (the I/O base below the
formats, formats below the engine, no command importing another, no import circle, no
click below the CLI), and the checker finds each breach when one is planted (in a fake
graph, and in a small package it parses)."""

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


@pytest.fixture(scope="module")
def clicky(tool):
    return tool.cli_only_imports()


def test_the_package_keeps_its_layers(tool, real, clicky):
    assert tool.violations(real, clicky) == [], "\n".join(tool.violations(real, clicky))
    layers = {m: tool.layer(m) for m in real}
    assert layers["relight_cli.formats.dgsm_exr"] == "formats"
    assert layers["relight_cli.gaussians.dgsm"] == "engine"
    assert layers["relight_cli.provenance"] == "engine"
    assert layers["relight_cli.jobs.relight_hand"] == "jobs"
    assert layers["relight_cli.cli.tools"] == layers["relight_cli.cli.inputs"] == "cli-tools"
    assert layers["relight_cli.commands.relight"] == "commands"
    assert layers["relight_cli.cli"] == layers["relight_cli.cli.manpage"] == "cli-group"
    assert layers["relight_cli.errors"] == layers["relight_cli.fileio"] == "base"
    assert set(tool.LAYERS) == set(layers.values())


def test_only_the_cli_imports_click(tool, real, clicky):
    """click is imported by the CLI package and the commands, and by nothing below them
    (the engine's notes go through a log callback or sys.stderr; the I/O base, the
    formats, progress and the jobs never see click)."""
    assert {tool.layer(m) for m in clicky} <= set(tool.CLI_LAYERS), clicky
    assert "relight_cli.cli.tools" in clicky and "relight_cli.cli" in clicky
    below = [m for m in real if tool.layer(m) not in tool.CLI_LAYERS]
    assert {"relight_cli.neural.distill", "relight_cli.jobs.synth_capture", "relight_cli.progress",
            "relight_cli.fileio"} <= set(below)
    assert not set(below) & set(clicky)
    # nor through a module of the CLI: nothing below imports relight_cli.cli.*
    assert not [(m, d) for m in below for d in real[m] if tool.layer(d) in tool.CLI_LAYERS]


def test_click_below_the_cli_is_reported(tool, tmp_path):
    """The check can fail: a planted package whose engine imports click inside a function
    and whose I/O base does at module level is refused, naming both; the same imports in
    the CLI's modules and a command are allowed."""
    engine, formats, commands = tmp_path / "relight_cli", tmp_path / "formats", tmp_path / "commands"
    for folder in (engine, engine / "neural", engine / "cli", formats, commands):
        folder.mkdir()
        (folder / "__init__.py").write_text("")
    (engine / "cli" / "__init__.py").write_text("import click\n")
    (engine / "cli" / "tools.py").write_text("import click\n")
    (commands / "run.py").write_text("from click import option\n")
    (engine / "fileio.py").write_text("import click.testing\n")
    (engine / "neural" / "distill.py").write_text("def note(m):\n    from click import echo\n"
                                                  "    echo(m, err=True)\n")
    sources = {"relight_cli": engine, "relight_cli.commands": commands,
               "relight_cli.formats": formats}
    clicky = tool.cli_only_imports(sources)
    assert set(clicky) == {"relight_cli.cli", "relight_cli.cli.tools", "relight_cli.commands.run",
                           "relight_cli.fileio", "relight_cli.neural.distill"}
    found = tool.violations(tool.graph(sources), clicky)
    assert found == [
        "base module relight_cli.fileio imports click (only the CLI may: cli-tools, commands, "
        "cli-group)",
        "engine module relight_cli.neural.distill imports click (only the CLI may: cli-tools, "
        "commands, cli-group)",
    ], found
    assert tool.violations(tool.graph(sources)) == []   # without the scan: not seen


def test_the_graph_counts_lazy_relative_and_aliased_imports(real):
    # formats/keypoints.py imports .leap inside read_keypoints (relative, in a function)
    assert "relight_cli.formats.leap" in real["relight_cli.formats.keypoints"]
    # jobs/relight_gaussians.py: `from relight_cli.gaussians import dgsm as D` names a module
    assert "relight_cli.gaussians.dgsm" in real["relight_cli.jobs.relight_gaussians"]
    # `from . import __version__` is the package itself
    assert "relight_cli" in real["relight_cli.provenance"]
    # `from ..fileio import ...` inside the cli package resolves two levels up
    assert "relight_cli.fileio" in real["relight_cli.cli"]
    assert all(m not in deps for m, deps in real.items())


def test_the_moved_pieces_stay_below(real):
    """What issue 22 moved: formats import no engine module, commands no command; what
    issue 48 moved: formats write through the I/O base, not the provenance module."""
    assert "relight_cli.preview" not in real["relight_cli.formats.image"]
    assert not {d for d in real["relight_cli.formats.dgsm_exr"] if d.startswith("relight_cli.gaussians")}
    assert "relight_cli.hand.model" not in real["relight_cli.formats.leap"]
    assert "relight_cli.cli.inputs" in real["relight_cli.commands.envmap"]
    assert "relight_cli.fileio" in real["relight_cli.formats.image"]
    assert not [m for m, deps in real.items()
                if m.startswith("relight_cli.formats") and "relight_cli.provenance" in deps]
    assert real["relight_cli.fileio"] <= {"relight_cli", "relight_cli.errors"}


def test_planted_breaches_are_reported(tool, real):
    """The checker can fail: each kind of breach added to the real graph is reported."""
    plants = {
        ("relight_cli.formats.image", "relight_cli.preview"): "formats module relight_cli.formats.image imports engine module relight_cli.preview",
        ("relight_cli.formats.leap", "relight_cli.hand.model"): "formats module relight_cli.formats.leap imports engine",
        ("relight_cli.formats.camera", "relight_cli.commands.camera"): "imports commands module",
        ("relight_cli.errors", "relight_cli.formats.exr"): "base module relight_cli.errors imports formats",
        ("relight_cli.fileio", "relight_cli.formats.exr"): "base module relight_cli.fileio imports formats",
        ("relight_cli.formats.exr", "relight_cli.provenance"): "formats module relight_cli.formats.exr imports engine module relight_cli.provenance",
        ("relight_cli.jobs.synth_capture", "relight_cli.cli.inputs"): "jobs module relight_cli.jobs.synth_capture imports cli-tools module relight_cli.cli.inputs",
        ("relight_cli.cli.tools", "relight_cli.commands.relight"): "cli-tools module relight_cli.cli.tools imports commands module",
        ("relight_cli.commands.relight", "relight_cli.cli"): "commands module relight_cli.commands.relight imports cli-group module relight_cli.cli",
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
                                  "relight_cli.fileio"},
        "relight_cli.formats.b": set(),
        "relight_cli.errors": set(),
        "relight_cli.fileio": {"relight_cli.errors"},
        "relight_cli.provenance": {"relight_cli", "relight_cli.fileio"},
        "relight_cli": set(),
        "relight_cli.cli.inputs": {"relight_cli.formats.a"},
        "relight_cli.commands.one": {"relight_cli.commands._shared", "relight_cli.cli.inputs"},
        "relight_cli.commands._shared": {"relight_cli.cli.inputs"},
        "relight_cli.cli": {"relight_cli.commands.one"},
        "relight_cli.cli.manpage": {"relight_cli.cli"},
    }
    clicky = {m: {"click"} for m in ("relight_cli.cli.inputs", "relight_cli.commands.one",
                                     "relight_cli.commands._shared", "relight_cli.cli")}
    assert tool.violations(graph, clicky) == []


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
        "they share below the commands, e.g. relight_cli/cli/inputs.py or a job)",
        "formats module relight_cli.formats.leap imports engine module relight_cli.hand.model "
        "(formats may import only base, formats)",
    ], found


def test_the_script_prints_the_graph_and_exits_0():
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "imports.py")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr
    lines = r.stdout.splitlines()
    assert "relight_cli.formats.image [formats] -> relight_cli.errors, relight_cli.fileio, " \
           "relight_cli.formats.exr" in lines
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
