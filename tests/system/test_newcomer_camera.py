"""What a newcomer sees (issue 24): the README's `relight camera --from` calls run as
written, the camera JSON goes to stdout when -o is not given, and imported cameras keep
their names (a render's or a capture image's EXR header included).

The README lines are taken from its "Cameras" section and run as they stand, in-process
and through the installed console script; the render line gets cheap quality options
(`--tex-res 16 --aa 1 --env-res 8x4`), which change the pixels, not the header the camera
is read back from.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, relight_executable
from relight_cli.formats.camera import Camera, openexr_camera_name, read_camera, write_cameras

CHEAP_RENDER = ["--tex-res", "16", "--aa", "1", "--env-res", "8x4", "-q"]


def readme_camera_lines() -> list[str]:
    """The `relight ...` lines of the sh block in the README's "Cameras" section."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("\n### Cameras\n", 1)[1].split("\n### ", 1)[0]
    block = section.split("```sh\n", 1)[1].split("```", 1)[0]
    return [line for line in block.splitlines() if line.startswith("relight ")]


def _argv(line: str) -> list[str]:
    words = shlex.split(line, comments=True)
    return words[1:] + (CHEAP_RENDER if words[1] == "relight" else [])


def _check_read_back(stdout: str, folder: Path) -> None:
    """The last README call printed cam001 back: its name and (float32) pose."""
    doc = json.loads(stdout)
    assert doc["format"] == "relight/camera" and doc["name"] == "cam001"
    made = read_camera(str(folder / "cam001.json"))
    np.testing.assert_allclose(doc["K"], made.K, rtol=1e-5)
    np.testing.assert_allclose(doc["R"], made.R, atol=1e-6)
    np.testing.assert_allclose(doc["t"], made.t, atol=1e-6)
    assert (doc["width"], doc["height"]) == (made.width, made.height)


def test_readme_documents_the_call_without_o():
    lines = readme_camera_lines()
    assert lines[-1].split("#")[0].split() == ["relight", "camera", "--from", "cam001.exr"]
    assert any(" --camera cam001.json -o cam001.exr" in line for line in lines)


def test_readme_camera_lines_in_process(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    monkeypatch.chdir(tmp_path)
    for line in readme_camera_lines():
        r = CliRunner().invoke(cli, _argv(line))
        assert r.exit_code == 0, (line, r.output)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cam001.exr", "cam001.json",
                                                          "rig.json"]
    _check_read_back(r.stdout, tmp_path)
    assert "wrote" not in r.stdout               # logs stay on stderr


def test_readme_camera_lines_console_script(tmp_path):
    """The same lines through bash and the installed `relight`, as a user types them."""
    bin_dir = os.path.dirname(relight_executable())
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}",
               PYTHONWARNINGS="ignore")
    lines = readme_camera_lines()
    script = "\n".join(line + (" " + " ".join(CHEAP_RENDER) if line.startswith("relight relight")
                               else "") for line in lines[:-1])
    r = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    r = subprocess.run(["bash", "-euo", "pipefail", "-c", lines[-1]], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    _check_read_back(r.stdout, tmp_path)
    assert r.stderr == ""                         # nothing but the JSON: no "wrote" line


def _exr_with_camera(path: Path, cam: Camera, label) -> None:
    """An EXR carrying the header a relight render (label: the camera JSON) or a capture
    image (label: the name) writes."""
    from relight_cli.formats.exr import write_exr
    attrs = {} if label is None else {"relight.camera": label}
    write_exr(str(path), {"A": np.ones((cam.height, cam.width), np.float32)}, attributes=attrs,
              camera=cam)


@pytest.mark.parametrize("label, name", [
    ("render", "front"),          # a render: the whole camera as a JSON string
    ("capture", "cam007"),        # a capture image: the name itself
    (None, None),                 # another tool's EXR: matrices only, no name
])
def test_exr_import_keeps_the_name_with_and_without_o(tmp_path, run_cli, label, name):
    cam = Camera.look_at([0.1, 0.2, 0.5], [0, 0.05, 0], fov_y_deg=35, width=12, height=10,
                         name=name or "")
    value = {"render": json.dumps(cam.to_json()), "capture": name, None: None}[label]
    _exr_with_camera(tmp_path / "r.exr", cam, value)
    r = run_cli("camera", "--from", tmp_path / "r.exr")
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert doc.get("name") == name
    r = run_cli("camera", "--from", tmp_path / "r.exr", "-o", tmp_path / "c.json", "-q")
    assert r.exit_code == 0 and r.stdout == "", r.output
    assert read_camera(str(tmp_path / "c.json")).name == (name or "")
    back = read_camera(str(tmp_path / "c.json"))
    np.testing.assert_allclose(back.R, cam.R, atol=1e-6)        # float32 header precision
    np.testing.assert_allclose(back.K, cam.K, rtol=1e-5)


def test_openexr_camera_name_reads_both_forms_and_never_fails():
    assert openexr_camera_name(None) == ""
    assert openexr_camera_name("cam003") == "cam003"
    assert openexr_camera_name('{"name": "left", "K": []}') == "left"
    assert openexr_camera_name({"name": "dict"}) == "dict"
    assert openexr_camera_name('{"K": []}') == ""               # a render's unnamed camera
    assert openexr_camera_name("{not json") == ""                # damaged: no name
    assert openexr_camera_name('{"name": 5}') == ""


def test_every_mode_writes_json_to_stdout_without_o(tmp_path, run_cli):
    """All camera modes write JSON, so -o is optional for each; identical bytes either way
    but for the command line in the provenance."""
    write_cameras(str(tmp_path / "rig.json"), [Camera.look_at([0, 0, 1], [0, 0, 0], name="a"),
                                               Camera.look_at([1, 0, 0], [0, 0, 0], name="b")])
    for args in (["--eye", "0,0.1,0.5", "--size", "8x6", "--name", "front"],
                 ["--orbit", "3", "--radius", "1"],
                 ["--dome", "4", "--radius", "1"],
                 ["--from", tmp_path / "rig.json", "--select", "b"]):
        r = run_cli("camera", *args)
        assert r.exit_code == 0, (args, r.output)
        doc = json.loads(r.stdout)
        assert doc["format"] == "relight/camera" and "wrote" not in r.stderr
        r2 = run_cli("camera", *args, "-o", tmp_path / "f.json", "-q")
        assert r2.exit_code == 0 and r2.stdout == ""
        from_file = json.loads((tmp_path / "f.json").read_text())
        assert {k: v for k, v in from_file.items() if k != "provenance"} == \
            {k: v for k, v in doc.items() if k != "provenance"}
    assert read_camera(str(tmp_path / "f.json")).name == "b"


def test_help_says_stdout_is_the_default(run_cli):
    r = run_cli("camera", "--help")
    assert r.exit_code == 0
    assert "default: '-', stdout" in r.output and "relight camera --from render.exr\n" in r.output
