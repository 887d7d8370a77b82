"""CPU EWA splatting of 3D Gaussians (the 3DGS rasterizer's forward pass, in numpy).

Model (Zwicker et al. 2001; Kerbl et al. 2023), shared exactly by the fast
tile-based renderer :func:`render` and the per-pixel twin :func:`render_reference`:

* Camera: OpenCV pinhole (``formats/camera.py``), x_cam = R x + t, pixel
  u = fx·x/z + cx, v = fy·y/z + cy; pixel (i, j) has its centre at (u, v) = (i, j).
* Projection: Σ' = J W Σ Wᵀ Jᵀ + ``dilation``·I (pixels²) with W = R and the
  perspective Jacobian J at the centre; like 3DGS, x/z and y/z in J are
  clamped to ±1.3·(half field of view) so Gaussians far outside the view do not
  get absurd footprints.  Gaussians with z ≤ ``near`` are dropped.
* Per pixel p: α = min(0.99, o·exp(−½ dᵀΣ'⁻¹d)), d = p − centre; α < 1/255 is
  skipped.  Gaussians are composited front to back in order of camera-space
  depth z (ties by index): C = Σ c_k α_k T_k, T_{k+1} = T_k(1 − α_k), and a pixel
  stops before the Gaussian that would bring T below 1e-4 (as 3DGS).
* Colour c_k = max(0, 0.5 + Σ sh_k Y(d_k)) with d_k the unit direction from the
  camera centre to the Gaussian centre (``relight_cli.sh`` basis), unless
  per-Gaussian colours are given.

The footprint cut-off is exact, not a 3σ rule: a Gaussian can reach a pixel
only where o·exp(−q/2) ≥ 1/255, i.e. q ≤ 2 ln(255·o), so its tile list is the
bounding box of that ellipse and the tiled result equals the per-pixel one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from relight_cli.formats.camera import Camera
from relight_cli.formats.gaussians_ply import Gaussians
from relight_cli.progress import LateProgress
from relight_cli.sh import sh_basis

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
#: A render expected to take at least this many seconds shows progress over its tiles
#: (unless ``quiet``; relight_cli.progress.LateProgress), so short renders stay silent.
#: A 100k+-Gaussian scene at 400x300 takes 20-55 s on the 2-core test machine.
PROGRESS_SECONDS = 5.0


@dataclass
class RenderResult:
    """A rendered view.

    Attributes:
        image: [H, W, 3] float64 linear RGB (background added where T > 0).
        alpha: [H, W] float64 accumulated opacity 1 − T.
        depth: [H, W] float64 Σ w_k z_k, the opacity-weighted camera depth
            (metres; divide by alpha for the mean depth of what is seen).
    """

    image: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray


@dataclass
class Projected:
    """Gaussians projected to a camera (only those in front of the near plane).

    Attributes:
        index: [M] indices into the input Gaussians, sorted front to back.
        mean2d: [M, 2] pixel centres (u, v).
        conic: [M, 3] inverse 2D covariance (a, b, c): q = a dx² + 2b dx dy + c dy².
        depth: [M] camera-space z, metres.
        opacity: [M] peak opacity.
        color: [M, 3] RGB.
        extent: [M, 2] half-widths (pixels) of the bounding box of the α ≥ 1/255 ellipse.
    """

    index: np.ndarray
    mean2d: np.ndarray
    conic: np.ndarray
    depth: np.ndarray
    opacity: np.ndarray
    color: np.ndarray
    extent: np.ndarray


def gaussian_colors(g: Gaussians, camera_center: np.ndarray) -> np.ndarray:
    """[N, 3] view-dependent colours max(0, 0.5 + Σ sh Y(d)), d = unit(mean − camera centre)."""
    if g.sh_degree == 0:
        return g.colors()
    d = g.means - np.asarray(camera_center, np.float64)[None, :]
    basis = sh_basis(d, g.sh_degree)                      # [N, K]
    return np.maximum(0.5 + np.einsum("nk,nkc->nc", basis, g.sh), 0.0)


def project(g: Gaussians, camera: Camera, near: float = 0.01, dilation: float = 0.3,
            colors: np.ndarray | None = None) -> Projected:
    """Project Gaussians (vectorized), drop those behind ``near`` or too faint, sort by depth."""
    K, R, t = camera.K, camera.R, camera.t
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    p = g.means @ R.T + t                                  # [N, 3] camera frame
    z = p[:, 2]
    keep = (z > near) & (g.opacities >= ALPHA_MIN)
    idx = np.flatnonzero(keep)
    p, z = p[idx], z[idx]
    lim_x = 1.3 * _half_tan(cx, camera.width, fx)
    lim_y = 1.3 * _half_tan(cy, camera.height, fy)
    tx = np.clip(p[:, 0] / z, -lim_x, lim_x) * z
    ty = np.clip(p[:, 1] / z, -lim_y, lim_y) * z
    J = np.zeros((len(idx), 2, 3))
    J[:, 0, 0] = fx / z
    J[:, 0, 2] = -fx * tx / z ** 2
    J[:, 1, 1] = fy / z
    J[:, 1, 2] = -fy * ty / z ** 2
    M = J @ R                                              # [M, 2, 3]
    sigma = g.subset(idx).covariances()                    # [M, 3, 3]
    cov = M @ sigma @ M.transpose(0, 2, 1)
    cov[:, 0, 0] += dilation
    cov[:, 1, 1] += dilation
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * c - b * b
    ok = det > 0
    opacity = g.opacities[idx]
    # q ≤ q_max where o·exp(−q/2) ≥ 1/255; the ellipse's bounding box half-widths are √(q_max Σ'_ii).
    q_max = 2.0 * np.log(np.maximum(opacity / ALPHA_MIN, 1.0))
    extent = np.sqrt(np.stack([q_max * a, q_max * c], axis=1).clip(min=0))
    mean2d = np.stack([fx * p[:, 0] / z + cx, fy * p[:, 1] / z + cy], axis=1)
    conic = np.stack([c, -b, a], axis=1) / np.where(ok, det, 1.0)[:, None]
    if colors is None:
        col = gaussian_colors(g.subset(idx), camera.center)
    else:
        col = np.asarray(colors, np.float64).reshape(-1, 3)[idx]
    order = np.argsort(z[ok], kind="stable")
    sel = np.flatnonzero(ok)[order]
    return Projected(idx[sel], mean2d[sel], conic[sel], z[sel], opacity[sel], col[sel], extent[sel])


def _half_tan(c: float, size: int, f: float) -> float:
    """tan of the half field of view on the wider side of the principal point."""
    return max(c + 0.5, size - 0.5 - c) / f


def render(g: Gaussians, camera: Camera, background=(0.0, 0.0, 0.0), near: float = 0.01,
           dilation: float = 0.3, colors: np.ndarray | None = None, tile: int = 8,
           chunk: int = 64, quiet: bool = True) -> RenderResult:
    """Tile-based, vectorized EWA splatting (see the module docstring for the model).

    Each tile of ``tile``×``tile`` pixels composites its depth-sorted Gaussian
    list in chunks (``chunk`` Gaussians first, doubling up to 4096) as
    [chunk, pixels] arrays (cumulative products for T), stopping once every
    pixel of the tile is saturated.

    Args:
        g: the Gaussians (world frame).
        camera: OpenCV camera.
        background: RGB added with weight T.
        near: near plane, metres; dilation: low-pass added to Σ' (pixels²).
        colors: optional [N, 3] per-Gaussian colours replacing the SH evaluation.
        quiet: False shows progress over the tiles on stderr (relight_cli.progress)
            when the render looks long (:data:`PROGRESS_SECONDS`).

    Returns:
        :class:`RenderResult`.
    """
    H, W = camera.height, camera.width
    pr = project(g, camera, near, dilation, colors)
    tiles_x = (W + tile - 1) // tile
    tiles_y = (H + tile - 1) // tile
    image = np.zeros((H, W, 3))
    transmittance = np.ones((H, W))
    depth = np.zeros((H, W))
    if len(pr.index):
        # Tile ranges of each Gaussian's exact footprint box (pixel centres at integers).
        lo = np.floor(pr.mean2d - pr.extent)
        hi = np.ceil(pr.mean2d + pr.extent)
        tx0 = np.clip(lo[:, 0] // tile, 0, tiles_x).astype(np.int64)
        tx1 = np.clip(hi[:, 0] // tile + 1, 0, tiles_x).astype(np.int64)
        ty0 = np.clip(lo[:, 1] // tile, 0, tiles_y).astype(np.int64)
        ty1 = np.clip(hi[:, 1] // tile + 1, 0, tiles_y).astype(np.int64)
        nx = np.maximum(tx1 - tx0, 0)
        ny = np.maximum(ty1 - ty0, 0)
        counts = nx * ny
        gauss = np.repeat(np.arange(len(counts)), counts)   # sorted by depth already
        offset = np.arange(len(gauss)) - np.repeat(np.cumsum(counts) - counts, counts)
        nxr = np.repeat(np.maximum(nx, 1), counts)
        tile_id = (np.repeat(ty0, counts) + offset // nxr) * tiles_x + np.repeat(tx0, counts) + offset % nxr
        order = np.argsort(tile_id, kind="stable")         # stable: depth order kept per tile
        tile_id, gauss = tile_id[order], gauss[order]
        starts = np.searchsorted(tile_id, np.arange(tiles_x * tiles_y + 1))
        busy = np.flatnonzero(np.diff(starts))              # tiles some Gaussian reaches
        bar = LateProgress(len(busy), "splatting", "tiles", quiet, PROGRESS_SECONDS)
        for tid in busy:
            ty, tx = divmod(int(tid), tiles_x)
            y0, x0 = ty * tile, tx * tile
            y1, x1 = min(y0 + tile, H), min(x0 + tile, W)
            ys, xs = np.mgrid[y0:y1, x0:x1]
            px = xs.reshape(-1).astype(np.float64)
            py = ys.reshape(-1).astype(np.float64)
            col, T, dep = _composite_tile(pr, gauss[starts[tid]:starts[tid + 1]], px, py, chunk)
            image[y0:y1, x0:x1] = col.reshape(y1 - y0, x1 - x0, 3)
            transmittance[y0:y1, x0:x1] = T.reshape(y1 - y0, x1 - x0)
            depth[y0:y1, x0:x1] = dep.reshape(y1 - y0, x1 - x0)
            bar.update(1)
        bar.close()
    image += transmittance[..., None] * np.asarray(background, np.float64)[None, None, :]
    return RenderResult(image, 1.0 - transmittance, depth)


def _composite_tile(pr: Projected, ids: np.ndarray, px: np.ndarray, py: np.ndarray, chunk: int):
    """Front-to-back compositing of depth-sorted Gaussians ``ids`` over pixels (px, py) [P]."""
    P = len(px)
    color = np.zeros((P, 3))
    depth = np.zeros(P)
    T = np.ones(P)
    done = np.zeros(P, bool)
    # Chunks grow geometrically: most tiles saturate within the first few dozen
    # Gaussians, while deep tiles should not pay per-chunk overhead many times.
    s, size = 0, chunk
    while s < len(ids):
        k = ids[s:s + size]
        s, size = s + size, min(size * 2, 4096)
        dx = px[None, :] - pr.mean2d[k, 0:1]               # [m, P]
        dy = py[None, :] - pr.mean2d[k, 1:2]
        a, b, c = pr.conic[k, 0:1], pr.conic[k, 1:2], pr.conic[k, 2:3]
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        alpha = np.minimum(ALPHA_MAX, pr.opacity[k, None] * np.exp(np.minimum(power, 0.0)))
        alpha = np.where((power <= 0) & (alpha >= ALPHA_MIN), alpha, 0.0)
        t_after = T[None, :] * np.cumprod(1.0 - alpha, axis=0)          # [m, P]
        use = (t_after >= T_MIN) & ~done[None, :]
        t_before = np.concatenate([T[None, :], t_after[:-1]], axis=0)
        weight = np.where(use, alpha * t_before, 0.0)                    # [m, P]
        color += weight.T @ pr.color[k]
        depth += weight.T @ pr.depth[k]
        done |= (~use & (alpha > 0)).any(axis=0)
        T = T * np.prod(np.where(use, 1.0 - alpha, 1.0), axis=0)
        if done.all():
            break
    return color, T, depth


def render_reference(g: Gaussians, camera: Camera, background=(0.0, 0.0, 0.0), near: float = 0.01,
                     dilation: float = 0.3, colors: np.ndarray | None = None) -> RenderResult:
    """Slow per-pixel twin of :func:`render` (plain loops; tests only, tiny images)."""
    K, R, t = camera.K, camera.R, camera.t
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    centre = -R.T @ t
    items = []
    for i in range(len(g)):
        pc = R @ g.means[i] + t
        z = pc[2]
        if z <= near or g.opacities[i] < ALPHA_MIN:
            continue
        lim_x = 1.3 * max(cx + 0.5, camera.width - 0.5 - cx) / fx
        lim_y = 1.3 * max(cy + 0.5, camera.height - 0.5 - cy) / fy
        tx = min(max(pc[0] / z, -lim_x), lim_x) * z
        ty = min(max(pc[1] / z, -lim_y), lim_y) * z
        J = np.array([[fx / z, 0, -fx * tx / z / z], [0, fy / z, -fy * ty / z / z]])
        w, x, y, zq = g.rotations[i] / np.linalg.norm(g.rotations[i])
        Rg = np.array([[1 - 2 * (y * y + zq * zq), 2 * (x * y - w * zq), 2 * (x * zq + w * y)],
                       [2 * (x * y + w * zq), 1 - 2 * (x * x + zq * zq), 2 * (y * zq - w * x)],
                       [2 * (x * zq - w * y), 2 * (y * zq + w * x), 1 - 2 * (x * x + y * y)]])
        S = Rg @ np.diag(g.scales[i] ** 2) @ Rg.T
        cov = J @ R @ S @ R.T @ J.T + dilation * np.eye(2)
        if np.linalg.det(cov) <= 0:
            continue
        if colors is not None:
            col = np.asarray(colors[i], np.float64)
        else:
            d = g.means[i] - centre
            col = np.maximum(0.5 + sh_basis(d[None], g.sh_degree)[0] @ g.sh[i], 0.0)
        items.append((z, i, np.array([fx * pc[0] / z + cx, fy * pc[1] / z + cy]),
                      np.linalg.inv(cov), g.opacities[i], col))
    items.sort(key=lambda it: (it[0], it[1]))
    H, W = camera.height, camera.width
    image = np.zeros((H, W, 3))
    alpha_img = np.zeros((H, W))
    depth = np.zeros((H, W))
    bg = np.asarray(background, np.float64)
    for v in range(H):
        for u in range(W):
            T, col, dep = 1.0, np.zeros(3), 0.0
            for z, _, m, inv, o, c in items:
                d = np.array([u - m[0], v - m[1]])
                power = -0.5 * d @ inv @ d
                if power > 0:
                    continue
                a = min(ALPHA_MAX, o * math.exp(power))
                if a < ALPHA_MIN:
                    continue
                t_next = T * (1 - a)
                if t_next < T_MIN:
                    break
                col += c * a * T
                dep += z * a * T
                T = t_next
            image[v, u] = col + T * bg
            alpha_img[v, u] = 1 - T
            depth[v, u] = dep
    return RenderResult(image, alpha_img, depth)
