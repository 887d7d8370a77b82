"""``relight bake-features`` end to end: help, in-process runs, console script, bad input."""

from __future__ import annotations

import copy
import json
import math
import subprocess

import numpy as np
import pytest
from click.testing import CliRunner

from relight_cli.cli import cli

SMALL = ["--res", "32", "--env-res", "16x8"]


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def relight_exe() -> str:
    from conftest import relight_executable
    return relight_executable()


@pytest.fixture(scope="module")
def hand_file(tmp_path_factory):
    """A two-frame hand.npz (relaxed, then fist) of the built-in right hand."""
    from relight_cli.formats.hand_npz import write_hand
    from relight_cli.hand.model import builtin_hand
    relaxed = builtin_hand("right", "relaxed")
    fist = builtin_hand("right", "fist")
    data = copy.deepcopy(relaxed)
    inst = data.hands[0]
    inst.poses = np.concatenate([relaxed.hands[0].poses, fist.hands[0].poses])
    inst.translations = np.concatenate([relaxed.hands[0].translations,
                                        fist.hands[0].translations])
    path = tmp_path_factory.mktemp("hand") / "hand.npz"
    write_hand(str(path), data)
    return path


def test_help():
    r = invoke("bake-features", "--help")
    assert r.exit_code == 0
    assert "--env-res" in r.output and "--per-vertex" in r.output
    assert "bake-features" in invoke("--help").output


def test_bake_reads_back_and_matches_engine(tmp_path, hand_file):
    out = tmp_path / "feats.exr"
    npz = tmp_path / "verts.npz"
    r = invoke("bake-features", hand_file, "builtin:sky", "-o", out, "--per-vertex", npz,
               "--specular", "both", "--eye", "0,0.2,0.5", "-q", *SMALL)
    assert r.exit_code == 0, r.output
    from relight_cli.formats.features_exr import read_features, read_vertex_features
    maps = read_features(str(out))
    assert set(maps.layers) == {"diffuse", "phong16", "phong32", "phong64", "ggx",
                                "visibility", "mask"}
    assert maps.layers["diffuse"].shape == (32, 32, 3)
    a = maps.attributes
    assert a["relight.format"] == "relight/features" and a["relight.version"] == 1
    assert a["relight.env_res"] == "8x16" and a["relight.frame"] == 0
    assert a["relight.rays_traced"] > 0
    np.testing.assert_allclose(a["relight.view"], [0, 0.2, 0.5])
    # The per-vertex file equals the engine run directly (float32 storage: 1e-6 relative).
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.features import FeatureBaker, FeatureSettings, PoseMesh
    from relight_cli.formats.hand_npz import read_hand
    from relight_cli.hand.scene import posed_meshes
    from relight_cli.envmap import discretize_env
    pm = posed_meshes(read_hand(str(hand_file)), 0)[0]
    # the command's default --env-sources auto: the sky's sun is a direction of its own
    sky = discretize_env(builtin_envmap("builtin:sky"), 8, 16, sources="auto")
    assert sky.sources == 1
    baker = FeatureBaker([PoseMesh(pm.vertices, pm.faces, pm.normals)],
                         FeatureSettings(specular="both"), grid=sky)
    direct = baker.bake([sky], [0, 0.2, 0.5])[0][0]
    verts = read_vertex_features(str(npz))
    np.testing.assert_allclose(verts["vertices"], pm.vertices)
    for name in ("diffuse", "phong32", "ggx", "visibility"):
        np.testing.assert_allclose(verts[name], direct[name], rtol=1e-6, atol=1e-6)
    # Texel maps: mask from the UV raster; inside texels interpolate the vertex values.
    from relight_cli.uvraster import rasterize_uv
    raster = rasterize_uv(pm.uv, pm.faces_uv, 32)
    np.testing.assert_array_equal(maps.layers["mask"], raster.mask)
    expect = raster.interpolate(direct["diffuse"], pm.faces, fill=None)
    inside = raster.inside
    np.testing.assert_allclose(maps.layers["diffuse"][inside], expect[inside], rtol=1e-5, atol=1e-6)
    # Outside texels are dilation-filled from the charts (the same fill, float32 storage).
    filled = raster.interpolate(direct["diffuse"], pm.faces, fill="dilate")
    np.testing.assert_allclose(maps.layers["diffuse"], filled, rtol=1e-5, atol=1e-6)
    assert (maps.layers["diffuse"][~inside] > 0).mean() > 0.5


def test_multi_env_pattern_frames_all(tmp_path, hand_file):
    pattern = str(tmp_path / "f_{env}_{frame:02d}.exr")
    r = invoke("bake-features", hand_file, "builtin:sky", "builtin:uniform", "--frames", "all",
               "-o", pattern, "-q", *SMALL)
    assert r.exit_code == 0, r.output
    from relight_cli.formats.features_exr import read_features
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["f_sky_00.exr", "f_sky_01.exr", "f_uniform_00.exr", "f_uniform_01.exr"]
    relaxed = read_features(str(tmp_path / "f_uniform_00.exr"))
    fist = read_features(str(tmp_path / "f_uniform_01.exr"))
    m = relaxed.layers["mask"] > 0
    # A fist occludes itself deeply: its mean cosine-weighted visibility drops.
    assert fist.layers["visibility"][m].mean() < relaxed.layers["visibility"][m].mean() - 0.02
    # Uniform white env: diffuse = visibility · Σ max(n·ω,0)Δω per vertex (the definitions),
    # and that sum is π within the 8×16 quadrature error (≤ 2.5 % for any normal,
    # measured); interpolation is linear, so the maps obey it too.
    np.testing.assert_allclose(relaxed.layers["diffuse"][m][:, 0],
                               math.pi * relaxed.layers["visibility"][m], rtol=0.03, atol=1e-6)


def test_two_hands_shadow_each_other(tmp_path):
    out_one = tmp_path / "one.exr"
    out_two = tmp_path / "two.exr"
    assert invoke("bake-features", "builtin:right", "builtin:uniform", "-o", out_one, "-q",
                  *SMALL).exit_code == 0
    r = invoke("bake-features", "builtin:two", "builtin:uniform", "-o", out_two, "-q", *SMALL)
    assert r.exit_code == 0, r.output
    from relight_cli.formats.features_exr import read_features
    one = read_features(str(out_one))
    two = read_features(str(out_two))
    assert two.hands == ["left", "right"]
    assert set(two.layers) >= {"right.diffuse", "left.diffuse", "right.mask", "left.visibility"}
    m = one.layers["mask"] > 0
    # The neighbouring hand can only remove light.
    assert (two.layers["right.visibility"][m] <= one.layers["visibility"][m] + 1e-6).all()


def test_console_script(tmp_path):
    out = tmp_path / "f.exr"
    png = tmp_path / "f.png"
    r = subprocess.run([relight_exe(), "bake-features", "builtin:right", "builtin:studio",
                        "-o", str(out), "--preview", str(png), "--no-visibility", *SMALL],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert out.exists() and png.exists()
    assert r.stdout == ""            # logs go to stderr
    assert "wrote" in r.stderr


# ---------------------------------------------------------------- bad input


def _bad(tmp_path, *args, code, subprocess_run=False):
    """Run a failing command: one error line on stderr, the exit code, nothing written."""
    out = tmp_path / "o.exr"
    argv = ["bake-features", *SMALL, *map(str, args), "-o", str(out)]  # later options win
    if subprocess_run:
        r = subprocess.run([relight_exe(), *argv], capture_output=True, text=True, timeout=300)
        returncode, stderr = r.returncode, r.stderr
    else:
        r = CliRunner().invoke(cli, argv)
        returncode, stderr = r.exit_code, r.stderr
    assert returncode == code, (returncode, stderr)
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0] and "Traceback" not in stderr, stderr
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".o.exr")]
    return lines[0]


def test_missing_hand(tmp_path):
    line = _bad(tmp_path, tmp_path / "nope.npz", "builtin:sky", code=1, subprocess_run=True)
    assert "nope.npz" in line


def test_damaged_hand_and_env(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    assert "junk.npz" in _bad(tmp_path, junk, "builtin:sky", code=1)
    env = tmp_path / "env.exr"
    env.write_bytes(b"\x76\x2f\x31\x01garbage")
    assert "env.exr" in _bad(tmp_path, "builtin:right", env, code=1)


def test_nan_env(tmp_path):
    from relight_cli.formats.exr import write_exr
    rgb = np.ones((8, 16), np.float32)
    rgb[2, 3] = np.nan
    env = tmp_path / "nan.exr"
    write_exr(str(env), {"R": rgb, "G": rgb, "B": rgb}, envmap="latlong")
    assert "nan.exr" in _bad(tmp_path, "builtin:right", env, code=1)


def test_usage_errors(tmp_path, hand_file):
    _bad(tmp_path, hand_file, "builtin:sky", "--frame", "5", code=2)
    _bad(tmp_path, hand_file, "builtin:sky", "builtin:studio", code=2)        # no {env}
    _bad(tmp_path, hand_file, "builtin:sky", "--frames", "all", code=2)     # no {frame}
    assert "may only use {frame} and {env}" in _bad(
        tmp_path, hand_file, "builtin:sky", "--preview",
        str(tmp_path / "f_{frame:c}.png"), code=2)                     # a NUL byte: refused
    assert "give one of them" in _bad(tmp_path, hand_file, "builtin:sky", "--frame", "0",
                                      "--frames", "all", code=2)
    _bad(tmp_path, hand_file, "builtin:sky", "--shininess", "16,x", code=2)
    _bad(tmp_path, hand_file, "builtin:sky", "--shininess", "16,0", code=2)
    _bad(tmp_path, hand_file, "builtin:sky", "--roughness", "0", code=2)
    _bad(tmp_path, hand_file, "builtin:sky", "--eye", "1,2", code=2)
    _bad(tmp_path, "builtin:middle", "builtin:sky", code=2)
    assert "--env-res" in _bad(tmp_path, hand_file, "builtin:sky", "--env-res", "banana", code=2)
    # sizes are WxH (issue 16): the old HxW default 16x32 says what it should be
    assert "did you mean 32x16" in _bad(tmp_path, hand_file, "builtin:sky", "--env-res", "16x32",
                                        code=2)
    # one frame grammar (issue 48): --all-frames is --frames all, as in relight
    assert "--all-frames was renamed --frames all" in _bad(tmp_path, hand_file, "builtin:sky",
                                                           "--all-frames", code=2)
    assert "name it .png" in _bad(tmp_path, hand_file, "builtin:sky", "--preview",
                                  tmp_path / "sheet.jpg", code=2)
    assert "--env-sources" in _bad(tmp_path, hand_file, "builtin:sky", "--env-sources", "9x",
                                   code=2)
    assert "--ggx-shadowing" in _bad(tmp_path, hand_file, "builtin:sky", "--ggx-shadowing",
                                     "ue4", code=2)


def test_sources_and_lobe_options(tmp_path, hand_file):
    """--env-sources none integrates the sky's sun on the grid (another direction: other
    features); --ggx-shadowing schlick gives a darker ggx layer than the default Smith; both
    recorded in the provenance."""
    from relight_cli.formats.features_exr import read_features
    maps = {}
    for name, extra in (("auto", []), ("none", ["--env-sources", "none"]),
                        ("schlick", ["--ggx-shadowing", "schlick"])):
        out = tmp_path / f"{name}.exr"
        r = CliRunner().invoke(cli, ["bake-features", str(hand_file), "builtin:sky", "-o",
                                     str(out), "--specular", "ggx", "-q", *SMALL, *extra])
        assert r.exit_code == 0, r.output
        maps[name] = read_features(str(out))
    mask = maps["auto"].layers["mask"] > 0
    assert np.abs(maps["none"].layers["diffuse"] - maps["auto"].layers["diffuse"])[mask].max() > 1e-3
    assert maps["schlick"].layers["ggx"][mask].sum() < maps["auto"].layers["ggx"][mask].sum()
    settings = json.loads(maps["schlick"].attributes["relight.provenance"])["settings"]
    assert settings["ggx_shadowing"] == "schlick" and settings["env_sources"] == "auto"


def test_no_clobber(tmp_path):
    out = tmp_path / "o.exr"
    out.write_bytes(b"keep")
    r = invoke("bake-features", "builtin:right", "builtin:sky", "-o", out, "--no-clobber",
               *SMALL)
    assert r.exit_code == 2
    assert out.read_bytes() == b"keep"


def test_roughness_map_and_camera_match_scalar_and_eye(tmp_path):
    # A constant UV roughness map equals the scalar; a camera file equals --eye at its centre.
    from relight_cli.formats.camera import Camera, write_cameras
    from relight_cli.formats.exr import write_exr
    from relight_cli.formats.features_exr import read_features
    rough = tmp_path / "rough.exr"
    write_exr(str(rough), {"Y": np.full((8, 8), 0.3, np.float32)})
    cam = Camera.look_at([0.1, 0.3, 0.5], [0, 0.08, 0])
    cam_path = tmp_path / "cam.json"
    write_cameras(str(cam_path), [cam])
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    assert invoke("bake-features", "builtin:right", "builtin:studio", "-o", a, "--specular", "ggx",
                  "--roughness", rough, "--camera", cam_path, "-q", *SMALL).exit_code == 0
    eye = ",".join(repr(float(x)) for x in cam.center)
    assert invoke("bake-features", "builtin:right", "builtin:studio", "-o", b, "--specular", "ggx",
                  "--roughness", "0.3", "--eye", eye, "-q", *SMALL).exit_code == 0
    ga, gb = read_features(str(a)).layers["ggx"], read_features(str(b)).layers["ggx"]
    assert ga.max() > 0
    # float32 map value 0.3 vs float64 0.3: ~1e-8 relative difference in roughness.
    np.testing.assert_allclose(ga, gb, rtol=1e-5, atol=1e-7)
    bad = tmp_path / "badrough.exr"
    write_exr(str(bad), {"Y": np.full((8, 8), 1.5, np.float32)})
    assert "badrough.exr" in _bad(tmp_path, "builtin:right", "builtin:sky", "--specular", "ggx",
                                  "--roughness", bad, code=1)


def test_env_grid_is_the_one_place_width_and_height_meet():
    """``--env-res WxH`` → EnvGrid, the engine's (height, width) tuple; printed WxH again."""
    from relight_cli.envmap import EnvGrid
    from relight_cli.errors import UsageProblem
    from relight_cli.cli.inputs import env_grid
    grid = env_grid("32x16")
    assert isinstance(grid, EnvGrid) and tuple(grid) == (16, 32)
    assert (grid.width, grid.height) == (32, 16) and str(grid) == "32x16"
    assert EnvGrid.from_wh(64, 32) == (32, 64)
    with pytest.raises(UsageProblem, match="did you mean 32x16"):
        env_grid("16x32")
