"""Deep Gaussian Shadow Maps: per-light transmittance tabulated on radial shells.

For each point light at L, an H×W direction atlas (octahedral, paper Eq. 6, or a
cube map for the ablation) of world directions ω from the light is crossed with
K radial bins whose centres are t_k = (k + ½)·t_max / K.  The table holds
T(ω, t_k) = exp(−τ(L, L + t_k ω)), the closed-form transmittance through the
occluder Gaussians (:mod:`relight_cli.gaussians.transmittance`).

Only what the scene needs is computed:

* Receiver ROI: receivers (scene points) that can be shadowed at all — within
  ``roi_radius`` of the occluders' alpha-weighted centroid (if given), inside
  robust height bounds, and whose segment to the light passes through the
  occluders' bounding sphere — mark the atlas texels (with their bilinear
  neighbours) and the radial bin range [k0, k1] that lookups will read.
  Everything else is T = 1 by construction.
* Light-space occluder culling: a Gaussian i may be dropped from a ray when its
  optical depth there is below ``cull_tolerance`` ε.  With the per-Gaussian peak
  bound b_i (:meth:`Mixture.peak_bound`) that happens outside the Mahalanobis
  radius k_i = √(2 ln(b_i / ε)) (the k_σ ellipse of the projected covariance in
  the plane ⊥ the ray).  Culling is hierarchical: radial (a Gaussian entirely
  beyond the last needed bin), one cone around all needed texels, then every
  (texel, Gaussian) pair whose texel direction lies in the Gaussian's bounding
  cone — found by k-d tree range searches over the texel directions
  (:func:`cone_texel_pairs`), the analogue of the paper's 8×8 tile buckets
  (Sec. 3.2) without their rectangle slack — and finally the exact
  projected-covariance ellipse m² ≤ k_i².  The culled table equals the
  unculled one to (number of nearly-touching Gaussians)·ε (tested ≤ 1e-5).

Octahedral atlas (this toolkit's Eq. 6 convention, spec in formats/dgsm_exr.md):
direction ω = (x, y, z), n = |x| + |y| + |z|; the lower hemisphere (y ≤ 0, where
receivers of a ceiling light are) is the central diamond (u, v) = (x, z)/n; the
upper hemisphere folds out to the corners: u = (1 − |z/n|)·sgn x,
v = (1 − |x/n|)·sgn z (sgn 0 = +1).  Texel column x ↦ u = 2(x + ½)/W − 1, row y
(top row 0) ↦ v = 1 − 2(y + ½)/H.  Cube atlas: OpenEXR's ImfEnvmap cube layout
(six N×N faces stacked +X −X +Y −Y +Z −Z, W = N, H = 6N), as relight_cli.envmap.
"""

from __future__ import annotations

import functools
import math
import time

import numpy as np

from relight_cli.formats.dgsm_exr import DGSM, LAYOUTS   # the table lives with its file format

from . import transmittance as TR

BACKENDS = ("auto", "numpy", "torch")
TORCH_AUTO_PAIRS = 8_000_000          # pairs of one light: torch pays for its import
TORCH_AUTO_PAIRS_IMPORTED = 1_000_000  # pairs of one light when torch is already loaded
FOOTPRINTS = ("centre", "stencil", "mc")
_ERF_WINDOW = 6.5          # |u| beyond which erf(u) = ±1 to < 1e-19 (erfc(6.5) ≈ 4e-20)
_STENCIL_H = math.sqrt(3.5)  # 7 equal weights: mean and covariance of the Gaussian exact


# ------------------------------------------------------------------ atlas geometry


def octahedral_encode(directions: np.ndarray) -> np.ndarray:
    """[N, 3] directions (any length > 0) → [N, 2] (u, v) ∈ [−1, 1]² (see module doc)."""
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    n = np.abs(d).sum(axis=1)
    n = np.where(n > 0, n, 1.0)
    x, y, z = d[:, 0] / n, d[:, 1] / n, d[:, 2] / n
    sx = np.where(x >= 0, 1.0, -1.0)
    sz = np.where(z >= 0, 1.0, -1.0)
    up = y > 0
    u = np.where(up, (1 - np.abs(z)) * sx, x)
    v = np.where(up, (1 - np.abs(x)) * sz, z)
    return np.stack([u, v], axis=1)


def octahedral_decode(uv: np.ndarray) -> np.ndarray:
    """[N, 2] (u, v) → [N, 3] unit directions (inverse of :func:`octahedral_encode`)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    u, v = uv[:, 0], uv[:, 1]
    h = 1 - np.abs(u) - np.abs(v)
    su = np.where(u >= 0, 1.0, -1.0)
    sv = np.where(v >= 0, 1.0, -1.0)
    x = np.where(h >= 0, u, (1 - np.abs(v)) * su)
    z = np.where(h >= 0, v, (1 - np.abs(u)) * sv)
    d = np.stack([x, -h, z], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def cube_face_size(height: int, width: int) -> int:
    """Face size N of a cube atlas with about as many texels as an H×W octahedral one."""
    return max(2, int(round(math.sqrt(height * width / 6.0))))


@functools.lru_cache(maxsize=8)
def _atlas_directions_cached(layout: str, height: int, width: int) -> np.ndarray:
    if layout == "octahedral":
        xs = 2 * (np.arange(width) + 0.5) / width - 1
        ys = 1 - 2 * (np.arange(height) + 0.5) / height
        u, v = np.meshgrid(xs, ys)
        d = octahedral_decode(np.stack([u.ravel(), v.ravel()], axis=1)).reshape(height, width, 3)
    elif layout == "cube":
        from relight_cli.envmap import cube_directions
        if height != 6 * width:
            raise ValueError(f"a cube atlas is N wide and 6N high, got {width}x{height}")
        d = cube_directions(width)
    else:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    d.setflags(write=False)
    return d


def atlas_directions(layout: str, height: int, width: int) -> np.ndarray:
    """[H, W, 3] float64 unit world directions at texel centres."""
    return _atlas_directions_cached(layout, int(height), int(width))


def atlas_pixel(directions: np.ndarray, layout: str, height: int, width: int) -> np.ndarray:
    """[N, 2] continuous texel coordinates (x, y) of directions (texel centres at integers)."""
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    if layout == "octahedral":
        uv = octahedral_encode(d)
        x = (uv[:, 0] + 1) * width / 2 - 0.5
        y = (1 - uv[:, 1]) * height / 2 - 0.5
        return np.stack([x, y], axis=1)
    from relight_cli.envmap import cube_pixel
    return cube_pixel(d, width)


def _bilinear_taps(pix: np.ndarray, layout: str, height: int, width: int):
    """The 4 texels and weights of bilinear lookups: ([N, 4] rows, [N, 4] cols, [N, 4] w).

    Octahedral: clamped to the atlas.  Cube: clamped inside the face (no
    cross-face filtering; an ablation-quality choice, documented).
    """
    x, y = pix[:, 0], pix[:, 1]
    if layout == "octahedral":
        ylo, yhi = 0.0, height - 1.0
    else:
        face = np.clip(np.floor((y + 0.5) / width), 0, 5)
        ylo, yhi = face * width, face * width + width - 1.0
    x = np.clip(x, 0, width - 1.0)
    y = np.clip(y, ylo, yhi)
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = x - x0
    fy = y - y0
    x1 = np.minimum(x0 + 1, width - 1)
    y1 = np.minimum(y0 + 1, yhi)
    cols = np.stack([x0, x1, x0, x1], axis=1).astype(np.int64)
    rows = np.stack([y0, y0, y1, y1], axis=1).astype(np.int64)
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    return rows, cols, w


# ------------------------------------------------------------------ receiver footprints


def footprint_samples(points, scales=None, rotations=None, footprint: str = "centre",
                      samples: int = 16, seed: int = 0):
    """Sample points over each receiver's footprint (paper ablation A).

    Args:
        points: [M, 3] receiver centres, metres, world.
        scales: [M, 3] receiver Gaussian std devs (metres), needed unless "centre".
        rotations: [M, 4] w-first quaternions (or [M, 3, 3]), needed unless "centre".
        footprint: "centre" (1 sample), "stencil" (deterministic 7 points: the
            centre and ±√3.5·s_k along each principal axis, equal weights, which
            reproduce the Gaussian's mean and covariance exactly) or "mc"
            (``samples`` seeded normal draws in the principal frame, equal weights).
    Returns:
        ([M, S, 3] sample positions, S) with equal weights 1/S.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if footprint not in FOOTPRINTS:
        raise ValueError(f"footprint must be one of {FOOTPRINTS}, got {footprint!r}")
    if footprint == "centre":
        return points[:, None, :], 1
    if scales is None or rotations is None:
        raise ValueError(f"footprint {footprint!r} needs the receivers' scales and rotations")
    m = len(points)
    s = np.asarray(scales, np.float64).reshape(m, 3)
    rot = np.asarray(rotations, np.float64)
    R = TR._quat_to_matrix(rot.reshape(m, 4)) if rot.size == 4 * m else rot.reshape(m, 3, 3)
    if footprint == "stencil":
        offsets = np.zeros((7, 3))
        for k in range(3):
            offsets[1 + 2 * k, k] = _STENCIL_H
            offsets[2 + 2 * k, k] = -_STENCIL_H
    else:
        if samples < 1:
            raise ValueError("samples must be ≥ 1")
        offsets = np.random.default_rng(seed).standard_normal((samples, 3))
    local = offsets[None, :, :] * s[:, None, :]                  # [M, S, 3] principal frame
    world = np.einsum("mij,msj->msi", R, local)
    return points[:, None, :] + world, len(offsets)


# ------------------------------------------------------------------ ROI


def receiver_roi(mix: TR.Mixture, light, receivers: np.ndarray, roi_radius: float | None = None,
                 cull_tolerance: float = 1e-7):
    """Which receivers of one light need a table entry (see module doc).

    Args:
        mix: occluders.
        light: [3] position, metres.
        receivers: [M, 3] points (centres or footprint samples), metres, world.
        roi_radius: optional cap R on the distance to the occluders' alpha-weighted
            centroid, metres.
    Returns:
        ([M] bool mask, info dict with centroid, radius, height bounds).
    """
    light = np.asarray(light, np.float64).reshape(3)
    receivers = np.asarray(receivers, np.float64).reshape(-1, 3)
    centroid = mix.alpha_weighted_centroid()
    radius_k = _truncation_radius(mix, cull_tolerance)
    keep_g = np.isfinite(radius_k)
    if keep_g.any():
        reach = np.linalg.norm(mix.means[keep_g] - centroid, axis=1) + radius_k[keep_g] * mix.scale_max[keep_g]
        bound = float(reach.max())
        top = float(np.max(mix.means[keep_g, 1] + radius_k[keep_g] * mix.scale_max[keep_g]))
    else:
        bound, top = 0.0, -np.inf
    mask = np.ones(len(receivers), bool)
    if roi_radius is not None:
        mask &= np.linalg.norm(receivers - centroid, axis=1) <= roi_radius
    # Robust height bounds: below, drop floaters under the floor (0.5th percentile
    # minus 5 cm); above, a receiver higher than every occluder cannot be shadowed
    # by a light that is higher still.
    lo = -np.inf
    if len(receivers) >= 200:
        lo = float(np.percentile(receivers[:, 1], 0.5)) - 0.05
    hi = top if light[1] >= top else np.inf
    mask &= (receivers[:, 1] >= lo) & (receivers[:, 1] <= hi)
    # Exact reach test: the segment light→receiver must pass through the bounding sphere.
    if keep_g.any():
        v = receivers - light
        length = np.linalg.norm(v, axis=1)
        dirs = v / np.where(length > 0, length, 1)[:, None]
        w = centroid - light
        t = np.clip(dirs @ w, 0, length)
        closest = light + t[:, None] * dirs
        mask &= np.linalg.norm(closest - centroid, axis=1) <= bound
    else:
        mask[:] = False
    info = {"centroid": [float(c) for c in centroid],
            "radius": None if roi_radius is None else float(roi_radius),
            "height": [float(lo), float(hi)],
            "bounding_radius": bound}
    return mask, info


def _truncation_radius(mix: TR.Mixture, tolerance: float) -> np.ndarray:
    """[N] Mahalanobis radius k_i beyond which Gaussian i adds < tolerance to τ (NaN: nowhere)."""
    bound = mix.peak_bound()
    with np.errstate(divide="ignore"):
        k2 = 2 * np.log(np.maximum(bound, 1e-300) / tolerance)
    k = np.sqrt(np.maximum(k2, 0.0))
    # a Gaussian whose peak is already below the tolerance contributes nothing anywhere
    return np.where(bound > tolerance, k, np.nan)


# ------------------------------------------------------------------ build


def build_dgsm(occluders, lights, receivers=None, size: tuple[int, int] = (128, 128),
               bins: int = 64, layout: str = "octahedral", mapping: str = TR.DEFAULT_MAPPING,
               kappa: float = 1.0, t_max=None, roi: bool = True,
               roi_radius: float | None = None, cull: bool = True,
               cull_tolerance: float = 1e-7, dtype=np.float32, chunk: int = 1 << 20,
               progress=None, intensities=None, colors=None, backend: str = "auto",
               radial: str = "full", t_min=None) -> DGSM:
    """Build a deep Gaussian shadow map.

    Args:
        occluders: a ``Gaussians`` (formats.gaussians_ply) or a prepared
            :class:`~relight_cli.gaussians.transmittance.Mixture` (then
            ``mapping``/``kappa`` are taken from it).
        lights: [L, 3] point-light positions, metres, world.
        receivers: [M, 3] receiver points (scene Gaussian centres, or footprint
            samples from :func:`footprint_samples`), metres, world; None = no ROI
            (then ``t_max`` is required).
        size: (H, W) of the octahedral atlas; a cube atlas uses faces of
            :func:`cube_face_size` (about the same texel count).
        bins: K radial bins.
        layout: "octahedral" (paper) or "cube" (ablation C).
        t_max: per-light radial extent (scalar or [L]); default: the farthest ROI
            receiver sits at the last bin centre, t_max = d_max·K/(K − ½).
        radial: where the K radial bins lie: ``"full"`` (the paper's concentric shells
            from the light, centres (k + ½)·t_max/K) or ``"roi"`` (ours: over the ROI
            receivers' distances only, the nearest at the first bin centre and the
            farthest at the last, centres t_min + (k + ½)(t_max − t_min)/K: the same K
            bins, spent where receivers are; T still integrates from the light).
        t_min: with ``t_max`` given, the per-light start of the bins (default 0).
        roi: restrict to texels/bins that ROI receivers read.
        roi_radius: optional radius R around the occluders' alpha-weighted centroid.
        cull: light-space occluder culling (tiles, texels, k_σ ellipse, radial).
        cull_tolerance: ε, the largest optical depth a culled Gaussian may have had.
        dtype: precision of the per-pair closed form (float32 fast path or float64,
            the reference twin, always numpy).
        backend: float32 inner loop in ``"numpy"`` or ``"torch"``
            (:mod:`relight_cli.gaussians.dgsm_torch`: ≈ 10× faster erf, ≈ 2× faster
            dense builds); ``"auto"`` uses torch for a light with ≥ TORCH_AUTO_PAIRS
            kept pairs (where importing torch, ≈ 1.5 s, pays for itself), or ≥
            TORCH_AUTO_PAIRS_IMPORTED when torch is already imported.
        progress: optional callable(iterable, total) → iterable for a progress bar.
        intensities: [L] light intensities and colors: [L, 3] linear RGB, stored
            with the map for the per-light weighting of direct light (Sec. 3.3);
            default 1 and white.
    Returns:
        :class:`DGSM`.
    """
    start = time.perf_counter()
    if isinstance(occluders, TR.Mixture):
        mix = occluders
    else:
        mix = TR.from_gaussians(occluders, mapping, kappa)
    lights = np.asarray(lights, np.float64).reshape(-1, 3)
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    h, w = int(size[0]), int(size[1])
    if layout == "cube":
        n = cube_face_size(h, w)
        h, w = 6 * n, n
    if bins < 1:
        raise ValueError("bins must be ≥ 1")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if receivers is None and t_max is None:
        raise ValueError("without receivers, t_max must be given")
    if radial not in RADIAL:
        raise ValueError(f"radial must be one of {RADIAL}, got {radial!r}")
    dirs = atlas_directions(layout, h, w).reshape(-1, 3)
    n_lights = len(lights)
    table = np.ones((n_lights, bins, h, w), np.float32)
    t_maxes = np.zeros(n_lights)
    t_mins = np.zeros(n_lights)
    rois = []
    stats = {"pairs_tested": 0, "pairs_kept": 0, "gaussians": len(mix), "gaussians_used": [],
             "texels_computed": 0, "bins_computed": 0}
    trunc = _truncation_radius(mix, cull_tolerance)
    iterator = range(n_lights) if progress is None else progress(range(n_lights), n_lights)
    for li in iterator:
        light = lights[li]
        if receivers is not None:
            recv = np.asarray(receivers, np.float64).reshape(-1, 3)
            if roi:
                mask, info = receiver_roi(mix, light, recv, roi_radius, cull_tolerance)
            else:
                mask = np.ones(len(recv), bool)
                info = {"centroid": [float(c) for c in mix.alpha_weighted_centroid()],
                        "radius": None, "height": [-math.inf, math.inf]}
            sel = recv[mask]
        else:
            sel = np.zeros((0, 3))
            info = {"centroid": [float(c) for c in mix.alpha_weighted_centroid()],
                    "radius": None, "height": [-math.inf, math.inf]}
        tn = 0.0
        if t_max is not None:
            tm = float(np.broadcast_to(np.asarray(t_max, np.float64), (n_lights,))[li])
            if t_min is not None:
                tn = float(np.broadcast_to(np.asarray(t_min, np.float64), (n_lights,))[li])
        else:
            all_recv = np.asarray(receivers, np.float64).reshape(-1, 3)
            far = np.linalg.norm((sel if len(sel) else all_recv) - light, axis=1)
            tm = float(far.max()) * bins / (bins - 0.5) if len(far) else 1.0
            tm = max(tm, 1e-6)
            if radial == "roi" and len(sel):
                tn, tm = roi_radial_range(far, bins, tm)
        t_maxes[li] = tm
        t_mins[li] = tn
        # Texels and bins to compute.
        if roi and receivers is not None:
            texel_mask = np.zeros(h * w, bool)
            if len(sel):
                v = sel - light
                dist = np.linalg.norm(v, axis=1)
                rows, cols, _ = _bilinear_taps(atlas_pixel(v, layout, h, w), layout, h, w)
                texel_mask[(rows * w + cols).ravel()] = True
                r = (dist - tn) * bins / (tm - tn) - 0.5
                k0 = int(np.clip(np.floor(r.min()), 0, bins - 1))
                k1 = int(np.clip(np.floor(r.max()) + 1, 0, bins - 1))
            else:
                k0, k1 = 0, -1
        else:
            texel_mask = np.ones(h * w, bool)
            k0, k1 = 0, bins - 1
        texels = np.flatnonzero(texel_mask)
        if k1 < k0:
            texels = texels[:0]
        info.update(receivers=int(len(sel)), texels=int(len(texels)), bins=[k0, k1])
        if len(texels):
            ys, xs = np.divmod(texels, w)
            info["pixels"] = [int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())]
        else:
            info["pixels"] = [0, 0, -1, -1]
        rois.append(info)
        if len(texels) == 0:
            stats["gaussians_used"].append(0)
            continue
        tau = _light_optical_depth(mix, light, dirs, texels, k0, k1, bins, tm, h, w, cull,
                                   trunc, dtype, chunk, stats, layout, backend, tn)
        table[li, k0:k1 + 1].reshape(k1 - k0 + 1, h * w)[:, texels] = np.exp(-tau.T)
        stats["texels_computed"] += int(len(texels))
        stats["bins_computed"] += int(k1 - k0 + 1)
    intensities, colors = _light_properties(n_lights, intensities, colors)
    return DGSM(table, lights, t_maxes, layout, mix.mapping, mix.kappa, rois,
                time.perf_counter() - start, stats, intensities=intensities, colors=colors,
                t_min=t_mins if (t_mins > 0).any() else None)


#: Where a map's radial bins lie (build_dgsm ``radial``).
RADIAL = ("full", "roi")


def roi_radial_range(distances, bins: int, full_t_max: float) -> tuple[float, float]:
    """(t_min, t_max) putting the nearest of ``distances`` at the first bin centre and the
    farthest at the last; the full range (0, ``full_t_max``) where that would start at or
    before the light, or the distances are one."""
    near, far = float(np.min(distances)), float(np.max(distances))
    if bins < 2 or not far > near:
        return 0.0, full_t_max
    step = (far - near) / (bins - 1)
    if near - step / 2 <= 0:
        return 0.0, full_t_max
    return near - step / 2, far + step / 2


def _light_properties(n_lights, intensities, colors):
    """([L] intensities ≥ 0, [L, 3] colours ≥ 0), defaults 1 and white."""
    i = np.ones(n_lights) if intensities is None else np.asarray(intensities, np.float64)
    c = np.ones((n_lights, 3)) if colors is None else np.asarray(colors, np.float64)
    i = np.broadcast_to(i, (n_lights,)).copy()
    c = np.broadcast_to(c, (n_lights, 3)).copy()
    if not (np.isfinite(i).all() and np.isfinite(c).all() and (i >= 0).all() and (c >= 0).all()):
        raise ValueError("light intensities and colours must be finite and ≥ 0")
    return i, c


def build_dgsm_groups(groups, lights, receivers=None, group_receivers=None, names=None,
                      t_max=None, progress=None, own_receivers=None, **kwargs) -> DGSM:
    """One shadow map per occluder group (several objects in one scene), sharing t_max.

    Group j's table is built from its own Gaussians only, for the receivers
    ``receivers`` plus every OTHER group's ``group_receivers`` (so objects
    shadow each other where the table covers them); ``transmittance`` is the
    product over groups, which equals the table of the concatenated set
    bin for bin (τ adds over disjoint Gaussians; tested) wherever each group's
    ROI covers what the combined ROI covers.

    Args:
        groups: J ``Gaussians`` (or prepared Mixtures), world frame.
        lights: [L, 3] metres, world.
        receivers: [M, 3] scene receiver points or None.
        group_receivers: None or J arrays [M_j, 3] (points of group j that receive
            the others' shadows: its centres or footprint samples).
        names: J labels stored with the map.
        own_receivers: None or J arrays [M_j, 3] that group j's OWN table covers too
            (its self-shadow lookups, :func:`self_lookup_points`).
        t_max: as :func:`build_dgsm`; default: the farthest ROI receiver of any
            group sits at the last bin centre.
        **kwargs: passed to :func:`build_dgsm` (size, bins, layout, mapping,
            kappa, roi, roi_radius, cull, cull_tolerance, dtype).
    Returns:
        :class:`DGSM` with ``groups`` [J, L, K, H, W].
    """
    start = time.perf_counter()
    mixes = [g if isinstance(g, TR.Mixture)
             else TR.from_gaussians(g, kwargs.get("mapping", TR.DEFAULT_MAPPING),
                                kwargs.get("kappa", 1.0))
             for g in groups]
    lights = np.asarray(lights, np.float64).reshape(-1, 3)
    n = len(mixes)
    if n == 0:
        raise ValueError("no occluder groups")
    extra = [np.zeros((0, 3)) if group_receivers is None
             else np.asarray(group_receivers[j], np.float64).reshape(-1, 3) for j in range(n)]
    base = np.zeros((0, 3)) if receivers is None else np.asarray(receivers, np.float64).reshape(-1, 3)
    own = [np.zeros((0, 3)) if own_receivers is None
           else np.asarray(own_receivers[j], np.float64).reshape(-1, 3) for j in range(n)]
    per_group = [np.concatenate([base] + [extra[i] for i in range(n) if i != j] + [own[j]])
                 for j in range(n)]
    if receivers is None and group_receivers is None and t_max is None:
        raise ValueError("without receivers, t_max must be given")
    bins = int(kwargs.get("bins", 64))
    radial = kwargs.pop("radial", "full")
    t_min = kwargs.pop("t_min", None)
    if t_max is None:
        t_max = np.zeros(len(lights))
        t_min = np.zeros(len(lights))
        for li, light in enumerate(lights):
            far, near = 0.0, math.inf
            for j in range(n):
                recv = per_group[j]
                if not len(recv):
                    continue
                if kwargs.get("roi", True):
                    mask, _ = receiver_roi(mixes[j], light, recv, kwargs.get("roi_radius"),
                                           kwargs.get("cull_tolerance", 1e-7))
                    recv = recv[mask] if mask.any() else recv
                d = np.linalg.norm(recv - light, axis=1)
                far, near = max(far, float(d.max())), min(near, float(d.min()))
            t_max[li] = max(far * bins / (bins - 0.5), 1e-6)
            if radial == "roi" and math.isfinite(near):
                t_min[li], t_max[li] = roi_radial_range([near, far], bins, t_max[li])
    maps = []
    iterator = range(n) if progress is None else progress(range(n), n)
    for j in iterator:
        maps.append(build_dgsm(mixes[j], lights, per_group[j] if len(per_group[j]) else None,
                               t_max=t_max, t_min=t_min, **kwargs))
    table = np.prod(np.stack([m.transmittance for m in maps]), axis=0, dtype=np.float32)
    rois = []
    for li in range(len(lights)):
        infos = [m.roi[li] for m in maps]
        used = [i for i in infos if i["texels"]]
        rois.append({
            "receivers": int(sum(i["receivers"] for i in infos)),
            "texels": int(sum(i["texels"] for i in infos)),
            "bins": ([min(i["bins"][0] for i in used), max(i["bins"][1] for i in used)]
                     if used else [0, -1]),
            "pixels": ([min(i["pixels"][0] for i in used), min(i["pixels"][1] for i in used),
                        max(i["pixels"][2] for i in used), max(i["pixels"][3] for i in used)]
                       if used else [0, 0, -1, -1]),
            "groups": infos})
    stats = {"pairs_tested": sum(m.stats["pairs_tested"] for m in maps),
             "pairs_kept": sum(m.stats["pairs_kept"] for m in maps),
             "gaussians": sum(m.stats["gaussians"] for m in maps),
             "groups": [m.stats for m in maps]}
    first = maps[0]
    return DGSM(table, lights, first.t_max, first.layout, first.mapping, first.kappa, rois,
                time.perf_counter() - start, stats,
                np.stack([m.transmittance for m in maps]),
                list(names) if names is not None else [f"group{j}" for j in range(n)],
                first.intensities, first.colors, t_min=first.t_min)


def _use_torch(backend, dtype, pairs: int) -> bool:
    if np.dtype(dtype) != np.float32 or backend == "numpy":
        return False
    import sys
    if backend == "auto":
        # torch's float32 erf loop is ≈ 2× the numpy one on dense work (2 threads), but a
        # fresh import costs ≈ 1.5 s and small culled builds gain nothing (gathers dominate)
        threshold = TORCH_AUTO_PAIRS_IMPORTED if "torch" in sys.modules else TORCH_AUTO_PAIRS
        if pairs < threshold:
            return False
    from . import dgsm_torch
    if not dgsm_torch.available():
        if backend == "torch":
            raise ValueError("backend 'torch' needs torch installed")
        return False
    return True


def _light_optical_depth(mix, light, dirs, texels, k0, k1, bins, t_max, h, w, cull, trunc,
                         dtype, chunk, stats, layout="octahedral", backend="numpy",
                         t_min: float = 0.0):
    """[T, k1−k0+1] optical depth for the given texels and bins of one light (bin centres
    t_min + (k + ½)(t_max − t_min)/bins)."""
    n_bins = k1 - k0 + 1
    t_centres = t_min + (np.arange(k0, k1 + 1) + 0.5) * (t_max - t_min) / bins
    # Per-Gaussian light-space quantities (shared by every texel of this light).
    rel = mix.means - light
    dist = np.linalg.norm(rel, axis=1)
    gdir = rel / np.where(dist > 0, dist, 1)[:, None]
    r_l_all = np.einsum("nji,nj->ni", mix.rotation, -rel / mix.scale_max[:, None])
    if cull:
        usable = np.isfinite(trunc)
        reach = np.where(usable, trunc, 0) * mix.scale_max           # bounding-sphere radius, m
        usable &= dist - reach <= t_centres[-1]                      # radial: not beyond the last bin
        with np.errstate(invalid="ignore"):
            half_angle = np.where(dist > reach, np.arcsin(np.clip(reach / np.maximum(dist, 1e-300), 0, 1)),
                                  np.pi)
        candidates = np.flatnonzero(usable)
    else:
        candidates = np.arange(len(mix))
    stats["gaussians_used"].append(int(len(candidates)))   # after radial culling
    pair_tex, pair_g = [], []
    if cull and len(candidates):
        tex_dirs = dirs[texels]
        # One cone around all needed texels first: most occluders of a light
        # project far from the receivers' texels.
        all_centre = tex_dirs.mean(axis=0)
        all_centre /= max(np.linalg.norm(all_centre), 1e-300)
        all_rad = float(np.arccos(np.clip(tex_dirs @ all_centre, -1, 1)).max())
        ang_all = np.arccos(np.clip(gdir[candidates] @ all_centre, -1, 1))
        candidates = candidates[ang_all <= half_angle[candidates] + all_rad + 1e-9]
        ti, gj, tested = cone_texel_pairs(tex_dirs, gdir[candidates], half_angle[candidates])
        stats["pairs_tested"] += tested
        pair_tex.append(ti)
        pair_g.append(candidates[gj])
    elif len(candidates):
        stats["pairs_tested"] += int(len(candidates)) * len(texels)
        pair_tex.append(np.repeat(np.arange(len(texels)), len(candidates)))
        pair_g.append(np.tile(candidates, len(texels)))
    tau = np.zeros((len(texels), n_bins))
    if not pair_tex:
        return tau
    pt = np.concatenate(pair_tex)
    pg = np.concatenate(pair_g)
    if _use_torch(backend, dtype, len(pt)):
        from . import dgsm_torch
        stats["backend"] = "torch"
        return dgsm_torch.light_pairs_optical_depth(mix, dirs[texels], r_l_all, pt, pg, trunc,
                                                    cull, t_max, bins, k0, k1, stats, t_min)
    stats["backend"] = "numpy"
    step = np.zeros(len(texels) * (n_bins + 1))
    direct = np.zeros(len(texels) * n_bins)
    kept = 0
    for s in range(0, len(pt), chunk):
        ti, gi = pt[s:s + chunk], pg[s:s + chunk]
        d = dirs[texels[ti]]
        d_l = np.einsum("pji,pj->pi", mix.rotation[gi], d).astype(dtype)
        terms = TR.local_pair_terms(mix, r_l_all[gi].astype(dtype), d_l, gi, dtype)
        if cull:
            ok = terms.m2 <= trunc[gi] ** 2
            ti, gi = ti[ok], gi[ok]
            terms = TR.PairTerms(terms.t_star[ok], terms.sigma_t[ok], terms.m2[ok],
                                 terms.half_amplitude[ok])
        kept += len(ti)
        _accumulate(terms, ti, t_max, bins, k0, k1, step, direct, t_min)
    stats["pairs_kept"] += kept
    step = step.reshape(len(texels), n_bins + 1)[:, :n_bins]
    return np.cumsum(step, axis=1) + direct.reshape(len(texels), n_bins)


def cone_texel_pairs(texel_dirs, cone_dirs, half_angles, growth: float = 1.5):
    """All (texel, cone) pairs with the texel direction inside the cone (light-space culling).

    The exact test is angle(texel, cone axis) ≤ half-angle, evaluated as the
    chord |t − g| ≤ 2 sin(θ/2) on unit vectors (a little slack, 1e-9 relative
    + 1e-12, only makes it conservative; the k_σ ellipse test follows per
    pair).  Cones are grouped by radius into classes a factor ``growth``
    apart; each class is one k-d tree range search of its largest radius
    against a tree of the texel directions (scipy's sparse_distance_matrix, no
    Python loop over Gaussians), then filtered by each cone's own radius.  It
    replaces the per-tile and per-cone-bounding-box enumerations of the
    octahedral atlas (10× more candidate pairs on a volumetric avatar) and
    works for any layout.

    Args:
        texel_dirs: [T, 3] unit directions of the needed texels.
        cone_dirs: [G, 3] unit cone axes (light → Gaussian centre).
        half_angles: [G] radians (π: the cone is the whole sphere).
    Returns:
        ([P] texel indices into texel_dirs, [P] cone indices, pairs tested).
    """
    from scipy.spatial import cKDTree

    texel_dirs = np.asarray(texel_dirs, np.float64).reshape(-1, 3)
    cone_dirs = np.asarray(cone_dirs, np.float64).reshape(-1, 3)
    if len(texel_dirs) == 0 or len(cone_dirs) == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty, 0
    chord = 2 * np.sin(np.minimum(np.asarray(half_angles, np.float64), np.pi) / 2) * (1 + 1e-9) + 1e-12
    texel_tree = cKDTree(texel_dirs)
    cls = np.floor(np.log(chord) / math.log(growth)).astype(np.int64)
    order = np.argsort(cls, kind="stable")
    bounds = np.flatnonzero(np.diff(cls[order])) + 1
    out_t, out_g, tested = [], [], 0
    for idx in np.split(order, bounds):
        found = cKDTree(cone_dirs[idx]).sparse_distance_matrix(
            texel_tree, float(chord[idx].max()), output_type="ndarray")
        tested += len(found)
        ok = found["v"] <= chord[idx[found["i"]]]
        out_t.append(found["j"][ok].astype(np.int64))
        out_g.append(idx[found["i"][ok]])
    return np.concatenate(out_t), np.concatenate(out_g), tested


def _accumulate(terms: TR.PairTerms, ti, t_max, bins, k0, k1, step, direct, t_min=0.0):
    """Add each pair's τ(t_k) = G·[erf(u_k) − erf(u_0)] for bins k0..k1 (centres
    t_k = t_min + (k + ½)(t_max − t_min)/bins; τ always integrates from the light).

    Bins inside the erf's transition window |u| ≤ 6.5 are evaluated explicitly;
    from the first bin past the window on, the term is the constant G·erfc(u_0),
    added once to ``step`` and spread by a cumulative sum.
    """
    n_bins = k1 - k0 + 1
    t_star = terms.t_star.astype(np.float64)
    sig = terms.sigma_t.astype(np.float64)
    G = terms.half_amplitude.astype(np.float64)
    width = _ERF_WINDOW * math.sqrt(2) * sig
    scale = bins / (t_max - t_min)
    k_lo = np.ceil((t_star - t_min - width) * scale - 0.5)
    k_hi = np.floor((t_star - t_min + width) * scale - 0.5) + 1  # first bin past the window
    k_lo = np.clip(k_lo, k0, k1 + 1).astype(np.int64)
    k_hi = np.clip(k_hi, k0, k1 + 1).astype(np.int64)
    u0 = terms.u(np.zeros((), terms.t_star.dtype))
    # step: G·erfc(u0) at k_hi (if inside the range)
    from scipy.special import erfc
    has_step = k_hi <= k1
    if has_step.any():
        full = G[has_step] * erfc(u0[has_step].astype(np.float64))
        idx = ti[has_step] * (n_bins + 1) + (k_hi[has_step] - k0)
        step += np.bincount(idx, full, minlength=len(step))
    count = np.maximum(k_hi - k_lo, 0)
    total = int(count.sum())
    if total:
        rep = np.repeat(np.arange(len(count)), count)
        first = np.repeat(np.cumsum(count) - count, count)
        k = k_lo[rep] + (np.arange(total) - first)
        tk = t_min + (k + 0.5) * ((t_max - t_min) / bins)
        u_k = ((tk - t_star[rep]) / (math.sqrt(2) * sig[rep]))
        vals = G[rep] * TR.erf_difference(u0[rep].astype(np.float64), np.maximum(u_k, u0[rep]))
        idx = ti[rep] * n_bins + (k - k0)
        direct += np.bincount(idx, vals, minlength=len(direct))


def build_dgsm_reference(mix: TR.Mixture, light, size, bins, t_max, layout="octahedral",
                         t_min: float = 0.0):
    """Slow twin: [K, H, W] T for EVERY texel and bin by the dense float64 closed form."""
    h, w = size
    if layout == "cube":
        n = cube_face_size(h, w)
        h, w = 6 * n, n
    dirs = atlas_directions(layout, h, w).reshape(-1, 3)
    light = np.asarray(light, np.float64)
    out = np.empty((bins, h * w))
    for k in range(bins):
        tk = t_min + (k + 0.5) * (t_max - t_min) / bins
        out[k] = TR.transmittance(mix, np.broadcast_to(light, dirs.shape), dirs, 0.0, tk)
    return out.reshape(bins, h, w)


# ------------------------------------------------------------------ lookup


def lookup(dgsm: DGSM, light_index: int, points: np.ndarray) -> np.ndarray:
    """[M] trilinear T at points [M, 3] (metres, world) for one light.

    Bilinear over texels (clamped at the atlas border, or inside the face for
    the cube), linear over bins; between the light (T = 1 at t = 0) and the first
    bin centre it interpolates from 1; beyond the last bin centre it clamps.  A map whose
    bins start at t_min > 0 (``radial`` ``roi``) clamps below its first bin centre too
    (no receiver it was built for lies there).
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    light = dgsm.lights[light_index]
    table = dgsm.transmittance[light_index]                       # [K, H, W]
    K, H, W = table.shape
    v = points - light
    dist = np.linalg.norm(v, axis=1)
    rows, cols, wts = _bilinear_taps(atlas_pixel(v, dgsm.layout, H, W), dgsm.layout, H, W)
    t_min = 0.0 if dgsm.t_min is None else float(dgsm.t_min[light_index])
    r = (dist - t_min) * K / (dgsm.t_max[light_index] - t_min) - 0.5
    r = np.clip(r, -0.5 if t_min == 0 else 0.0, K - 1)
    k0 = np.floor(r).astype(np.int64)
    f = r - k0
    ka = np.clip(k0, 0, K - 1)
    kb = np.clip(k0 + 1, 0, K - 1)
    ta = (table[ka[:, None], rows, cols] * wts).sum(axis=1)
    tb = (table[kb[:, None], rows, cols] * wts).sum(axis=1)
    ta = np.where(k0 < 0, 1.0, ta)                                # T(t=0) = 1
    return ((1 - f) * ta + f * tb).astype(np.float64)


def sample_transmittance(dgsm: DGSM, points, scales=None, rotations=None,
                         footprint: str = "centre", samples: int = 16, seed: int = 0,
                         light_index: int | None = None) -> np.ndarray:
    """Transmittance from each light to each receiver, averaged over its footprint.

    This is the render-time entry point (used by ``relight relight``).

    Args:
        dgsm: a built or loaded :class:`DGSM`.
        points: [M, 3] receiver centres, metres, world.
        scales, rotations: [M, 3] std devs and [M, 4] w-first quaternions of the
            receiver Gaussians (needed for "stencil" and "mc").
        footprint: "centre", "stencil" (7-point) or "mc" (``samples`` seeded draws).
        light_index: one light (returns [M]) or None for all (returns [L, M]).
    Returns:
        [L, M] (or [M]) float64 T in [0, 1].
    """
    pts, n = footprint_samples(points, scales, rotations, footprint, samples, seed)
    m = len(pts)
    flat = pts.reshape(-1, 3)
    which = range(len(dgsm.lights)) if light_index is None else [light_index]
    out = np.stack([lookup(dgsm, i, flat).reshape(m, n).mean(axis=1) for i in which])
    out = np.clip(out, 0.0, 1.0)
    return out[0] if light_index is not None else out


# ------------------------------------------------------------------ self-shadowing

#: Self-shadow lookups start this many standard deviations of the receiving Gaussian
#: (along the direction to the light) towards the light: its own optical depth before
#: that point is Φ(−3) = 0.13 % of its whole (a Gaussian never shadows itself).
SELF_SIGMAS = 3.0


def self_offsets(lights, means, scales, rotations, bin_width) -> np.ndarray:
    """[L, M] how far (metres) a Gaussian's self-shadow lookups move towards each light:
    ``SELF_SIGMAS`` of its own extent along that direction, σ_u = √(uᵀΣu), plus one
    radial bin (``bin_width`` [L], metres) so the table's interpolation between bins
    does not reach back into the bin holding the Gaussian."""
    lights = np.asarray(lights, np.float64).reshape(-1, 3)
    means = np.asarray(means, np.float64).reshape(-1, 3)
    m = len(means)
    s = np.asarray(scales, np.float64).reshape(m, 3)
    rot = np.asarray(rotations, np.float64)
    R = TR._quat_to_matrix(rot.reshape(m, 4)) if rot.size == 4 * m else rot.reshape(m, 3, 3)
    out = np.empty((len(lights), m))
    for i, light in enumerate(lights):
        u = light - means
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
        local = np.einsum("mji,mj->mi", R, u)                  # u in each principal frame
        sigma = np.sqrt(((local * s) ** 2).sum(axis=1))
        out[i] = SELF_SIGMAS * sigma + np.asarray(bin_width, np.float64).reshape(-1)[i]
    return out


def self_lookup_points(lights, means, scales, rotations, bin_width, footprint="centre",
                       samples=16, seed=0) -> list:
    """Per light, [M, S, 3] footprint samples of each Gaussian moved towards that light by
    :func:`self_offsets` (never past the light): where its self-shadow is looked up."""
    pts, _ = footprint_samples(means, scales, rotations, footprint, samples, seed)
    offsets = self_offsets(lights, means, scales, rotations, bin_width)
    out = []
    for i, light in enumerate(np.asarray(lights, np.float64).reshape(-1, 3)):
        v = light - pts                                          # [M, S, 3]
        dist = np.linalg.norm(v, axis=2, keepdims=True)
        step = np.minimum(offsets[i][:, None, None], 0.999 * dist)
        out.append(pts + v / np.maximum(dist, 1e-300) * step)
    return out


def sample_self_transmittance(dgsm: DGSM, means, scales, rotations, footprint: str = "centre",
                              samples: int = 16, seed: int = 0) -> np.ndarray:
    """[L, M] transmittance from each light to Gaussians of the occluders the map was built
    from, each Gaussian's own optical depth left out: looked up at its footprint moved
    towards the light (:func:`self_lookup_points`), so only what lies between it and the
    light shadows it (self-shadowing; the paper's avatars receive no shadow of their own).
    The map must cover those points (built with them as receivers: relight_cli.jobs.
    dgsm_build, ``self_shadow``)."""
    t_min = 0.0 if dgsm.t_min is None else np.asarray(dgsm.t_min, np.float64)
    width = (np.asarray(dgsm.t_max, np.float64) - t_min) / dgsm.bins
    points = self_lookup_points(dgsm.lights, means, scales, rotations, width, footprint,
                                samples, seed)
    out = np.stack([lookup(dgsm, i, p.reshape(-1, 3)).reshape(p.shape[:2]).mean(axis=1)
                    for i, p in enumerate(points)])
    return np.clip(out, 0.0, 1.0)


# ------------------------------------------------------------------ table-free


def exact_transmittance(mix: TR.Mixture, light, points, cull_tolerance: float = 1e-7,
                        dtype=np.float32) -> np.ndarray:
    """[M] closed-form T from a point light to points, without a table (culled).

    The same per-Gaussian cones as the DGSM build select, through a k-d tree on
    the receivers' unit directions, which receivers each Gaussian can shadow;
    only those pairs are evaluated (segment [0, |p − L|]).  The dense twin is
    :func:`relight_cli.gaussians.transmittance.transmittance_between`; they agree
    to (number of nearly-touching Gaussians)·``cull_tolerance``.

    Args:
        mix: occluders.
        light: [3] metres, world.
        points: [M, 3] metres, world.
    """
    from scipy.spatial import cKDTree

    light = np.asarray(light, np.float64).reshape(3)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    v = points - light
    dist = np.linalg.norm(v, axis=1)
    dirs = v / np.where(dist > 0, dist, 1)[:, None]
    tau = np.zeros(len(points))
    trunc = _truncation_radius(mix, cull_tolerance)
    usable = np.isfinite(trunc)
    if not usable.any() or len(points) == 0:
        return np.ones(len(points))
    rel = mix.means - light
    gdist = np.linalg.norm(rel, axis=1)
    reach = np.where(usable, trunc, 0) * mix.scale_max
    usable &= gdist - reach <= dist.max()
    idx = np.flatnonzero(usable)
    gdir = rel[idx] / np.where(gdist[idx] > 0, gdist[idx], 1)[:, None]
    inside = gdist[idx] <= reach[idx]
    half = np.where(inside, np.pi, np.arcsin(np.clip(reach[idx] / np.maximum(gdist[idx], 1e-300),
                                                      0, 1)))
    chord = 2 * np.sin(np.minimum(half, np.pi) / 2) * (1 + 1e-9) + 1e-12
    tree = cKDTree(dirs)
    lists = tree.query_ball_point(gdir, chord)
    counts = np.fromiter((len(x) for x in lists), np.int64, len(lists))
    if counts.sum() == 0:
        return np.ones(len(points))
    pr = np.fromiter((j for x in lists for j in x), np.int64, int(counts.sum()))
    pg = np.repeat(idx, counts)
    r_l_all = np.einsum("nji,nj->ni", mix.rotation, -rel / mix.scale_max[:, None])
    for s in range(0, len(pr), 1 << 20):
        ri, gi = pr[s:s + (1 << 20)], pg[s:s + (1 << 20)]
        d_l = np.einsum("pji,pj->pi", mix.rotation[gi], dirs[ri]).astype(dtype)
        terms = TR.local_pair_terms(mix, r_l_all[gi].astype(dtype), d_l, gi, dtype)
        ok = terms.m2 <= trunc[gi] ** 2
        seg = TR.segment_terms(TR.PairTerms(terms.t_star[ok], terms.sigma_t[ok], terms.m2[ok],
                                            terms.half_amplitude[ok]),
                               np.zeros((), dtype), dist[ri[ok]].astype(dtype))
        tau += np.bincount(ri[ok], seg.astype(np.float64), minlength=len(points))
    return np.exp(-tau)
