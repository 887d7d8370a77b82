"""Closed-form transmittance along rays through a mixture of 3D Gaussians.

The absorption field of N Gaussians is (Mir et al., Eq. 1)

    σ(x) = Σ_i β_i exp(−½ (x − μ_i)ᵀ Σ_i⁻¹ (x − μ_i)),

and along a ray x(t) = o + t·d (d unit) each term integrates in closed form with
the error function (Eq. 2–4):

    ∫_{t0}^{t1} β_i e^{−½q_i(t)} dt = ½ τ_peak,i · e^{−½ m_i²} · [erf(u(t1)) − erf(u(t0))],
    u(t) = (t − t*_i) / (√2 σ_t,i),   τ_peak,i = β_i √(2π) σ_t,i,

where t*_i is the ray parameter of the closest approach in the Mahalanobis
metric, σ_t,i = (dᵀΣ_i⁻¹d)^(−½) the Gaussian's standard deviation along the ray
and m_i² the squared Mahalanobis distance of the ray from μ_i (the 2-D
Mahalanobis distance of the projected covariance in the plane ⊥ d).
T = exp(−τ), τ = Σ_i (term i).

Numerical stability (why each formula is written the way it is):

* No precision matrices.  With c = r × d (r = o − μ) and adj Σ the adjugate
  (all evaluated in the Gaussian's principal frame as sums of squares),
  m² = cᵀΣc / (dᵀ adjΣ d), σ_t² = det Σ / (dᵀ adjΣ d) and
  t* = −dᵀ adjΣ r / (dᵀ adjΣ d): a flat Gaussian (one scale → 0) stays finite,
  there is no catastrophic cancellation c − b²/a, and a ray nearly parallel to
  a thin disc (dᵀΣ⁻¹d → its in-plane value, or an elongated Gaussian where
  a = dᵀΣ⁻¹d → 0) needs no special case.  Each Gaussian is normalized by its
  largest scale first, so float32 never underflows (s⁴ terms).
* Scales below 1e-6 of a Gaussian's largest scale are raised to that (and the
  largest to at least 1e-9 m): a "zero" scale is a disc 1e-6 as thick as it is
  wide.  This is the model; the references in the tests use the same floor.
* erf differences never subtract two numbers near ±1: both arguments ≥ 0 use
  erfc(u0) − erfc(u1), both ≤ 0 use erfc(−u1) − erfc(−u0), and a short interval
  (half-width h with h·max(1,|ū|) ≤ ¼, e.g. a receiver next to the light or a
  Gaussian much longer than the segment) is integrated by 8-point
  Gauss–Legendre on e^{−s²}, exact to ~1e-15 relative there.
* Opacity α is clipped to [0, 1 − 1e-12] before τ* = −ln(1 − α), so α → 1
  gives a large but finite peak optical depth (≈ 27.6) and never ∞·0 = NaN.
* An empty or reversed segment (t1 ≤ t0, e.g. a receiver behind the light
  along the query direction) has τ = 0, T = 1.  A light inside a Gaussian is
  ordinary: t0 = 0 lies inside the erf's transition.

Opacity → absorption (β) mappings (paper Sec. 3.2 Eq. 5 and Sec. 4.4 B, Table 4).
τ* = −ln(1 − α) is the optical depth that makes a slab of opacity α; κ is the
global strength knob.  The paper's four give each Gaussian ONE absorption
amplitude β_i (units 1/m for Eq. 1 to be an absorption density), so a ray
through the centre along d collects τ_centre(d) = β_i √(2π) σ_t,i(d), with
σ_t(d) = (dᵀA d)^(−½) and A = Σ⁻¹ the precision matrix:

* ``avg`` (default; paper Eq. 5, Table 4 mapping 2):
  β = κ τ* √(tr(A)/3) / √(2π), tr(A) = Σ_k 1/s_k², the "direction-agnostic
  proxy for √a".  τ_centre(d) = κ τ* √(tr(A)/3) / √(dᵀAd): exactly κτ* for an
  isotropic Gaussian; for a flat disc (s_z → 0) ≈ κτ*/(√3 |cos θ|), θ the angle
  to the disc normal (a slab's 1/cos).
* ``simple`` (Table 4 mapping 1): β = κ τ*, i.e. τ_centre = κτ* √(2π) σ_t(d) —
  shadow strength grows with the Gaussian's size in metres.
* ``mass`` (Table 4 mapping 3): β = κ τ* / ((2π)^{3/2} √det A) with A, as the
  paper's Sec. 4.4 defines it for mappings 3–4, the COVARIANCE in the Gaussian's
  local frame: the absorption integrates to κτ* over space (∫σ dV = κτ*).
  det is taken in the local frame (where Σ = diag(s²)); it is rotation
  invariant, and the world-frame det(R S² Rᵀ) agrees to rounding.
* ``diag`` (Table 4 mapping 4): β = κ τ* / ((2π)^{3/2} s_x s_y s_z), the
  diagonal scales.  **mass and diag coincide**: in the local frame Σ =
  diag(s_x², s_y², s_z²), so √det Σ = s_x s_y s_z for every 3DGS Gaussian (Σ =
  R S² Rᵀ, det R = 1): the two give the same β (tested).  The paper's Table 4
  reports different numbers for them (SAE 0.171 vs 0.177), which this reading
  cannot reproduce; reading A in mapping 3 as the precision of Eq. 5 instead
  would give β ∝ τ* s_x s_y s_z, not a density, so we follow Sec. 4.4's text.
  The paper writes mappings 2–4 without κ; κ = 1 (the default) is the paper's.
* ``peak`` (this toolkit's variant, called ``eq5`` before DGSM version 2):
  direction-dependent β_i(d) = κ τ*_i / (√(2π) σ_t,i(d)), so every ray through
  the centre sees optical depth exactly κτ*, i.e. T = (1 − α)^κ, the splat
  rasterizer's own peak opacity, in every direction; off-centre rays see
  κτ* e^{−½m²}.  Not a fixed absorption field (departs from Eq. 1); kept
  because it reproduces 3DGS opacities exactly.  An old file saying ``eq5``
  reads as ``peak``.

Where two coincide besides mass ≡ diag: avg ≡ peak for isotropic Gaussians
(tr(A)/3 = dᵀAd = 1/s²), and simple ≡ avg for isotropic ones of s = 1/√(2π) m.
τ_centre is clipped at 1e30 to stay inside float32 (only mass/diag of
Gaussians thinner than ~1e-9 m with α → 1 reach it, where T = 0 anyway).
``formats/dgsm_exr.md`` and the provenance record which mapping ran.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# the mapping names, which DGSM files record (their format defines the vocabulary)
from relight_cli.formats.dgsm_exr import DEFAULT_MAPPING, MAPPINGS
# names of DGSM version 1 files: "eq5" was what is now "peak"; version 1's
# "simple", "mass" and "diag" were other (direction-dependent) definitions.
LEGACY_MAPPINGS = {"eq5": "peak"}
TAU_CENTRE_MAX = 1e30
ALPHA_MAX = 1.0 - 1e-12
SCALE_FLOOR_RELATIVE = 1e-6
SCALE_FLOOR_ABSOLUTE = 1e-9  # metres

# 8-point Gauss–Legendre nodes/weights on [−1, 1].
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)
_SQRT_PI = float(np.sqrt(np.pi))
_SQRT2 = float(np.sqrt(2.0))


@dataclass
class Mixture:
    """Occluder Gaussians prepared for transmittance queries (float64).

    Every per-Gaussian quantity is normalized by the largest (floored) scale,
    Σ̃ = Σ / s_max², and kept in the Gaussian's principal frame, so the forms
    dᵀ adjΣ̃ d, cᵀΣ̃c and dᵀΣ̃d are sums of non-negative terms (no cancellation,
    even in float32, even for needles and discs 1e-6 thin).

    Attributes:
        means: [N, 3] centres, metres, world.
        scale_max: [N] largest (floored) scale, metres.
        rotation: [N, 3, 3] local→world rotations (columns are the principal axes).
        var: [N, 3] normalized variances s̃_k² (≤ 1, ≥ 1e-12).
        cof: [N, 3] cofactors s̃_j² s̃_k² (the adjugate's eigenvalues).
        det: [N] det Σ̃ = Π s̃_k².
        scale_min: [N] smallest normalized scale (s_min / s_max).
        alpha: [N] opacities, clipped to [0, ALPHA_MAX].
        tau_star: [N] −ln(1 − α).
        mapping: one of MAPPINGS.
        kappa: global absorption scale κ.
        beta_sigma: [N] β_i·√(2π)·s_max,i for the fixed-β mappings (avg,
            simple, mass, diag): the centre ray's optical depth along d is
            beta_sigma·σ̃(d), σ̃ = σ_t/s_max ≤ 1; NaN for ``peak``.
    """

    means: np.ndarray
    scale_max: np.ndarray
    rotation: np.ndarray
    var: np.ndarray
    cof: np.ndarray
    det: np.ndarray
    scale_min: np.ndarray
    alpha: np.ndarray
    tau_star: np.ndarray
    mapping: str = DEFAULT_MAPPING
    kappa: float = 1.0
    beta_sigma: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.means)

    def subset(self, index) -> "Mixture":
        return Mixture(self.means[index], self.scale_max[index], self.rotation[index],
                       self.var[index], self.cof[index], self.det[index],
                       self.scale_min[index], self.alpha[index], self.tau_star[index],
                       self.mapping, self.kappa, self.beta_sigma[index])

    def peak_bound(self) -> np.ndarray:
        """[N] an upper bound of the optical depth any ray can collect from each Gaussian."""
        if self.mapping == "peak":
            return self.kappa * self.tau_star
        return self.beta_sigma  # σ_t ≤ s_max, so σ̃ ≤ 1

    def absorption(self) -> np.ndarray:
        """[N] β_i of Eq. 1 in 1/m (fixed-β mappings; NaN for the direction-dependent ``peak``)."""
        return self.beta_sigma / (math.sqrt(2 * math.pi) * self.scale_max)

    def alpha_weighted_centroid(self) -> np.ndarray:
        """[3] Σ α_i μ_i / Σ α_i (metres, world); the plain mean if all α are 0."""
        w = self.alpha
        if w.sum() <= 0:
            return self.means.mean(axis=0)
        return (w[:, None] * self.means).sum(0) / w.sum()


def canonical_mapping(name: str) -> str:
    """A mapping name of MAPPINGS, upgrading the legacy ``eq5`` to ``peak``."""
    name = LEGACY_MAPPINGS.get(name, name)
    if name not in MAPPINGS:
        raise ValueError(f"mapping must be one of {MAPPINGS}, got {name!r}")
    return name


def prepare(means, scales, rotations, opacities, mapping: str = DEFAULT_MAPPING,
            kappa: float = 1.0) -> Mixture:
    """Build a :class:`Mixture` from raw 3DGS parameters.

    Args:
        means: [N, 3] centres, metres, world.
        scales: [N, 3] per-axis standard deviations, metres (linear, ≥ 0).
        rotations: [N, 4] w-first quaternions (normalized here) or [N, 3, 3] matrices.
        opacities: [N] peak opacities α ∈ [0, 1].
        mapping: opacity→absorption mapping, one of MAPPINGS.
        kappa: absorption scale κ > 0.
    """
    mapping = canonical_mapping(mapping)
    if not (np.isfinite(kappa) and kappa > 0):
        raise ValueError(f"kappa must be positive and finite, got {kappa!r}")
    means = np.asarray(means, np.float64).reshape(-1, 3)
    n = len(means)
    scales = np.abs(np.asarray(scales, np.float64).reshape(n, 3))
    rot = np.asarray(rotations, np.float64)
    if rot.shape == (n, 4):
        R = _quat_to_matrix(rot)
    else:
        R = rot.reshape(n, 3, 3)
    s_max = np.maximum(scales.max(axis=1) if n else np.zeros(0), SCALE_FLOOR_ABSOLUTE)
    s = np.maximum(scales / s_max[:, None], SCALE_FLOOR_RELATIVE)  # normalized, ≤ 1
    s2 = s * s
    # adj Σ̃ = R diag(s2_j s2_k) Rᵀ: the cofactors of the diagonal form.
    cof = np.stack([s2[:, 1] * s2[:, 2], s2[:, 0] * s2[:, 2], s2[:, 0] * s2[:, 1]], axis=1)
    det = s2.prod(axis=1)
    alpha = np.clip(np.asarray(opacities, np.float64).reshape(n), 0.0, ALPHA_MAX)
    tau_star = -np.log1p(-alpha)
    beta_sigma = _beta_sigma(mapping, float(kappa), tau_star, s_max, s)
    return Mixture(means, s_max, R, s2, cof, det, s.min(axis=1), alpha, tau_star, mapping,
                   float(kappa), beta_sigma)


def _beta_sigma(mapping, kappa, tau_star, s_max, s):
    """[N] β·√(2π)·s_max per fixed-β mapping (paper Eq. 5; Sec. 4.4 B), from normalized scales s̃.

    With Ã = s_max² A and Σ̃ = Σ / s_max² (both dimensionless):
    avg:    β√(2π) s_max = κτ* √(tr Ã / 3)
    simple: β√(2π) s_max = κτ* √(2π) s_max
    mass:   β√(2π) s_max = κτ* / (2π s_max² √det Σ̃)   (det in the local frame)
    diag:   β√(2π) s_max = κτ* / (2π s_max² s̃_x s̃_y s̃_z)
    """
    n = len(tau_star)
    if mapping == "peak":
        return np.full(n, np.nan)
    kt = kappa * tau_star
    if mapping == "avg":
        out = kt * np.sqrt((1.0 / (s * s)).sum(axis=1) / 3.0)
    elif mapping == "simple":
        out = kt * math.sqrt(2 * math.pi) * s_max
    elif mapping == "mass":
        # det of the covariance in the Gaussian's local frame, where it is diag(s̃²)
        # (paper Sec. 4.4): a world-frame det(R S² Rᵀ) would lose the relative
        # precision of a thin disc's small eigenvalue (≈ 1e-4 at s_min/s_max = 1e-6).
        out = kt / (2 * math.pi * s_max ** 2 * np.sqrt((s * s).prod(axis=1)))
    else:  # diag
        out = kt / (2 * math.pi * s_max ** 2 * s.prod(axis=1))
    return np.minimum(out, TAU_CENTRE_MAX)


def from_gaussians(g, mapping: str = DEFAULT_MAPPING, kappa: float = 1.0) -> Mixture:
    """:func:`prepare` from a :class:`relight_cli.formats.gaussians_ply.Gaussians`."""
    return prepare(g.means, g.scales, g.rotations, g.opacities, mapping, kappa)


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    from relight_cli.formats.gaussians_ply import quaternion_to_matrix
    return quaternion_to_matrix(q)


# ------------------------------------------------------------------ per-pair geometry


@dataclass
class PairTerms:
    """Per (ray, Gaussian) pair quantities, world units.

    Attributes:
        t_star: [P] ray parameter of the Mahalanobis closest approach, metres.
        sigma_t: [P] standard deviation along the ray, metres (> 0).
        m2: [P] squared Mahalanobis distance of the ray from the centre.
        half_amplitude: [P] ½ τ_peak e^{−½m²}: the term equals
            half_amplitude · [erf(u(t1)) − erf(u(t0))].
    """

    t_star: np.ndarray
    sigma_t: np.ndarray
    m2: np.ndarray
    half_amplitude: np.ndarray

    def u(self, t) -> np.ndarray:
        """[P] erf argument u(t) = (t − t*) / (√2 σ_t) (t broadcast)."""
        return (t - self.t_star) / (_SQRT2 * self.sigma_t)


def pair_terms(mix: Mixture, origins, directions, gaussian_index,
               dtype=np.float64) -> PairTerms:
    """Closed-form terms for ray/Gaussian pairs.

    Args:
        mix: prepared mixture.
        origins: [P, 3] (or broadcastable) ray origins, metres, world.
        directions: [P, 3] unit ray directions.
        gaussian_index: [P] int index into ``mix``.
        dtype: np.float64 (reference) or np.float32 (fast path); the per-Gaussian
            normalization is done in float64 before the cast.
    """
    gi = np.asarray(gaussian_index, np.int64)
    o = np.asarray(origins, np.float64)
    rot = mix.rotation[gi]
    # Principal-frame coordinates d_l = Rᵀd, r_l = Rᵀ(o − μ)/s_max, projected in
    # float64 and only then cast: each component keeps its own relative precision,
    # so a ray 1 µm off a 1 µm thin disc is still resolved in float32.
    d_l = np.einsum("pji,pj->pi", rot, np.asarray(directions, np.float64)).astype(dtype)
    r_l = np.einsum("pji,pj->pi", rot, (o - mix.means[gi]) / mix.scale_max[gi, None]).astype(dtype)
    return local_pair_terms(mix, r_l, d_l, gi, dtype)


def local_pair_terms(mix: Mixture, r_l, d_l, gaussian_index, dtype=np.float64) -> PairTerms:
    """:func:`pair_terms` from principal-frame inputs (for callers that batch them).

    Args:
        r_l: [P, 3] Rᵀ(o − μ)/s_max, the ray origin in the Gaussian's normalized frame.
        d_l: [P, 3] Rᵀd, the unit direction in the Gaussian's frame.
        gaussian_index: [P] int.
    """
    gi = gaussian_index
    smax = mix.scale_max[gi]
    cof = mix.cof[gi].astype(dtype, copy=False)
    var = mix.var[gi].astype(dtype, copy=False)
    A = np.einsum("pi,pi->p", cof, d_l * d_l)                 # dᵀ adjΣ̃ d ≥ min cof > 0
    c = np.cross(r_l, d_l)                                    # (r × d) in the local frame
    m2 = np.einsum("pi,pi->p", var, c * c) / A                # cᵀΣ̃c / dᵀadjΣ̃d
    t_star = -np.einsum("pi,pi->p", cof * d_l, r_l) / A       # normalized units
    sigma = np.sqrt(mix.det[gi].astype(dtype) / A)            # normalized units
    smax_t = smax.astype(dtype)
    t_star = t_star * smax_t
    sigma_t = sigma * smax_t
    tau_peak = _tau_peak(mix, gi, d_l, sigma, var, dtype)
    half_amp = (0.5 * tau_peak * np.exp(-0.5 * m2)).astype(dtype)
    return PairTerms(t_star, sigma_t, m2, half_amp)


def _tau_peak(mix: Mixture, gi, d_l, sigma_norm, var, dtype):
    """[P] optical depth through the centre along d, per mapping (see module doc)."""
    if mix.mapping == "peak":
        return (mix.kappa * mix.tau_star[gi]).astype(dtype)
    # fixed β (Eq. 1): β √(2π) σ_t(d) = beta_sigma · σ̃(d)
    return mix.beta_sigma[gi].astype(dtype) * sigma_norm


# ------------------------------------------------------------------ erf differences


def erf_difference(u0, u1) -> np.ndarray:
    """erf(u1) − erf(u0) for u0 ≤ u1, without cancellation near ±1 or for u1 ≈ u0.

    Both arrays broadcast; the result has their dtype (float32 or float64).
    """
    from scipy.special import erf, erfc

    u0, u1 = np.broadcast_arrays(np.asarray(u0), np.asarray(u1))
    dtype = np.result_type(u0.dtype, u1.dtype, np.float32)
    u0 = u0.astype(dtype, copy=False)
    u1 = u1.astype(dtype, copy=False)
    out = np.empty(u0.shape, dtype)
    mid = 0.5 * (u0 + u1)
    half = 0.5 * (u1 - u0)
    short = half * np.maximum(1, np.abs(mid)) <= 0.25
    pos = ~short & (u0 >= 0)
    neg = ~short & (u1 <= 0)
    mixed = ~short & ~pos & ~neg
    if pos.any():
        out[pos] = erfc(u0[pos]) - erfc(u1[pos])
    if neg.any():
        out[neg] = erfc(-u1[neg]) - erfc(-u0[neg])
    if mixed.any():
        out[mixed] = erf(u1[mixed]) - erf(u0[mixed])
    if short.any():
        m = mid[short].astype(np.float64)
        h = half[short].astype(np.float64)
        s = m[:, None] + h[:, None] * _GL_X[None, :]
        out[short] = (2 / _SQRT_PI) * h * (np.exp(-s * s) @ _GL_W)
    return out


def segment_terms(terms: PairTerms, t0, t1) -> np.ndarray:
    """[P] optical depth of each pair over the segment t ∈ [t0, t1] (0 when t1 ≤ t0)."""
    t0 = np.asarray(t0, terms.t_star.dtype)
    t1 = np.asarray(t1, terms.t_star.dtype)
    t1 = np.maximum(t1, t0)
    u0 = terms.u(t0)
    u1 = terms.u(t1)
    return terms.half_amplitude * erf_difference(u0, u1)


# ------------------------------------------------------------------ public queries


def optical_depth(mix: Mixture, origins, directions, t0, t1, dtype=np.float64,
                  chunk: int = 1 << 21) -> np.ndarray:
    """τ along R rays through all N Gaussians (dense R×N, chunked).

    Args:
        mix: prepared mixture.
        origins: [R, 3] metres, world.
        directions: [R, 3] unit.
        t0, t1: [R] (or scalars) segment bounds along each ray, metres; t1 ≤ t0 → τ = 0.
        dtype: np.float64 (reference precision) or np.float32 (fast path).
    Returns:
        [R] optical depth (float64 accumulation of the chosen-precision terms).
    """
    origins = np.asarray(origins, np.float64).reshape(-1, 3)
    directions = np.asarray(directions, np.float64).reshape(-1, 3)
    n_rays = len(origins)
    t0 = np.broadcast_to(np.asarray(t0, np.float64), (n_rays,))
    t1 = np.broadcast_to(np.asarray(t1, np.float64), (n_rays,))
    n = len(mix)
    tau = np.zeros(n_rays)
    if n == 0 or n_rays == 0:
        return tau
    rays_per_chunk = max(1, chunk // n)
    for start in range(0, n_rays, rays_per_chunk):
        stop = min(n_rays, start + rays_per_chunk)
        ri = np.repeat(np.arange(start, stop), n)
        gi = np.tile(np.arange(n), stop - start)
        terms = pair_terms(mix, origins[ri], directions[ri], gi, dtype)
        seg = segment_terms(terms, t0[ri], t1[ri]).astype(np.float64)
        tau[start:stop] = seg.reshape(stop - start, n).sum(axis=1)
    return tau


def transmittance(mix: Mixture, origins, directions, t0, t1, dtype=np.float64) -> np.ndarray:
    """[R] T = exp(−τ) along segments (see :func:`optical_depth`)."""
    return np.exp(-optical_depth(mix, origins, directions, t0, t1, dtype))


def transmittance_between(mix: Mixture, light, points, dtype=np.float64) -> np.ndarray:
    """[M] transmittance from a point light [3] to points [M, 3] (metres, world).

    A point at the light's position has T = 1.
    """
    light = np.asarray(light, np.float64).reshape(3)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    v = points - light
    dist = np.linalg.norm(v, axis=1)
    d = np.where(dist[:, None] > 0, v / np.where(dist > 0, dist, 1)[:, None], [0.0, -1.0, 0.0])
    return transmittance(mix, np.broadcast_to(light, points.shape), d, 0.0, dist, dtype)
