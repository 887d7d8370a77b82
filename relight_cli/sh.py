"""Real spherical harmonics (orthonormal, Condon–Shortley phase as in 3DGS).

Index l² + l + m, m = −l..l.  The polar axis is world +Z and the azimuth is
atan2(y, x), so degree 1 is (−C1·y, C1·z, −C1·x) with C1 = √(3/4π), exactly the
3DGS convention.  Fitting with exact solid angles and ridge regularization
(paper Eq. 7) and the Lambertian cosine convolution (Ramamoorthi & Hanrahan
2001) live here too.
"""

from __future__ import annotations

import math

import numpy as np


def n_coefficients(degree: int) -> int:
    return (degree + 1) ** 2


def sh_basis(directions: np.ndarray, degree: int) -> np.ndarray:
    """Evaluate the real SH basis.

    Args:
        directions: [N, 3] directions (normalized here; zero vectors give the
            value at +Z).
        degree: maximum band l (≥ 0).

    Returns:
        [N, (degree+1)²] float64.
    """
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(norm > 0, d / np.where(norm > 0, norm, 1), np.array([0.0, 0.0, 1.0]))
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    n = len(d)
    out = np.zeros((n, n_coefficients(degree)))
    # Associated Legendre P_l^m(z) with the Condon–Shortley phase, times the
    # azimuthal factors written in x, y (cos mφ sinᵐθ and sin mφ sinᵐθ) so that
    # nothing divides by sin θ at the poles.
    cos_m = [np.ones(n)]   # sinᵐθ·cos(mφ)
    sin_m = [np.zeros(n)]  # sinᵐθ·sin(mφ)
    for m in range(1, degree + 1):
        c, s = cos_m[-1], sin_m[-1]
        cos_m.append(x * c - y * s)
        sin_m.append(x * s + y * c)
    # Q_l^m = P_l^m / sinᵐθ, a polynomial in z (recurrences from DLMF 14.10).
    q = {}
    for m in range(degree + 1):
        q[(m, m)] = (-1) ** m * _double_factorial(2 * m - 1) * np.ones(n)
        if m + 1 <= degree:
            q[(m + 1, m)] = (2 * m + 1) * z * q[(m, m)]
        for l in range(m + 2, degree + 1):
            q[(l, m)] = ((2 * l - 1) * z * q[(l - 1, m)] - (l + m - 1) * q[(l - 2, m)]) / (l - m)
    for l in range(degree + 1):
        for m in range(0, l + 1):
            k = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - m) / math.factorial(l + m))
            if m == 0:
                out[:, l * l + l] = k * q[(l, 0)]
            else:
                out[:, l * l + l + m] = math.sqrt(2) * k * q[(l, m)] * cos_m[m]
                out[:, l * l + l - m] = math.sqrt(2) * k * q[(l, m)] * sin_m[m]
    return out


def _double_factorial(n: int) -> int:
    return 1 if n <= 0 else n * _double_factorial(n - 2)


def fit_sh(directions: np.ndarray, values: np.ndarray, weights: np.ndarray, degree: int,
           ridge: float = 0.0) -> np.ndarray:
    """Weighted ridge least squares: argmin_c Σ w_i |B(ω_i)c − L_i|² + λ|c|².

    With weights = exact solid angles this approximates the projection integral
    ∫ L Y dω and stays well-posed when directions cover only part of the sphere.
    The normal equations are summed over blocks of :data:`FIT_BLOCK` samples, so
    a 1k HDRI at degree 16 needs a few tens of MB, not the [N, K] basis at once
    (a map of at most FIT_BLOCK texels is one block, as before).

    Args:
        directions: [N, 3]; values: [N, C]; weights: [N] (≥ 0, e.g. steradians).
        degree: SH degree; ridge: λ ≥ 0.

    Returns:
        [(degree+1)², C] coefficients.
    """
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    w = np.asarray(weights, np.float64).reshape(-1)
    v = np.asarray(values, np.float64).reshape(len(w), -1)
    k = n_coefficients(degree)
    gram = ridge * np.eye(k)
    rhs = np.zeros((k, v.shape[1]))
    for start in range(0, max(len(w), 1), FIT_BLOCK):
        basis = sh_basis(d[start:start + FIT_BLOCK], degree)            # [B, K]
        gram = gram + basis.T @ (basis * w[start:start + FIT_BLOCK, None])
        rhs = rhs + basis.T @ (v[start:start + FIT_BLOCK] * w[start:start + FIT_BLOCK, None])
    return np.linalg.solve(gram, rhs)


#: Samples per block of :func:`fit_sh`'s normal equations ([65536, 289] float64 = 150 MB
#: at degree 16; a 64×128 map or a 64² scene probe's 24576 pixels are one block).
FIT_BLOCK = 65536


# ------------------------------------------------------------------ deringing windows

#: ``--window`` names: no window, or a standard deringing window (Sloan, "Stupid
#: Spherical Harmonics (SH) Tricks", GDC 2008, sec. "Windowing").
WINDOWS = ("none", "hanning", "lanczos")


def window_factors(kind: str, degree: int) -> np.ndarray:
    """[degree+1] per-band factors h_l of a deringing window of width w = degree + 1.

    ``none``: h_l = 1.  ``hanning``: h_l = (1 + cos(π l / w)) / 2.  ``lanczos``
    (Lanczos σ factors): h_l = sin(π l / w) / (π l / w), h_0 = 1.  Multiplying
    band l of a probe by h_l convolves its radiance with a zonal kernel, which
    damps the Gibbs ringing of a truncated expansion (negative lobes) at the
    price of blur: the irradiance of a windowed probe is less accurate at the
    same degree (formats/sh_probe_json.md has the measured trade).
    """
    if kind not in WINDOWS:
        raise ValueError(f"window must be one of {WINDOWS}, got {kind!r}")
    band = np.arange(degree + 1, dtype=np.float64) / (degree + 1)
    if kind == "hanning":
        return (1 + np.cos(math.pi * band)) / 2
    if kind == "lanczos":
        return np.sinc(band)          # numpy's sinc is sin(πx)/(πx)
    return np.ones(degree + 1)


def apply_window(coefficients: np.ndarray, kind: str) -> np.ndarray:
    """[(d+1)², C] coefficients with band l scaled by :func:`window_factors` (a copy)."""
    c = np.asarray(coefficients, np.float64)
    degree = int(round(math.sqrt(c.shape[0]))) - 1
    factors = window_factors(kind, degree)
    per_coef = np.concatenate([np.full(2 * l + 1, factors[l]) for l in range(degree + 1)])
    return c * per_coef.reshape(-1, *([1] * (c.ndim - 1)))


def lambert_band_factors(degree: int) -> np.ndarray:
    """Â_l of the clamped-cosine kernel: irradiance E_lm = Â_l · L_lm.

    Â_0 = π, Â_1 = 2π/3, Â_l = 0 for odd l > 1, and for even l
    Â_l = 2π (−1)^(l/2−1) / ((l+2)(l−1)) · l! / (2^l ((l/2)!)²).
    """
    out = np.zeros(degree + 1)
    for l in range(degree + 1):
        if l == 0:
            out[l] = math.pi
        elif l == 1:
            out[l] = 2 * math.pi / 3
        elif l % 2 == 0:
            out[l] = (2 * math.pi * (-1) ** (l // 2 - 1) / ((l + 2) * (l - 1))
                      * math.factorial(l) / (2 ** l * math.factorial(l // 2) ** 2))
    return out


def irradiance_coefficients(radiance_coefficients: np.ndarray) -> np.ndarray:
    """Convolve radiance SH [(d+1)², C] with the clamped cosine → irradiance SH."""
    c = np.asarray(radiance_coefficients, np.float64)
    degree = int(round(math.sqrt(c.shape[0]))) - 1
    factors = lambert_band_factors(degree)
    per_coef = np.concatenate([np.full(2 * l + 1, factors[l]) for l in range(degree + 1)])
    return c * per_coef.reshape(-1, *([1] * (c.ndim - 1)))


def evaluate_sh(coefficients: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Σ_k c_k Y_k(ω): [(d+1)², C] coefficients at [N, 3] directions → [N, C]."""
    c = np.asarray(coefficients, np.float64)
    degree = int(round(math.sqrt(c.shape[0]))) - 1
    return sh_basis(directions, degree) @ c.reshape(c.shape[0], -1)
