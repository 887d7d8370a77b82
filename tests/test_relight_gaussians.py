"""Per-Gaussian SH radiance transfer (Eq. 9–10), normals, shadow attenuation and `relight relight`."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import eval_legendre
from scipy.spatial.transform import Rotation

from conftest import run_relight
from relight_cli import envmap as E
from relight_cli.formats.camera import Camera, write_cameras
from relight_cli.formats.envmap import EnvMap
from relight_cli.formats.gaussians_ply import (Gaussians, matrix_to_quaternion, read_gaussians,
                                               rgb_to_sh_dc, write_gaussians)
from relight_cli.formats.sh_probe_json import ShProbe, write_probe
from relight_cli.gaussians import probe as P
from relight_cli.gaussians import transfer as TF
from relight_cli.sh import lambert_band_factors, sh_basis


@pytest.mark.parametrize("q", [0.5, 1.0, 2.0, 7.3])
def test_lobe_moments_vs_quadrature(q):
    m = TF.lobe_moments(q, 8)
    ref = [quad(lambda x, l=l: x ** q * eval_legendre(l, x), 0, 1, epsabs=1e-14, limit=200)[0]
           for l in range(9)]
    np.testing.assert_allclose(m, ref, atol=1e-11)   # adaptive quadrature of a polynomial×|x|^q


def test_lambert_case_matches_irradiance_factors():
    np.testing.assert_allclose(TF.lobe_band_factors(1.0, 8) * math.pi, lambert_band_factors(8),
                               atol=1e-15)


@pytest.mark.parametrize("q", [1.0, 4.5])
def test_shading_vs_sphere_quadrature(q):
    rng = np.random.default_rng(1)
    c = rng.normal(size=(16, 3))
    normals = Rotation.random(6, random_state=2).apply([0, 0, 1.0])
    fast = TF.shading(c, normals, q)
    slow = TF.shading_reference(lambda d: sh_basis(d, 3) @ c, normals, q)
    # 200k-point Fibonacci quadrature of a smooth integrand with a kink at n·ω = 0: ~1e-6.
    np.testing.assert_allclose(fast, slow, atol=2e-5)


def test_uniform_probe_shading_is_its_radiance():
    c = np.zeros((9, 3))
    c[0] = np.array([0.5, 1.0, 2.0]) * math.sqrt(4 * math.pi)   # L(ω) = (0.5, 1, 2) everywhere
    normals = Rotation.random(10, random_state=0).apply([0, 1.0, 0])
    for q in (0.7, 1.0, 12.0):
        np.testing.assert_allclose(TF.shading(c, normals, q), np.tile([0.5, 1.0, 2.0], (10, 1)),
                                   atol=1e-14)


def test_linear_env_closed_form_through_probe():
    """L(ω) = a + b (ω·u) ⇒ S(n) = a + (2/3) b (n·u) for q = 1 (env map → Eq. 7 fit → transfer)."""
    u = np.array([0.3, 0.8, -0.52])
    u /= np.linalg.norm(u)
    a, b = 2.0, 1.5
    d = E.latlong_directions(64, 128)
    env = EnvMap((a + b * (d @ u))[..., None].repeat(3, -1), "latlong")
    coeffs = P.fit_probe(P.env_samples(env), 2)
    normals = Rotation.random(20, random_state=5).apply([1.0, 0, 0])
    expected = a + 2 / 3 * b * (normals @ u)
    # The fit of a band-1 signal is exact to rounding; 1e-10 covers it.
    np.testing.assert_allclose(TF.shading(coeffs, normals, 1.0), expected[:, None].repeat(3, 1),
                               atol=1e-10)


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


@pytest.mark.parametrize("flat_axis", [0, 2])
def test_axis_normals_are_outward_radial(flat_axis):
    g, radial = sphere_of_splats(flat_axis=flat_axis)
    n = TF.estimate_normals(g, "axis")
    np.testing.assert_allclose(n, radial, atol=1e-9)


def test_pca_normals_on_a_sphere():
    g, radial = sphere_of_splats(n=3000)
    n = TF.estimate_normals(g, "pca", neighbours=12)
    # 12 random neighbours lie within ~7° of arc on a 0.5 m sphere; a one-sided neighbourhood
    # fits a secant plane tilted by up to about half that: worst case < 5°, typical < 1.5°.
    cos = np.einsum("ij,ij->i", n, radial)
    assert cos.min() > math.cos(math.radians(5)) and np.median(cos) > math.cos(math.radians(1.5))


def test_relight_colours_and_clip():
    g, radial = sphere_of_splats()
    c = np.zeros((4, 3))
    c[0] = 1.0 * math.sqrt(4 * math.pi)
    c[2] = 0.8                               # + C1·z lobe: brighter towards +Z
    out = TF.relight_gaussians(g, c, q=1.0, intensity=1.7, t_max=1.2)
    S = TF.shading(c, radial, 1.0)
    np.testing.assert_allclose(out.colors(), g.colors() * 1.7 * np.clip(S, 0, 1.2), atol=1e-12)
    assert np.allclose(out.normals, radial, atol=1e-9)
    np.testing.assert_array_equal(out.means, g.means)


def test_relight_scales_view_dependence():
    rng = np.random.default_rng(3)
    g, _ = sphere_of_splats(n=20)
    g = g.with_sh_degree(2)
    g.sh[:, 1:] = rng.normal(size=(20, 8, 3)) * 0.05
    c = np.zeros((1, 3))
    c[0] = 2.0 * math.sqrt(4 * math.pi)      # uniform radiance 2 → factor 2
    out = TF.relight_gaussians(g, c)
    d = rng.normal(size=(20, 3))
    col = lambda h: 0.5 + np.einsum("nk,nkc->nc", sh_basis(d, 2), h.sh)  # noqa: E731
    np.testing.assert_allclose(col(out), 2 * col(g), atol=1e-12)


def test_attenuate_and_shadow_factor():
    g, _ = sphere_of_splats(n=30)
    g = g.with_sh_degree(1)
    g.sh[:, 1:] = 0.1
    f = np.linspace(0, 1, 30)
    out = TF.attenuate(g, f)
    d = np.tile([0.0, 0.0, 1.0], (30, 1))
    col = lambda h: 0.5 + np.einsum("nk,nkc->nc", sh_basis(d, 1), h.sh)  # noqa: E731
    np.testing.assert_allclose(col(out), f[:, None] * col(g), atol=1e-12)
    T = np.array([[1.0, 0.0, 0.5], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(TF.shadow_factor(T), [0.5, 0.0, 0.75])
    np.testing.assert_allclose(TF.shadow_factor(T, [3.0, 1.0], strength=0.5),
                               1 - 0.5 * (1 - np.array([0.75, 0.0, 0.625])))


def test_per_light_weights_attenuate_each_lights_direct_part():
    """Sec. 3.3: light l's T_l scales only light l's share of the direct light, per channel."""
    T = np.array([[0.2, 1.0, 0.0], [1.0, 0.5, 0.0]])            # [L=2, M=3]
    intensities = np.array([3.0, 1.0])
    # white lights: the intensity-weighted mean, in every channel
    w = TF.direct_light_weights("intensity", intensities, np.ones((2, 3)))
    assert w.shape == (2, 1, 3)
    f = TF.shadow_factor(T, w)
    np.testing.assert_allclose(f, np.repeat([[0.4], [0.875], [0.0]], 3, axis=1))
    # a red light and a cyan light: each light's shadow removes only its own colour
    colours = np.array([[1.0, 0, 0], [0, 1.0, 1.0]])
    f = TF.shadow_factor(T, TF.direct_light_weights("intensity", intensities, colours))
    np.testing.assert_allclose(f[0], [0.2, 1.0, 1.0])
    np.testing.assert_allclose(f[1], [1.0, 0.5, 0.5])
    # direct share s: (1 − s) of the colour is never shadowed
    f = TF.shadow_factor(T, TF.direct_light_weights("intensity", intensities, colours), 0.25)
    np.testing.assert_allclose(f[2], [0.75, 0.75, 0.75])
    # a light of zero intensity casts no shadow; equal weights are the old plain mean
    f = TF.shadow_factor(T, TF.direct_light_weights("intensity", [0.0, 1.0], np.ones((2, 3))))
    np.testing.assert_allclose(f[:, 0], T[1])
    f = TF.shadow_factor(T, TF.direct_light_weights("equal", n_lights=2))
    np.testing.assert_allclose(f[:, 1], TF.shadow_factor(T))


def test_irradiance_weights_and_unlit_receivers():
    """irradiance: w_l = I_l C_l |n·ω_l| / r_l²; a receiver no light reaches keeps its colour."""
    lights = np.array([[0.0, 1.0, 0.0], [2.0, 0.0, 0.0]])
    points = np.zeros((2, 3))
    normals = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])      # facing light 0; facing neither
    w = TF.direct_light_weights("irradiance", [1.0, 8.0], np.ones((2, 3)), lights, points, normals)
    assert w.shape == (2, 2, 3)
    np.testing.assert_allclose(w[:, 0, 0], [1.0, 0.0])          # light 1 is at grazing incidence
    np.testing.assert_allclose(w[:, 1, 0], [0.0, 0.0])
    T = np.array([[0.3, 0.3], [0.9, 0.9]])
    f = TF.shadow_factor(T, w)
    np.testing.assert_allclose(f[0], 0.3)
    np.testing.assert_allclose(f[1], 1.0)
    # tilt the first receiver 45° towards light 1: |n·ω| = 1/√2 each, r² = 1 and 4
    n45 = np.array([[1.0, 1.0, 0.0]]) / math.sqrt(2)
    w = TF.direct_light_weights("irradiance", [1.0, 8.0], None, lights, points[:1], n45)
    np.testing.assert_allclose(w[:, 0, 1], [1 / math.sqrt(2), 8 / (4 * math.sqrt(2))])
    with pytest.raises(ValueError):
        TF.direct_light_weights("bogus", [1.0])


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


def test_direct_light_share_shadows_each_lights_term_exactly():
    """An object lit by the probe (S) and by point lights (D_l): the direct share D/(S + D) with
    weights D_l turns shadow_factor into (S + Σ D_l T_l)/(S + D): each light's term times its T."""
    rng = np.random.default_rng(3)
    S = rng.uniform(0, 2, (50, 3))
    D = rng.uniform(0, 1, (3, 50, 3)) * (rng.uniform(size=(3, 50, 1)) > 0.3)
    T = rng.uniform(0, 1, (3, 50))
    share = D.sum(0) / (S + D.sum(0))
    f = TF.shadow_factor(T, D, share)
    np.testing.assert_allclose((S + D.sum(0)) * f, S + (D * T[:, :, None]).sum(0), rtol=1e-12)
    # direct_share itself: E_d/(E_d + π S(n)); zero where nothing lights the receiver
    c = np.zeros((1, 3))
    c[0] = 2.0 * math.sqrt(4 * math.pi)                    # uniform radiance 2
    e = np.array([[1.0, 2.0, 0.0], [0.0, 0.0, 0.0]])
    n = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    np.testing.assert_allclose(TF.direct_share(e, c, n), e / (e + 2 * math.pi))
    assert TF.direct_share(np.zeros((1, 3)), np.zeros((1, 3)), n[:1]).tolist() == [[0, 0, 0]]
    # normals turned towards the lights; flat splats have no inherent side
    turned = TF.facing_lights(np.zeros((2, 3)), [[0, -1.0, 0], [0, 1.0, 0]], [[0, 3.0, 0]])
    np.testing.assert_array_equal(turned, [[0, 1.0, 0], [0, 1.0, 0]])


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


# ------------------------------------------------------------------ light estimation (Sec. 3.1)


def room_with_lamps(seed=0):
    """A 4×3×4 m grey room (floor + walls), a bright extended window, and two compact lamps."""
    rng = np.random.default_rng(seed)
    parts = []

    def add(means, rgb, scale=0.05, opacity=0.9, sh_rest=None):
        n = len(means)
        sh = rgb_to_sh_dc(np.broadcast_to(rgb, (n, 3)))[:, None, :]
        if sh_rest is not None:
            sh = np.concatenate([sh, np.broadcast_to(sh_rest, (n, 3, 3))], axis=1)
        else:
            sh = np.concatenate([sh, np.zeros((n, 3, 3))], axis=1)
        parts.append(Gaussians(means, np.full((n, 3), scale), np.tile([1.0, 0, 0, 0], (n, 1)),
                               np.full(n, opacity), sh, 1))

    u = rng.uniform(-2, 2, (3000, 2))
    add(np.column_stack([u[:, 0], np.zeros(3000), u[:, 1]]), [0.3, 0.3, 0.3])                  # floor
    w = rng.uniform([-2, 0], [2, 3], (2000, 2))
    add(np.column_stack([w[:, 0], w[:, 1], np.full(2000, -2.0)]), [0.3, 0.3, 0.3])             # wall
    win = rng.uniform([-0.5, 1.0], [0.5, 2.0], (600, 2))
    add(np.column_stack([win[:, 0], win[:, 1], np.full(600, -1.99)]), [1.8, 1.8, 1.9])       # window
    lamp_a, lamp_b = np.array([1.2, 2.6, 0.5]), np.array([-1.5, 1.8, 1.0])
    add(lamp_a + rng.normal(0, 0.01, (12, 3)), [4.0, 3.0, 2.0], scale=0.01)
    add(lamp_b + rng.normal(0, 0.01, (12, 3)), [2.0, 3.0, 5.0], scale=0.01)
    # A specular glint: bright only from +x (degree-1 SH), dim on average.
    add(np.array([[0.5, 0.3, -1.0]]) + rng.normal(0, 0.005, (5, 3)), [0.3, 0.3, 0.3],
        sh_rest=np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-6.0, -6.0, -6.0]]), scale=0.01)
    from relight_cli.formats.gaussians_ply import concatenate
    return concatenate(parts), lamp_a, lamp_b


def test_estimate_lights_finds_compact_emitters():
    from relight_cli.gaussians.lights import LUMA, estimate_lights
    scene, lamp_a, lamp_b = room_with_lamps()
    est = estimate_lights(scene, 2)
    found = sorted(est.positions.tolist(), key=lambda p: p[0])
    # Positions are Gaussian centres of the lamp clusters (σ = 1 cm jitter): within 4 cm.
    np.testing.assert_allclose(found[0], lamp_b, atol=0.04)
    np.testing.assert_allclose(found[1], lamp_a, atol=0.04)
    np.testing.assert_allclose(est.colors @ LUMA, 1.0, atol=1e-12)
    a = int(np.argmin(np.linalg.norm(est.positions - lamp_a, axis=1)))
    np.testing.assert_allclose(est.colors[a] / est.colors[a].max(), [1.0, 0.75, 0.5], atol=1e-6)
    # paper: intensity = the base score b = opacity·(Ȳ + Ŷ)/2·(½ + ½s)·(½ + ½δ); a lamp looks
    # the same from everywhere (s = 1) and has no view-dependent SH energy (δ = 1)
    assert est.intensities[a] == pytest.approx(0.9 * np.array([4.0, 3.0, 2.0]) @ LUMA, rel=1e-6)
    v1 = estimate_lights(scene, 2, variant="v1")            # the earlier variant: mean luminance
    np.testing.assert_allclose(sorted(v1.positions.tolist()), sorted(est.positions.tolist()))
    a1 = int(np.argmin(np.linalg.norm(v1.positions - lamp_a, axis=1)))
    assert v1.intensities[a1] == pytest.approx(np.array([4.0, 3.0, 2.0]) @ LUMA, rel=1e-6)
    # K = 3: the window (bright but extended) comes after both lamps; the glint never wins.
    est3 = estimate_lights(scene, 3)
    assert -0.6 < est3.positions[2, 0] < 0.6 and est3.positions[2, 2] < -1.9
    assert est3.scores[0] >= est3.scores[1] >= est3.scores[2]


def test_estimate_lights_roi_and_errors():
    from relight_cli.gaussians.lights import estimate_lights, parse_auto
    scene, lamp_a, _ = room_with_lamps()
    est = estimate_lights(scene, 1, roi_center=lamp_a, roi_radius=0.5)
    np.testing.assert_allclose(est.positions[0], lamp_a, atol=0.04)
    with pytest.raises(ValueError, match="no scene Gaussians"):
        estimate_lights(scene, 1, roi_center=[50.0, 0, 0], roi_radius=1.0)
    assert parse_auto("auto:3") == 3 and parse_auto("lights.json") is None
    with pytest.raises(ValueError):
        parse_auto("auto:0")
    with pytest.raises(ValueError):
        parse_auto("auto:x")


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


def test_estimate_lights_paper_details():
    """Sec. 3.1: ROI and viewpoints at the character, soft clipping, colour toward the character."""
    from relight_cli.gaussians.lights import colour_toward, estimate_lights, soft_clip
    scene, lamp_a, lamp_b = room_with_lamps()
    # the character stands next to lamp b: a 0.8 m ROI around it finds only that lamp
    char = Gaussians(lamp_b + [0.3, -0.5, 0.0] + np.random.default_rng(1).normal(0, 0.1, (50, 3)),
                     np.full((50, 3), 0.02), np.tile([1.0, 0, 0, 0], (50, 1)), np.full(50, 0.9),
                     np.zeros((50, 1, 3)), 0)
    est = estimate_lights(scene, 1, roi_radius=0.8, character=char)
    np.testing.assert_allclose(est.positions[0], lamp_b, atol=0.04)
    # soft clipping: below the fence untouched, order kept, bounded above
    v = np.r_[np.linspace(0, 1, 200), 5.0, 50.0, 1e6]
    c = soft_clip(v)
    fence = 10 * np.percentile(v, 99)
    np.testing.assert_array_equal(c[v <= fence], v[v <= fence])
    assert c[200] == 5.0                                      # a lamp 5× the bulk: kept
    assert np.all(np.diff(c) >= 0) and c.max() <= 2 * fence
    # a blown-out floater (luminance 1e4): clipping keeps the order but not its 1000× margin,
    # so its score no longer swamps the lamps (what an intensity-from-score light inherits)
    from relight_cli.formats.gaussians_ply import concatenate
    floater = Gaussians(np.array([[0.0, 1.5, 1.5]]), np.full((1, 3), 0.01), [[1.0, 0, 0, 0]],
                        [0.9], np.concatenate([rgb_to_sh_dc(np.full((1, 3), 1e4))[:, None, :],
                                               np.zeros((1, 3, 3))], axis=1), 1)
    with_floater = concatenate([scene, floater])
    paper = estimate_lights(with_floater, 2)
    v1 = estimate_lights(with_floater, 2, variant="v1")
    assert v1.positions[0][2] == pytest.approx(1.5) and paper.positions[0][2] == pytest.approx(1.5)
    assert v1.scores[0] > 1000 * v1.scores[1]                 # unclipped (measured 3500×)
    assert paper.scores[0] < 50 * paper.scores[1]             # soft-clipped (measured 20×)
    # colour toward the character: the SH evaluated from the character's centroid
    # (the glint is bright for viewing directions along +x, i.e. seen from a camera at −x)
    glint = len(scene) - 5
    from_minus_x = colour_toward(scene, [glint], scene.means[glint] - [1.0, 0, 0])
    from_plus_x = colour_toward(scene, [glint], scene.means[glint] + [1.0, 0, 0])
    assert from_minus_x[0].min() > 1.0 and from_plus_x[0].max() == 0.0
    with pytest.raises(ValueError, match="estimator"):
        estimate_lights(scene, 1, variant="bogus")


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
