"""Closed-form Gaussian transmittance vs adaptive quadrature (scipy.integrate.quad).

The reference integrates the absorption density β(d)·exp(−½|B + tA|²), written
from the precision-matrix (whitening) form and the mapping definitions in the
module docstring, never from the erf/adjugate formulas under test.  Quadrature
is split at the closest approach t* ± {1,3,6,12}σ_t so that thin peaks are
resolved; quad's own error estimate is asserted below 1e-9.

Tolerances (|ΔT|, the issue's contract): 1e-6 for float64, 1e-4 for float32.
T = exp(−τ) and |dT/dτ| ≤ 1, so |ΔT| ≤ |Δτ|.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy.integrate import IntegrationWarning, quad

from relight_cli.gaussians import transmittance as TR

TOL64 = 1e-6   # issue contract for the float64 path
TOL32 = 1e-4   # issue contract for the float32 fast path


def _rotation(q):
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def reference_tau(mu, s, q, alpha, o, d, t0, t1, mapping, kappa):
    """Optical depth of ONE Gaussian over [t0, t1] by adaptive quadrature."""
    if t1 <= t0:
        return 0.0
    R = _rotation(q)
    s = np.abs(np.asarray(s, np.float64))
    smax = max(s.max(), TR.SCALE_FLOOR_ABSOLUTE)
    s = np.maximum(s, TR.SCALE_FLOOR_RELATIVE * smax)   # the documented model
    s = np.maximum(s, 0) if s.max() > 0 else np.full(3, smax)
    A = (R.T @ d) / s                  # whitened direction
    B = (R.T @ (o - mu)) / s           # whitened origin
    a = float(A @ A)                   # dᵀΣ⁻¹d
    sigma_t = 1 / math.sqrt(a)
    t_star = -float(A @ B) / a
    alpha = min(max(alpha, 0.0), TR.ALPHA_MAX)
    tau_star = -math.log1p(-alpha)
    # β from the definitions (paper Eq. 5; Sec. 4.4 B), written from the precision
    # matrix Σ⁻¹ = R diag(1/s²) Rᵀ and the world-frame covariance, not from the
    # module's normalized-scale formulas.
    precision = R @ np.diag(1 / s ** 2) @ R.T
    covariance = R @ np.diag(s ** 2) @ R.T
    if mapping == "peak":            # direction-dependent: τ through the centre = κτ*
        beta = kappa * tau_star / (math.sqrt(2 * math.pi) * sigma_t)
    elif mapping == "avg":
        beta = kappa * tau_star * math.sqrt(np.trace(precision) / 3) / math.sqrt(2 * math.pi)
    elif mapping == "simple":
        beta = kappa * tau_star
    elif mapping == "mass":
        # det of a near-singular world-frame covariance loses relative precision
        # (≈ cond·eps); where it is well conditioned use it, else its exact value Πs²
        det = np.linalg.det(covariance) if s.min() > 1e-3 * s.max() else float(np.prod(s ** 2))
        beta = kappa * tau_star / ((2 * math.pi) ** 1.5 * math.sqrt(det))
    else:  # diag
        beta = kappa * tau_star / ((2 * math.pi) ** 1.5 * float(np.prod(s)))
    # the documented clip of the centre optical depth β√(2π)σ_t ≤ β√(2π)s_max ≤ 1e30
    beta = min(beta, TR.TAU_CENTRE_MAX / (math.sqrt(2 * math.pi) * smax))
    Ax, Ay, Az = A
    Bx, By, Bz = B

    def density(t):
        x, y, z = Bx + t * Ax, By + t * Ay, Bz + t * Az
        return beta * math.exp(-0.5 * (x * x + y * y + z * z))

    cuts = sorted({t0, t1, *[min(max(t_star + k * sigma_t, t0), t1)
                             for k in (-12, -6, -3, -1, 0, 1, 3, 6, 12)]})
    total = 0.0
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        if hi > lo:
            with warnings.catch_warnings():
                # roundoff warnings at 1e-13 requests are fine: the error bound is asserted
                warnings.simplefilter("ignore", IntegrationWarning)
                val, err = quad(density, lo, hi, epsabs=1e-14, epsrel=1e-13, limit=200)
            # quadrature error must be far below the 1e-6 contract it checks
            assert err < 1e-9 * max(1.0, beta * sigma_t), (val, err)
            total += val
    return total


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def random_cases(rng, n):
    """Generic single-Gaussian cases: log-uniform scales, rays aimed near the Gaussian."""
    cases = []
    for _ in range(n):
        mu = rng.uniform(-1, 1, 3)
        s = np.exp(rng.uniform(np.log(1e-3), np.log(0.5), 3))
        q = rng.normal(size=4)
        alpha = rng.uniform(0, 1)
        o = rng.uniform(-3, 3, 3)
        aim = mu + rng.normal(size=3) * s.max() * rng.uniform(0, 3)
        d = _unit(aim - o)
        dist = np.linalg.norm(aim - o)
        t0 = rng.choice([0.0, rng.uniform(0, dist)])
        t1 = rng.uniform(0, 2 * dist)
        cases.append((mu, s, q, alpha, o, d, t0, t1))
    return cases


def adversarial_cases(rng):
    """Hand-made hard cases from the issue's list (each repeated with random jitter)."""
    cases = []
    for _ in range(40):
        q = rng.normal(size=4)
        R = _rotation(q)
        n = R[:, 2]                                   # thin axis of a flat Gaussian
        mu = rng.uniform(-1, 1, 3)
        o = mu + rng.uniform(1, 3) * _unit(rng.normal(size=3))
        # 1. flat discs (thickness 0, 1e-7, 1e-4 relative), generic rays through them
        for thin in (0.0, 1e-7, 1e-4):
            s = np.array([0.2, 0.1, 0.2 * thin])
            d = _unit(mu + R[:, 0] * rng.normal() * 0.1 - o)
            cases.append((mu, s, q, rng.uniform(0.1, 1), o, d, 0.0, 5.0))
        # 2. rays (nearly) parallel to a flat disc, in or just off its plane
        s = np.array([0.2, 0.1, 1e-5])
        for tilt in (0.0, 1e-9, 1e-6, 1e-3):
            inplane = _unit(np.cross(n, rng.normal(size=3)))
            d = _unit(inplane + tilt * n)
            for off in (0.0, 3e-6, 1e-4):
                start = mu - 1.0 * d + off * n
                cases.append((mu, s, q, 0.9, start, d, 0.0, 2.0))
        # 3. a → 0: a needle much longer than the segment, ray along it
        s = np.array([50.0, 0.01, 0.01])
        d = R[:, 0]
        cases.append((mu, s, q, 0.8, mu - 0.3 * d + 0.005 * R[:, 1], d, 0.0, rng.uniform(1e-6, 0.6)))
        cases.append((mu, s, q, 0.8, mu + 0.005 * R[:, 2], d, 0.0, 1e-9))
        # 4. opacity → 1 and exactly 1, through and beside the centre
        for alpha in (1 - 1e-9, 1 - 1e-15, 1.0):
            s = np.array([0.05, 0.05, 0.05])
            for off in (0.0, 0.1, 0.3):
                d = _unit(mu + off * R[:, 1] - o)
                cases.append((mu, s, q, alpha, o, d, 0.0, 6.0))
        # 5. zero and tiny scales
        for s in (np.zeros(3), np.array([1e-12, 1e-12, 1e-12]), np.array([0.1, 0.0, 0.0]),
                  np.array([0.1, 0.1, 0.0])):
            d = _unit(mu - o + 1e-3 * rng.normal(size=3))
            cases.append((mu, s, q, 0.7, o, d, 0.0, 6.0))
        # 6. light inside the Gaussian (origin near μ), segment forwards and short
        s = np.array([0.3, 0.2, 0.1])
        inside = mu + 0.05 * rng.normal(size=3)
        d = _unit(rng.normal(size=3))
        for t1 in (1e-8, 0.02, 0.3, 4.0):
            cases.append((mu, s, q, 0.95, inside, d, 0.0, t1))
        # 7. receiver behind the light: reversed segment → τ = 0
        cases.append((mu, s, q, 0.95, inside, d, 0.5, -0.5))
        # 8. far tails: segment bounds several σ_t on one side (erf near ±1)
        s = np.array([0.01, 0.01, 0.01])
        d = _unit(mu - o)
        dist = float(np.linalg.norm(mu - o))
        for a0, a1 in ((5, 7), (-7, -5), (-40, -4), (4, 40), (-3, 3)):
            cases.append((mu, s, q, 0.999, o + 0.002 * R[:, 0], d, dist + a0 * 0.01,
                          dist + a1 * 0.01))
    return cases


def _closed_form(cases, mapping, kappa, dtype):
    mu = np.array([c[0] for c in cases])
    s = np.array([c[1] for c in cases])
    q = np.array([c[2] for c in cases])
    alpha = np.array([c[3] for c in cases])
    o = np.array([c[4] for c in cases])
    d = np.array([c[5] for c in cases])
    t0 = np.array([c[6] for c in cases])
    t1 = np.array([c[7] for c in cases])
    mix = TR.prepare(mu, s, q, alpha, mapping, kappa)
    terms = TR.pair_terms(mix, o, d, np.arange(len(cases)), dtype)
    return TR.segment_terms(terms, t0.astype(dtype), t1.astype(dtype)).astype(np.float64)


def _check(cases, mapping, kappa):
    ref = np.array([reference_tau(*c, mapping=mapping, kappa=kappa) for c in cases])
    for dtype, tol in ((np.float64, TOL64), (np.float32, TOL32)):
        tau = _closed_form(cases, mapping, kappa, dtype)
        assert np.all(np.isfinite(tau)), f"non-finite τ for {dtype.__name__}"
        err = np.abs(np.exp(-tau) - np.exp(-ref))
        worst = int(np.argmax(err))
        assert err.max() <= tol, (mapping, dtype.__name__, worst, cases[worst], tau[worst], ref[worst])
    return ref


@pytest.mark.parametrize("mapping", TR.MAPPINGS)
def test_random_cases_match_quadrature(mapping):
    rng = np.random.default_rng(TR.MAPPINGS.index(mapping))
    cases = random_cases(rng, 800)  # 5 mappings × 800 = 4000 random cases
    # simple's τ through the centre is κτ*√(2π)σ_t (σ_t of cm): a larger κ so
    # that its set also has dark rays
    ref = _check(cases, mapping, kappa=40.0 if mapping == "simple" else 2.0)
    # the set must exercise both clear and dark rays, or it tests nothing
    T = np.exp(-ref)
    assert (T < 0.6).sum() > 20 and (T > 0.99).sum() > 20


@pytest.mark.parametrize("mapping", TR.MAPPINGS)
def test_adversarial_cases_match_quadrature(mapping):
    rng = np.random.default_rng(100 + TR.MAPPINGS.index(mapping))
    cases = adversarial_cases(rng)   # ≈ 1,500 per mapping
    _check(cases, mapping, kappa=1.7)


def test_reversed_and_empty_segments_are_clear():
    rng = np.random.default_rng(3)
    mix = TR.prepare(rng.normal(size=(5, 3)), np.full((5, 3), 0.3), rng.normal(size=(5, 4)),
                     np.full(5, 0.99))
    o = np.zeros((4, 3))
    d = np.tile([0.0, 0.0, 1.0], (4, 1))
    for dtype in (np.float64, np.float32):
        T = TR.transmittance(mix, o, d, np.array([1.0, 1.0, 0.0, 2.0]),
                             np.array([1.0, -1.0, 0.0, 1.5]), dtype)
        assert np.array_equal(T, np.ones(4))


def test_mixture_sum_matches_quadrature_of_whole_density():
    """τ of a mixture (dense path) vs one quadrature of the summed density."""
    rng = np.random.default_rng(7)
    for trial in range(30):
        n = 6
        mu = rng.uniform(-0.5, 0.5, (n, 3))
        s = np.exp(rng.uniform(np.log(0.01), np.log(0.3), (n, 3)))
        q = rng.normal(size=(n, 4))
        alpha = rng.uniform(0.2, 1.0, n)
        o = np.array([0.0, 2.0, 0.0]) + rng.normal(size=3) * 0.2
        d = _unit(rng.normal(size=3) * 0.2 - o)
        mix = TR.prepare(mu, s, q, alpha, "avg", 1.0)
        ref = sum(reference_tau(mu[i], s[i], q[i], alpha[i], o, d, 0.0, 4.0, "avg", 1.0)
                  for i in range(n))
        for dtype, tol in ((np.float64, TOL64), (np.float32, TOL32)):
            tau = TR.optical_depth(mix, o[None], d[None], 0.0, 4.0, dtype)[0]
            assert abs(math.exp(-tau) - math.exp(-ref)) <= tol


def test_transmittance_between_point_at_light_is_one():
    mix = TR.prepare(np.zeros((1, 3)), np.full((1, 3), 0.1), np.array([[1.0, 0, 0, 0]]), [0.9])
    T = TR.transmittance_between(mix, [0.0, 0.0, 0.0], np.array([[0.0, 0.0, 0.0], [0, 0, 1.0]]))
    assert T[0] == 1.0
    # from the centre outwards: half the Gaussian, T = (1−α)^(1/2) (isotropic: avg = peak)
    assert abs(T[1] - math.sqrt(0.1)) < 1e-12


def test_peak_ray_through_centre_has_splat_opacity():
    """peak: any full ray through μ sees exactly τ* = −ln(1−α), for any direction."""
    rng = np.random.default_rng(11)
    mix = TR.prepare(np.zeros((1, 3)), [[0.3, 0.02, 0.1]], rng.normal(size=(1, 4)), [0.8], "peak", 1.0)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    T = TR.transmittance(mix, -5 * d, d, 0.0, 10.0)
    np.testing.assert_allclose(T, 0.2, atol=1e-12)


def test_erf_difference_edge_cases():
    from scipy.special import erf
    u0 = np.array([-50.0, 6.0, -6.0, 0.0, 1.0, 30.0, -1e-12])
    u1 = np.array([50.0, 6.5, -5.5, 0.0, 1.0 + 1e-13, 31.0, 1e-12])
    out = TR.erf_difference(u0, u1)
    assert np.all(np.isfinite(out)) and np.all(out >= 0)
    assert abs(out[0] - 2.0) < 1e-15
    # erfc-based: relative accuracy where erf(6.5) − erf(6) would round to 0 in float64
    from scipy.special import erfc
    assert abs(out[1] / (erfc(6.0) - erfc(6.5)) - 1) < 1e-12 and out[1] > 0
    assert out[3] == 0.0
    width = u1[4] - u0[4]   # the representable interval (≈ 1e-13)
    assert abs(out[4] / (2 / math.sqrt(math.pi) * math.exp(-1) * width) - 1) < 1e-9
    assert abs(out[6] - (erf(1e-12) - erf(-1e-12))) < 1e-25


# ------------------------------------------------------------------ the paper's mappings in closed form


def _full_line_tau(mix, d, through=np.zeros(3)):
    """τ along the whole line through ``through`` in direction d (± 50 m)."""
    d = _unit(d)
    return TR.optical_depth(mix, (through - 50 * d)[None], d[None], 0.0, 100.0)[0]


@pytest.mark.parametrize("alpha", [0.3, 1 - 1e-9, 1 - 1e-15, 1.0])
def test_mappings_through_the_centre_closed_forms(alpha):
    """∫ β e^{−½ xᵀAx} along a line through μ = β √(2π) σ_t, σ_t = (dᵀAd)^{−½} (Gauss integral).

    Written per mapping from the paper's β (Eq. 5; Sec. 4.4 B): isotropic and
    axis-aligned anisotropic Gaussians, opacity up to exactly 1 (clipped to
    1 − 1e-12, τ* ≈ 27.6, finite).
    """
    kappa = 0.7
    tau_star = -math.log1p(-min(alpha, TR.ALPHA_MAX))
    s = np.array([0.05, 0.02, 0.004])
    trace = (1 / s ** 2).sum()
    for axis in range(3):
        d = np.eye(3)[axis]
        expected = {
            "avg": kappa * tau_star * math.sqrt(trace / 3) * s[axis],
            "simple": kappa * tau_star * math.sqrt(2 * math.pi) * s[axis],
            "mass": kappa * tau_star * s[axis] / (2 * math.pi * s.prod()),
            "diag": kappa * tau_star * s[axis] / (2 * math.pi * s.prod()),
            "peak": kappa * tau_star,
        }
        for mapping, want in expected.items():
            mix = TR.prepare(np.zeros((1, 3)), s[None], [[1.0, 0, 0, 0]], [alpha], mapping, kappa)
            got = _full_line_tau(mix, d)
            assert np.isfinite(got)
            assert abs(got / want - 1) < 1e-12, (mapping, axis, got, want)
    # isotropic: avg = peak = κτ*, mass = diag = κτ*/(2π s²), simple = κτ*√(2π)s
    iso = 0.03
    for mapping, want in (("avg", kappa * tau_star), ("peak", kappa * tau_star),
                          ("mass", kappa * tau_star / (2 * math.pi * iso ** 2)),
                          ("simple", kappa * tau_star * math.sqrt(2 * math.pi) * iso)):
        mix = TR.prepare(np.zeros((1, 3)), [[iso] * 3], [[0.3, 0.1, -0.5, 0.2]], [alpha], mapping,
                         kappa)
        got = _full_line_tau(mix, [0.3, -1.0, 0.2])
        assert abs(got / want - 1) < 1e-12, (mapping, got, want)


def test_mass_and_diag_coincide_and_match_the_covariance_determinant():
    """Sec. 4.4: A = covariance in the local frame, so √det A = s_x s_y s_z (mass ≡ diag)."""
    rng = np.random.default_rng(21)
    n = 500
    s = np.exp(rng.uniform(np.log(1e-3), np.log(0.3), (n, 3)))
    q = rng.normal(size=(n, 4))
    alpha = rng.uniform(0.01, 1, n)
    mass = TR.prepare(np.zeros((n, 3)), s, q, alpha, "mass").absorption()
    diag = TR.prepare(np.zeros((n, 3)), s, q, alpha, "diag").absorption()
    np.testing.assert_allclose(mass, diag, rtol=1e-13)
    R = np.array([_rotation(x) for x in q])
    cov = np.einsum("nij,nj,nkj->nik", R, s ** 2, R)        # world-frame Σ
    # world-frame det(Σ) carries rounding ∝ its condition number (≤ 9e4 here → rtol 1e-9)
    expected = -np.log1p(-alpha) / ((2 * math.pi) ** 1.5 * np.sqrt(np.linalg.det(cov)))
    np.testing.assert_allclose(mass, expected, rtol=1e-9)
    # avg from the trace of the world-frame precision matrix (Eq. 5)
    precision = np.einsum("nij,nj,nkj->nik", R, 1 / s ** 2, R)
    avg = TR.prepare(np.zeros((n, 3)), s, q, alpha, "avg").absorption()
    np.testing.assert_allclose(
        avg, -np.log1p(-alpha) * np.sqrt(np.trace(precision, axis1=1, axis2=2) / 3)
        / math.sqrt(2 * math.pi), rtol=1e-12)
    # peak has no fixed β
    assert np.isnan(TR.prepare(np.zeros((1, 3)), s[:1], q[:1], alpha[:1], "peak").absorption()).all()


def test_flat_and_degenerate_gaussians_per_mapping():
    """A disc of zero thickness (floored to 1e-6 of its width): finite, and avg ≈ κτ*/(√3 cos θ)."""
    rng = np.random.default_rng(5)
    q = rng.normal(size=4)
    R = _rotation(q)
    normal = R[:, 2]
    s = np.array([0.2, 0.1, 0.0])
    tau_star = -math.log1p(-0.5)
    for theta in (0.0, math.radians(60), math.radians(89)):
        d = math.cos(theta) * normal + math.sin(theta) * R[:, 0]
        mix = TR.prepare(np.zeros((1, 3)), s[None], q[None], [0.5], "avg", 1.0)
        got = _full_line_tau(mix, d)
        # tr(A)/3 ≈ 1/(3 s_z²) and σ_t ≈ s_z / cos θ (the in-plane terms are 1e-12 relative)
        want = tau_star / (math.sqrt(3) * math.cos(theta))
        assert abs(got / want - 1) < 1e-6, (theta, got, want)
        for mapping in TR.MAPPINGS:
            for dtype in (np.float64, np.float32):
                mixm = TR.prepare(np.zeros((1, 3)), s[None], q[None], [0.5], mapping, 1.0)
                tau = TR.optical_depth(mixm, (-50 * d)[None], d[None], 0.0, 100.0, dtype)
                assert np.isfinite(tau).all() and (tau >= 0).all()
    # all scales zero, opacity 1: finite, and mass/diag hit the documented clip
    mix = TR.prepare(np.zeros((1, 3)), [[0.0, 0.0, 0.0]], [q], [1.0], "mass")
    assert mix.peak_bound()[0] == TR.TAU_CENTRE_MAX
    assert np.isfinite(_full_line_tau(mix, [0, 1.0, 0]))


def test_legacy_eq5_name_reads_as_peak():
    assert TR.canonical_mapping("eq5") == "peak"
    mix = TR.prepare(np.zeros((1, 3)), [[0.1, 0.2, 0.3]], [[1.0, 0, 0, 0]], [0.5], "eq5")
    assert mix.mapping == "peak"
    assert TR.DEFAULT_MAPPING == "avg"
    with pytest.raises(ValueError):
        TR.canonical_mapping("nope")
