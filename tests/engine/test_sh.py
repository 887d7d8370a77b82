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
