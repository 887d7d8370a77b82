"""``relight metrics lighting`` (commands/metrics_lighting.py): in-process, console script, bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from conftest import run_relight
from relight_cli.formats.gaussians_ply import Gaussians, rgb_to_sh_dc, write_gaussians
from relight_cli.metrics.lighting import scene_radiance_sh
from relight_cli.sh import evaluate_sh, irradiance_coefficients


def fibonacci_sphere(n):
    i = np.arange(n) + 0.5
    polar = np.arccos(1 - 2 * i / n)
    azimuth = math.pi * (1 + 5 ** 0.5) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.cos(polar),
                     np.sin(azimuth) * np.sin(polar)], axis=1)


def gaussians(means, colors, scale=0.02, normals=None):
    n = len(means)
    sh = np.zeros((n, 1, 3))
    sh[:, 0] = rgb_to_sh_dc(np.asarray(colors, np.float64))
    return Gaussians(means, np.full((n, 3), scale), np.tile([1.0, 0, 0, 0], (n, 1)),
                     np.full(n, 0.9), sh, 0, normals)


KEY = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])


@pytest.fixture(scope="module")
def setup():
    """A scene shell with a warm key light towards KEY, and an avatar sphere lit by it."""
    d = fibonacci_sphere(500)
    colors = 0.15 + 0.8 * np.clip(d @ KEY, 0, None)[:, None] ** 4 * np.array([1.0, 0.9, 0.7])
    scene = gaussians(d * 1.2, colors, 0.05)
    radiance, _ = scene_radiance_sh(scene.means, scene.colors(), scene.opacities, scene.scales,
                                    np.zeros(3), 1.5)
    irr = irradiance_coefficients(radiance)
    normals = fibonacci_sphere(700)
    e = evaluate_sh(irr, normals)                        # [N, 3] exact SH irradiance
    avatar_colors = 0.9 * e / e.max()                    # albedo × irradiance (affine: scale only)
    avatar = gaussians(normals * 0.3, avatar_colors, 0.01)
    return scene, irr, normals, avatar


# ------------------------------------------------------------------ CLI


@pytest.fixture
def plys(setup, tmp_path):
    scene, _, _, avatar = setup
    write_gaussians(str(tmp_path / "scene.ply"), scene)
    write_gaussians(str(tmp_path / "avatar.ply"), avatar)
    cast = gaussians(avatar.means, np.clip(avatar.colors() * [1.3, 1.0, 0.7], 0, 1), 0.01)
    write_gaussians(str(tmp_path / "relit.ply"), cast)
    return tmp_path


def test_cli_in_process(run_cli, plys):
    out = plys / "l.json"
    r = run_cli("metrics", "lighting", "--scene", plys / "scene.ply", "--avatar", plys / "avatar.ply",
                "--relit", plys / "relit.ply", "--radius", "1.5", "-o", out)
    assert r.exit_code == 0, r.output
    rec = json.loads(out.read_text())
    assert rec["kind"] == "lighting" and list(rec["metrics"]) == ["orig", "relit", "delta"]
    assert rec["metrics"]["orig"]["paa_angle"] < 0.5 and rec["metrics"]["delta"]["ncm_ab"] > 5
    assert set(rec["metrics"]["orig"]) == {"paa_y", "apf_y", "ncm_ab", "paa_angle", "apf_rms",
                                           "ncm_ab_weighted"}
    assert set(rec["inputs"]) == {"scene", "avatar:0", "relit:0"}
    assert len(rec["frames"]) == 1


def test_cli_subprocess_and_bad_input(plys):
    r = run_relight("metrics", "lighting", "--scene", plys / "scene.ply", "--avatar",
                    plys / "avatar.ply", "-q")
    assert r.returncode == 0, r.stderr
    assert list(json.loads(r.stdout)["metrics"]) == ["orig"]
    out = plys / "x.json"
    r = run_relight("metrics", "lighting", "--scene", plys / "scene.ply", "--avatar",
                    plys / "avatar.ply", "--normals", "ply", "-o", out)
    assert r.returncode == 1 and "no normals" in r.stderr and "avatar.ply" in r.stderr
    r = run_relight("metrics", "lighting", "--scene", plys / "scene.ply", "--avatar",
                    plys / "avatar.ply", "--radius", "0.5", "-o", out)
    assert r.returncode == 1 and "within radius" in r.stderr
    r = run_relight("metrics", "lighting", "--scene", plys / "scene.ply", "--avatar",
                    plys / "avatar.ply", "--relit", plys / "relit.ply", "--relit",
                    plys / "relit.ply", "-o", out)
    assert r.returncode == 2
    # A PLY without colours (no f_dc_*): the reader's one-line error.
    from plyfile import PlyData, PlyElement
    v = np.zeros(20, dtype=[(n, "f4") for n in ("x", "y", "z", "opacity", "scale_0", "scale_1",
                                                  "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")])
    v["rot_0"] = 1
    PlyData([PlyElement.describe(v, "vertex")]).write(str(plys / "nocolour.ply"))
    r = run_relight("metrics", "lighting", "--scene", plys / "scene.ply", "--avatar",
                    plys / "nocolour.ply", "-o", out)
    assert r.returncode == 1 and "f_dc" in r.stderr and "nocolour.ply" in r.stderr
    assert r.stderr.strip().count("\n") == 0
    assert not out.exists()
