"""Spherical-harmonic light probes (paper Eq. 7 and Sec. 3.4).

A probe is radiance L(ω) ≈ Σ_k c_k Y_k(ω), coefficients [(d+1)², 3], fitted by
weighted ridge least squares with exact solid angles as weights:

    c = argmin Σ_i Δω_i |B(ω_i) c − L_i|² + λ |c|²        (Eq. 7)

from an environment map (texel directions and exact texel solid angles,
``relight_cli.envmap``) or from six 90° cube faces of a Gaussian scene rendered
at a point with the CPU splatter (exact pinhole-pixel solid angles).  The
``auto`` degree is the smallest one whose cosine-convolved irradiance is within
a tolerance of a direct quadrature of the samples (no SH involved) and whose
radiance rings no deeper than a limit: model only the lighting the scene has.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relight_cli.formats.camera import Camera
from relight_cli.formats.envmap import EnvMap
from relight_cli.formats.gaussians_ply import Gaussians
from relight_cli.sh import apply_window, fit_sh, irradiance_coefficients, sh_basis

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
    return _solve_nested(gram, rhs, max_degree, ridge)


def _solve_nested(gram, rhs, max_degree, ridge, degrees=None) -> dict[int, np.ndarray]:
    out = {}
    for d in (range(max_degree + 1) if degrees is None else degrees):
        k = (d + 1) ** 2
        out[d] = np.linalg.solve(gram[:k, :k] + ridge * np.eye(k), rhs[:k])
    return out


# ------------------------------------------------------------------ the auto degree

# Defaults of `relight sh-probe --degree auto` (measured choices: formats/sh_probe_json.md).
AUTO_TOLERANCE = 0.03          # relative RMS irradiance error against the quadrature reference
AUTO_MAX_NEGATIVITY = 2.0      # deepest negative radiance allowed, in units of the mean radiance
SEARCH_HEIGHT = 64             # the search and the reference work on 64×128 lat-long cells
SEARCH_NORMALS = 1024          # Fibonacci-sphere normals the irradiance error is measured on


@dataclass
class Cells:
    """Radiance samples summed into the cells of a coarse lat-long grid (empty cells left out).

    Attributes:
        solid_angles: [M] Σ Δω of the samples in each cell (sr; Σ = 4π for a whole sphere).
        centroids: [M, 3] unit area-weighted mean direction of each cell's samples.
        power: [M, 3] Σ L Δω per channel.
        moments: [M, 3, 3] Σ L Δω ω per channel (channel, xyz): the cell's radiant vector.
    """

    solid_angles: np.ndarray
    centroids: np.ndarray
    power: np.ndarray
    moments: np.ndarray


def reduce_samples(samples: Samples, height: int = SEARCH_HEIGHT) -> Cells:
    """Sum samples into height×2·height lat-long cells (by the cell each direction falls in).

    Power and radiant vector are kept exactly (sums, no interpolation), so the
    irradiance of a cell that lies wholly above a surface's horizon,
    Σ L Δω max(n·ω, 0) = n·Σ L Δω ω, is exact whatever the cell size; only
    cells the horizon cuts are approximated.  Works for any sample set (env
    map texels of either layout, or a scene probe's cube-face pixels).
    """
    from relight_cli import envmap as E
    d = np.asarray(samples.directions, np.float64)
    w = np.asarray(samples.weights, np.float64)
    lw = np.asarray(samples.radiance, np.float64) * w[:, None]
    n = height * 2 * height
    idx = E.pixel_index(d, "latlong", height, 2 * height)
    omega = np.bincount(idx, w, minlength=n)
    geo = np.stack([np.bincount(idx, w * d[:, k], minlength=n) for k in range(3)], axis=1)
    power = np.stack([np.bincount(idx, lw[:, c], minlength=n) for c in range(3)], axis=1)
    moments = np.stack([np.stack([np.bincount(idx, lw[:, c] * d[:, k], minlength=n)
                                  for k in range(3)], axis=1) for c in range(3)], axis=1)
    keep = omega > 0
    geo = geo[keep]
    norm = np.linalg.norm(geo, axis=1, keepdims=True)
    return Cells(omega[keep], geo / np.where(norm > 0, norm, 1), power[keep], moments[keep])


def reference_irradiance(cells: Cells, normals: np.ndarray) -> np.ndarray:
    """[N, 3] irradiance E(n) = ∫ L(ω) max(n·ω, 0) dω by direct quadrature (no SH).

    Each cell contributes max(n·M, 0) with M = Σ L Δω ω its radiant vector: exact
    for cells wholly above or below the horizon of n.  Against a full-resolution
    sum over the texels of the built-in maps and the Poly Haven 1k HDRIs this is
    within 5.3e-4 (relative RMS over the sphere of normals) at 64×128 cells.
    """
    nrm = np.asarray(normals, np.float64).reshape(-1, 3)
    vectors = cells.moments.transpose(2, 1, 0).reshape(3, -1)    # [xyz, channel·M]
    out = np.empty((len(nrm), 3))
    for i in range(0, len(nrm), 128):                             # [128, 3M] blocks: a few MB
        dots = nrm[i:i + 128] @ vectors
        np.maximum(dots, 0, out=dots)
        out[i:i + 128] = dots.reshape(len(dots), 3, -1).sum(axis=2)
    return out


def fit_cells(cells: Cells, degrees, ridge: float = 0.0) -> dict[int, np.ndarray]:
    """Eq. 7 fits on the cells (the search's small problem), for each degree in ``degrees``.

    The Gram matrix uses each cell's area centroid and solid angle; the right-hand
    side Σ L Δω Y(ω) of a cell uses its channel's radiance-weighted centroid
    direction M/|M|, so a sun keeps its direction inside the cell (first order).
    """
    degrees = list(degrees)
    top = max(degrees)
    basis = sh_basis(cells.centroids, top)
    gram = basis.T @ (basis * cells.solid_angles[:, None])
    rhs = np.empty((basis.shape[1], 3))
    for c in range(3):
        m = cells.moments[:, c, :]
        norm = np.linalg.norm(m, axis=1, keepdims=True)
        dirs = np.where(norm > 0, m / np.where(norm > 0, norm, 1), cells.centroids)
        rhs[:, c] = sh_basis(dirs, top).T @ cells.power[:, c]
    return _solve_nested(gram, rhs, top, ridge, degrees)


def irradiance_error(coefficients: np.ndarray, normals: np.ndarray,
                     reference: np.ndarray) -> float:
    """Relative RMS error ‖E_SH − E_ref‖ / ‖E_ref‖ over normals and channels (0 if E_ref = 0)."""
    scale = float(np.sqrt(np.mean(reference ** 2)))
    if scale == 0:
        return 0.0
    e = irradiance_from_sh(coefficients, normals)
    return float(np.sqrt(np.mean((e - reference) ** 2)) / scale)


def _negativity_grid(height: int = SEARCH_HEIGHT):
    from relight_cli import envmap as E
    return (E.latlong_directions(height, 2 * height).reshape(-1, 3),
            np.asarray(E.latlong_solid_angles(height, 2 * height), np.float64).reshape(-1))


def radiance_negativity(coefficients: np.ndarray, height: int = SEARCH_HEIGHT, _grid=None):
    """Ringing of an SH radiance probe: (negativity, negative solid-angle fraction).

    negativity = max over channels of max(0, −min_ω L_c(ω)) / L̄_c, the deepest
    negative radiance in units of the channel's mean radiance L̄_c = c_00/√(4π)
    (channels with no light are skipped); the fraction is the part of the sphere
    where some channel is negative.  Both on the pixel centres of a
    height×2·height lat-long grid.  A lone point light truncated to degree 1 or
    2 dips to −2 and −1.8 times its mean; higher degrees ring deeper.
    """
    c = np.asarray(coefficients, np.float64)
    degree = int(round(np.sqrt(c.shape[0]))) - 1
    dirs, omega = _grid if _grid is not None else _negativity_grid(height)
    radiance = sh_basis(dirs, degree) @ c
    mean = c[0] / np.sqrt(4 * np.pi)
    top = float(mean.max())
    lit = mean > 1e-12 * top if top > 0 else np.zeros(len(mean), bool)
    depth = np.clip(-radiance.min(axis=0), 0, None)
    negativity = float((depth[lit] / mean[lit]).max()) if lit.any() else 0.0
    negative = (radiance[:, lit] < 0).any(axis=1) if lit.any() else np.zeros(len(dirs), bool)
    return negativity, float(omega[negative].sum() / omega.sum())


def candidate_degrees(max_degree: int) -> list[int]:
    """0, 1 and the even degrees up to max_degree: odd bands above 1 add nothing to
    irradiance (Â_l = 0) but their ringing, so the search never stops at one."""
    return [d for d in range(max_degree + 1) if d <= 1 or d % 2 == 0]


@dataclass
class DegreeChoice:
    """Result of the ``auto`` degree search.

    Attributes:
        degree: chosen degree.
        coefficients: [(degree+1)², 3] the Eq. 7 fit at that degree on all samples
            (the same numbers as ``fit_probe(samples, degree, ridge)``).
        error: relative RMS irradiance error of ``coefficients`` against the reference.
        negativity: :func:`radiance_negativity` of ``coefficients``.
        negative_fraction: part of the sphere where ``coefficients`` are negative.
        errors: {degree: search error} for the candidate degrees (fits on the cells).
        negativities: {degree: search negativity} likewise.
        tolerance, max_negativity, max_degree: the criterion.
        tolerance_met: error ≤ tolerance.
        limited_by: None when the tolerance is met, else ``"max_negativity"`` (a
            degree with a smaller error rings past the limit) or ``"max_degree"``.
        reference: how the reference irradiance was computed (cells, normals).
        window: the deringing window applied to every candidate (``relight_cli.sh``).
    """

    degree: int
    coefficients: np.ndarray
    error: float
    negativity: float
    negative_fraction: float
    errors: dict
    negativities: dict
    tolerance: float
    max_negativity: float
    max_degree: int
    tolerance_met: bool
    limited_by: str | None
    reference: str = ""
    window: str = "none"


def choose_degree(samples: Samples, tolerance: float = AUTO_TOLERANCE, ridge: float = 0.0,
                  max_degree: int = AUTO_MAX_DEGREE, max_negativity: float = AUTO_MAX_NEGATIVITY,
                  n_normals: int = SEARCH_NORMALS, height: int = SEARCH_HEIGHT,
                  window: str = "none") -> DegreeChoice:
    """The smallest degree whose irradiance is within ``tolerance`` of a direct quadrature of
    the samples and whose radiance rings no deeper than ``max_negativity``.

    Error = ‖E_d − E_ref‖ / ‖E_ref‖, RMS over ``n_normals`` Fibonacci-sphere normals
    and the three channels, E_ref from :func:`reference_irradiance` (independent of
    SH).  The search fits every candidate degree on the samples summed into
    height×2·height cells (:func:`reduce_samples`, :func:`fit_cells`), so it costs
    the same for a 1k map as for a 64×128 one; the chosen degree is then fitted
    on all samples (Eq. 7, as ``--degree N``) and its own error and negativity are
    measured (a candidate whose full fit fails the criterion is passed over).
    If no candidate within the negativity limit reaches the tolerance, the one
    of them with the smallest error is taken and ``limited_by`` says why.
    ``window`` (``relight_cli.sh.WINDOWS``) is applied to every candidate's fit
    before it is judged: what is judged is what would be written.
    """
    if not tolerance >= 0 or not max_negativity >= 0:
        raise ValueError("tolerance and max_negativity must be ≥ 0")
    normals = fibonacci_sphere(n_normals)
    cells = reduce_samples(samples, height)
    reference = reference_irradiance(cells, normals)
    grid = _negativity_grid(height)
    degrees = candidate_degrees(max_degree)
    fits = {d: apply_window(c, window) for d, c in fit_cells(cells, degrees, ridge).items()}
    errors = {d: irradiance_error(fits[d], normals, reference) for d in degrees}
    negativities = {d: radiance_negativity(fits[d], _grid=grid)[0] for d in degrees}
    admissible = [d for d in degrees if negativities[d] <= max_negativity]
    meets = [d for d in admissible if errors[d] <= tolerance]

    how = (f"direct quadrature over {height}x{2 * height} lat-long cells, {n_normals} "
           f"Fibonacci-sphere normals")

    def full(d):
        c = apply_window(fit_probe(samples, d, ridge), window)
        return (c, irradiance_error(c, normals, reference)) + radiance_negativity(c, _grid=grid)

    for d in meets:
        c, err, neg, frac = full(d)
        if err <= tolerance and neg <= max_negativity:
            return DegreeChoice(d, c, err, neg, frac, errors, negativities, tolerance,
                                max_negativity, max_degree, True, None, how, window)
    pool = admissible or [0]
    d = min(pool, key=lambda k: (errors[k], k))
    c, err, neg, frac = full(d)
    ringing = any(errors[k] < errors[d] for k in degrees if k not in admissible)
    return DegreeChoice(d, c, err, neg, frac, errors, negativities, tolerance, max_negativity,
                        max_degree, err <= tolerance, None if err <= tolerance else
                        ("max_negativity" if ringing else "max_degree"), how, window)


def degree_search_record(choice: DegreeChoice) -> dict:
    """The probe JSON's ``degree_search`` object (formats/sh_probe_json.md)."""
    return {"tolerance": choice.tolerance, "max_negativity": choice.max_negativity,
            "max_degree": choice.max_degree, "window": choice.window,
            "reference": choice.reference,
            "irradiance_error": choice.error, "negativity": choice.negativity,
            "negative_solid_angle": choice.negative_fraction,
            "tolerance_met": choice.tolerance_met, "limited_by": choice.limited_by,
            "candidates": {str(d): {"irradiance_error": choice.errors[d],
                                    "negativity": choice.negativities[d]}
                           for d in choice.errors}}


def degree_search_log(choice: DegreeChoice) -> list[str]:
    """Log lines (stderr) of an ``auto`` degree choice: its error against the reference."""
    lines = [f"auto degree: {choice.degree} (irradiance error {choice.error:.2e} against a direct "
             f"quadrature of the input, tolerance {choice.tolerance:g}; radiance negativity "
             f"{choice.negativity:.2f}, limit {choice.max_negativity:g})"]
    if choice.limited_by == "max_negativity":
        better = [d for d in choice.errors if choice.errors[d] < choice.errors[choice.degree]]
        d = min(better)
        lines.append(f"auto degree: tolerance not reached: degree {d} would cut the error to "
                     f"{choice.errors[d]:.2e} but rings to negativity {choice.negativities[d]:.2f}, "
                     f"past --max-negativity {choice.max_negativity:g}")
    elif choice.limited_by == "max_degree":
        lines.append(f"auto degree: tolerance not reached by any degree up to --max-degree "
                     f"{choice.max_degree}")
    return lines


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
