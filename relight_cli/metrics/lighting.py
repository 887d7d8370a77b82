"""Lighting consistency of a Gaussian avatar in a Gaussian scene: PAA-Y, APF-Y, NCM-ab.

Our reading of the DGSM paper's Sec. 4.1 metrics (the exact formulas are ours
where the paper leaves them open; formats/metrics_json.md documents them):

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

   * **APF-Y** (affine photometric fit error) = RMS of the trimmed residuals /
     mean trimmed Y: 0 when the avatar's shading is exactly an affine function
     of the scene's irradiance at its normals.
   * **PAA-Y** (principal axis angle) = angle in degrees between the dominant
     direction of the avatar's luminance — the l = 1 part of a robust order-3
     SH fit of Y_i over n_i — and that of the scene irradiance.  0 when the
     avatar is lit from where the scene's light comes from.
4. **NCM-ab** (chromaticity mismatch) = the 1-Wasserstein distance, in CIE-Lab
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
SH_DEGREE = 2          # "order 3": bands 0, 1, 2
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
    """[N, 2] CIE-Lab (a*, b*) of degree-0 colours read as sRGB in [0, 1]."""
    from skimage.color import rgb2lab
    rgb = np.clip(np.asarray(colors, np.float64), 0.0, 1.0).reshape(-1, 1, 3)
    return rgb2lab(rgb).reshape(-1, 3)[:, 1:]


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


# ------------------------------------------------------------------ the metrics


def luminance(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(rgb, np.float64) @ LUMA


def avatar_lighting_metrics(avatar_means, avatar_colors, avatar_opacities, irradiance_sh,
                            scene_ab, scene_ab_weights, normals=None, k: int = 16,
                            max_points: int = 512, seed: int = 0) -> dict:
    """PAA-Y, APF-Y and NCM-ab of one avatar frame against the scene's lighting.

    Args:
        avatar_means [N, 3], avatar_colors [N, 3] (degree-0 RGB), avatar_opacities [N].
        irradiance_sh: [9, 3] irradiance SH of the scene at the avatar.
        scene_ab: [M, 2] scene (a*, b*); scene_ab_weights: [M].
        normals: [N, 3] or None for pseudo-normals.

    Returns:
        {"metrics": {paa_y (degrees), apf_y, ncm_ab}, "details": {...}}.
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
    return {"metrics": {"paa_y": paa, "apf_y": apf, "ncm_ab": ncm},
            "details": {"ncm_a": ncm_a, "ncm_b": ncm_b, "ncm_method": method,
                        "calibration": {"scale": float(scale), "offset": float(offset)},
                        "kept_fraction": float(kept.mean()),
                        "avatar_direction": _unit_list(v_avatar),
                        "scene_direction": _unit_list(v_scene),
                        "scene_directional": bool(scene_directional),
                        "gaussians": int(len(p))}}


def _unit_list(v):
    norm = float(np.linalg.norm(v))
    return [float(x) for x in (v / norm if norm > 0 else v)]


def lighting_metrics(scene, avatars, relits=None, radius: float = 1.5, k: int = 16,
                     use_file_normals: bool = False, max_points: int = 512, seed: int = 0) -> dict:
    """Orig, relit and delta metrics over frames.

    Args:
        scene: a :class:`relight_cli.formats.gaussians_ply.Gaussians` (the environment).
        avatars: list of Gaussians, one per frame (the original avatar).
        relits: None or a list of the same length (the relit avatar per frame).
        radius: scene Gaussians within this distance (metres) of each frame's
            avatar centroid light the avatar.

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
        record = {"frame": i, "centre": [float(c) for c in centre],
                  "scene_gaussians": int(select.sum())}
        for role, g in (("orig", avatar), ("relit", None if relits is None else relits[i])):
            if g is None:
                continue
            normals = g.normals if use_file_normals else None
            record[role] = avatar_lighting_metrics(g.means, g.colors(), g.opacities, irr,
                                                   scene_ab, scene_w, normals, k, max_points,
                                                   seed + i)
        frames.append(record)
    roles = ["orig"] + (["relit"] if relits is not None else [])
    metrics = {}
    for role in roles:
        metrics[role] = {name: float(np.mean([f[role]["metrics"][name] for f in frames]))
                         for name in ("paa_y", "apf_y", "ncm_ab")}
    if relits is not None:
        metrics["delta"] = {name: metrics["relit"][name] - metrics["orig"][name]
                            for name in ("paa_y", "apf_y", "ncm_ab")}
    return {"metrics": metrics, "frames": frames}
