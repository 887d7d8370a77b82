"""Environment-map geometry: directions, exact solid angles, resampling, rotation.

Conventions are OpenEXR's (ImfEnvmap), exactly:

* lat-long, H×W: pixel centre (x, y) has latitude φ = π/2 − π·y/(H−1) and
  longitude λ = π − 2π·x/(W−1); direction (sin λ cos φ, sin φ, cos λ cos φ).
  So the top row is +Y, the image centre is +Z and a quarter of the width
  from the left edge is +X.
* cube, N×6N: faces stacked top to bottom +X −X +Y −Y +Z −Z, each oriented as
  ImfEnvmap's ``CubeMap::pixelPosition``/``direction``.

OpenEXR maps pixel *centres* onto the end points (the first and last rows sit on
the poles, the first and last columns on λ = ±π; cube texels on face edges).
Each texel owns the cell [x−½, x+½]×[y−½, y+½] *clipped* to that range, so the
cells tile the sphere exactly: solid angles are closed forms and sum to 4π,
and integrals ∫L dω = Σ L·Δω do not depend on the resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from relight_cli.formats.envmap import EnvMap

# ---------------------------------------------------------------- lat-long


class EnvGrid(NamedTuple):
    """A lat-long direction grid, the one place its two orders meet: the engine indexes
    it (height, width) like the arrays it shapes, so ``EnvGrid`` *is* that tuple
    (``discretize_env(env, *grid)``, ``config.env_res = grid``), while users write it
    ``WxH``, width first like every size (``str(grid)``, :meth:`from_wh` via
    :func:`relight_cli.cli.inputs.env_grid`)."""

    height: int
    width: int

    @classmethod
    def from_wh(cls, width: int, height: int) -> "EnvGrid":
        return cls(int(height), int(width))

    def __str__(self) -> str:
        return f"{self.width}x{self.height}"


#: The lat-long grid an env map is integrated over when nobody says otherwise: 32x16
#: (WxH), 512 directions (RelightableHands sums its env maps over 16×32 directions).
DEFAULT_GRID = EnvGrid(16, 32)


def _latlong_edges(height: int, width: int):
    """Cell bounds: latitude [H, 2] (top, bottom) and longitude [W, 2] (left, right), radians."""
    y = np.arange(height, dtype=np.float64)
    x = np.arange(width, dtype=np.float64)
    if height > 1:
        lat = np.stack([math.pi / 2 - math.pi * (y - 0.5) / (height - 1),
                        math.pi / 2 - math.pi * (y + 0.5) / (height - 1)], axis=1)
    else:
        lat = np.array([[math.pi / 2, -math.pi / 2]])
    if width > 1:
        lon = np.stack([math.pi - 2 * math.pi * (x - 0.5) / (width - 1),
                        math.pi - 2 * math.pi * (x + 0.5) / (width - 1)], axis=1)
    else:
        lon = np.array([[math.pi, -math.pi]])
    return np.clip(lat, -math.pi / 2, math.pi / 2), np.clip(lon, -math.pi, math.pi)


def latlong_angles(height: int, width: int):
    """Pixel-centre latitude [H] and longitude [W] in radians (OpenEXR convention)."""
    lat = (math.pi / 2 - math.pi * np.arange(height) / (height - 1)) if height > 1 else np.zeros(1)
    lon = (math.pi - 2 * math.pi * np.arange(width) / (width - 1)) if width > 1 else np.zeros(1)
    return lat, lon


def latlong_directions(height: int, width: int) -> np.ndarray:
    """[H, W, 3] float64 unit directions at pixel centres."""
    lat, lon = latlong_angles(height, width)
    cl = np.cos(lat)[:, None]
    return np.stack([np.sin(lon)[None, :] * cl,
                     np.broadcast_to(np.sin(lat)[:, None], (height, width)),
                     np.cos(lon)[None, :] * cl], axis=-1)


def latlong_solid_angles(height: int, width: int) -> np.ndarray:
    """[H, W] float64 exact solid angle of each (clipped) texel cell; sums to 4π."""
    lat, lon = _latlong_edges(height, width)
    band = np.sin(lat[:, 0]) - np.sin(lat[:, 1])          # [H] ∫cos φ dφ
    width_rad = lon[:, 0] - lon[:, 1]                     # [W]
    return band[:, None] * width_rad[None, :]


def latlong_pixel(directions: np.ndarray, height: int, width: int) -> np.ndarray:
    """Continuous pixel positions [N, 2] (x, y) of directions, ImfEnvmap's pixelPosition."""
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    r = np.hypot(d[:, 0], d[:, 2])
    lat = np.arctan2(d[:, 1], r)
    lon = np.arctan2(d[:, 0], d[:, 2])
    x = (lon / (-2 * math.pi) + 0.5) * (width - 1)
    y = (lat / -math.pi + 0.5) * (height - 1)
    return np.stack([x, y], axis=1)


# ---------------------------------------------------------------- cube

FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")


def _face_direction(face: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Unnormalized direction for face index and face coordinates a, b ∈ [−1, 1]."""
    one = np.ones_like(a)
    out = np.empty(a.shape + (3,))
    sign = np.where(face % 2 == 0, 1.0, -1.0)
    axis = face // 2
    # +X/−X: (±1, a, b); +Y/−Y: (a, ±1, b); +Z/−Z: (a, b, ±1)
    out[..., 0] = np.where(axis == 0, sign * one, a)
    out[..., 1] = np.where(axis == 0, a, np.where(axis == 1, sign * one, b))
    out[..., 2] = np.where(axis == 2, sign * one, b)
    return out


def _cube_position_in_face(size: int):
    """For every pixel of the stacked image: face [6N, N], positionInFace px, py (ImfEnvmap)."""
    rows, cols = np.mgrid[0:6 * size, 0:size].astype(np.float64)
    face = (rows // size).astype(np.int64)
    local_y = rows - face * size           # row inside the face's data window
    last = size - 1
    px = np.empty_like(rows)
    py = np.empty_like(rows)
    # Inverse of CubeMap::pixelPosition, face by face.
    m = face == 0; px[m] = last - local_y[m]; py[m] = cols[m]              # +X
    m = face == 1; px[m] = last - local_y[m]; py[m] = last - cols[m]       # −X
    m = face == 2; px[m] = cols[m]; py[m] = last - local_y[m]              # +Y
    m = face == 3; px[m] = cols[m]; py[m] = local_y[m]                     # −Y
    m = face == 4; px[m] = last - cols[m]; py[m] = last - local_y[m]       # +Z
    m = face == 5; px[m] = cols[m]; py[m] = last - local_y[m]              # −Z
    return face, px, py


def _to_face_coord(p: np.ndarray, size: int) -> np.ndarray:
    return p / (size - 1) * 2 - 1 if size > 1 else np.zeros_like(p)


def cube_directions(size: int) -> np.ndarray:
    """[6N, N, 3] float64 unit directions at pixel centres of the stacked cube image."""
    face, px, py = _cube_position_in_face(size)
    d = _face_direction(face, _to_face_coord(px, size), _to_face_coord(py, size))
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _rect_solid_angle(a0, a1, b0, b1):
    """Solid angle of the rectangle [a0,a1]×[b0,b1] on the plane at unit distance."""
    def f(a, b):
        return np.arctan2(a * b, np.sqrt(a * a + b * b + 1))
    return np.abs(f(a1, b1) - f(a0, b1) - f(a1, b0) + f(a0, b0))


def _cube_cell_bounds(p: np.ndarray, size: int):
    if size == 1:
        return -np.ones_like(p), np.ones_like(p)
    lo = _to_face_coord(np.clip(p - 0.5, 0, size - 1), size)
    hi = _to_face_coord(np.clip(p + 0.5, 0, size - 1), size)
    return lo, hi


def cube_solid_angles(size: int) -> np.ndarray:
    """[6N, N] float64 exact solid angle of each (clipped) texel cell; sums to 4π."""
    _, px, py = _cube_position_in_face(size)
    a0, a1 = _cube_cell_bounds(px, size)
    b0, b1 = _cube_cell_bounds(py, size)
    return _rect_solid_angle(a0, a1, b0, b1)


def cube_pixel(directions: np.ndarray, size: int) -> np.ndarray:
    """Continuous stacked-image pixel positions [N, 2] (x, y) of directions (ImfEnvmap)."""
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    ax = np.abs(d)
    use_x = (ax[:, 0] >= ax[:, 1]) & (ax[:, 0] >= ax[:, 2])
    use_y = ~use_x & (ax[:, 1] >= ax[:, 2])
    major = np.where(use_x, ax[:, 0], np.where(use_y, ax[:, 1], ax[:, 2]))
    major = np.where(major > 0, major, 1.0)
    u = np.where(use_x, d[:, 1], d[:, 0]) / major
    v = np.where(use_x | use_y, d[:, 2], d[:, 1]) / major
    positive = np.where(use_x, d[:, 0], np.where(use_y, d[:, 1], d[:, 2])) > 0
    face = np.where(use_x, 0, np.where(use_y, 2, 4)) + np.where(positive, 0, 1)
    last = size - 1
    pif_x = (u + 1) / 2 * last
    pif_y = (v + 1) / 2 * last
    base = face * size
    x = np.empty_like(pif_x)
    y = np.empty_like(pif_y)
    # CubeMap::pixelPosition
    for f, (fx, fy) in enumerate([
        (lambda a, b: b, lambda a, b: last - a),           # +X
        (lambda a, b: last - b, lambda a, b: last - a),    # −X
        (lambda a, b: a, lambda a, b: last - b),           # +Y
        (lambda a, b: a, lambda a, b: b),                  # −Y
        (lambda a, b: last - a, lambda a, b: last - b),    # +Z
        (lambda a, b: a, lambda a, b: last - b),           # −Z
    ]):
        m = face == f
        x[m] = fx(pif_x[m], pif_y[m])
        y[m] = base[m] + fy(pif_x[m], pif_y[m])
    return np.stack([x, y], axis=1)


# ---------------------------------------------------------------- generic


def directions(env_or_layout, height: int | None = None, width: int | None = None) -> np.ndarray:
    """[H, W, 3] unit directions at pixel centres of an EnvMap (or layout, H, W)."""
    layout, h, w = _shape(env_or_layout, height, width)
    return latlong_directions(h, w) if layout == "latlong" else cube_directions(w)


def solid_angles(env_or_layout, height: int | None = None, width: int | None = None) -> np.ndarray:
    """[H, W] exact texel solid angles (steradians) of an EnvMap (or layout, H, W)."""
    layout, h, w = _shape(env_or_layout, height, width)
    return _cached_solid_angles(layout, h, w)


@lru_cache(maxsize=16)
def _cached_solid_angles(layout, h, w):
    out = latlong_solid_angles(h, w) if layout == "latlong" else cube_solid_angles(w)
    out.setflags(write=False)
    return out


def _shape(env_or_layout, height, width):
    if isinstance(env_or_layout, EnvMap):
        return env_or_layout.layout, env_or_layout.height, env_or_layout.width
    return env_or_layout, int(height), int(width)


def pixel_index(directions_: np.ndarray, layout: str, height: int, width: int) -> np.ndarray:
    """[N] flat index (row·W + col) of the texel whose cell contains each direction."""
    if layout == "latlong":
        p = latlong_pixel(directions_, height, width)
    else:
        p = cube_pixel(directions_, width)
    x = np.clip(np.rint(p[:, 0]), 0, width - 1).astype(np.int64)
    y = np.clip(np.rint(p[:, 1]), 0, height - 1).astype(np.int64)
    return y * width + x


def lookup(env: EnvMap, directions_: np.ndarray) -> np.ndarray:
    """[N, 3] radiance of the texel containing each direction (nearest texel)."""
    idx = pixel_index(directions_, env.layout, env.height, env.width)
    return env.radiance.reshape(-1, 3)[idx]


def power(env: EnvMap) -> np.ndarray:
    """[3] ∫ L dω per channel (float64), with exact texel solid angles."""
    omega = solid_angles(env)
    return np.einsum("hwc,hw->c", env.radiance.astype(np.float64), omega)


def irradiance(env: EnvMap, normals: np.ndarray) -> np.ndarray:
    """[N, 3] unshadowed irradiance E(n) = Σ L(ω) max(n·ω, 0) Δω for unit normals [N, 3]."""
    dirs = directions(env).reshape(-1, 3)
    weighted = env.radiance.reshape(-1, 3).astype(np.float64) * solid_angles(env).reshape(-1, 1)
    cos = np.clip(np.asarray(normals, np.float64).reshape(-1, 3) @ dirs.T, 0, None)
    return cos @ weighted


def rotation_y(degrees: float) -> np.ndarray:
    """[3, 3] right-handed rotation about +Y (moves +Z towards +X for positive angles)."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


# ---------------------------------------------------------------- resampling

# Budget of sub-cells per resampling call (memory is streamed; this bounds time).
_MAX_SUBCELLS = 8_000_000
# Sub-cells per target texel aimed for when splatting.
_SUBCELLS_PER_TEXEL = 256
# Source texels brighter than this multiple of the map's mean luminance are
# "peaks" whose power splatting keeps exactly.
_PEAK_FACTOR = 64.0


def _peaks(env: EnvMap, flat: np.ndarray) -> np.ndarray:
    """[H·W] bool: texels brighter than _PEAK_FACTOR × the map's mean luminance."""
    mean_luminance = float(luminance(flat.T @ solid_angles(env).reshape(-1)) / (4 * math.pi))
    return luminance(flat) > _PEAK_FACTOR * max(mean_luminance, 1e-30)


def _interval_overlap(lo_a, hi_a, lo_b, hi_b):
    """Overlap length matrix [len(a), len(b)] of intervals [lo, hi] (lo ≤ hi)."""
    return np.clip(np.minimum(hi_a[:, None], hi_b[None, :]) - np.maximum(lo_a[:, None], lo_b[None, :]),
                   0, None)


def _resample_latlong_exact(src: np.ndarray, height: int, width: int, shift: float) -> np.ndarray:
    """Exact area-weighted lat-long → lat-long resampling, with a longitude shift (radians).

    Cells are latitude×longitude rectangles, so the overlap solid angle of two
    cells factorizes into (sin-latitude overlap) × (longitude overlap): two
    small matrix products.  Power is preserved to rounding.
    """
    sh, sw = src.shape[:2]
    s_lat, s_lon = _latlong_edges(sh, sw)
    d_lat, d_lon = _latlong_edges(height, width)
    # Latitude: overlap measured in sin φ (the area element).
    lat_w = _interval_overlap(np.sin(d_lat[:, 1]), np.sin(d_lat[:, 0]),
                              np.sin(s_lat[:, 1]), np.sin(s_lat[:, 0]))       # [H', H]
    # Longitude: source cells move by +shift; overlap on the circle (three copies).
    lo_s, hi_s = s_lon[:, 1] + shift, s_lon[:, 0] + shift
    lon_w = np.zeros((width, sw))
    for k in (-2, -1, 0, 1, 2):
        lon_w += _interval_overlap(d_lon[:, 1], d_lon[:, 0],
                                   lo_s + 2 * math.pi * k, hi_s + 2 * math.pi * k)
    dst_omega = latlong_solid_angles(height, width)
    rows = np.tensordot(lat_w, src.astype(np.float64), axes=(1, 0))          # [H', W, 3]
    power_grid = np.tensordot(rows, lon_w, axes=(1, 1)).transpose(0, 2, 1)   # [H', W', 3]
    return power_grid / dst_omega[..., None]


def _subcells(layout: str, height: int, width: int, n: int, rows=None):
    """Split every texel cell into n×n exact sub-cells.

    Returns directions [P, 3], solid angles [P] and texel flat index [P]
    (P = H·W·n²), generated lazily per chunk of rows to bound memory.  ``rows``
    (a set of row indices) restricts the work to those image rows.
    """
    edges = np.arange(n + 1) / n
    if layout == "latlong":
        lat, lon = _latlong_edges(height, width)
        s_top, s_bot = np.sin(lat[:, 0]), np.sin(lat[:, 1])
        for row in range(height):
            if rows is not None and row not in rows:
                continue
            s_edges = s_top[row] + (s_bot[row] - s_top[row]) * edges      # equal-area in sin φ
            s_mid = 0.5 * (s_edges[:-1] + s_edges[1:])
            band = np.abs(np.diff(s_edges))                                 # [n]
            lon_edges = lon[:, :1] + (lon[:, 1:] - lon[:, :1]) * edges[None, :]   # [W, n+1]
            lon_mid = 0.5 * (lon_edges[:, :-1] + lon_edges[:, 1:])
            lon_w = np.abs(np.diff(lon_edges, axis=1))                       # [W, n]
            phi = np.arcsin(np.clip(s_mid, -1, 1))                           # [n]
            cl = np.cos(phi)
            lam = lon_mid[:, None, :]                                        # [W, 1, n]
            d = np.stack([np.sin(lam) * cl[None, :, None],
                          np.broadcast_to(np.sin(phi)[None, :, None], (width, n, n)),
                          np.cos(lam) * cl[None, :, None]], axis=-1)         # [W, n, n, 3]
            omega = band[None, :, None] * lon_w[:, None, :]
            idx = np.repeat(row * width + np.arange(width), n * n)
            yield d.reshape(-1, 3), omega.reshape(-1), idx
    else:
        size = width
        face, px, py = _cube_position_in_face(size)
        a0, a1 = _cube_cell_bounds(px, size)
        b0, b1 = _cube_cell_bounds(py, size)
        rows_per_chunk = max(1, (1 << 20) // max(1, size * n * n))
        for r0 in range(0, 6 * size, rows_per_chunk):
            sl = slice(r0, min(6 * size, r0 + rows_per_chunk))
            if rows is not None and not any(r in rows for r in range(sl.start, sl.stop)):
                continue
            fa0, fa1, fb0, fb1, ff = a0[sl], a1[sl], b0[sl], b1[sl], face[sl]
            ae = fa0[..., None] + (fa1 - fa0)[..., None] * edges                # [r, N, n+1]
            be = fb0[..., None] + (fb1 - fb0)[..., None] * edges
            am = 0.5 * (ae[..., :-1] + ae[..., 1:])
            bm = 0.5 * (be[..., :-1] + be[..., 1:])
            A = np.broadcast_to(am[..., :, None], am.shape + (n,))
            B = np.broadcast_to(bm[..., None, :], bm.shape[:-1] + (n, n))
            F = np.broadcast_to(ff[..., None, None], A.shape)
            d = _face_direction(F, A, B)
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            omega = _rect_solid_angle(ae[..., :-1, None], ae[..., 1:, None],
                                      be[..., None, :-1], be[..., None, 1:])
            chunk_rows = np.arange(sl.start, sl.stop)
            idx = (chunk_rows[:, None] * size + np.arange(size)[None, :])
            idx = np.repeat(idx.reshape(-1), n * n)
            yield d.reshape(-1, 3), omega.reshape(-1), idx


def resample(env: EnvMap, layout: str, height: int, width: int,
             rotation: np.ndarray | None = None, supersample: int | None = None) -> EnvMap:
    """Area-weighted resampling to another layout/resolution, optionally rotated.

    The result's texel holds the mean radiance of the environment over its
    cell: L'_j = (1/Ω_j) ∫_cell_j L dω.

    * lat-long → lat-long (with or without a rotation about +Y): exact, via
      separable cell overlaps; power is preserved to rounding.
    * otherwise by splatting: every source texel is cut into n×n exact
      sub-cells whose power goes to the target texel containing the
      sub-cell's direction, so a single bright texel is never lost; the
      target texel takes the mean radiance of what lands in it, except that
      peaks (texels > 64× the mean luminance, e.g. a sun) keep their power
      exactly.  With ~256 sub-cells per target texel (within a budget of 8M
      sub-cells) power is preserved to ~1e-5 on smooth maps.
      Texels no sub-cell reaches take the source radiance at their centre.
    * large upsampling beyond the budget gathers instead: each target texel
      is cut into n×n sub-cells that take the radiance of the source texel
      containing them (a box filter; power to a source texel's boundary).

    Args:
        env: source map.
        layout, height, width: target layout and size (cube: width = face
            size, height = 6·width).
        rotation: [3, 3] rotation applied to the environment (content at
            direction ω moves to R·ω); None = identity.
        supersample: sub-cells per axis n (default: chosen from the size ratio).
    """
    if layout == "cube" and height != 6 * width:
        raise ValueError("cube maps are N wide and 6N tall")
    rot = np.eye(3) if rotation is None else np.asarray(rotation, np.float64)
    src = env.radiance
    is_y_rotation = (abs(rot[1, 1] - 1) < 1e-12 and np.allclose(rot[1], [0, 1, 0])
                     and np.allclose(rot[:, 1], [0, 1, 0]))
    if env.layout == "latlong" and layout == "latlong" and is_y_rotation:
        shift = math.atan2(rot[0, 2], rot[2, 2])  # R·(+Z) = (sin a, 0, cos a): longitude +a
        out = _resample_latlong_exact(src, height, width, shift)
        return EnvMap(out.astype(np.float32), "latlong", env.name)

    n_src = env.height * env.width
    n_dst = height * width
    flat = src.reshape(-1, 3).astype(np.float64)
    dst_omega = (latlong_solid_angles(height, width) if layout == "latlong"
                 else cube_solid_angles(width)).reshape(-1)
    n_fine = int(max(1, math.ceil(math.sqrt(_SUBCELLS_PER_TEXEL * n_dst / n_src))))
    if supersample is not None or n_dst <= n_src or n_src * n_fine ** 2 <= _MAX_SUBCELLS:
        n = supersample or n_fine
        if supersample is None and n_src * n * n > _MAX_SUBCELLS:
            n = max(1, int(math.sqrt(_MAX_SUBCELLS / n_src)))
        # Smooth content: each target texel gets the solid-angle-weighted mean
        # radiance of the sub-cells that land in it, Σ L ω / Σ ω (dividing by
        # the exact target solid angle instead would add several percent of
        # per-texel noise from sub-cells straddling texel borders).  Peaks
        # (texels far brighter than the map's mean, e.g. a sun) keep their
        # power exactly: it is divided by the exact target solid angle and
        # only the rest of the texel takes the mean of the smooth content.
        peak = _peaks(env, flat)
        acc = np.zeros((n_dst, 3))
        received = np.zeros(n_dst)
        acc_peak = np.zeros((n_dst, 3))
        received_peak = np.zeros(n_dst)
        for d, omega, idx in _subcells(env.layout, env.height, env.width, n):
            target = pixel_index(d @ rot.T, layout, height, width)
            p = flat[idx] * omega[:, None]
            is_peak = peak[idx]
            for mask, a, r in ((~is_peak, acc, received), (is_peak, acc_peak, received_peak)):
                if not mask.any():
                    continue
                for c in range(3):
                    a[:, c] += np.bincount(target[mask], weights=p[mask, c], minlength=n_dst)
                r += np.bincount(target[mask], weights=omega[mask], minlength=n_dst)
        empty = (received + received_peak) == 0
        smooth_mean = acc / np.where(received > 0, received, 1.0)[:, None]
        rest_area = np.clip(dst_omega - received_peak, 0, None)
        out = (smooth_mean * rest_area[:, None] + acc_peak) / dst_omega[:, None]
        if empty.any():
            centres = (latlong_directions(height, width) if layout == "latlong"
                       else cube_directions(width)).reshape(-1, 3)[empty]
            out[empty] = lookup(env, centres @ rot)  # R⁻¹ = Rᵀ; row-vector form
    else:
        # Gathering: target sub-cells take the radiance of the source texel that
        # contains them.  Peaks are left out of the gather and splatted finely
        # with their exact power instead, so a sun keeps its power.
        peak = _peaks(env, flat)
        n = int(max(1, min(8, math.sqrt(_MAX_SUBCELLS / n_dst))))
        rest = np.where(peak[:, None], 0.0, flat)
        acc = np.zeros((n_dst, 3))
        for d, omega, idx in _subcells(layout, height, width, n):
            source = pixel_index(d @ rot, env.layout, env.height, env.width)
            p = rest[source] * omega[:, None]
            for c in range(3):
                acc[:, c] += np.bincount(idx, weights=p[:, c], minlength=n_dst)
        peak_texels = np.nonzero(peak)[0]
        if len(peak_texels):
            n_peak = int(max(2, min(64, math.sqrt(_MAX_SUBCELLS / len(peak_texels)),
                                    math.ceil(4 * math.sqrt(n_dst / n_src)))))
            rows = set((peak_texels // env.width).tolist())
            for d, omega, idx in _subcells(env.layout, env.height, env.width, n_peak, rows):
                keep = peak[idx]
                target = pixel_index(d[keep] @ rot.T, layout, height, width)
                p = flat[idx[keep]] * omega[keep, None]
                for c in range(3):
                    acc[:, c] += np.bincount(target, weights=p[:, c], minlength=n_dst)
        out = acc / dst_omega[:, None]
    return EnvMap(out.reshape(height, width, 3).astype(np.float32), layout, env.name)


# ---------------------------------------------------------------- statistics


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 / sRGB-primaries luminance of linear RGB [..., 3]."""
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


def info(env: EnvMap) -> dict:
    """Summary statistics for ``relight envmap --info``.

    ``min``/``max``/``mean`` are per channel over texels (as an image viewer
    shows them); ``mean_radiance`` is the solid-angle-weighted mean, power/4π;
    ``dominant_direction`` is the normalized luminance-weighted mean direction
    and ``directionality`` its length over the total (0 uniform, 1 a point).
    """
    rgb = env.radiance.reshape(-1, 3).astype(np.float64)
    omega = solid_angles(env).reshape(-1)
    dirs = directions(env).reshape(-1, 3)
    total = rgb.T @ omega
    lum = luminance(rgb) * omega
    vec = lum @ dirs
    length = float(np.linalg.norm(vec))
    lum_total = float(lum.sum())
    dominant = (vec / length).tolist() if length > 0 else [0.0, 1.0, 0.0]
    return {
        "width": env.width,
        "height": env.height,
        "layout": env.layout,
        "face_size": env.width if env.layout == "cube" else None,
        "min": rgb.min(axis=0).tolist(),
        "max": rgb.max(axis=0).tolist(),
        "mean": rgb.mean(axis=0).tolist(),
        "mean_radiance": (total / (4 * math.pi)).tolist(),
        "power": total.tolist(),
        "dominant_direction": dominant,
        "directionality": length / lum_total if lum_total > 0 else 0.0,
    }


# ---------------------------------------------------------------- discretized for shading


@dataclass
class DiscreteEnv:
    """An environment map as M directions with exact solid angles.

    Attributes:
        directions: [M, 3] float64 unit world directions: the H×W lat-long grid's pixel
            centres, then ``sources`` bright sources (:func:`bright_sources`).
        solid_angle: [M] float64 steradians, Σ = 4π (a source's own texels' solid angle
            is taken out of the grid cell its direction falls in).
        radiance: [M, 3] float64 linear RGB.
        height, width: the lat-long grid the first H·W directions came from.
        name: source label.
        sources: how many directions at the end are extracted bright sources.
    """

    directions: np.ndarray
    solid_angle: np.ndarray
    radiance: np.ndarray
    height: int
    width: int
    name: str = ""
    sources: int = 0

    @property
    def lit(self) -> np.ndarray:
        """[M] bool: texels with any non-zero radiance (the only ones worth tracing)."""
        return np.any(self.radiance != 0, axis=1)


#: ``sources="auto"``: a connected region of texels brighter than SOURCE_CONTRAST × the
#: map's mean radiance is a source when it is smaller than half a grid cell (radius
#: about its centre) and carries at least SOURCE_FRACTION of the map's power; at most
#: MAX_SOURCES of them, the strongest first.
SOURCE_CONTRAST = 20.0
SOURCE_FRACTION = 0.01
MAX_SOURCES = 8


@dataclass
class BrightSource:
    """A small bright region of an env map, as one distant light.

    Attributes:
        direction: [3] unit, the luminance-weighted mean direction of its texels.
        power: [3] ∫ L dω over its texels (W m⁻² per unit of the map's radiance).
        solid_angle: Σ Δω of its texels.
        radius_deg: the largest angle between a texel of it and ``direction``.
        texels: [T] flat texel indices (row·W + col) in the map.
    """

    direction: np.ndarray
    power: np.ndarray
    solid_angle: float
    radius_deg: float
    texels: np.ndarray


def bright_sources(env: EnvMap, max_radius_deg: float, limit: int = MAX_SOURCES,
                   contrast: float = SOURCE_CONTRAST,
                   fraction: float = SOURCE_FRACTION) -> list[BrightSource]:
    """The suns and lamps of ``env`` that a coarse grid would misplace.

    A lat-long grid of cells ~11° wide puts a 0.5° sun at its cell's centre, up to
    half a cell away (6.5° for ``builtin:sky`` at 32×16), and blurs its shadow over the
    cell.  Here the map's own texels decide: 8-connected regions of texels whose
    luminance exceeds ``contrast`` × the map's mean radiance (power / 4π), each kept
    when its radius ≤ ``max_radius_deg`` and its power ≥ ``fraction`` of the map's (a
    region larger than that is resolved by the grid itself; a weaker one moves too
    little light to matter).  Strongest first, at most ``limit``."""
    from scipy import ndimage

    rgb = np.asarray(env.radiance, np.float64)[..., :3]
    omega = solid_angles(env)
    lum = luminance(rgb)
    total = float((lum * omega).sum())
    if limit <= 0 or not np.isfinite(total) or total <= 0:
        return []
    bright = lum > contrast * total / (4 * math.pi)
    if not bright.any():
        return []
    labels, count = ndimage.label(bright, structure=np.ones((3, 3), bool))
    flat = labels.ravel()
    dirs = directions(env).reshape(-1, 3)
    weights = (lum * omega).ravel()
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(1, count + 2))
    found = []
    for j in range(count):
        texels = order[bounds[j]:bounds[j + 1]]
        wsum = float(weights[texels].sum())
        if wsum < fraction * total:
            continue
        mean = weights[texels] @ dirs[texels]
        norm = float(np.linalg.norm(mean))
        if norm <= 0:
            continue
        direction = mean / norm
        radius = math.degrees(math.acos(float(np.clip((dirs[texels] @ direction).min(), -1, 1))))
        if radius > max_radius_deg:
            continue
        power = (rgb.reshape(-1, 3)[texels] * omega.reshape(-1)[texels, None]).sum(0)
        found.append((wsum, BrightSource(direction, power, float(omega.reshape(-1)[texels].sum()),
                                         radius, np.sort(texels))))
    found.sort(key=lambda item: -item[0])
    return [src for _, src in found[:limit]]


def discretize_env(env: EnvMap, height: int = 16, width: int = 32,
                   sources="none") -> DiscreteEnv:
    """Resample ``env`` to an H×W lat-long grid, area-weighted (power preserved).

    Every texel's radiance is the mean over its cell, so Σ L Δω equals the
    source's ∫ L dω and a tiny bright source is kept, not missed, but placed at its
    cell's centre.  ``sources`` (``"auto"``, or a maximum count; ``"none"``/0 = off) first
    takes the map's bright sources out (:func:`bright_sources`, radius ≤ half a cell) and
    appends each as one direction at its own mean direction carrying its exact power;
    their texels' solid angle leaves the cell their direction falls in, so the cell keeps
    the mean radiance of the rest of it and Σ Δω stays 4π.  A map already on the grid is
    used as it is (a source then is its own cell).
    """
    limit = {"auto": MAX_SOURCES, "none": 0}.get(sources, sources)
    if not isinstance(limit, (int, np.integer)) or isinstance(limit, bool) or limit < 0:
        raise ValueError(f"sources must be 'auto', 'none' or a count >= 0, got {sources!r}")
    grid_dirs = latlong_directions(height, width).reshape(-1, 3)
    omega = np.asarray(latlong_solid_angles(height, width)).reshape(-1).copy()
    if env.layout == "latlong" and (env.height, env.width) == (height, width):
        return DiscreteEnv(grid_dirs, omega, np.asarray(env.radiance, np.float64).reshape(-1, 3),
                           height, width, env.name)
    found = bright_sources(env, 90.0 / height, int(limit)) if limit else []
    source = env
    if found:
        residual = np.asarray(env.radiance, np.float64)[..., :3].reshape(-1, 3).copy()
        for src in found:
            residual[src.texels] = 0.0
        source = EnvMap(residual.reshape(env.radiance.shape[:2] + (3,)).astype(env.radiance.dtype),
                        env.layout, env.name)
    rad = np.asarray(resample(source, "latlong", height, width).radiance,
                     np.float64).reshape(-1, 3)
    if not found:
        return DiscreteEnv(grid_dirs, omega, rad, height, width, env.name)
    # the cell a source lies in loses its texels' solid angle; its radiance, the mean over
    # the whole cell of the residual, becomes the mean over the rest (power unchanged)
    cells = pixel_index(np.stack([s.direction for s in found]), "latlong", height, width)
    kept = omega.copy()
    np.subtract.at(kept, cells, [s.solid_angle for s in found])
    kept = np.maximum(kept, 1e-3 * omega)
    rad *= (omega / kept)[:, None]
    src_omega = np.array([s.solid_angle for s in found])
    src_rad = np.stack([s.power for s in found]) / src_omega[:, None]
    return DiscreteEnv(np.concatenate([grid_dirs, np.stack([s.direction for s in found])]),
                       np.concatenate([kept, src_omega]), np.concatenate([rad, src_rad]),
                       height, width, env.name, len(found))


def share_directions(envs: list[DiscreteEnv]) -> list[DiscreteEnv]:
    """DiscreteEnvs of one lat-long grid (each with its own bright sources) on one direction
    set: the grid, then every map's sources, so a visibility cache and transport weights
    serve them all.  Every cell gives up the solid angle of every source in it (Σ Δω stays
    4π, the sphere partitioned more finely), and each map's cell radiance is rescaled by
    its old over its new solid angle, so its power Σ L Δω is unchanged; a map is dark in
    the other maps' source directions."""
    if not envs:
        return []
    first = envs[0]
    n_grid = first.height * first.width
    for e in envs:
        if (e.height, e.width) != (first.height, first.width):
            raise ValueError("env maps to share directions must be on one grid")
    if not any(e.sources for e in envs):
        return list(envs)
    grid_omega = np.asarray(latlong_solid_angles(first.height, first.width)).reshape(-1)
    src_dirs = np.concatenate([e.directions[n_grid:] for e in envs])
    src_omega = np.concatenate([e.solid_angle[n_grid:] for e in envs])
    cells = pixel_index(src_dirs, "latlong", first.height, first.width)
    kept = grid_omega.copy()
    np.subtract.at(kept, cells, src_omega)
    kept = np.maximum(kept, 1e-3 * grid_omega)
    directions = np.concatenate([first.directions[:n_grid], src_dirs])
    omega = np.concatenate([kept, src_omega])
    out, start = [], 0
    for e in envs:
        rad = np.zeros((len(directions), 3))
        rad[:n_grid] = e.radiance[:n_grid] * (e.solid_angle[:n_grid] / kept)[:, None]
        rad[n_grid + start:n_grid + start + e.sources] = e.radiance[n_grid:]
        start += e.sources
        out.append(DiscreteEnv(directions, omega, rad, e.height, e.width, e.name,
                               len(src_dirs)))
    return out
