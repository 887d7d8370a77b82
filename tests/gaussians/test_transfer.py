"""Per-Gaussian SH radiance transfer (relight_cli/gaussians/transfer.py, Eq. 9–10): lobe moments,
shading against quadrature, normals, relit colours, shadow attenuation, per-light weights."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import eval_legendre
from scipy.spatial.transform import Rotation

from relight_cli import envmap as E
from relight_cli.formats.envmap import EnvMap
from relight_cli.formats.gaussians_ply import Gaussians, matrix_to_quaternion, rgb_to_sh_dc
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
