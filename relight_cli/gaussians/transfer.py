"""Per-Gaussian SH radiance transfer (paper Sec. 3.4, Eq. 9–10) and DGSM shadow attenuation.

Relighting an avatar Gaussian i with normal n_i under an SH probe L(ω) = Σ c_k Y_k(ω):

* Transfer (Eq. 9): a clamped cosine lobe of exponent q, t(ω) = max(n·ω, 0)^q,
  normalized to unit mass, so the shading is the lobe-weighted mean radiance

      S_i = ∫ L(ω) t(ω) dω / ∫ t(ω) dω,

  in closed form by Funk–Hecke: S(n) = Σ_{l,m} a_l(q) c_lm Y_lm(n), with
  a_l(q) = 2π I_l(q) / (2π/(q+1)), I_l(q) = ∫_0^1 μ^q P_l(μ) dμ.  For q = 1 this is
  the irradiance divided by π; a uniform environment of radiance 1 gives S = 1.
* Relit colour (Eq. 10): c'_i = γ · ρ_i ⊙ clip(S_i, 0, t_max), with ρ_i the
  Gaussian's captured degree-0 colour (0.5 + C0·f_dc) taken as its albedo, γ
  a global intensity, and t_max a clip against blow-out from bright probes.
  Higher SH bands (captured view dependence) are scaled by the same factor.

Normals: the Gaussian's shortest axis (a flat splat's surface normal), or the
smallest principal axis of its k nearest neighbours (local PCA), oriented away
from the opacity-weighted centroid (outward for star-shaped avatars).

Receivers (scene Gaussians) are shadowed by DGSM transmittance (paper Sec. 3.3:
"we multiply the direct term of its color by this transmittance").  A
receiver's captured colour c is split into the direct light of the L point
lights and the rest (ambient/indirect light and anything the lights do not
explain, never shadowed):

    c = (1 − s)·c  +  s·c,        s·c = Σ_l s·c·w_l,c / Σ_k w_k,c,

with s the direct share (``--shadow-strength``) and w_l,c light l's share of
the direct light in channel c.  Each light's part is multiplied by that light's
transmittance T_l:

    c'_c = c_c · [(1 − s) + s · Σ_l w_l,c T_l / Σ_l w_l,c]      (per channel).

The paper's reading is s = 1 (the whole captured colour is direct light, so a
full shadow is black).  ``--shadow-strength auto`` (this toolkit's default,
:func:`direct_share`) estimates s per receiver and channel as the share of its
light that the DGSM's point lights deliver, against the SH probe's light:

    s_c = E_d,c / (E_d,c + E_p,c),   E_d,c = Σ_l I_l C_l,c |n·ω_l| / r_l²,
    E_p,c = π · S_c(n)  (Eq. 9 with q = 1: the probe's irradiance),

n the receiver's normal turned towards the lights.  Both are in the units of
the lights file and the probe, so the estimate is as good as their agreement;
a receiver neither lights (E_d = 0) keeps its colour.  The same formula gives
an inserted object its shadow from the others when the lights also light it
directly (``relight --direct-light``, :func:`direct_irradiance`): its colour
ρ·(S + D) with D = Σ_l I_l C_l max(n·ω_l, 0)/(π r_l²) has direct share D/(S + D),
and (1 − s) + s·Σ D_l T_l / D = (S + Σ D_l T_l)/(S + D): each light's term
times its transmittance, exactly.

Weights (:func:`direct_light_weights`, ``--light-weights``):

* ``intensity`` (default; the paper's "weighted by the light's intensity"):
  w_l,c = I_l · C_l,c, the light's intensity times its colour (so a red light's
  shadow takes away red);
* ``irradiance`` (this toolkit's): w_l,c = I_l · C_l,c · |n·ω_l| / r_l², the
  direct irradiance each light delivers to that receiver (n its normal, ω_l
  and r_l the direction and distance to the light); a receiver no light
  reaches (all w = 0) keeps its colour;
* ``equal``: w = 1, the unweighted mean T of the versions before DGSM 2 (and
  the fallback for version 1 maps, which stored no intensities).
"""

from __future__ import annotations

import math

import numpy as np

from relight_cli.formats.gaussians_ply import Gaussians, rgb_to_sh_dc
from relight_cli.sh import sh_basis

NORMAL_METHODS = ("auto", "axis", "pca", "stored")


def lobe_moments(q: float, degree: int) -> np.ndarray:
    """[degree+1] I_l(q) = ∫_0^1 μ^q P_l(μ) dμ for q ≥ 0.

    I_0 = 1/(q+1), I_1 = 1/(q+2) and I_l = (q − l + 2)/(q + l + 1) · I_{l−2}
    (integrate the Legendre recurrence by parts; exact for real q ≥ 0).
    """
    out = np.zeros(degree + 1)
    out[0] = 1.0 / (q + 1)
    if degree >= 1:
        out[1] = 1.0 / (q + 2)
    for l in range(2, degree + 1):
        out[l] = (q - l + 2) / (q + l + 1) * out[l - 2]
    return out


def lobe_band_factors(q: float, degree: int) -> np.ndarray:
    """[degree+1] a_l(q): S(n) = Σ a_l c_lm Y_lm(n) for the unit-mass lobe max(n·ω,0)^q.

    Funk–Hecke: ∫ Y_lm(ω) max(n·ω,0)^q dω = 2π I_l(q) Y_lm(n); the lobe's mass is
    2π/(q+1).  For q = 1, a_l = Â_l / π with the Lambertian Â_l.
    """
    return lobe_moments(q, degree) * (q + 1)


def shading(probe_coefficients: np.ndarray, normals: np.ndarray, q: float = 1.0) -> np.ndarray:
    """[N, 3] lobe-weighted mean radiance S(n) of an SH probe [(d+1)², 3] at unit normals [N, 3]."""
    c = np.asarray(probe_coefficients, np.float64)
    degree = int(round(math.sqrt(c.shape[0]))) - 1
    a = lobe_band_factors(q, degree)
    per_coef = np.concatenate([np.full(2 * l + 1, a[l]) for l in range(degree + 1)])
    return sh_basis(normals, degree) @ (c * per_coef[:, None])


def shading_reference(radiance_fn, normals: np.ndarray, q: float = 1.0, n: int = 200_000,
                      seed: int = 0) -> np.ndarray:
    """Slow twin of :func:`shading`: quasi-uniform sphere quadrature of ∫ L t dω / ∫ t dω.

    ``radiance_fn(directions [M, 3]) -> [M, 3]``.  Tests only.
    """
    from .probe import fibonacci_sphere
    d = fibonacci_sphere(n)
    rng = np.random.default_rng(seed)
    d = d @ _random_rotation(rng)                      # decorrelate from the spiral's axis
    L = radiance_fn(d)                                 # [M, 3]
    out = []
    for nrm in np.asarray(normals, np.float64).reshape(-1, 3):
        w = np.clip(d @ nrm, 0, None) ** q
        out.append((w[:, None] * L).sum(0) / w.sum())
    return np.array(out)


def _random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.diag(r))


def estimate_normals(g: Gaussians, method: str = "auto", neighbours: int = 16) -> np.ndarray:
    """[N, 3] unit normals, oriented away from the opacity-weighted centroid.

    ``axis``: the rotation column of the smallest scale; ``pca``: the smallest
    eigenvector of the covariance of the k nearest centres; ``stored``: the
    file's nx, ny, nz; ``auto``: stored if present, else axis.
    """
    if method not in NORMAL_METHODS:
        raise ValueError(f"normal method must be one of {NORMAL_METHODS}")
    if method == "auto":
        method = "stored" if g.normals is not None else "axis"
    if method == "stored":
        if g.normals is None:
            raise ValueError("the Gaussians have no stored normals")
        n = g.normals.copy()
    elif method == "axis":
        R = g.rotation_matrices()                                  # [N, 3, 3] columns = axes
        k = np.argmin(g.scales, axis=1)
        n = R[np.arange(len(g)), :, k]
    else:
        from scipy.spatial import cKDTree
        k = int(min(max(neighbours, 3), len(g)))
        _, idx = cKDTree(g.means).query(g.means, k=k)
        nb = g.means[idx.reshape(len(g), k)]                       # [N, k, 3]
        centred = nb - nb.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", centred, centred)
        _, vecs = np.linalg.eigh(cov)                              # ascending eigenvalues
        n = vecs[:, :, 0]
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(norm > 0, n / np.where(norm > 0, norm, 1), np.array([0.0, 1.0, 0.0]))
    centroid = (g.opacities[:, None] * g.means).sum(0) / max(g.opacities.sum(), 1e-300)
    flip = np.einsum("ij,ij->i", n, g.means - centroid) < 0
    n[flip] *= -1
    return n


def relight_gaussians(g: Gaussians, probe_coefficients: np.ndarray, q: float = 1.0,
                      intensity: float = 1.0, t_max: float = float("inf"),
                      normals: np.ndarray | None = None, normal_method: str = "auto",
                      extra: np.ndarray | None = None) -> Gaussians:
    """Eq. 9–10: a copy of ``g`` whose colours are the captured albedo times the probe's shading.

    Args:
        g: avatar Gaussians (world frame, as in the scene).
        probe_coefficients: [(d+1)², 3] SH radiance of the probe.
        q: cosine lobe exponent (> 0; 1 = Lambertian).
        intensity: γ, global multiplier.
        t_max: clip of the shading factor (per channel).
        normals: [N, 3] unit normals; estimated with ``normal_method`` when None.
        extra: [N, 3] shading added to S before the clip (``relight --direct-light``:
            the point lights' Σ E_l/π), or None.

    Returns:
        New Gaussians: DC = the relit colour, higher bands scaled per channel
        by the same factor γ·clip(S, 0, t_max); geometry and opacity unchanged;
        normals stored.
    """
    if normals is None:
        normals = estimate_normals(g, normal_method)
    s = shading(probe_coefficients, normals, q)
    if extra is not None:
        s = np.clip(s, 0.0, None) + extra
    factor = intensity * np.clip(s, 0.0, t_max)                                         # [N, 3]
    albedo = g.colors()
    sh = g.sh * factor[:, None, :]
    sh[:, 0, :] = rgb_to_sh_dc(albedo * factor)
    return Gaussians(g.means.copy(), g.scales.copy(), g.rotations.copy(), g.opacities.copy(), sh,
                     g.sh_degree, normals)


LIGHT_WEIGHTS = ("intensity", "irradiance", "equal")


def direct_light_weights(mode: str, intensities=None, colors=None, lights=None, points=None,
                         normals=None, n_lights: int | None = None) -> np.ndarray:
    """Each light's share of a receiver's direct light, per channel (paper Sec. 3.3).

    Args:
        mode: one of LIGHT_WEIGHTS (see the module doc).
        intensities: [L] light intensities ≥ 0 (None: 1).
        colors: [L, 3] linear RGB ≥ 0 (None: white).
        lights: [L, 3] positions, metres, world (``irradiance`` only).
        points: [M, 3] receiver centres, metres, world (``irradiance`` only).
        normals: [M, 3] unit receiver normals, either orientation (``irradiance`` only).
        n_lights: L, when neither intensities, colours nor positions are given.
    Returns:
        [L, 1, 3] (``intensity``, ``equal``) or [L, M, 3] (``irradiance``) weights ≥ 0.
    """
    if mode not in LIGHT_WEIGHTS:
        raise ValueError(f"light weights must be one of {LIGHT_WEIGHTS}, got {mode!r}")
    n = next(len(x) for x in (intensities, colors, lights, range(n_lights or 0)) if x is not None)
    if mode == "equal":
        return np.ones((n, 1, 3))
    if mode == "irradiance":
        return direct_irradiance(intensities, colors, lights, points, normals)
    i = np.ones(n) if intensities is None else np.asarray(intensities, np.float64).reshape(n)
    c = np.ones((n, 3)) if colors is None else np.asarray(colors, np.float64).reshape(n, 3)
    return (i[:, None] * c)[:, None, :]                                  # [L, 1, 3]


def facing_lights(points, normals, lights) -> np.ndarray:
    """[M, 3] ``normals`` flipped where needed to face the side the lights [L, 3] shine
    from (Σ_l n·(p_l − x)/|p_l − x|³ ≥ 0): a flat splat's axis has no inherent side."""
    n = np.asarray(normals, np.float64).copy()
    v = np.asarray(lights, np.float64)[:, None, :] - np.asarray(points, np.float64)[None]
    r = np.linalg.norm(v, axis=2)
    pull = (np.einsum("lmi,mi->lm", v, n) / np.maximum(r, 1e-12) ** 3).sum(0)
    n[pull < 0] *= -1
    return n


def direct_irradiance(intensities, colors, lights, points, normals, one_sided=False) -> np.ndarray:
    """[L, M, 3] E_l,c = I_l C_l,c cos / r_l² of point lights [L, 3] at receivers
    ``points`` [M, 3] with unit ``normals``: cos = |n·ω_l| (two-sided), or max(n·ω_l, 0)
    (``one_sided``, for outward-normal objects)."""
    n = len(lights)
    i = np.ones(n) if intensities is None else np.asarray(intensities, np.float64).reshape(n)
    c = np.ones((n, 3)) if colors is None else np.asarray(colors, np.float64).reshape(n, 3)
    v = np.asarray(lights, np.float64).reshape(n, 1, 3) - np.asarray(points, np.float64)[None]
    r2 = (v * v).sum(axis=2)
    r = np.sqrt(r2)
    dot = np.einsum("lmi,mi->lm", v, np.asarray(normals, np.float64)) / np.where(r > 0, r, 1)
    cos = np.maximum(dot, 0.0) if one_sided else np.abs(dot)
    geometry = np.where(r2 > 0, cos / np.where(r2 > 0, r2, 1), 0.0)
    return (i[:, None] * c)[:, None, :] * geometry[:, :, None]


def direct_share(direct: np.ndarray, probe_coefficients: np.ndarray, normals) -> np.ndarray:
    """[M, 3] s = E_d / (E_d + E_p) (module doc; ``--shadow-strength auto``).

    Args:
        direct: [M, 3] E_d, the lights' irradiance at each receiver (summed
            :func:`direct_irradiance`).
        probe_coefficients: [(d+1)², 3] SH radiance of the probe.
        normals: [M, 3] unit normals facing the lights (:func:`facing_lights`).
    Returns:
        s in [0, 1]; 0 where neither the lights nor the probe light the receiver.
    """
    e_probe = math.pi * np.clip(shading(probe_coefficients, normals, 1.0), 0.0, None)
    total = direct + e_probe
    return np.where(total > 0, direct / np.where(total > 0, total, 1), 0.0)


def effective_light_weights(mode: str, intensities) -> str:
    """``mode``, or ``equal`` when the shadow map stores no intensities (DGSM version 1)."""
    return "equal" if mode != "equal" and intensities is None else mode


def dgsm_light_weights(mode: str, shadow_map, receivers: Gaussians,
                       normals: np.ndarray | None = None) -> np.ndarray:
    """:func:`direct_light_weights` for a DGSM's lights at ``receivers`` ([L, 1|M, 3]).

    ``irradiance`` uses ``normals`` [M, 3] or the receivers' shortest axes.
    """
    if mode != "irradiance":
        return direct_light_weights(mode, shadow_map.intensities, shadow_map.colors,
                                    n_lights=len(shadow_map.lights))
    if normals is None:
        normals = estimate_normals(receivers, "axis")
    return direct_light_weights("irradiance", shadow_map.intensities, shadow_map.colors,
                                shadow_map.lights, receivers.means, normals)


def shadow_factor(transmittance: np.ndarray, weights: np.ndarray | None = None,
                  strength: float = 1.0) -> np.ndarray:
    """Multiplier (1 − s) + s·Σ_l w_l T_l / Σ_l w_l of receiver colours (module doc).

    Args:
        transmittance: [L, M] per-light T at the receivers.
        weights: None (equal), [L] (one weight per light), [L, 3] or [L, 1|M, 3]
            (per channel, from :func:`direct_light_weights`).
        strength: s, the direct share of the receivers' colour.
    Returns:
        [M] for None/[L] weights, else [M, 3].  Where Σ_l w_l = 0 (no direct
        light) the factor is 1.
    """
    T = np.atleast_2d(np.asarray(transmittance, np.float64))
    if weights is None or np.ndim(weights) == 1:
        w = np.ones(len(T)) if weights is None else np.asarray(weights, np.float64)
        mean = (w[:, None] * T).sum(0) / max(w.sum(), 1e-300)
        return 1.0 - strength * (1.0 - mean)
    w = np.asarray(weights, np.float64)
    if w.ndim == 2:
        w = w[:, None, :]
    w = np.broadcast_to(w, (T.shape[0], T.shape[1], 3))
    total = w.sum(axis=0)                                                # [M, 3]
    lit = (w * T[:, :, None]).sum(axis=0)
    mean = np.where(total > 0, lit / np.where(total > 0, total, 1), 1.0)
    return 1.0 - strength * (1.0 - mean)


def attenuate(g: Gaussians, factor: np.ndarray) -> Gaussians:
    """A copy of receivers ``g`` with colours (all SH bands and the 0.5 offset) scaled by factors.

    ``factor`` is [M] (grey) or [M, 3] (per channel).  Scaling the full colour
    0.5 + Σ sh Y by f means DC' = f·DC + (f − 1)·0.5/C0 and higher bands f·sh.
    """
    f = np.asarray(factor, np.float64)
    f = f.reshape(-1, 1) if f.ndim == 1 else f.reshape(-1, 3)
    sh = g.sh * f[:, None, :]
    sh[:, 0, :] = rgb_to_sh_dc(g.colors(clamp=False) * f)
    return Gaussians(g.means.copy(), g.scales.copy(), g.rotations.copy(), g.opacities.copy(), sh,
                     g.sh_degree, None if g.normals is None else g.normals.copy())
