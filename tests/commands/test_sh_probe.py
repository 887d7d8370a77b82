"""``relight sh-probe`` (commands/sh_probe.py): help, env maps and scenes in-process, stdout, bad
input, and ``--degree auto`` reporting its error in the log and the JSON."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from conftest import run_relight
from relight_cli.formats.gaussians_ply import Gaussians, rgb_to_sh_dc, write_gaussians
from relight_cli.formats.sh_probe_json import read_probe


def shell_scene(colour_up, colour_down, n=3000, radius=1.0, seed=0):
    """Opaque Gaussians on a sphere around the origin: one colour for y > 0, another below."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rgb = np.where(d[:, 1:2] > 0, colour_up, colour_down)
    return Gaussians(d * radius, np.full((n, 3), 0.06), np.tile([1.0, 0, 0, 0], (n, 1)),
                     np.full(n, 0.99), rgb_to_sh_dc(rgb)[:, None, :], 0)


# ------------------------------------------------------------------ CLI


def test_cli_help(run_cli):
    r = run_cli("sh-probe", "--help")
    assert r.exit_code == 0 and "--degree" in r.output and "--at" in r.output


def test_cli_env_in_process(run_cli, tmp_path):
    out = tmp_path / "u.json"
    r = run_cli("sh-probe", "builtin:uniform", "-o", out, "-q")
    assert r.exit_code == 0, r.output
    p = read_probe(str(out))
    assert p.degree == 0 and p.extra["degree_search"]["max_degree"] == 8
    np.testing.assert_allclose(p.coefficients[0], math.sqrt(4 * math.pi), rtol=1e-12)
    assert p.provenance["format"] == "relight/sh-probe" and "sh-probe" in p.provenance["command"]


def test_cli_scene_in_process(run_cli, tmp_path):
    scene = tmp_path / "room.ply"
    write_gaussians(str(scene), shell_scene(np.array([0.8, 0.8, 0.8]), np.array([0.2, 0.2, 0.2]),
                                            n=1500))
    out = tmp_path / "p.json"
    r = run_cli("sh-probe", scene, "--at", "0,0,0", "--degree", "1", "--face-size", "12", "-o", out,
                "-q")
    assert r.exit_code == 0, r.output
    p = read_probe(str(out))
    assert p.degree == 1 and p.coefficients[1, 0] < 0       # brighter above: −C1·y coefficient < 0
    np.testing.assert_array_equal(p.position, [0, 0, 0])


def test_cli_subprocess_stdout():
    r = run_relight("sh-probe", "builtin:sky", "--degree", "2", "-o", "-", "-q")
    assert r.returncode == 0, r.stderr
    obj = json.loads(r.stdout)
    assert obj["format"] == "relight/sh-probe" and len(obj["coefficients"]) == 9


@pytest.mark.parametrize("args, code, message", [
    (["builtin:sky", "--at", "0,0,0"], 2, "--at is only for Gaussian scenes"),
    (["scene.ply"], 2, "needs the probe position"),
    (["builtin:sky", "--degree", "x"], 2, "--degree must be"),
    (["builtin:sky", "--degree", "-1"], 2, "--degree must be in"),
    (["builtin:sky", "--ridge", "-1"], 2, "--ridge"),
    (["missing.exr"], 1, "no such file"),
    (["missing.ply", "--at", "0,0,0"], 1, "no such file"),
    (["bad.ply", "--at", "0,0,0"], 1, "not a readable PLY"),
    (["good.ply", "--at", "0,0"], 2, "--at must be 3"),
])
def test_cli_bad_input(run_cli, tmp_path, args, code, message, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.ply").write_text("not a ply")
    write_gaussians(str(tmp_path / "good.ply"), shell_scene(np.ones(3), np.ones(3), n=10))
    r = run_cli("sh-probe", *args, "-o", "out.json")
    assert r.exit_code == code, r.output
    assert message in r.output and "error" in r.output
    assert not (tmp_path / "out.json").exists()


def test_cli_reports_error_in_log_and_json(run_cli, tmp_path):
    auto, fixed = tmp_path / "auto.json", tmp_path / "fixed.json"
    r = run_cli("sh-probe", "builtin:sky", "--degree", "auto", "-o", auto)
    assert r.exit_code == 0, r.output
    search = read_probe(str(auto)).extra["degree_search"]
    assert (f"auto degree: 2 (irradiance error {search['irradiance_error']:.2e} against a direct "
            "quadrature") in r.stderr
    assert "past --max-negativity 2" in r.stderr and search["limited_by"] == "max_negativity"
    assert search["negativity"] <= search["max_negativity"] == 2.0
    assert set(search["candidates"]) == {"0", "1", "2", "4", "6", "8"}
    # The written coefficients are --degree 2's.
    assert run_cli("sh-probe", "builtin:sky", "--degree", "2", "-o", fixed, "-q").exit_code == 0
    np.testing.assert_array_equal(read_probe(str(auto)).coefficients,
                                  read_probe(str(fixed)).coefficients)


def test_subprocess_auto_reports_error():
    r = run_relight("sh-probe", "builtin:uniform", "--degree", "auto", "--tolerance", "0.01",
                    "-o", "-")
    assert r.returncode == 0, r.stderr
    obj = json.loads(r.stdout)
    search = obj["degree_search"]
    assert obj["degree"] == 0 and search["tolerance_met"] and search["irradiance_error"] < 1e-3
    assert f"irradiance error {search['irradiance_error']:.2e}" in r.stderr
    assert obj["provenance"]["settings"]["tolerance"] == 0.01


@pytest.mark.parametrize("args, option", [
    (["--tolerance", "-0.1"], "--tolerance"),
    (["--tolerance", "0"], "--tolerance"),
    (["--max-negativity", "-1"], "--max-negativity"),
    (["--max-negativity", "nan"], "--max-negativity"),
])
def test_bad_criterion_is_a_usage_error(tmp_path, args, option):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    out = tmp_path / "p.json"
    r = CliRunner().invoke(cli, ["sh-probe", "builtin:sky", *args, "-o", str(out)],
                           prog_name="relight")
    assert r.exit_code == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("relight sh-probe: error: ")
    assert option in lines[0] and not out.exists()


def test_cli_scene_colour_space(run_cli, tmp_path):
    """A foreign (3DGS training) scene PLY is sRGB: its splatted radiance is decoded before
    the fit, so the probe of a uniform 0.5-grey shell is EOTF(0.5)/0.5 of the one fitted to
    the stored colours (--colour-space linear); an env map takes no --colour-space."""
    from conftest import as_foreign_ply
    from relight_cli.formats.gaussians_ply import srgb_eotf
    scene = tmp_path / "room.ply"
    write_gaussians(str(scene), shell_scene(np.full(3, 0.5), np.full(3, 0.5), n=1500))
    as_foreign_ply(scene)
    probes = {}
    for space in ("auto", "linear"):
        out = tmp_path / f"{space}.json"
        r = run_cli("sh-probe", scene, "--at", "0,0,0", "--degree", "0", "--face-size", "12",
                    "--colour-space", space, "-o", out, "-q")
        assert r.exit_code == 0, r.output
        probes[space] = read_probe(str(out))
        assert probes[space].provenance["settings"]["colour_space"] == space
    np.testing.assert_allclose(probes["auto"].coefficients[0] / probes["linear"].coefficients[0],
                               srgb_eotf(0.5) / 0.5, rtol=1e-6)
    r = run_cli("sh-probe", "builtin:sky", "--colour-space", "srgb", "-o", tmp_path / "s.json")
    assert r.exit_code == 2 and "--colour-space" in r.output
    r = run_cli("sh-probe", scene, "--at", "0,0,0", "--colour-space", "rgb", "-o",
                tmp_path / "b.json")
    assert r.exit_code == 2 and not (tmp_path / "b.json").exists()
