"""relight_cli/sh.py: the real SH basis against scipy, the 3DGS convention, poles, Lambert band
factors, least-squares fits."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, special

from relight_cli import sh


def _unit(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_sh_basis_matches_scipy_complex_harmonics():
    """Real SH from scipy's complex Y_l^m (which includes the Condon–Shortley phase)."""
    d = _unit(np.random.default_rng(0), 64)
    theta, phi = np.arccos(d[:, 2]), np.arctan2(d[:, 1], d[:, 0])
    basis = sh.sh_basis(d, 7)
    for l in range(8):
        for m in range(-l, l + 1):
            y = special.sph_harm_y(l, abs(m), theta, phi)
            ref = math.sqrt(2) * (y.real if m > 0 else y.imag) if m else y.real
            np.testing.assert_allclose(basis[:, l * l + l + m], ref, atol=1e-12)


def test_sh_degree1_is_the_3dgs_convention():
    d = _unit(np.random.default_rng(1), 10)
    c1 = math.sqrt(3 / (4 * math.pi))
    np.testing.assert_allclose(sh.sh_basis(d, 1)[:, 1:],
                               np.stack([-c1 * d[:, 1], c1 * d[:, 2], -c1 * d[:, 0]], 1), atol=1e-15)


def test_sh_poles_are_finite():
    b = sh.sh_basis(np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 0, 0.0]]), 10)
    assert np.isfinite(b).all()


def test_lambert_band_factors_match_quadrature():
    """Â_l = 2π ∫₀^{π/2} cos θ P_l(cos θ) sin θ dθ (Funk–Hecke)."""
    factors = sh.lambert_band_factors(8)
    for l in range(9):
        ref, _ = integrate.quad(lambda t: math.cos(t) * special.eval_legendre(l, math.cos(t))
                                * math.sin(t), 0, math.pi / 2)
        assert factors[l] == pytest.approx(2 * math.pi * ref, abs=1e-12)


def test_fit_sh_recovers_coefficients_on_a_grid():
    from relight_cli import envmap as E
    dirs = E.latlong_directions(64, 128).reshape(-1, 3)
    omega = E.latlong_solid_angles(64, 128).reshape(-1)
    truth = np.random.default_rng(2).normal(size=(9, 3))
    values = sh.sh_basis(dirs, 2) @ truth
    np.testing.assert_allclose(sh.fit_sh(dirs, values, omega, 2), truth, atol=1e-9)


def test_fit_sh_in_blocks_equals_one_block(monkeypatch):
    """The blocked normal equations are the one-block ones, summed in another order."""
    rng = np.random.default_rng(5)
    dirs, values, weights = _unit(rng, 1000), rng.normal(size=(1000, 3)), rng.random(1000)
    whole = sh.fit_sh(dirs, values, weights, 4)
    monkeypatch.setattr(sh, "FIT_BLOCK", 37)              # 28 blocks, the last one short
    np.testing.assert_allclose(sh.fit_sh(dirs, values, weights, 4), whole, rtol=1e-10,
                               atol=1e-12)


def test_window_factors_known_values():
    """Sloan's windows at width w = degree + 1, by hand: Hanning (1 + cos(πl/w))/2,
    Lanczos σ = sin(πl/w)/(πl/w)."""
    np.testing.assert_allclose(sh.window_factors("hanning", 2), [1, 0.75, 0.25], atol=1e-15)
    np.testing.assert_allclose(sh.window_factors("lanczos", 1), [1, 2 / math.pi], atol=1e-15)
    np.testing.assert_allclose(sh.window_factors("lanczos", 2),
                               [1, 1.5 * math.sqrt(3) / math.pi, 0.75 * math.sqrt(3) / math.pi],
                               atol=1e-15)
    np.testing.assert_array_equal(sh.window_factors("none", 5), np.ones(6))
    with pytest.raises(ValueError, match="window"):
        sh.window_factors("hann", 2)


@pytest.mark.parametrize("kind", ["none", "hanning", "lanczos"])
def test_windowed_point_light_is_the_closed_form_zonal_sum(kind):
    """A unit point light at ω0 projects to c_lm = Y_lm(ω0); windowed, its radiance is
    Σ_l h_l (2l+1)/(4π) P_l(ω·ω0) (addition theorem), at an ω0 off every axis."""
    degree = 6
    light = np.array([[0.3, -0.5, 0.81]])
    light /= np.linalg.norm(light)
    coefficients = sh.apply_window(sh.sh_basis(light, degree).T, kind)        # [49, 1]
    dirs = _unit(np.random.default_rng(3), 500)
    cos = dirs @ light[0]
    h = sh.window_factors(kind, degree)
    closed = sum(h[l] * (2 * l + 1) / (4 * math.pi) * special.eval_legendre(l, cos)
                 for l in range(degree + 1))
    np.testing.assert_allclose(sh.evaluate_sh(coefficients, dirs)[:, 0], closed, atol=1e-12)


def test_hanning_damps_the_point_light_dip_closed_form():
    """Degree 2 of a point light: Σ (2l+1) h_l P_l(c) has its minimum −1.8 at c = −0.2
    unwindowed and −0.3 at c = −0.6 with Hanning (1, 0.75, 0.25), in units of the mean
    radiance 1/(4π); radiance_negativity finds both on its 64×128 grid (light at the pole,
    so the grid's rows sample c; 1e-2: the minimum lies between two rows)."""
    from relight_cli.gaussians.probe import radiance_negativity
    pole = sh.sh_basis(np.array([[0.0, 1.0, 0.0]]), 2).T.repeat(3, axis=1)     # [9, 3]
    assert radiance_negativity(pole)[0] == pytest.approx(1.8, abs=1e-2)
    assert radiance_negativity(sh.apply_window(pole, "hanning"))[0] == pytest.approx(0.3, abs=1e-2)


@pytest.mark.parametrize("kind", ["hanning", "lanczos"])
def test_windowed_irradiance_matches_brute_force_quadrature(kind):
    """Irradiance of a windowed probe (band factors Â_l h_l) against a brute-force sum of
    the windowed radiance times max(n·ω, 0) over a 512×1024 lat-long grid (1e-3 of the
    peak: the grid's error where the horizon cuts the cells)."""
    from relight_cli import envmap as E
    from relight_cli.gaussians.probe import irradiance_from_sh
    rng = np.random.default_rng(9)
    coefficients = sh.apply_window(rng.normal(size=(25, 1)) + np.eye(25, 1) * 10, kind)
    dirs = E.latlong_directions(512, 1024).reshape(-1, 3)
    omega = E.latlong_solid_angles(512, 1024).reshape(-1)
    radiance = sh.evaluate_sh(coefficients, dirs)[:, 0] * omega
    normals = _unit(rng, 20)
    brute = np.array([radiance @ np.maximum(dirs @ n, 0) for n in normals])
    fast = irradiance_from_sh(coefficients, normals)[:, 0]
    np.testing.assert_allclose(fast, brute, atol=1e-3 * np.abs(brute).max())
