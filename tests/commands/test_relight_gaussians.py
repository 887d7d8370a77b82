"""``relight relight`` on Gaussians (commands/relight_gaussians.py): relit PLYs, renders, hands as
Gaussians, the console script, bad input, DGSM shadows, light weights, direct light."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import run_relight
from relight_cli.formats.camera import Camera, write_cameras
from relight_cli.formats.gaussians_ply import (Gaussians, matrix_to_quaternion, read_gaussians,
                                               rgb_to_sh_dc, write_gaussians)
from relight_cli.formats.sh_probe_json import ShProbe, write_probe
from relight_cli.gaussians import transfer as TF
from relight_cli.sh import sh_basis


def sphere_of_splats(n=400, radius=0.5, seed=0, flat_axis=2):
    """Flat Gaussians tangent to a sphere (shortest axis = radial), random in-plane rotation."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # Rotation whose column `flat_axis` is the radial direction.
    helper = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(d, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(d, t1)
    cols = [t1, t2]
    cols.insert(flat_axis, d)
    R = np.stack(cols, axis=2)
    if np.linalg.det(R[0]) < 0:
        R[:, :, (flat_axis + 1) % 3] *= -1
    R = R * np.sign(np.linalg.det(R))[:, None, None]
    scales = np.full((n, 3), 0.03)
    scales[:, flat_axis] = 0.002
    rgb = rng.uniform(0.2, 0.9, (n, 3))
    return Gaussians(d * radius + [0.1, 1.0, -0.2], scales, matrix_to_quaternion(R),
                     np.full(n, 0.9), rgb_to_sh_dc(rgb)[:, None, :], 0), d


# ------------------------------------------------------------------ CLI


@pytest.fixture
def files(tmp_path):
    g, _ = sphere_of_splats(n=300)
    write_gaussians(str(tmp_path / "avatar.ply"), g)
    c = np.zeros((4, 3))
    c[0] = math.sqrt(4 * math.pi)
    c[1] = -0.5                                                   # −C1·y: brighter from above
    write_probe(str(tmp_path / "probe.json"), ShProbe(c, 1, 0.0, "test"))
    floor = Gaussians(np.column_stack([np.linspace(-1, 1, 50), np.zeros(50), np.zeros(50)]),
                      np.full((50, 3), 0.1), np.tile([1.0, 0, 0, 0], (50, 1)), np.full(50, 0.8),
                      np.zeros((50, 1, 3)), 0)
    write_gaussians(str(tmp_path / "scene.ply"), floor)
    write_cameras(str(tmp_path / "cam.json"),
                  [Camera.look_at([0.1, 1.0, 2.5], [0.1, 1.0, -0.2], width=40, height=30)])
    return tmp_path


def test_cli_help(run_cli):
    r = run_cli("relight", "--help")
    assert r.exit_code == 0 and "--probe" in r.output and "--dgsm" in r.output


def test_cli_relit_ply(run_cli, files):
    out = files / "relit.ply"
    r = run_cli("relight", files / "avatar.ply", "--probe", files / "probe.json", "-o", out, "-q")
    assert r.exit_code == 0, r.output
    relit, avatar = read_gaussians(str(out)), read_gaussians(str(files / "avatar.ply"))
    ratio = relit.colors() / avatar.colors()
    # Probe L = 1 + 0.5·C1·y (c_1,−1 = −0.5 on −C1·y) ⇒ S(n) = 1 + (2/3)·0.5·C1·n_y (q = 1);
    # float32 PLY storage of colours ~1e-6 relative.
    expected = 1 + (2 / 3) * 0.5 * math.sqrt(3 / (4 * math.pi)) * relit.normals[:, 1]
    np.testing.assert_allclose(ratio, expected[:, None].repeat(3, 1), rtol=1e-5)
    assert ratio[relit.normals[:, 1] > 0.5].min() > 1.05                 # lit from above
    assert relit.provenance["format"] == "relight/gaussians"
    assert set(relit.provenance["inputs"]) == {"input", "probe"}


def test_cli_render(run_cli, files):
    from relight_cli.formats.exr import read_exr
    out = files / "view.exr"
    r = run_cli("relight", files / "avatar.ply", "--probe", files / "probe.json", "--receivers",
                files / "scene.ply", "--camera", files / "cam.json", "-o", out, "--preview",
                files / "view.png", "-q")
    assert r.exit_code == 0, r.output
    img = read_exr(str(out))
    assert set(img.channels) == {"R", "G", "B", "A"} and img.width == 40 and img.height == 30
    assert img.channels["A"].max() > 0.9 and (files / "view.png").exists()


def test_cli_hand_npz_as_gaussians(run_cli, files):
    """With Gaussian options a hand.npz is its posed hand as Gaussians: relit, shadowed
    into a scene, and the mesh pseudo-GT matte (Sec. 4.2) reads the same posed mesh."""
    from relight_cli.formats.exr import read_exr
    hand = files / "hand.npz"
    assert run_cli("fit-geometry", "--pose", "fist", "-o", hand, "-q").exit_code == 0
    r = run_cli("relight", hand, "--probe", files / "probe.json", "-o", files / "hand.ply", "-q")
    assert r.exit_code == 0, r.output
    relit = read_gaussians(str(files / "hand.ply"))
    assert len(relit) > 1000 and relit.provenance["inputs"]["input"]["path"].endswith("hand.npz")
    write_cameras(str(files / "hcam.json"),
                  [Camera.look_at([0.0, 0.25, 0.45], [0, 0.03, 0], width=48, height=36)])
    lights = files / "lights.json"
    lights.write_text('{"format": "relight/lights", "version": 1, "lights": [{"position": '
                      '[0.1, 1.5, 0.2], "color": [1, 1, 1], "intensity": 5}]}')
    xs, zs = np.meshgrid(np.linspace(-0.3, 0.3, 40), np.linspace(-0.3, 0.3, 40))
    n = xs.size
    floor = Gaussians(np.column_stack([xs.ravel(), np.zeros(n), zs.ravel()]),
                      np.tile([0.012, 0.001, 0.012], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)),
                      np.full(n, 0.9), np.full((n, 1, 3), 1.0), 0)
    write_gaussians(str(files / "floor.ply"), floor)
    spec = f"{hand}:translate=0,0.1,0"
    assert run_cli("dgsm-build", spec, "--receivers", files / "floor.ply", "--lights", lights,
                   "--size", "64", "-o", files / "sh.exr", "-q").exit_code == 0
    mattes = {}
    for mode in ("dgsm", "mesh"):
        r = run_cli("relight", spec, "--shadow-matte", mode, "--dgsm", files / "sh.exr",
                    "--receivers", files / "floor.ply", "--camera", files / "hcam.json",
                    "-o", files / f"{mode}.exr", "-q")
        assert r.exit_code == 0, r.output
        mattes[mode] = read_exr(str(files / f"{mode}.exr")).channels["R"]
    assert mattes["mesh"].max() > 0.5                     # the hand does shadow the floor
    shadowed = mattes["mesh"] > 0.5
    assert np.abs(mattes["dgsm"] - mattes["mesh"]).mean() < 0.05
    assert np.abs(mattes["dgsm"] - mattes["mesh"])[shadowed].mean() < 0.2


def test_cli_subprocess(files):
    r = run_relight("relight", files / "avatar.ply", "--probe", files / "probe.json", "-o",
                    files / "relit2.ply", "--normals", "pca", "--lobe", "3", "--shading-clip", "2")
    assert r.returncode == 0, r.stderr
    assert len(read_gaussians(str(files / "relit2.ply"))) == 300


@pytest.mark.parametrize("args, code, message", [
    (["hand.npz"], 2, "give an env map ENV"),   # hand mode: lighting is required
    (["thing.xyz", "--probe", "probe.json"], 2, "IN must be a Gaussians .ply"),
    (["thing.obj", "--probe", "probe.json"], 1, "no such file"),   # meshes are Gaussian inputs
    (["hand.npz", "--object", "avatar.ply"], 2, "needs --probe"),   # a hand.npz as Gaussians
    (["avatar.ply:scale=0", "--probe", "probe.json"], 2, "scale must be > 0"),
    (["avatar.ply", "--object", "avatar.ply:spin=3", "--probe", "probe.json"], 2,
     "unknown placement key 'spin'"),
    (["avatar.ply"], 2, "needs --probe"),
    (["avatar.ply", "--probe", "probe.json", "--dgsm", "x.exr"], 2, "give --receivers"),
    (["avatar.ply", "--probe", "probe.json", "--lobe", "0"], 2, "--lobe"),
    (["avatar.ply", "--probe", "probe.json", "--camera", "cam.json"], 2, "-o is an EXR"),
    (["avatar.ply", "--probe", "missing.json"], 1, "no such file"),
    (["avatar.ply", "--probe", "bad_probe.json"], 1, "version 9 is newer"),
    (["avatar.ply", "--probe", "probe.json", "--normals", "stored"], 1, "no stored normals"),
    (["nan.ply", "--probe", "probe.json"], 1, "non-finite"),
    # renamed (issue 16): dgsm-build's --t-max is metres; relight's clip is --shading-clip
    (["avatar.ply", "--probe", "probe.json", "--t-max", "2"], 2, "--t-max was renamed "
                                                                 "--shading-clip"),
    (["avatar.ply", "--probe", "probe.json", "--preview", "view.exr", "--camera", "cam.json"],
     2, "name it .png"),
    # issue 52 cause 10: options that cannot apply are refused, even when given as their default
    (["avatar.ply", "--probe", "probe.json", "--shadow-strength", "0.5"], 2,
     "--shadow-strength only applies with --dgsm"),
    (["avatar.ply", "--probe", "probe.json", "--shadow-strength", "auto"], 2,
     "--shadow-strength only applies with --dgsm"),
    (["avatar.ply", "--probe", "probe.json", "--light-weights", "equal"], 2,
     "--light-weights only applies with --dgsm"),
    (["avatar.ply", "--receivers", "scene.ply", "--dgsm", "x.exr", "--camera", "cam.json",
      "--shadow-matte", "dgsm", "--direct-light"], 2, "--direct-light does not apply to "
                                                     "--shadow-matte"),
    (["avatar.ply", "--receivers", "scene.ply", "--dgsm", "x.exr", "--camera", "cam.json",
      "--shadow-matte", "mesh", "--shadow-strength", "1"], 2, "--shadow-strength does not "
                                                              "apply to --shadow-matte"),
])
def test_cli_bad_input(run_cli, files, monkeypatch, args, code, message):
    monkeypatch.chdir(files)
    (files / "bad_probe.json").write_text('{"format": "relight/sh-probe", "version": 9}')
    g, _ = sphere_of_splats(n=5)
    write_gaussians("nan.ply", g)
    import plyfile
    ply = plyfile.PlyData.read("nan.ply", mmap=False)
    ply["vertex"].data["x"][2] = np.nan
    ply.write("nan.ply")
    target = "out.exr" if "--camera" in args and "-o is an EXR" not in message else "out.ply"
    r = run_cli("relight", *args, "-o", target)
    assert r.exit_code == code, r.output
    assert message in r.output, r.output
    assert not (files / "out.ply").exists() and not (files / "out.exr").exists()


def _ball_over_floor(tmp_path, lights, grid, intensities=None):
    """An opaque ball of Gaussians at 1 m over a grey floor grid (nx, nz, half-width in x);
    writes ball.ply, floor.ply, a uniform probe p.json and the DGSM s.exr for ``lights``."""
    from relight_cli.formats import dgsm_exr
    from relight_cli.gaussians.dgsm import build_dgsm
    from relight_cli.provenance import provenance
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ball = Gaussians(d * 0.15 + [0, 1.0, 0], np.full((400, 3), 0.05), np.tile([1.0, 0, 0, 0], (400, 1)),
                     np.full(400, 0.95), np.zeros((400, 1, 3)), 0)
    nx, nz, half = grid
    xs, zs = np.meshgrid(np.linspace(-half, half, nx), np.linspace(-1, 1, nz))
    m = xs.size
    floor = Gaussians(np.column_stack([xs.ravel(), np.zeros(m), zs.ravel()]),
                      np.tile([0.05, 0.002, 0.05], (m, 1)),           # flat splats, normal ±y
                      np.tile([1.0, 0, 0, 0], (m, 1)), np.full(m, 0.9),
                      rgb_to_sh_dc(np.full((m, 3), 0.6))[:, None, :], 0)
    shadow = build_dgsm(ball, np.asarray(lights, float), floor.means, size=(32, 32), bins=16,
                        intensities=intensities)
    dgsm_exr.write_dgsm(str(tmp_path / "s.exr"), shadow, provenance(dgsm_exr.FORMAT, dgsm_exr.VERSION))
    write_gaussians(str(tmp_path / "ball.ply"), ball)
    write_gaussians(str(tmp_path / "floor.ply"), floor)
    c = np.zeros((1, 3))
    c[0] = math.sqrt(4 * math.pi)
    write_probe(str(tmp_path / "p.json"), ShProbe(c, 0))
    return shadow, floor


def test_cli_dgsm_shadows_receivers(run_cli, tmp_path):
    """An opaque ball between a point light and a floor: receivers under it darken by the DGSM's
    transmittance (equal to the engine's footprint lookup), receivers away from it do not."""
    dgsm_exr = pytest.importorskip("relight_cli.formats.dgsm_exr",
                                   reason="formats/dgsm_exr.py (DGSM format) not in this tree")
    from relight_cli.gaussians.dgsm import sample_transmittance
    shadow, floor = _ball_over_floor(tmp_path, [[0.0, 2.5, 0.0]], (15, 15, 1.0))
    r = run_cli("relight", tmp_path / "ball.ply", "--probe", tmp_path / "p.json", "--dgsm",
                tmp_path / "s.exr", "--receivers", tmp_path / "floor.ply", "--receivers-out",
                tmp_path / "floor-shadowed.ply", "--footprint", "centre", "--shadow-strength", "1",
                "-o", tmp_path / "o.ply", "-q")
    assert r.exit_code == 0, r.output
    out = read_gaussians(str(tmp_path / "floor-shadowed.ply"))
    ratio = out.colors()[:, 0] / floor.colors()[:, 0]
    T = sample_transmittance(shadow, floor.means, footprint="centre")[0]
    np.testing.assert_allclose(ratio, T, atol=1e-5)   # float32 table and PLY storage
    centre = np.argmin(np.linalg.norm(floor.means, axis=1))
    corner = np.argmax(np.linalg.norm(floor.means, axis=1))
    assert ratio[centre] < 0.2 and ratio[corner] > 0.999
    prov = read_gaussians(str(tmp_path / "floor-shadowed.ply")).provenance
    settings = (prov or {}).get("settings", {})
    if settings:
        assert settings["dgsm_mapping"] == "avg" and settings["light_weights"] == "intensity"


def test_cli_dgsm_weights_lights_by_intensity(run_cli, tmp_path):
    """Two lights, each casting the ball's shadow on a different spot: the spot of the light of
    intensity 3 darkens to (3·T + 1)/4, the one of intensity 1 to (3 + T)/4 (white lights)."""
    dgsm_exr = pytest.importorskip("relight_cli.formats.dgsm_exr")
    from relight_cli.gaussians.dgsm import sample_transmittance
    shadow, floor = _ball_over_floor(tmp_path, [[-0.5, 2.0, 0.0], [0.5, 2.0, 0.0]], (21, 9, 1.5),
                                     intensities=[3.0, 1.0])
    T = sample_transmittance(shadow, floor.means, footprint="centre")           # [2, M]
    for mode, want in (("intensity", (3 * T[0] + T[1]) / 4), ("equal", T.mean(axis=0))):
        r = run_cli("relight", tmp_path / "ball.ply", "--probe", tmp_path / "p.json", "--dgsm",
                    tmp_path / "s.exr", "--receivers", tmp_path / "floor.ply", "--receivers-out",
                    tmp_path / f"f-{mode}.ply", "--footprint", "centre", "--light-weights", mode,
                    "--shadow-strength", "1", "-o", tmp_path / "o.ply", "-q")
        assert r.exit_code == 0, r.output
        ratio = read_gaussians(str(tmp_path / f"f-{mode}.ply")).colors() / floor.colors()
        np.testing.assert_allclose(ratio, np.repeat(want[:, None], 3, axis=1), atol=1e-5)
    assert T.min(axis=1).max() < 0.2          # both lights really cast a shadow on the floor


def test_auto_strength_is_the_lights_share_against_the_probe(run_cli, tmp_path):
    """--shadow-strength auto (the default): a receiver's shadow takes away the lights' share
    of its light, E_d/(E_d + E_probe), E_d = I cosθ/r² of the light, E_probe = π·L for a
    uniform probe of radiance L (= 1 here): closed form against the CLI's receivers."""
    pytest.importorskip("relight_cli.formats.dgsm_exr")
    from relight_cli.gaussians.dgsm import sample_transmittance
    light = np.array([0.0, 2.5, 0.0])
    shadow, floor = _ball_over_floor(tmp_path, [light], (15, 15, 1.0), intensities=[25.0])
    r = run_cli("relight", tmp_path / "ball.ply", "--probe", tmp_path / "p.json", "--dgsm",
                tmp_path / "s.exr", "--receivers", tmp_path / "floor.ply", "--receivers-out",
                tmp_path / "f.ply", "--footprint", "centre", "-o", tmp_path / "o.ply", "-q")
    assert r.exit_code == 0, r.output
    ratio = read_gaussians(str(tmp_path / "f.ply")).colors()[:, 0] / floor.colors()[:, 0]
    v = light - floor.means
    r2 = (v * v).sum(axis=1)
    e_direct = 25.0 * (v[:, 1] / np.sqrt(r2)) / r2         # floor normal +y, towards the light
    s = e_direct / (e_direct + math.pi)
    T = sample_transmittance(shadow, floor.means, footprint="centre")[0]
    np.testing.assert_allclose(ratio, 1 - s * (1 - T), atol=1e-5)
    centre = np.argmin(np.linalg.norm(floor.means, axis=1))
    assert T[centre] < 0.05 and 0.3 < ratio[centre] < 0.6      # grey, not black: the probe's light
    settings = read_gaussians(str(tmp_path / "f.ply")).provenance["settings"]
    assert settings["shadow_strength"] == "auto" and settings["light_weights"] == "irradiance"


def test_cli_direct_light_lights_objects_one_sided(run_cli, tmp_path):
    """--direct-light: an object's colour is its albedo × (probe shading + Σ I max(n·ω, 0)/(π r²))
    (normals stored, radial): the side facing the light brightens, the far side keeps the probe's."""
    pytest.importorskip("relight_cli.formats.dgsm_exr")
    light = np.array([0.0, 2.5, 0.0])
    _ball_over_floor(tmp_path, [light], (5, 5, 1.0), intensities=[4.0])
    rng = np.random.default_rng(1)
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    obj = Gaussians(d * 0.1 + [0.5, 0.3, 0.0], np.tile([0.02, 0.02, 0.002], (300, 1)),
                    np.tile([1.0, 0, 0, 0], (300, 1)), np.full(300, 0.9),
                    rgb_to_sh_dc(np.full((300, 3), 0.4))[:, None, :], 0, d.copy())
    write_gaussians(str(tmp_path / "obj.ply"), obj)
    r = run_cli("relight", tmp_path / "obj.ply", "--probe", tmp_path / "p.json", "--dgsm",
                tmp_path / "s.exr", "--receivers", tmp_path / "floor.ply", "--direct-light",
                "-o", tmp_path / "o.ply", "-q")
    assert r.exit_code == 0, r.output
    got = read_gaussians(str(tmp_path / "o.ply")).colors()[:, 0]
    v = light - obj.means
    dist = np.linalg.norm(v, axis=1)
    cos = np.maximum((v * d).sum(axis=1) / dist, 0)
    np.testing.assert_allclose(got, 0.4 * (1.0 + 4.0 * cos / (math.pi * dist ** 2)), rtol=1e-5)
    r = run_cli("relight", tmp_path / "obj.ply", "--probe", tmp_path / "p.json",
                "--direct-light", "-o", tmp_path / "x.ply", "-q")
    assert r.exit_code == 2 and "--direct-light takes its lights from --dgsm" in r.output
    r = run_cli("relight", tmp_path / "obj.ply", "--probe", tmp_path / "p.json",
                "--shadow-strength", "most", "-o", tmp_path / "x.ply", "-q")
    assert r.exit_code == 2 and "--shadow-strength" in r.output


def test_cli_dgsm_version1_file_weights_lights_equally(run_cli, tmp_path):
    """A version 1 shadow map (no intensities, mapping 'eq5') still relights: equal weights, said."""
    from relight_cli.formats.exr import read_exr, write_exr
    from relight_cli.gaussians.dgsm import sample_transmittance
    from relight_cli.provenance import provenance
    shadow, floor = _ball_over_floor(tmp_path, [[-0.5, 2.0, 0.0], [0.5, 2.0, 0.0]], (21, 9, 1.5),
                                     intensities=[3.0, 1.0])
    img = read_exr(str(tmp_path / "s.exr"))
    attrs = {k: v for k, v in img.attributes.items() if k.startswith("relight.dgsm.")
             and k not in ("relight.dgsm.light_intensities", "relight.dgsm.light_colors")}
    attrs["relight.dgsm.mapping"] = "eq5"
    write_exr(str(tmp_path / "v1.exr"), dict(img.channels), attributes=attrs,
              provenance=provenance("relight/dgsm", 1))
    r = run_cli("relight", tmp_path / "ball.ply", "--probe", tmp_path / "p.json", "--dgsm",
                tmp_path / "v1.exr", "--receivers", tmp_path / "floor.ply", "--receivers-out",
                tmp_path / "f.ply", "--footprint", "centre", "-o", tmp_path / "o.ply")
    assert r.exit_code == 0, r.output
    assert "version 1" in r.output and "equally" in r.output
    out = read_gaussians(str(tmp_path / "f.ply"))
    T = sample_transmittance(shadow, floor.means, footprint="centre")
    np.testing.assert_allclose(out.colors()[:, 0] / floor.colors()[:, 0], T.mean(axis=0), atol=1e-5)
    assert out.provenance["settings"]["dgsm_mapping"] == "peak"
    assert out.provenance["settings"]["light_weights"] == "equal"


def test_real_robot_view_dependence_survives_placement_and_relighting(shared):
    """The real SH-degree-2 robot: placement (rotate-x=180, as captured it is upside down)
    rotates its view-dependent bands, c'(d) = c(Qᵀd), and relighting by a uniform probe of
    radiance 2 doubles its colour from every view direction (bands scaled with the DC)."""
    from relight_cli.gaussians.placement import axis_rotation, parse_placement, place
    robot = read_gaussians(str(shared("gaussians", "playbot-lod3.ply")))
    assert robot.sh_degree == 2
    rng = np.random.default_rng(0)
    sub = robot.subset(rng.choice(len(robot), 400, replace=False))
    sub = sub.subset(np.flatnonzero(sub.colors(clamp=False).min(axis=1) > 0))  # DC unclamped
    placed = place(sub, parse_placement("rotate-x=180;translate=0.5,0,0"))
    Q = axis_rotation("x", 180)
    d = rng.normal(size=(len(sub), 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)

    def colour(g, dirs):           # 3DGS colour before the clamp, seen along dirs
        return 0.5 + np.einsum("nk,nkc->nc", sh_basis(dirs, g.sh_degree), g.sh)

    view_dependent = np.abs(colour(sub, d) - colour(sub, -d)).max()
    assert view_dependent > 0.05                       # the bands really carry something
    np.testing.assert_allclose(colour(placed, d), colour(sub, d @ Q), atol=1e-9)
    c = np.zeros((9, 3))
    c[0] = 2.0 * math.sqrt(4 * math.pi)                 # uniform radiance 2 → factor 2
    relit = TF.relight_gaussians(placed, c)
    np.testing.assert_allclose(colour(relit, d), 2 * colour(placed, d), atol=1e-9)


def test_cli_info_lines_of_a_failing_run_are_not_said(run_cli, files, monkeypatch):
    """Without -q, a run refused after it has read some inputs says only its one error line:
    the ``read …`` lines of the inputs read before the bad one are held until the run's
    inputs pass (issue 52: here the camera, read after the Gaussians).  A run that succeeds
    says them as before, first, and its ``wrote`` line last."""
    monkeypatch.chdir(files)
    (files / "bad_cam.json").write_text("{")
    r = run_cli("relight", "avatar.ply", "--probe", "probe.json", "--camera", "bad_cam.json",
                "-o", "out.exr")
    assert r.exit_code == 1, r.output
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("relight relight: error: "), r.output
    assert lines[0].endswith("(bad_cam.json)") and not (files / "out.exr").exists()
    r = run_cli("relight", "avatar.ply", "--probe", "probe.json", "-o", "out.ply")
    assert r.exit_code == 0, r.output
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert lines[0] == "read avatar.ply: 300 Gaussians", r.output
    assert lines[-1].startswith("wrote out.ply"), r.output


def test_cli_colour_space(run_cli, files):
    """A 3DGS PLY from another tool is sRGB: relit under a uniform probe of radiance 1 its
    colours come out decoded (the EOTF of the stored colour), as stored with --colour-space
    linear; the relit PLY says it is linear, its provenance records the option, and a PLY
    this tool wrote reads back linear (no second decode)."""
    from conftest import as_foreign_ply
    from relight_cli.formats.gaussians_ply import srgb_eotf
    c = np.zeros((1, 3))
    c[0] = math.sqrt(4 * math.pi)
    write_probe(str(files / "one.json"), ShProbe(c, 0, 0.0, "test"))
    as_foreign_ply(files / "avatar.ply")
    stored = read_gaussians(str(files / "avatar.ply"), colour_space="linear").colors()
    outs = {}
    for space in ("auto", "srgb", "linear"):
        out = files / f"relit-{space}.ply"
        r = run_cli("relight", files / "avatar.ply", "--probe", files / "one.json",
                    "--colour-space", space, "-o", out, "-q")
        assert r.exit_code == 0, r.output
        outs[space] = read_gaussians(str(out))
        assert outs[space].source_colour_space == "linear"
        assert outs[space].provenance["settings"]["colour_space"] == space
        assert b"relight.colour-space linear" in out.read_bytes()[:4000]
    np.testing.assert_allclose(outs["auto"].colors(), srgb_eotf(stored), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(outs["srgb"].colors(), outs["auto"].colors(), rtol=0, atol=0)
    np.testing.assert_allclose(outs["linear"].colors(), stored, rtol=1e-5, atol=1e-7)
    # relighting our own output again (auto): read as linear, the colours stay
    again = files / "again.ply"
    assert run_cli("relight", files / "relit-auto.ply", "--probe", files / "one.json", "-o",
                   again, "-q").exit_code == 0
    np.testing.assert_allclose(read_gaussians(str(again)).colors(), outs["auto"].colors(),
                               rtol=1e-5, atol=1e-7)
    r = run_cli("relight", files / "avatar.ply", "--probe", files / "one.json",
                "--colour-space", "rgb", "-o", files / "bad.ply", "-q")
    assert r.exit_code == 2 and "rgb" in r.output and not (files / "bad.ply").exists()


def test_cli_colour_space_render_of_real_file(run_cli, tmp_path, shared):
    """The real donut (a 3DGS training output) renders darker in its mid tones decoded
    (auto) than read as linear: the EXR is linear radiance."""
    from relight_cli.formats.exr import read_exr
    donut = shared("gaussians", "donut-fused.ply")
    c = np.zeros((1, 3))
    c[0] = math.sqrt(4 * math.pi)
    write_probe(str(tmp_path / "one.json"), ShProbe(c, 0, 0.0, "test"))
    g = read_gaussians(str(donut))
    centre = np.median(g.means, axis=0)
    write_cameras(str(tmp_path / "cam.json"),
                  [Camera.look_at(centre + [0, 0.15, 0.35], centre, width=48, height=36)])
    means = {}
    for space in ("auto", "linear"):
        out = tmp_path / f"{space}.exr"
        r = run_cli("relight", donut, "--probe", tmp_path / "one.json", "--receivers", donut,
                    "--camera", tmp_path / "cam.json", "--colour-space", space, "-o", out, "-q")
        assert r.exit_code == 0, r.output
        img = read_exr(str(out))
        assert img.provenance()["settings"]["colour_space"] == space
        rgb = np.stack([img.channels[k] for k in "RGB"], -1)
        assert np.isfinite(rgb).all()
        means[space] = rgb[img.channels["A"] > 0.5].mean()
    assert means["auto"] < 0.8 * means["linear"], means


# ------------------------------------------------------------------ relight in place (issue 53)


def _vertex(path):
    """The PLY's raw vertex record (the bytes as stored)."""
    import plyfile
    return plyfile.PlyData.read(str(path), mmap=False)["vertex"].data


#: Stored byte for byte through relighting.  Rotations are written normalized (1 float32 ulp
#: from an input's) and opacity logits re-derived (extreme logits clamped) by the PLY writer
#: itself, with or without relighting: _same_geometry checks those to float32.
GEOMETRY = ("x", "y", "z", "scale_0", "scale_1", "scale_2")


def _same_geometry(path, source_path):
    stored, source = _vertex(path), _vertex(source_path)
    for name in GEOMETRY:
        assert stored[name].tobytes() == source[name].tobytes(), (path, name)
    a, b = read_gaussians(str(path)), read_gaussians(str(source_path))
    np.testing.assert_allclose(a.rotations, b.rotations, atol=1.2e-7)
    np.testing.assert_allclose(a.opacities, b.opacities, atol=1e-7)


@pytest.fixture
def sh_files(tmp_path):
    """A small avatar with view-dependent SH (degree 2) off the origin, and a degree-2 probe
    lit unevenly from every side (all bands non-zero, radiance positive)."""
    g, _ = sphere_of_splats(n=120, seed=3)
    rng = np.random.default_rng(7)
    sh = np.concatenate([g.sh, rng.normal(0, 0.05, (len(g), 8, 3))], axis=1)
    g = Gaussians(g.means, g.scales, g.rotations, g.opacities, sh, 2)
    write_gaussians(str(tmp_path / "avatar.ply"), g)
    c = rng.normal(0, 0.15, (9, 3))
    c[0] = math.sqrt(4 * math.pi)
    c[2] = [0.6, 0.5, 0.4]                                        # brighter towards +z
    write_probe(str(tmp_path / "probe.json"), ShProbe(c, 2, 0.0, "test"))
    return tmp_path


def test_up_minus_y_turns_the_light_as_flipping_the_data_and_back(run_cli, sh_files):
    """--up -y (the lighting turned into a +Y-down frame) equals placing the avatar upright
    (rotate-x=180), relighting it there and writing it back in its own frame: the same
    colours and view-dependent bands, and the geometry of the input byte for byte."""
    f = sh_files
    assert run_cli("relight", f / "avatar.ply", "--probe", f / "probe.json", "--up", "-y",
                   "-o", f / "up.ply", "-q").exit_code == 0
    r = run_cli("relight", f"{f / 'avatar.ply'}:rotate-x=180", "--probe", f / "probe.json",
                "-o", f / "flipped.ply", "-q")
    assert r.exit_code == 0, r.output
    up, flipped = read_gaussians(str(f / "up.ply")), read_gaussians(str(f / "flipped.ply"))
    # two float64 routes to the same numbers (lstsq SH rotation blocks, cos 180° = -1 + 0 ·
    # 1e-16): equal to a few float32 ulps of the stored values
    np.testing.assert_allclose(up.sh, flipped.sh, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(up.normals, flipped.normals, atol=1e-6)
    for path in ("up.ply", "flipped.ply"):
        _same_geometry(f / path, f / "avatar.ply")
    assert read_gaussians(str(f / "flipped.ply")).provenance["settings"]["coordinates"] == "source"
    # and the light really turned: the flip of the probe is not the probe
    assert run_cli("relight", f / "avatar.ply", "--probe", f / "probe.json", "-o",
                   f / "plain.ply", "-q").exit_code == 0
    assert np.abs(read_gaussians(str(f / "plain.ply")).sh - up.sh).max() > 0.01


@pytest.mark.parametrize("up, axis, sign", [("-y", 1, -1), ("0,-2,0", 1, -1), ("+z", 2, 1),
                                             ("-x", 0, -1), ("0,0,5", 2, 1)])
def test_up_known_answer(run_cli, files, up, axis, sign):
    """Probe L = 1 + 0.5·C1·y (brighter from world +Y).  In a capture whose up is ``up`` the
    sky is along that axis: S(n) = 1 + sign·(2/3)·0.5·C1·n_axis (test_cli_relit_ply's answer
    with y replaced by the capture's up)."""
    out = files / "relit-up.ply"
    r = run_cli("relight", files / "avatar.ply", "--probe", files / "probe.json", "--up", up,
                "-o", out, "-q")
    assert r.exit_code == 0, r.output
    relit, avatar = read_gaussians(str(out)), read_gaussians(str(files / "avatar.ply"))
    expected = 1 + sign * (2 / 3) * 0.5 * math.sqrt(3 / (4 * math.pi)) * relit.normals[:, axis]
    np.testing.assert_allclose(relit.colors() / avatar.colors(),
                               expected[:, None].repeat(3, 1), rtol=1e-5)
    assert relit.provenance["settings"]["up"] == up


def test_relit_ply_keeps_the_inputs_positions(run_cli, sh_files):
    """A placed IN (fit, tilted rotations, translate) is relit in the scene but written back
    in its own frame: every geometry field byte-equal to the input's; --coordinates scene
    keeps the placed positions (placement.place's, to float32)."""
    from relight_cli.gaussians.placement import parse_placement, place
    f = sh_files
    placement = "fit=0.3;rotate-z=33;rotate-x=-71;translate=0.4,1.1,-2"
    spec = f"{f / 'avatar.ply'}:{placement}"
    assert run_cli("relight", spec, "--probe", f / "probe.json", "-o", f / "source.ply",
                   "-q").exit_code == 0
    assert run_cli("relight", spec, "--probe", f / "probe.json", "--coordinates", "scene",
                   "-o", f / "scene.ply", "-q").exit_code == 0
    _same_geometry(f / "source.ply", f / "avatar.ply")
    placed = place(read_gaussians(str(f / "avatar.ply")), parse_placement(placement))
    scene = read_gaussians(str(f / "scene.ply"))
    np.testing.assert_allclose(scene.means, placed.means, atol=1e-6)
    assert np.abs(scene.means - read_gaussians(str(f / "avatar.ply")).means).max() > 0.3
    # colour is the scene's relighting: the same shading factor in both frames (DC band)
    np.testing.assert_allclose(read_gaussians(str(f / "source.ply")).colors(), scene.colors(),
                               rtol=1e-5, atol=1e-7)
    # a crop (the source's frame) with the placement: the kept Gaussians, in place, byte
    # for byte (the crop box keeps the avatar's upper half: y > 1.0)
    crop = "crop=-9,1.0,-9,9,9,9;" + placement
    assert run_cli("relight", f"{f / 'avatar.ply'}:{crop}", "--probe", f / "probe.json",
                   "-o", f / "cropped.ply", "-q").exit_code == 0
    kept = _vertex(f / "avatar.ply")["y"] >= 1.0
    assert 0 < kept.sum() < len(kept)
    cropped = _vertex(f / "cropped.ply")
    for name in GEOMETRY:
        assert cropped[name].tobytes() == _vertex(f / "avatar.ply")[name][kept].tobytes(), name


def test_env_probe_equals_sh_probe_then_probe(run_cli, files):
    """relight AVATAR ENV fits the probe as sh-probe ENV --degree L does (L = 2 for the
    Lambertian lobe, 3 for --lobe 3): the relit colours equal sh-probe + --probe exactly."""
    for lobe, degree in (("1", 2), ("3", 3)):
        assert run_cli("sh-probe", "builtin:sky", "--degree", str(degree), "-o",
                       files / f"sky{degree}.json", "-q").exit_code == 0
        via_probe, via_env = files / f"p{degree}.ply", files / f"e{degree}.ply"
        assert run_cli("relight", files / "avatar.ply", "--probe", files / f"sky{degree}.json",
                       "--lobe", lobe, "--up", "+z", "-o", via_probe, "-q").exit_code == 0
        r = run_cli("relight", files / "avatar.ply", "builtin:sky", "--lobe", lobe, "--up", "+z",
                    "-o", via_env)
        assert r.exit_code == 0, r.output
        assert f"SH probe at degree {degree}" in r.output
        a, b = read_gaussians(str(via_probe)), read_gaussians(str(via_env))
        assert np.array_equal(a.sh, b.sh) and np.array_equal(a.normals, b.normals)
        assert b.provenance["settings"]["env_probe_degree"] == degree
        assert set(b.provenance["inputs"]) == {"input", "env"}


def test_transfer_degree_against_a_numerical_projection():
    """transfer_degree: the smallest L whose bands hold 99 % of the unit-mass lobe
    max(μ,0)^q's SH energy Σ (2l+1) a_l², the a_l found here by Gauss–Legendre quadrature
    of the Legendre projection (not the recurrence the engine uses)."""
    from numpy.polynomial import legendre
    from relight_cli.jobs.relight_gaussians import transfer_degree
    mu, w = legendre.leggauss(400)
    x, wx = (mu + 1) / 2, w / 2                                # nodes on [0, 1]
    for q in (1.0, 2.0, 3.0, 5.0, 10.0):
        a = np.array([(wx * x ** q * legendre.legval(x, np.eye(121)[l])).sum() * (q + 1)
                      for l in range(121)])
        held = np.cumsum((2 * np.arange(121) + 1) * a ** 2)
        held /= held[-1]
        assert transfer_degree(q) == min(int(np.argmax(held >= 0.99)), 8), q
    assert transfer_degree(1.0) == 2 and transfer_degree(50.0) == 8


def test_upright_rotation_takes_up_to_plus_y():
    """Each axis name and any vector: a proper rotation with U·up = +Y; the names agree
    with the minimal rotation of their vectors, and -y is rotate-x=180's flip."""
    from relight_cli.gaussians.placement import axis_rotation
    from relight_cli.jobs.relight_gaussians import UP_AXES, upright_rotation
    rng = np.random.default_rng(1)
    ups = [rng.normal(size=3) for _ in range(20)] + [np.array([1e-9, -1.0, 0.0])]
    for name in UP_AXES:
        axis = np.zeros(3)
        axis["xyz".index(name[1])] = 1.0 if name[0] == "+" else -1.0
        ups.append(axis)
        U = upright_rotation(name)
        np.testing.assert_array_equal(U @ axis, [0.0, 1.0, 0.0])
        np.testing.assert_allclose(upright_rotation(axis * 3), U, atol=1e-15)
    for up in ups:
        U = upright_rotation(up)
        np.testing.assert_allclose(U @ U.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(U) > 0
        np.testing.assert_allclose(U @ (up / np.linalg.norm(up)), [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(upright_rotation("-y"), axis_rotation("x", 180), atol=1e-15)
    for bad in ("up", "+w", (0, 0, 0), (np.nan, 1, 0)):
        with pytest.raises(ValueError):
            upright_rotation(bad)


@pytest.mark.parametrize("args, code, message", [
    (["avatar.ply", "builtin:sky", "--probe", "probe.json"], 2, "give the light once"),
    (["avatar.ply", "builtin:sky", "--receivers", "scene.ply", "--dgsm", "x.exr", "--camera",
      "cam.json", "--shadow-matte", "dgsm"], 2, "does not apply to --shadow-matte"),
    (["avatar.ply", "builtin:sky", "--frames", "all"], 2,
     "fit ENV's probe once with relight sh-probe builtin:sky -o probe.json"),
    (["avatar.ply", "builtin:sky", "--up", "-y", "--frame", "0"], 2, "fit ENV's probe once"),
    (["avatar.ply", "--probe", "probe.json", "--up", "-y", "--frames", "all"], 2,
     "place IN upright instead"),
    (["avatar.ply", "builtin:sky", "--up", "down"], 2, "--up: up must be one of"),
    (["avatar.ply", "builtin:sky", "--up", "0,0,0"], 2, "finite non-zero vector"),
    (["avatar.ply", "builtin:sky", "--up", "1,2"], 2, "--up must be 3"),
    (["avatar.ply", "builtin:sky", "--coordinates", "source", "--object", "avatar.ply"], 2,
     "--coordinates source writes IN back"),
    (["avatar.ply", "builtin:sky", "--coordinates", "scene", "--camera", "cam.json"], 2,
     "drop --coordinates"),
    (["avatar.ply", "missing.hdr"], 1, "no such file"),
    (["avatar.ply", "bad.exr"], 1, "bad.exr"),
])
def test_cli_env_and_up_bad_input(run_cli, files, monkeypatch, args, code, message):
    monkeypatch.chdir(files)
    (files / "bad.exr").write_bytes(b"not an exr")
    target = "out.exr" if "--camera" in args else "out.ply"
    r = run_cli("relight", *args, "-o", target)
    assert r.exit_code == code, r.output
    assert message in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1, r.output
    assert not (files / "out.ply").exists() and not (files / "out.exr").exists()


def test_real_colmap_capture_relit_where_it_stands(shared, tmp_path):
    """A real +Y-down 3DGS capture (statue-massa, COLMAP's frame) under builtin:sky with
    --up -y, through the console script: the sky lights what faces the capture's up (−y)
    several times more than what faces down (1.05 against 0.16 under forest_slope; without
    --up it is the other way round), and every position is the input's, byte for byte."""
    statue = shared("gaussians", "statue-massa.ply")
    out = tmp_path / "up.ply"
    r = run_relight("relight", statue, "builtin:sky", "--up", "-y", "-o", out, "-q")
    assert r.returncode == 0, r.stderr
    relit, source = read_gaussians(str(out)), read_gaussians(str(statue))
    lit = source.colors().mean(axis=1) > 0.05
    factor = relit.colors().mean(axis=1)[lit] / source.colors().mean(axis=1)[lit]
    n_y = relit.normals[lit, 1]
    assert np.median(factor[n_y < -0.5]) > 2 * np.median(factor[n_y > 0.5])   # the top is lit
    for field in "xyz":
        assert _vertex(out)[field].tobytes() == _vertex(statue)[field].tobytes()


def test_in_source_frame_undoes_the_placement():
    """jobs.relight_gaussians.in_source_frame: with the source's count, the source's own
    geometry arrays and the SH bands / normals turned back by Qᵀ; with another count (a
    library caller's subset) the inverse similarity, to round-off."""
    from relight_cli.gaussians.placement import parse_placement, place, resolve
    from relight_cli.jobs.relight_gaussians import in_source_frame
    g, _ = sphere_of_splats(n=60, seed=5)
    rng = np.random.default_rng(2)
    sh = np.concatenate([g.sh, rng.normal(0, 0.1, (len(g), 3, 3))], axis=1)
    g = Gaussians(g.means, g.scales, g.rotations, g.opacities, sh, 1, rng.normal(size=(60, 3)))
    placement = parse_placement("scale=2;rotate-y=40;rotate-x=-25;translate=1,2,3")
    similarity, placed = resolve(placement, g), place(g, placement)
    back = in_source_frame(placed, g, similarity)
    assert np.array_equal(back.means, g.means) and np.array_equal(back.rotations, g.rotations)
    np.testing.assert_allclose(back.sh, g.sh, atol=1e-12)
    np.testing.assert_allclose(back.normals, g.normals, atol=1e-12)
    keep = np.arange(0, 60, 3)
    subset = in_source_frame(placed.subset(keep), g, similarity)
    np.testing.assert_allclose(subset.means, g.means[keep], atol=1e-12)
    np.testing.assert_allclose(subset.scales, g.scales[keep], rtol=1e-12)
    np.testing.assert_allclose(subset.sh, g.sh[keep], atol=1e-12)
