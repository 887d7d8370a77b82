"""Lighting consistency of a Gaussian avatar in a Gaussian scene: PAA-Y, APF-Y, NCM-ab.

Two families, each under its own names (``formats/metrics_json.md``):

**The paper's (DGSM paper Sec. 4.1)** — ``paa_y``, ``apf_y``, ``ncm_ab``:

* Irradiance is modelled directly as real SH of order L = 3 in the normal,
  E(n̂; c) = Σ_{l ≤ 3} Σ_m c_lm Y_lm(n̂) (16 coefficients).
* Scene neighbourhood N = scene Gaussians within ``radius`` of the avatar's
  opacity-weighted centroid; its luminance factorizes as Y(I_i) ≈ α_i E(n̂_i;
  c_scene), α_i ≥ 0 per Gaussian, with pseudo-normals n̂_i oriented towards the
  avatar; the avatar likewise gives c_avatar and β_a ≥ 0 (normals outward).
  :func:`factorize_luminance` fits it (Huber loss, 5 % trimming).  Two things the
  paper leaves open are fixed here and documented: (i) the scale ambiguity
  (α, c) ~ (α·s, c/s) is fixed by ‖c‖₂ = 1 with c_00 > 0, so c is the *shape*
  of the lighting and α carries albedo × exposure (PAA-Y then lies in [0, 2√16];
  Table 1's 0.3–0.6 are of that magnitude, the paper does not say which
  normalization it used); (ii) with a free α_i per Gaussian any c with E(n̂_i) > 0 fits exactly,
  so the α update is a ridge towards the set's mean scale ᾱ,
  α_i = max(0, (E_i Y_i + λ ᾱ)/(E_i² + λ)), λ = ``albedo_ridge`` · mean(E²):
  albedo varies only where the shading cannot explain Y.  Alternated
  ``iterations`` times from α = 1.
* PAA-Y = ‖c_avatar − c_scene‖₁ (16 coefficients, both of unit norm).
* APF-Y = (1/|A|) Σ_a |Y_a − (s·E(n̂_a; c_scene) + b)|, the per-frame affine
  calibration (s, b) fitted with the same robust fit.
* NCM-ab = exact 1-Wasserstein distance (Euclidean ground cost, Lab units)
  between the empirical (unweighted) distributions of (a*, b*) of the avatar
  and of N: the transport LP on the full sets when |A|·|N| ≤
  EXACT_TRANSPORT_MAX, otherwise exactly (an assignment problem) on seeded
  uniform subsamples without replacement of min(``max_points``, |A|, |N|)
  points per side; ``details.ncm_method`` says which and the size.

**This toolkit's earlier variants** — ``paa_angle``, ``apf_rms``,
``ncm_ab_weighted`` (the exact formulas are ours):

1. **Pseudo-normals** (:func:`pseudo_normals`): 3DGS files carry no usable
   normals, so each avatar Gaussian gets the smallest-eigenvalue eigenvector of
   the weighted covariance of its k nearest centres (weights: neighbour opacity
   × a Gaussian kernel of the distance with bandwidth = the median k-th
   neighbour distance), oriented away from the avatar's opacity-weighted centroid.
2. **Scene lighting** (:func:`scene_radiance_sh`): scene Gaussians within
   ``radius`` of the avatar centre are radiance samples in their direction from
   the centre, weighted by opacity × their approximate solid angle
   π·s̄²/d² (s̄ = geometric-mean scale), fitted by weighted ridge least squares
   (:func:`relight_cli.sh.fit_sh`) to order-3 SH (bands l = 0, 1, 2: 9
   coefficients); irradiance is its Lambertian convolution
   (:func:`relight_cli.sh.irradiance_coefficients`).
3. **Luminance factorization** per frame: avatar luminance Y_i (Rec. 709 of the
   degree-0 colour) ≈ a·E_Y(n_i) + b, an affine calibration (unknown albedo
   scale a and ambient offset b) fitted with a Huber loss
   (``scipy.optimize.least_squares``, scale 1.345 σ̂ from the MAD), then the 5 %
   largest residuals are trimmed and the fit repeated.

   * **apf_rms** (affine photometric fit error) = RMS of the trimmed residuals /
     mean trimmed Y: 0 when the avatar's shading is exactly an affine function
     of the scene's irradiance at its normals.
   * **paa_angle** (principal axis angle) = angle in degrees between the dominant
     direction of the avatar's luminance — the l = 1 part of a robust order-3
     SH fit of Y_i over n_i — and that of the scene irradiance.  0 when the
     avatar is lit from where the scene's light comes from.
4. **ncm_ab_weighted** (chromaticity mismatch) = the 1-Wasserstein distance, in CIE-Lab
   units, between the opacity-weighted distributions of (a*, b*) of avatar and
   scene colours (``skimage.color.rgb2lab`` of the degree-0 colours, clipped to
   [0, 1] and read as sRGB).  Small sets are solved exactly as a transport
   linear program (``scipy.stats.wasserstein_distance_nd``); larger ones are
   resampled systematically by weight to equal size and solved exactly as an
   assignment (``scipy.optimize.linear_sum_assignment``).  The 1-D marginal
   distances of a* and b* (``scipy.stats.wasserstein_distance``) are reported too.
"""

from __future__ import annotations

import math

import numpy as np

from relight_cli.sh import evaluate_sh, fit_sh, irradiance_coefficients, sh_basis

LUMA = np.array([0.2126, 0.7152, 0.0722])
SH_DEGREE = 2          # the variants' "order 3": bands 0, 1, 2 (9 coefficients)
PAPER_ORDER = 3        # the paper's L = 3: bands 0..3 (16 coefficients)
TRIM = 0.05            # fraction of largest residuals dropped after the Huber fit
EXACT_TRANSPORT_MAX = 96 * 96  # Na·Nb up to which the transport LP is solved exactly


# ------------------------------------------------------------------ pseudo-normals


def pseudo_normals(points: np.ndarray, weights: np.ndarray, k: int = 16,
                   centre: np.ndarray | None = None) -> np.ndarray:
    """Weighted local-PCA normals.

    Args:
        points: [N, 3] Gaussian centres, metres, world.
        weights: [N] opacities (≥ 0).
        k: neighbours per point (itself included).
        centre: [3] orientation centre (default: weighted centroid).

    Returns:
        [N, 3] float64 unit normals pointing away from ``centre``.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64)
    w = np.asarray(weights, np.float64)
    k = int(min(k, len(p)))
    dist, idx = cKDTree(p).query(p, k=k)                      # [N, k]
    h = float(np.median(dist[:, -1])) or 1.0
    kw = w[idx] * np.exp(-0.5 * (dist / h) ** 2)              # [N, k]
    kw_sum = np.maximum(kw.sum(axis=1, keepdims=True), 1e-300)
    nbr = p[idx]                                              # [N, k, 3]
    mean = np.einsum("nk,nkc->nc", kw, nbr) / kw_sum
    d = nbr - mean[:, None, :]
    cov = np.einsum("nk,nki,nkj->nij", kw, d, d) / kw_sum[:, :, None]
    _, vecs = np.linalg.eigh(cov)                             # ascending eigenvalues
    normals = vecs[:, :, 0]
    return _orient(normals, p, w, centre)


def _orient(normals, p, w, centre):
    c = (w @ p) / max(w.sum(), 1e-300) if centre is None else np.asarray(centre, np.float64)
    flip = np.einsum("nc,nc->n", normals, p - c) < 0
    normals = np.where(flip[:, None], -normals, normals)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def pseudo_normals_reference(points, weights, k: int = 16, centre=None) -> np.ndarray:
    """Slow twin of :func:`pseudo_normals`: brute-force neighbours, one point at a time."""
    p = np.asarray(points, np.float64)
    w = np.asarray(weights, np.float64)
    k = int(min(k, len(p)))
    all_d = np.sqrt(((p[:, None, :] - p[None, :, :]) ** 2).sum(-1))
    order = np.argsort(all_d, axis=1, kind="stable")[:, :k]
    h = float(np.median(np.take_along_axis(all_d, order, 1)[:, -1])) or 1.0
    out = np.empty_like(p)
    for i in range(len(p)):
        nb = order[i]
        kw = w[nb] * np.exp(-0.5 * (all_d[i, nb] / h) ** 2)
        mean = (kw[:, None] * p[nb]).sum(0) / kw.sum()
        d = p[nb] - mean
        cov = (kw[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0) / kw.sum()
        vals, vecs = np.linalg.eigh(cov)
        out[i] = vecs[:, 0]
    return _orient(out, p, w, centre)


# ------------------------------------------------------------------ scene lighting


def scene_radiance_sh(means, colors, opacities, scales, centre, radius: float,
                      degree: int = SH_DEGREE, ridge: float = 1e-3):
    """Radiance SH [(degree+1)², 3] of the scene around ``centre`` and the samples used.

    Args:
        means [N, 3], colors [N, 3], opacities [N], scales [N, 3] (linear, metres).
        centre: [3]; radius: metres.
        ridge: λ relative to the total weight (weights are normalized to sum to 4π).

    Returns:
        (coefficients [(d+1)², 3], selection [N] bool).  Raises ValueError with
        fewer than (d+1)² Gaussians within the radius.
    """
    m = np.asarray(means, np.float64)
    offset = m - np.asarray(centre, np.float64)
    dist = np.linalg.norm(offset, axis=1)
    select = (dist <= radius) & (dist > 1e-12)
    n_min = (degree + 1) ** 2
    if int(select.sum()) < n_min:
        raise ValueError(f"only {int(select.sum())} scene Gaussian(s) within radius {radius:g} of "
                         f"the avatar centre; need at least {n_min}")
    dirs = offset[select] / dist[select, None]
    size = np.exp(np.mean(np.log(np.maximum(np.asarray(scales, np.float64)[select], 1e-12)), axis=1))
    weight = np.asarray(opacities, np.float64)[select] * math.pi * size ** 2 / dist[select] ** 2
    weight = weight * (4 * math.pi / max(weight.sum(), 1e-300))
    coeffs = fit_sh(dirs, np.asarray(colors, np.float64)[select], weight, degree, ridge=ridge * 4 * math.pi)
    return coeffs, select


def dominant_direction(coefficients: np.ndarray) -> np.ndarray:
    """[3] direction v of the l = 1 band: Σ_m c_1m Y_1m(ω) = C1·(v·ω) (zero vector if none)."""
    c = np.asarray(coefficients, np.float64).reshape(-1)
    return np.array([-c[3], -c[1], c[2]])


# ------------------------------------------------------------------ robust fits


def robust_linear_fit(design: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None,
                      trim: float = TRIM, ridge: float = 1e-9):
    """Huber fit of target ≈ design·x, then refit without the ``trim`` largest residuals.

    Returns:
        (x [P], residuals of the kept rows [M], kept [N] bool).
    """
    from scipy.optimize import least_squares

    A = np.asarray(design, np.float64)
    y = np.asarray(target, np.float64)
    sw = np.ones(len(y)) if weights is None else np.sqrt(np.asarray(weights, np.float64))

    def fit(rows):
        Aw, yw = A[rows] * sw[rows, None], y[rows] * sw[rows]
        gram = Aw.T @ Aw + ridge * np.trace(Aw.T @ Aw) / A.shape[1] * np.eye(A.shape[1])
        x0 = np.linalg.solve(gram, Aw.T @ yw)
        r0 = Aw @ x0 - yw
        scale = 1.4826 * float(np.median(np.abs(r0 - np.median(r0))))
        if scale <= 1e-12 * max(float(np.abs(yw).max()), 1e-300):
            return x0                                  # exact (or near-exact) data
        res = least_squares(lambda x: Aw @ x - yw, x0, jac=lambda x: Aw, loss="huber",
                            f_scale=1.345 * scale, method="trf", x_scale="jac")
        return res.x

    rows = np.ones(len(y), bool)
    x = fit(rows)
    residual = A @ x - y
    n_drop = int(math.floor(trim * len(y)))
    if n_drop > 0:
        keep = np.ones(len(y), bool)
        keep[np.argsort(np.abs(residual))[len(y) - n_drop:]] = False
        rows = keep
        x = fit(rows)
        residual = A @ x - y
    return x, residual[rows], rows


# ------------------------------------------------------------------ chromaticity transport


def lab_ab(colors: np.ndarray) -> np.ndarray:
    """[N, 2] CIE-Lab (a*, b*, D65) of degree-0 colours, which are linear RGB in memory
    (formats/gaussians_ply.md, "Colour space": a 3DGS file's sRGB is decoded on read):
    linear sRGB → XYZ → Lab (scikit-image's ``xyz2lab``), negatives clipped at 0, values
    above 1 kept (Lab of HDR colours has L* > 100; a* and b* stay chromaticity)."""
    from skimage.color import xyz2lab
    from skimage.color.colorconv import xyz_from_rgb     # linear sRGB → XYZ (its rgb2lab's)
    rgb = np.clip(np.asarray(colors, np.float64), 0.0, None).reshape(-1, 3)
    xyz = (rgb @ np.asarray(xyz_from_rgb).T).reshape(-1, 1, 3)
    return xyz2lab(xyz).reshape(-1, 3)[:, 1:]


def systematic_resample(weights: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """[n] indices drawn ∝ weights with one random offset (low-variance resampling)."""
    w = np.asarray(weights, np.float64)
    cdf = np.cumsum(w / w.sum())
    cdf[-1] = 1.0
    positions = (rng.uniform() + np.arange(n)) / n
    return np.searchsorted(cdf, positions, side="left")


def wasserstein_2d(a: np.ndarray, b: np.ndarray, wa=None, wb=None, max_points: int = 512,
                   seed: int = 0) -> tuple[float, str]:
    """1-Wasserstein distance (Euclidean ground cost) between weighted 2-D point sets.

    Returns:
        (distance, method): ``"exact-lp"`` for small sets (transport linear program),
        ``"assignment"`` for equal-size uniform sets, else ``"assignment-resampled"``.
    """
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial.distance import cdist
    from scipy.stats import wasserstein_distance_nd

    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    wa = np.ones(len(a)) if wa is None else np.asarray(wa, np.float64)
    wb = np.ones(len(b)) if wb is None else np.asarray(wb, np.float64)
    uniform = np.allclose(wa, wa[0]) and np.allclose(wb, wb[0])
    if uniform and len(a) == len(b) and len(a) <= 4 * max_points:
        r, c = linear_sum_assignment(cdist(a, b))
        return float(cdist(a, b)[r, c].mean()), "assignment"
    if len(a) * len(b) <= EXACT_TRANSPORT_MAX:
        return float(wasserstein_distance_nd(a, b, wa, wb)), "exact-lp"
    rng = np.random.default_rng(seed)
    n = int(min(max_points, max(len(a), len(b))))
    ia = systematic_resample(wa, n, rng)
    ib = systematic_resample(wb, n, rng)
    cost = cdist(a[ia], b[ib])
    r, c = linear_sum_assignment(cost)
    return float(cost[r, c].mean()), "assignment-resampled"


# ------------------------------------------------------------------ the paper's metrics


def factorize_luminance(y, normals, weights=None, order: int = PAPER_ORDER,
                        albedo_ridge: float = 1.0, iterations: int = 6, trim: float = TRIM,
                        ridge: float = 1e-9):
    """Y_i ≈ α_i E(n̂_i; c), α_i ≥ 0, ‖c‖₂ = 1 and c_00 > 0 (module doc; paper Sec. 4.1).

    Args:
        y: [N] luminance; normals: [N, 3] unit; weights: [N] (opacities) or None.
        order: SH order L (E has (L+1)² coefficients).
        albedo_ridge: λ relative to mean(E²) of the α update's pull towards ᾱ.
        iterations: alternations (c by a robust fit given α; α in closed form given c).
    Returns:
        (c [(L+1)²], α [N], kept [N] bool of the last robust fit).
    Raises:
        ValueError: too few Gaussians, or luminance whose fitted mean is not positive.
    """
    y = np.asarray(y, np.float64)
    w = np.ones(len(y)) if weights is None else np.asarray(weights, np.float64)
    basis = sh_basis(normals, order)                                  # [N, K]
    if len(y) < 2 * basis.shape[1]:
        raise ValueError(f"{len(y)} Gaussians are too few for an order-{order} SH fit "
                         f"(need at least {2 * basis.shape[1]})")
    alpha = np.ones(len(y))
    for it in range(iterations):
        c, _, kept = robust_linear_fit(alpha[:, None] * basis, y, w, trim, ridge=ridge)
        if not c[0] > 0:
            raise ValueError("the luminance has no positive mean irradiance to factorize")
        norm = float(np.linalg.norm(c))                               # the scale fix: |c|₂ = 1
        alpha = alpha * norm
        c = c / norm
        if it == iterations - 1:
            break
        e = basis @ c
        abar = float(np.average(alpha[kept], weights=w[kept]))
        lam = albedo_ridge * float(np.average(e * e, weights=w))
        alpha = np.maximum(0.0, (e * y + lam * abar) / (e * e + lam))
    return c, alpha, kept


def wasserstein_exact(a: np.ndarray, b: np.ndarray, max_points: int = 512, seed: int = 0):
    """Exact 1-Wasserstein distance of two unweighted 2-D point sets (paper's NCM-ab).

    Returns:
        (distance, method): ``"exact-lp"`` on the full sets when |a|·|b| ≤
        EXACT_TRANSPORT_MAX, ``"exact-assignment"`` for equal sizes up to
        ``max_points``, else ``"exact-on-subsamples(n=…)"``: the exact assignment
        between seeded uniform subsamples (without replacement) of n points each.
    """
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial.distance import cdist
    from scipy.stats import wasserstein_distance_nd

    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if len(a) == len(b) and len(a) <= max_points:
        cost = cdist(a, b)
        r, c = linear_sum_assignment(cost)
        return float(cost[r, c].mean()), "exact-assignment"
    if len(a) * len(b) <= EXACT_TRANSPORT_MAX:
        return float(wasserstein_distance_nd(a, b)), "exact-lp"
    rng = np.random.default_rng(seed)
    n = int(min(max_points, len(a), len(b)))
    ia = rng.choice(len(a), n, replace=False)
    ib = rng.choice(len(b), n, replace=False)
    cost = cdist(a[ia], b[ib])
    r, c = linear_sum_assignment(cost)
    return float(cost[r, c].mean()), f"exact-on-subsamples(n={n})"


def paper_avatar_metrics(y, normals, weights, ab, c_scene, scene_ab, max_points: int = 512,
                         seed: int = 0) -> dict:
    """PAA-Y, APF-Y, NCM-ab (paper Sec. 4.1) of one avatar frame against c_scene.

    Args:
        y: [N] avatar luminance; normals: [N, 3] outward unit; weights: [N] opacities.
        ab: [N, 2] avatar (a*, b*); c_scene: [16] scene lighting (from
            :func:`factorize_luminance`); scene_ab: [M, 2] of the neighbourhood.
    """
    c_avatar, beta, _ = factorize_luminance(y, normals, weights)
    paa = float(np.abs(c_avatar - c_scene).sum())
    e = sh_basis(normals, PAPER_ORDER) @ c_scene
    (s, b), _, _ = robust_linear_fit(np.stack([e, np.ones_like(e)], axis=1), y, weights)
    apf = float(np.mean(np.abs(y - (s * e + b))))
    ncm, method = wasserstein_exact(ab, scene_ab, max_points, seed)
    return {"metrics": {"paa_y": paa, "apf_y": apf, "ncm_ab": ncm},
            "details": {"c_avatar": [float(v) for v in c_avatar],
                        "calibration": {"s": float(s), "b": float(b)},
                        "avatar_scale_median": float(np.median(beta)),
                        "ncm_method": method}}


# ------------------------------------------------------------------ the variants


def luminance(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(rgb, np.float64) @ LUMA


def avatar_lighting_metrics(avatar_means, avatar_colors, avatar_opacities, irradiance_sh,
                            scene_ab, scene_ab_weights, normals=None, k: int = 16,
                            max_points: int = 512, seed: int = 0) -> dict:
    """The variants paa_angle, apf_rms, ncm_ab_weighted of one avatar frame (module doc).

    Args:
        avatar_means [N, 3], avatar_colors [N, 3] (degree-0 RGB), avatar_opacities [N].
        irradiance_sh: [9, 3] irradiance SH of the scene at the avatar.
        scene_ab: [M, 2] scene (a*, b*); scene_ab_weights: [M].
        normals: [N, 3] or None for pseudo-normals.

    Returns:
        {"metrics": {paa_angle (degrees), apf_rms, ncm_ab_weighted}, "details": {...}}.
    """
    from scipy.stats import wasserstein_distance

    p = np.asarray(avatar_means, np.float64)
    w = np.asarray(avatar_opacities, np.float64)
    if len(p) < max(k, 10):
        raise ValueError(f"the avatar has {len(p)} Gaussians; need at least {max(k, 10)}")
    n = pseudo_normals(p, w, k) if normals is None else np.asarray(normals, np.float64)
    y = luminance(avatar_colors)
    e_coef = irradiance_sh @ LUMA                                   # [9] luminance irradiance
    e_y = evaluate_sh(e_coef[:, None], n)[:, 0]                     # [N]
    design = np.stack([e_y, np.ones_like(e_y)], axis=1)
    (scale, offset), res, kept = robust_linear_fit(design, y, w)
    mean_y = float(np.average(y[kept], weights=w[kept]))
    apf = float(np.sqrt(np.average(res ** 2, weights=w[kept])) / max(abs(mean_y), 1e-12))
    basis = sh_basis(n, SH_DEGREE)
    c_avatar, _, _ = robust_linear_fit(basis, y, w)
    v_avatar = dominant_direction(c_avatar)
    v_scene = dominant_direction(e_coef)
    scene_directional = float(np.linalg.norm(v_scene)) > 1e-9 * abs(float(e_coef[0]))
    if scene_directional and np.linalg.norm(v_avatar) > 0:
        cos = float(v_avatar @ v_scene / (np.linalg.norm(v_avatar) * np.linalg.norm(v_scene)))
        paa = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
    else:
        paa = 0.0
    ab = lab_ab(avatar_colors)
    ncm, method = wasserstein_2d(ab, scene_ab, w, scene_ab_weights, max_points, seed)
    ncm_a = float(wasserstein_distance(ab[:, 0], scene_ab[:, 0], w, scene_ab_weights))
    ncm_b = float(wasserstein_distance(ab[:, 1], scene_ab[:, 1], w, scene_ab_weights))
    return {"metrics": {"paa_angle": paa, "apf_rms": apf, "ncm_ab_weighted": ncm},
            "details": {"ncm_a": ncm_a, "ncm_b": ncm_b, "ncm_weighted_method": method,
                        "calibration": {"scale": float(scale), "offset": float(offset)},
                        "kept_fraction": float(kept.mean()),
                        "avatar_direction": _unit_list(v_avatar),
                        "scene_direction": _unit_list(v_scene),
                        "scene_directional": bool(scene_directional),
                        "gaussians": int(len(p))}}


def _unit_list(v):
    norm = float(np.linalg.norm(v))
    return [float(x) for x in (v / norm if norm > 0 else v)]


METRIC_NAMES = ("paa_y", "apf_y", "ncm_ab", "paa_angle", "apf_rms", "ncm_ab_weighted")


def lighting_metrics(scene, avatars, relits=None, radius: float = 1.5, k: int = 16,
                     use_file_normals: bool = False, max_points: int = 512, seed: int = 0) -> dict:
    """Orig, relit and delta metrics over frames: the paper's and the variants (module doc).

    Args:
        scene: a :class:`relight_cli.formats.gaussians_ply.Gaussians` (the environment).
        avatars: list of Gaussians, one per frame (the original avatar).
        relits: None or a list of the same length (the relit avatar per frame).
        radius: scene Gaussians within this distance (metres) of each frame's
            avatar centroid are its neighbourhood N.
        k: neighbours of the pseudo-normals; use_file_normals: the avatar PLY's normals.
        max_points: subsample size of the exact transports of large sets.

    Returns:
        {"metrics": {"orig": {...}, ["relit": {...}, "delta": {relit − orig}]},
        "frames": [per-frame records]}; metrics are means over frames.
    """
    frames = []
    scene_colors = scene.colors()
    for i, avatar in enumerate(avatars):
        centre = (avatar.opacities @ avatar.means) / max(avatar.opacities.sum(), 1e-300)
        radiance, select = scene_radiance_sh(scene.means, scene_colors, scene.opacities,
                                             scene.scales, centre, radius)
        irr = irradiance_coefficients(radiance)
        scene_ab = lab_ab(scene_colors[select])
        scene_w = scene.opacities[select]
        # the paper's scene lighting: its neighbourhood's own luminance over normals
        # facing the avatar (pseudo-normals oriented towards the centroid)
        scene_n = -pseudo_normals(scene.means[select], scene_w, k, centre=centre)
        c_scene, alpha_scene, _ = factorize_luminance(luminance(scene_colors[select]), scene_n,
                                                      scene_w)
        record = {"frame": i, "centre": [float(c) for c in centre],
                  "scene_gaussians": int(select.sum()),
                  "c_scene": [float(v) for v in c_scene]}
        for role, g in (("orig", avatar), ("relit", None if relits is None else relits[i])):
            if g is None:
                continue
            normals = g.normals if use_file_normals else None
            variant = avatar_lighting_metrics(g.means, g.colors(), g.opacities, irr,
                                              scene_ab, scene_w, normals, k, max_points, seed + i)
            n = (pseudo_normals(g.means, g.opacities, k) if normals is None
                 else np.asarray(normals, np.float64))
            paper = paper_avatar_metrics(luminance(g.colors()), n, g.opacities, lab_ab(g.colors()),
                                         c_scene, scene_ab, max_points, seed + i)
            record[role] = {"metrics": {**paper["metrics"], **variant["metrics"]},
                            "details": {**variant["details"], **paper["details"]}}
        frames.append(record)
    roles = ["orig"] + (["relit"] if relits is not None else [])
    metrics = {}
    for role in roles:
        metrics[role] = {name: float(np.mean([f[role]["metrics"][name] for f in frames]))
                         for name in METRIC_NAMES}
    if relits is not None:
        metrics["delta"] = {name: metrics["relit"][name] - metrics["orig"][name]
                            for name in METRIC_NAMES}
    return {"metrics": metrics, "frames": frames}
