"""relight_cli.jobs.dgsm_build called without click: the closed-form transmittance, the CLI's
file, errors and auto lights."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relight_cli.errors import DataError, UsageProblem
from relight_cli.formats.gaussians_ply import Gaussians, rgb_to_sh_dc


def _gaussians(means, scale, alpha=0.9):
    means = np.asarray(means, np.float64).reshape(-1, 3)
    n = len(means)
    return Gaussians(means, np.full((n, 3), scale), np.tile([1.0, 0, 0, 0], (n, 1)),
                     np.full(n, alpha), rgb_to_sh_dc(np.full((n, 3), 0.6))[:, None, :], 0)


def _floor(n=12, half=0.6):
    gx, gz = np.meshgrid(np.linspace(-half, half, n), np.linspace(-half, half, n))
    return _gaussians(np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], 1), 0.03)


def _lights(positions, intensities=None):
    from relight_cli.formats.lights_json import Lights
    positions = np.asarray(positions, np.float64)
    return Lights(positions, np.ones_like(positions),
                  np.ones(len(positions)) if intensities is None else np.asarray(intensities))


def _cli(*args):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


# ------------------------------------------------------------------ dgsm-build


def test_dgsm_job_matches_the_closed_form_transmittance():
    """One occluder Gaussian between a light and the floor: the table's T at floor points
    agrees with the exact erf transmittance (to the atlas' resolution), in the umbra and
    beside it."""
    from relight_cli.gaussians import dgsm as D
    from relight_cli.gaussians import transmittance as TR
    from relight_cli.jobs.dgsm_build import DgsmOptions, build

    occ = _gaussians([[0.0, 0.5, 0.0]], 0.15)
    light = [0.0, 1.5, 0.0]
    result = build([occ], _lights([light]), DgsmOptions(size=(64, 64), bins=32),
                   receivers=_floor(), quiet=True)
    m = result.shadow_map
    assert m.transmittance.shape == (1, 32, 64, 64) and result.mapping == "avg"
    under = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.1], [0.6, 0.0, 0.6]])
    exact = TR.transmittance_between(TR.from_gaussians(occ, "avg", 1.0), np.array(light), under)
    looked = D.sample_transmittance(m, under, light_index=0)
    # the centre ray of an α = 0.9 Gaussian under the avg mapping keeps 1 − α
    assert exact[0] == pytest.approx(0.1, abs=1e-3) and exact[2] > 0.98
    np.testing.assert_allclose(looked, exact, atol=0.01)
    assert list(result.settings) == ["size", "bins", "atlas", "mapping", "kappa", "t_max", "roi",
                                     "roi_radius", "cull", "cull_tolerance", "footprint",
                                     "samples", "seed"]
    assert result.preview is None


def test_dgsm_job_equals_what_the_cli_writes(tmp_path):
    """Two objects (one table each and their product), the same arrays and settings as the
    command's EXR; the old mapping name is recorded canonical."""
    from relight_cli.formats.dgsm_exr import read_dgsm
    from relight_cli.formats.exr import read_exr
    from relight_cli.formats.gaussians_ply import read_gaussians, write_gaussians
    from relight_cli.formats.lights_json import write_lights
    from relight_cli.jobs.dgsm_build import DgsmOptions, build

    paths = {k: str(tmp_path / f"{k}.ply") for k in ("a", "b", "floor")}
    write_gaussians(paths["a"], _gaussians([[0.0, 0.5, 0.0], [0.05, 0.55, 0.0]], 0.04))
    write_gaussians(paths["b"], _gaussians([[0.3, 0.3, 0.1]], 0.05))
    write_gaussians(paths["floor"], _floor())
    write_lights(str(tmp_path / "l.json"), _lights([[0.2, 1.5, 0.1], [-0.5, 1.2, 0.0]], [3.0, 1.0]))
    out = tmp_path / "s.exr"
    r = _cli("dgsm-build", paths["a"], paths["b"], "--receivers", paths["floor"], "--lights",
             tmp_path / "l.json", "--size", "24x16", "--bins", "12", "--mapping", "eq5", "-q",
             "-o", out)
    assert r.exit_code == 0, r.output
    written = read_dgsm(str(out))
    lines = []
    result = build([read_gaussians(paths["a"]), read_gaussians(paths["b"])],
                   _lights([[0.2, 1.5, 0.1], [-0.5, 1.2, 0.0]], [3.0, 1.0]),
                   DgsmOptions(size=(16, 24), bins=12, mapping="eq5"),
                   receivers=read_gaussians(paths["floor"]), names=[paths["a"], paths["b"]],
                   log=lines.append, quiet=True)
    np.testing.assert_array_equal(result.shadow_map.transmittance, written.transmittance)
    np.testing.assert_array_equal(result.shadow_map.t_max, written.t_max)
    assert result.mapping == "peak" and any("old name of peak" in s for s in lines)
    settings = read_exr(str(out)).provenance()["settings"]
    assert {k: settings[k] for k in result.settings} == json.loads(json.dumps(result.settings))
    assert len(result.occluders) == 3


def test_dgsm_job_errors_and_auto_lights():
    """A light inside an occluder is bad data unless allowed (then a warning); auto:K needs
    receivers; the preview is an RGB sheet."""
    from relight_cli.jobs.dgsm_build import DgsmOptions, build

    occ = _gaussians([[0.0, 0.5, 0.0]], 0.05)
    inside = _lights([[0.0, 0.5, 0.0]])
    with pytest.raises(DataError, match="lies inside occluder Gaussian 0"):
        build([occ], inside, DgsmOptions(size=(8, 8), bins=4, t_max=2.0))
    lines = []
    result = build([occ], inside, DgsmOptions(size=(8, 8), bins=4, t_max=2.0,
                                              allow_light_inside=True, preview=True),
                   log=lines.append, quiet=True)
    assert any(s.startswith("warning: light 0") for s in lines)
    assert result.preview.shape[-1] == 3 and 0 <= result.preview.min() < result.preview.max() <= 1
    with pytest.raises(UsageProblem, match="give --receivers"):
        build([occ], 2, DgsmOptions(size=(8, 8), t_max=1.0))
