"""Spherical-harmonic light probes (paper Eq. 7 and Sec. 3.4).

A probe is radiance L(ω) ≈ Σ_k c_k Y_k(ω), coefficients [(d+1)², 3], fitted by
weighted ridge least squares with exact solid angles as weights:

    c = argmin Σ_i Δω_i |B(ω_i) c − L_i|² + λ |c|²        (Eq. 7)

from an environment map (texel directions and exact texel solid angles,
``relight_cli.envmap``) or from six 90° cube faces of a Gaussian scene rendered
at a point with the CPU splatter (exact pinhole-pixel solid angles).  The
``auto`` degree is the smallest one whose cosine-convolved irradiance is within
a tolerance of a high degree's: model only the lighting the scene has.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relight_cli.formats.camera import Camera
from relight_cli.formats.envmap import EnvMap
from relight_cli.formats.gaussians_ply import Gaussians
from relight_cli.sh import fit_sh, irradiance_coefficients, sh_basis

AUTO_MAX_DEGREE = 8
# (forward, down) axes of the six faces; right = down × forward (OpenCV x right, y down, z forward).
CUBE_FACES = {
    "+X": ((1, 0, 0), (0, -1, 0)), "-X": ((-1, 0, 0), (0, -1, 0)),
    "+Y": ((0, 1, 0), (0, 0, 1)), "-Y": ((0, -1, 0), (0, 0, -1)),
    "+Z": ((0, 0, 1), (0, -1, 0)), "-Z": ((0, 0, -1), (0, -1, 0)),
}


@dataclass
class Samples:
    """Radiance samples on the sphere: directions [N, 3] (unit, world), radiance [N, 3], weights [N] (sr)."""

    directions: np.ndarray
    radiance: np.ndarray
    weights: np.ndarray


def env_samples(env: EnvMap) -> Samples:
    """Texel-centre directions, radiance and exact texel solid angles (Σ weights = 4π)."""
    from relight_cli import envmap as E
    return Samples(E.directions(env).reshape(-1, 3), env.radiance.reshape(-1, 3).astype(np.float64),
                   np.asarray(E.solid_angles(env), np.float64).reshape(-1))


def fit_probe(samples: Samples, degree: int, ridge: float = 0.0) -> np.ndarray:
    """Eq. 7: [(degree+1)², 3] SH radiance coefficients by solid-angle-weighted ridge LS."""
    return fit_sh(samples.directions, samples.radiance, samples.weights, degree, ridge)


def fibonacci_sphere(n: int) -> np.ndarray:
    """[n, 3] nearly uniform unit directions (golden-angle spiral; deterministic)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(np.clip(1 - z * z, 0, None))
    phi = np.pi * (3 - np.sqrt(5)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def irradiance_from_sh(coefficients: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """[N, 3] irradiance E(n) = ∫ L(ω) max(n·ω, 0) dω of an SH radiance probe (Ramamoorthi–Hanrahan)."""
    c = irradiance_coefficients(coefficients)
    degree = int(round(np.sqrt(c.shape[0]))) - 1
    return sh_basis(normals, degree) @ c


def fit_nested(samples: Samples, max_degree: int, ridge: float = 0.0) -> dict[int, np.ndarray]:
    """Eq. 7 fits for every degree 0..max_degree from one basis evaluation.

    The SH basis is nested (degree d's functions are the first (d+1)² of any
    higher degree's), so the normal equations of degree d are the leading
    block of max_degree's: identical to :func:`fit_probe` per degree, computed once.
    """
    basis = sh_basis(samples.directions, max_degree)                 # [N, K]
    w = np.asarray(samples.weights, np.float64)
    gram = basis.T @ (basis * w[:, None])
    rhs = basis.T @ (np.asarray(samples.radiance, np.float64) * w[:, None])
    out = {}
    for d in range(max_degree + 1):
        k = (d + 1) ** 2
        out[d] = np.linalg.solve(gram[:k, :k] + ridge * np.eye(k), rhs[:k])
    return out


@dataclass
class DegreeChoice:
    """Result of the ``auto`` degree search.

    Attributes:
        degree: chosen degree.
        coefficients: [(degree+1)², 3] the fit at that degree.
        errors: {degree: relative RMS irradiance error vs the reference degree} (degrees tried).
        reference_degree: the high degree compared against.
        tolerance: the threshold used.
    """

    degree: int
    coefficients: np.ndarray
    errors: dict
    reference_degree: int
    tolerance: float


def choose_degree(samples: Samples, tolerance: float = 0.01, ridge: float = 0.0,
                  max_degree: int = AUTO_MAX_DEGREE, n_normals: int = 1024) -> DegreeChoice:
    """Smallest degree whose cosine-convolved irradiance is within ``tolerance`` of degree ``max_degree``'s.

    Error = ‖E_d − E_max‖ / ‖E_max‖, RMS over normals on a Fibonacci sphere and
    the three channels: the relative average irradiance error of Ramamoorthi &
    Hanrahan (2001), by which degree 2 is within ~1% for typical environments
    while a lone point light needs more (its max error at degree 2 is ~9%).
    Zero lighting gives degree 0.
    """
    normals = fibonacci_sphere(n_normals)
    fits = fit_nested(samples, max_degree, ridge)
    reference = irradiance_from_sh(fits[max_degree], normals)
    scale = float(np.sqrt(np.mean(reference ** 2)))
    errors = {}
    for d in range(max_degree + 1):
        e = irradiance_from_sh(fits[d], normals)
        errors[d] = float(np.sqrt(np.mean((e - reference) ** 2)) / scale) if scale > 0 else 0.0
        if errors[d] <= tolerance:
            return DegreeChoice(d, fits[d], errors, max_degree, tolerance)
    return DegreeChoice(max_degree, fits[max_degree], errors, max_degree, tolerance)


# ------------------------------------------------------------------ scene probes


def cube_face_cameras(position, size: int) -> list[Camera]:
    """Six 90° pinhole cameras at ``position`` (metres, world), ``size``×``size`` pixels.

    f = size/2 and the principal point at (size−1)/2 put the pixel *edges* at
    ±45°, so the six faces tile the sphere exactly.
    """
    position = np.asarray(position, np.float64)
    cams = []
    for name, (forward, down) in CUBE_FACES.items():
        fwd, dwn = np.asarray(forward, np.float64), np.asarray(down, np.float64)
        right = np.cross(dwn, fwd)
        R = np.stack([right, dwn, fwd])
        c = (size - 1) / 2
        K = np.array([[size / 2, 0, c], [0, size / 2, c], [0, 0, 1.0]])
        cams.append(Camera(K, R, -R @ position, size, size, name))
    return cams


def pixel_directions_and_solid_angles(camera: Camera):
    """[H·W, 3] unit world directions through pixel centres and [H·W] exact pixel solid angles (sr)."""
    K = camera.K
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    xs = (np.arange(camera.width) - cx) / fx
    ys = (np.arange(camera.height) - cy) / fy
    X, Y = np.meshgrid(xs, ys)
    d_cam = np.stack([X, Y, np.ones_like(X)], axis=-1).reshape(-1, 3)
    d = d_cam @ camera.R                                   # camera → world: Rᵀ d
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hx, hy = 0.5 / fx, 0.5 / fy

    def f(a, b):  # solid angle of [0, a]×[0, b] on the plane z = 1 (signed)
        return np.arctan2(a * b, np.sqrt(a * a + b * b + 1))
    a0, a1 = X - hx, X + hx
    b0, b1 = Y - hy, Y + hy
    omega = np.abs(f(a1, b1) - f(a0, b1) - f(a1, b0) + f(a0, b0)).reshape(-1)
    return d, omega


def scene_samples(scene: Gaussians, position, size: int = 64, near: float = 0.01,
                  background=(0.0, 0.0, 0.0), progress=None) -> Samples:
    """Render the six cube faces of ``scene`` at ``position`` and return their radiance samples."""
    from .splat import render
    dirs, rad, w = [], [], []
    cams = cube_face_cameras(position, size)
    for cam in (progress(cams) if progress else cams):
        out = render(scene, cam, background=background, near=near)
        d, omega = pixel_directions_and_solid_angles(cam)
        dirs.append(d)
        rad.append(out.image.reshape(-1, 3))
        w.append(omega)
    return Samples(np.concatenate(dirs), np.concatenate(rad), np.concatenate(w))
