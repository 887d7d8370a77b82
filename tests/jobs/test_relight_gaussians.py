"""relight_cli.jobs.relight_gaussians called without click: closed forms on a few Gaussians,
refusals, and arrays equal to what ``relight relight`` writes for the same inputs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest


def _gaussians(n=8, seed=0, offset=(0.0, 0.0, 0.0), flat=0.002):
    """n small flat Gaussians (shortest axis z, so axis normals are ±z) near ``offset``."""
    from relight_cli.formats.gaussians_ply import Gaussians, rgb_to_sh_dc
    rng = np.random.default_rng(seed)
    means = rng.normal(0.0, 0.03, (n, 3)) + np.asarray(offset, np.float64)
    scales = np.tile([0.02, 0.02, flat], (n, 1))
    rotations = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    colors = rng.uniform(0.2, 0.8, (n, 3))
    return Gaussians(means, scales, rotations, np.full(n, 0.9),
                     rgb_to_sh_dc(colors)[:, None, :], 0)


def _uniform_probe(radiance):
    """A degree-0 probe of constant radiance [3] (Y00 = 1/(2√π))."""
    from relight_cli.formats.sh_probe_json import ShProbe
    return ShProbe(np.asarray(radiance, np.float64)[None, :] * 2.0 * math.sqrt(math.pi), 0)


def test_a_uniform_probe_scales_the_albedo_in_closed_form():
    """Constant radiance L: the lobe-weighted mean is L for every normal, so each colour
    is γ · albedo · clip(L, 0, t_max), per channel, for any lobe."""
    from relight_cli.jobs.relight_gaussians import GaussianOptions, relight
    g = _gaussians()
    L = np.array([2.0, 1.0, 0.5])
    for lobe, intensity, t_max in ((1.0, 0.5, None), (4.0, 2.0, 1.5)):
        out = relight([g], _uniform_probe(L), GaussianOptions(lobe=lobe, intensity=intensity,
                                                              t_max=t_max))
        factor = intensity * np.minimum(L, math.inf if t_max is None else t_max)
        np.testing.assert_allclose(out.objects.colors(clamp=False), g.colors(clamp=False) * factor,
                                   rtol=1e-9, atol=1e-12)
        assert out.receivers is None and out.channels is None
        assert out.settings["lobe"] == lobe and out.settings["t_max"] == t_max
    two = relight([g, _gaussians(3, seed=1)], _uniform_probe(L), GaussianOptions())
    assert len(two.objects) == len(g) + 3          # IN and --object, concatenated in order


def test_the_job_refuses_what_it_cannot_run():
    from relight_cli.jobs.relight_gaussians import GaussianOptions, relight
    probe, g = _uniform_probe([1, 1, 1]), _gaussians()
    with pytest.raises(ValueError, match="receivers"):
        relight([g], probe, GaussianOptions(), shadow_map=object())
    with pytest.raises(ValueError, match="shadow map"):
        relight([g], probe, GaussianOptions(direct_light=True))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A few occluder Gaussians over a floor of receivers, one light above, its DGSM
    (dgsm-build), a camera and a probe, as files."""
    from click.testing import CliRunner

    from relight_cli.cli import cli
    from relight_cli.formats.gaussians_ply import write_gaussians
    from relight_cli.formats.sh_probe_json import write_probe
    root = tmp_path_factory.mktemp("jobs_relight")
    write_gaussians(str(root / "avatar.ply"), _gaussians(6, offset=(0, 0.2, 0), flat=0.02))
    floor = _gaussians(40, seed=2)
    floor.means[:, 1] = 0.0
    floor.means[:, [0, 2]] *= 4
    write_gaussians(str(root / "floor.ply"), floor)
    write_probe(str(root / "probe.json"), _uniform_probe([0.8, 0.9, 1.0]))
    (root / "lights.json").write_text(json.dumps({"format": "relight/lights", "version": 1,
                                                  "lights": [{"position": [0.02, 1.0, 0.01],
                                                              "color": [1, 1, 1],
                                                              "intensity": 3.0}]}))
    runner = CliRunner()
    for args in (["dgsm-build", root / "avatar.ply", "--receivers", root / "floor.ply",
                  "--lights", root / "lights.json", "--size", "16", "-q",
                  "-o", root / "shadows.exr"],
                 ["camera", "--eye", "0,0.6,0.6", "--target", "0,0.05,0", "--size", "24x16",
                  "-q", "-o", root / "cam.json"]):
        r = runner.invoke(cli, [str(a) for a in args], catch_exceptions=False)
        assert r.exit_code == 0, r.output
    return root


def _read_inputs(root):
    from relight_cli.formats.camera import read_camera
    from relight_cli.formats.dgsm_exr import read_dgsm
    from relight_cli.formats.gaussians_ply import read_gaussians
    from relight_cli.formats.sh_probe_json import read_probe
    return (read_gaussians(str(root / "avatar.ply")), read_gaussians(str(root / "floor.ply")),
            read_probe(str(root / "probe.json")), read_dgsm(str(root / "shadows.exr")),
            read_camera(str(root / "cam.json")))


def _same_as_written(array, written):
    """Equal at the file's precision (PLY float32 read back as float64; EXR half/float)."""
    written = np.asarray(written)
    dtype = np.float32 if written.dtype == np.float64 else written.dtype
    np.testing.assert_array_equal(written.astype(dtype), np.asarray(array).astype(dtype))


def test_gaussian_job_arrays_are_what_the_cli_writes(scene, run_cli, tmp_path):
    """PLY (objects, receivers) and the rendered view: the job's arrays, bit for bit at
    the files' precision, for shadowed receivers with a fixed shadow strength."""
    from relight_cli.formats.exr import read_exr
    from relight_cli.formats.gaussians_ply import read_gaussians
    from relight_cli.jobs.relight_gaussians import GaussianOptions, relight
    avatar, floor, probe, dgsm, camera = _read_inputs(scene)
    options = GaussianOptions(shadow_strength=0.8, footprint="centre")
    out = relight([avatar], probe, options, dgsm, floor, camera, (0.1, 0.1, 0.1))
    common = [scene / "avatar.ply", "--probe", scene / "probe.json", "--dgsm",
              scene / "shadows.exr", "--receivers", scene / "floor.ply", "--shadow-strength",
              "0.8", "--footprint", "centre", "-q"]
    r = run_cli("relight", *common, "-o", tmp_path / "relit.ply", "--receivers-out",
                tmp_path / "rec.ply")
    assert r.exit_code == 0, r.output
    for job, path in ((out.objects, "relit.ply"), (out.receivers, "rec.ply")):
        written = read_gaussians(str(tmp_path / path))
        _same_as_written(job.sh, written.sh)
        _same_as_written(job.means, written.means)
    assert not np.allclose(out.receivers.sh, floor.sh)     # the light's shadow lands
    r = run_cli("relight", *common, "--camera", scene / "cam.json", "--background",
                "0.1,0.1,0.1", "-o", tmp_path / "view.exr")
    assert r.exit_code == 0, r.output
    image = read_exr(str(tmp_path / "view.exr"))
    for name in "RGBA":
        _same_as_written(out.channels[name], image.channels[name])
    assert json.loads(image.attributes["relight.provenance"])["settings"]["shadow_strength"] \
        == out.settings["shadow_strength"] == 0.8


def test_no_shadow_strength_leaves_the_receivers_as_they_are(scene):
    """s = 0: colour × ((1 − 0) + 0·T) = colour, whatever the transmittance."""
    from relight_cli.jobs.relight_gaussians import GaussianOptions, relight
    avatar, floor, probe, dgsm, _ = _read_inputs(scene)
    out = relight([avatar], probe, GaussianOptions(shadow_strength=0.0), dgsm, floor)
    np.testing.assert_allclose(out.receivers.sh, floor.sh, rtol=0, atol=1e-12)
    assert out.settings["light_weights"] == "intensity"


def test_shadow_matte_job_is_the_cli_matte(scene, run_cli, tmp_path):
    from relight_cli.formats.exr import read_exr
    from relight_cli.jobs.relight_gaussians import GaussianOptions, shadow_matte
    _, floor, _, dgsm, camera = _read_inputs(scene)
    matte = shadow_matte("dgsm", floor, dgsm, camera, GaussianOptions(footprint="centre"))
    assert 0 <= matte.strength.min() and matte.strength.max() <= 1
    assert matte.strength.max() > 0.05       # some floor Gaussian is under the avatar
    r = run_cli("relight", scene / "avatar.ply", "--dgsm", scene / "shadows.exr",
                "--receivers", scene / "floor.ply", "--camera", scene / "cam.json",
                "--shadow-matte", "dgsm", "--footprint", "centre", "-q",
                "-o", tmp_path / "matte.exr")
    assert r.exit_code == 0, r.output
    image = read_exr(str(tmp_path / "matte.exr"))
    for name in "RGBA":
        _same_as_written(matte.channels[name], image.channels[name])
    with pytest.raises(ValueError, match="dgsm or mesh"):
        shadow_matte("nope", floor, dgsm, camera, GaussianOptions())
