"""UV-space rasterization of triangle meshes: texel → face + barycentrics.

Turns per-vertex quantities (shading features, positions, normals) into
texel-aligned maps, the representation RelightableHands' student and URHand's
linear lighting model consume.

Conventions (DESIGN.md): (u, v) ∈ [0, 1]², v = 0 at the BOTTOM image row
(OBJ/OpenGL).  An H×W map has texel (row r, column c) centred at

    u = (c + ½) / W,    v = 1 − (r + ½) / H,

so row 0 is the top of the image and v = 1.  A texel belongs to the triangle
whose UV footprint contains its centre; texels whose centre lies in no
triangle are *outside* the charts (``face == -1``, mask 0).

Meshes may carry separate UV indices (seams): ``faces_uv [F, 3]`` indexes the
``uv [T, 2]`` table, while per-vertex values are indexed by the geometric
``faces [F, 3]``; triangle ``f`` is the same triangle in both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# A texel centre counts as inside a triangle when every barycentric weight is
# ≥ −_INSIDE_TOL: centres exactly on an edge (common where a diagonal passes
# through texel centres) must not fall between two triangles because of
# rounding.  Weights are O(1), float64 rounding is ~1e-15; 1e-9 is far above it
# and far below one texel (≥ 1/65536 in weight units).
_INSIDE_TOL = 1e-9
# For overlap detection a centre must be strictly inside (every weight > this)
# so shared edges and vertices of neighbouring triangles never count twice.
_STRICT_TOL = 1e-7
# Rasterization works in chunks of candidate (face, texel) pairs to bound memory.
_CHUNK = 1 << 22


@dataclass
class UVRaster:
    """The UV-space rasterization of a mesh at one resolution.

    Attributes:
        face: [H, W] int64 triangle index covering each texel centre; −1 outside the charts.
        barycentric: [H, W, 3] float64 weights of the triangle's three corners at the
            texel centre (zero outside); they sum to 1 inside.
        coverage: [H, W] int32 number of triangles whose UV footprint contains the texel
            centre strictly inside (not on an edge): ≥ 2 means overlapping UV charts.
    """

    face: np.ndarray
    barycentric: np.ndarray
    coverage: np.ndarray

    @property
    def height(self) -> int:
        return int(self.face.shape[0])

    @property
    def width(self) -> int:
        return int(self.face.shape[1])

    @property
    def inside(self) -> np.ndarray:
        """[H, W] bool: texel centre lies in a UV chart."""
        return self.face >= 0

    @property
    def mask(self) -> np.ndarray:
        """[H, W] float32: 1 inside the UV charts, 0 outside."""
        return self.inside.astype(np.float32)

    @property
    def overlap(self) -> np.ndarray:
        """[H, W] bool: two or more triangles strictly cover the texel centre."""
        return self.coverage >= 2

    def overlap_fraction(self) -> float:
        """Fraction of covered texels that more than one triangle covers (0 for a valid atlas)."""
        covered = int(self.inside.sum())
        return float(self.overlap.sum()) / covered if covered else 0.0

    def interpolate(self, values: np.ndarray, faces: np.ndarray, fill: str | None = "dilate",
                    ) -> np.ndarray:
        """Barycentric interpolation of per-vertex ``values`` to texels.

        Args:
            values: [V, C] or [V] per-vertex values (any float dtype).
            faces: [F, 3] int indices into ``values`` (geometric faces for per-vertex
                values, ``faces_uv`` for per-UV-vertex values); same triangle order as
                the faces that were rasterized.
            fill: ``"dilate"`` fills texels outside the charts from their neighbours
                (see :func:`dilate`), ``None`` leaves them 0.

        Returns:
            [H, W, C] (or [H, W]) float64 texel values.
        """
        values = np.asarray(values)
        squeeze = values.ndim == 1
        vals = values.reshape(len(values), -1).astype(np.float64)
        faces = np.asarray(faces, np.int64)
        out = np.zeros((self.height, self.width, vals.shape[1]), np.float64)
        inside = self.inside
        f = self.face[inside]
        corners = faces[f]                                   # [K, 3]
        w = self.barycentric[inside]                         # [K, 3]
        out[inside] = np.einsum("kj,kjc->kc", w, vals[corners])
        if fill == "dilate":
            out = dilate(out, inside)
        elif fill is not None:
            raise ValueError(f"unknown fill {fill!r}")
        return out[..., 0] if squeeze else out


def texel_centers(height: int, width: int) -> np.ndarray:
    """[H, W, 2] float64 (u, v) of texel centres; v = 0 at the bottom row."""
    u = (np.arange(width) + 0.5) / width
    v = 1.0 - (np.arange(height) + 0.5) / height
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu, vv], axis=-1)


def _resolution(resolution) -> tuple[int, int]:
    if np.ndim(resolution) == 0:
        h = w = int(resolution)
    else:
        h, w = (int(x) for x in resolution)
    if h <= 0 or w <= 0:
        raise ValueError(f"resolution must be positive, got {resolution!r}")
    return h, w


def rasterize_uv(uv: np.ndarray, faces_uv: np.ndarray, resolution) -> UVRaster:
    """Rasterize a mesh's UV layout: which triangle covers each texel centre.

    Args:
        uv: [T, 2] float (u, v) texture coordinates, v = 0 at the bottom row.
        faces_uv: [F, 3] int indices into ``uv``.
        resolution: N (square N×N) or (H, W).

    Returns:
        A :class:`UVRaster`.  Where several triangles contain a centre (shared edges,
        or overlapping charts) the one containing it most deeply (largest minimum
        barycentric weight; lowest index on ties) wins, so the choice is
        deterministic.  Triangles with zero UV area cover nothing.
    """
    height, width = _resolution(resolution)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    faces_uv = np.asarray(faces_uv, np.int64).reshape(-1, 3)
    best_face = np.full(height * width, -1, np.int64)
    best_depth = np.full(height * width, -np.inf)
    best_bary = np.zeros((height * width, 3))
    coverage = np.zeros(height * width, np.int32)
    if len(faces_uv) == 0:
        return UVRaster(best_face.reshape(height, width), best_bary.reshape(height, width, 3),
                        coverage.reshape(height, width))
    if faces_uv.min() < 0 or faces_uv.max() >= len(uv):
        raise ValueError("faces_uv indexes outside the uv table")

    # Work in texel units: x = u·W − ½, y = (1 − v)·H − ½, so texel centres are integers.
    px = uv[:, 0] * width - 0.5
    py = (1.0 - uv[:, 1]) * height - 0.5
    tx = px[faces_uv]                                        # [F, 3]
    ty = py[faces_uv]
    # Signed doubled area; zero-area triangles cover nothing.
    area2 = (tx[:, 1] - tx[:, 0]) * (ty[:, 2] - ty[:, 0]) - (tx[:, 2] - tx[:, 0]) * (ty[:, 1] - ty[:, 0])
    usable = np.flatnonzero(np.abs(area2) > 1e-12 * max(width, height) ** 2)
    pad = 1e-6  # include centres within rounding of the bounding box
    x0 = np.clip(np.ceil(tx[usable].min(1) - pad), 0, width).astype(np.int64)
    x1 = np.clip(np.floor(tx[usable].max(1) + pad), -1, width - 1).astype(np.int64)
    y0 = np.clip(np.ceil(ty[usable].min(1) - pad), 0, height).astype(np.int64)
    y1 = np.clip(np.floor(ty[usable].max(1) + pad), -1, height - 1).astype(np.int64)
    bw = np.maximum(x1 - x0 + 1, 0)
    bh = np.maximum(y1 - y0 + 1, 0)
    counts = bw * bh                                         # candidate texels per face

    # Process faces in groups whose candidate totals fit in one chunk.
    cum = np.cumsum(counts)
    start = 0
    while start < len(usable):
        base = cum[start - 1] if start else 0
        stop = int(np.searchsorted(cum, base + _CHUNK, side="right"))
        stop = max(stop, start + 1)
        sel = np.arange(start, stop)
        _raster_group(usable[sel], x0[sel], y0[sel], bw[sel], counts[sel], tx, ty, area2,
                      width, best_face, best_depth, best_bary, coverage)
        start = stop
    return UVRaster(best_face.reshape(height, width), best_bary.reshape(height, width, 3),
                    coverage.reshape(height, width))


def _raster_group(faces, x0, y0, bw, counts, tx, ty, area2, width,
                  best_face, best_depth, best_bary, coverage):
    """Barycentrics of every candidate (face, texel) pair of a group; keep the deepest."""
    total = int(counts.sum())
    if total == 0:
        return
    owner = np.repeat(np.arange(len(faces)), counts)         # [P] group-local face
    local = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    cx = x0[owner] + local % bw[owner]
    cy = y0[owner] + local // bw[owner]
    f = faces[owner]
    ax, ay = tx[f, 0], ty[f, 0]
    bx, by = tx[f, 1], ty[f, 1]
    qx, qy = tx[f, 2], ty[f, 2]
    inv = 1.0 / area2[f]
    # Edge functions (signed sub-triangle areas) / total area = barycentric weights.
    w0 = ((bx - cx) * (qy - cy) - (qx - cx) * (by - cy)) * inv
    w1 = ((qx - cx) * (ay - cy) - (ax - cx) * (qy - cy)) * inv
    w2 = 1.0 - w0 - w1
    depth = np.minimum(np.minimum(w0, w1), w2)
    keep = depth >= -_INSIDE_TOL
    if not keep.any():
        return
    texel = (cy * width + cx)[keep]
    depth = depth[keep]
    f = f[keep]
    bary = np.stack([w0[keep], w1[keep], w2[keep]], axis=1)
    np.add.at(coverage, texel, (depth > _STRICT_TOL).astype(np.int32))
    # Per texel, the deepest candidate of this group (ties → lowest face index) ...
    order = np.lexsort((f, -depth, texel))
    first = np.ones(len(order), bool)
    first[1:] = texel[order][1:] != texel[order][:-1]
    pick = order[first]
    t = texel[pick]
    # ... replaces the current owner only if strictly deeper (earlier groups hold lower indices).
    better = depth[pick] > best_depth[t]
    t = t[better]
    best_face[t] = f[pick][better]
    best_depth[t] = depth[pick][better]
    w = np.clip(bary[pick][better], 0.0, None)               # clamp rounding on edges
    best_bary[t] = w / w.sum(axis=1, keepdims=True)


def dilate(values: np.ndarray, inside: np.ndarray, rings: int = 4) -> np.ndarray:
    """Fill texels outside the charts so bilinear lookups at seams never pull zeros.

    The first ``rings`` rings around each chart get the mean of their already
    filled 8-neighbours (a smooth continuation across the seam); any texels still
    empty take the value of the nearest inside texel (Euclidean distance
    transform).  Inside texels are returned unchanged.

    Args:
        values: [H, W, C] or [H, W] values, valid where ``inside``.
        inside: [H, W] bool.
        rings: averaging dilation steps before the nearest-texel fill.

    Returns:
        Array of the same shape and dtype as ``values`` with no empty texel (unless
        nothing is inside, in which case it is returned as is).
    """
    inside = np.asarray(inside, bool)
    squeeze = values.ndim == 2
    out = np.array(values, dtype=values.dtype, copy=True)
    if squeeze:
        out = out[..., None]
    filled = inside.copy()
    if not filled.any() or filled.all():
        return out[..., 0] if squeeze else out
    out[~filled] = 0
    h, w = filled.shape
    shifts = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]
    for _ in range(rings):
        padded_v = np.pad(out, ((1, 1), (1, 1), (0, 0)))
        padded_m = np.pad(filled, 1).astype(np.float64)
        total = np.zeros(out.shape, np.float64)
        count = np.zeros((h, w), np.float64)
        for dy, dx in shifts:
            sl = (slice(1 + dy, 1 + dy + h), slice(1 + dx, 1 + dx + w))
            m = padded_m[sl]
            total += padded_v[sl] * m[..., None]
            count += m
        grow = (~filled) & (count > 0)
        if not grow.any():
            break
        out[grow] = (total[grow] / count[grow][:, None]).astype(out.dtype)
        filled = filled | grow
    if not filled.all():
        from scipy.ndimage import distance_transform_edt
        _, (iy, ix) = distance_transform_edt(~filled, return_indices=True)
        out = out[iy, ix]
    return out[..., 0] if squeeze else out


def rasterize_uv_reference(uv, faces_uv, resolution) -> tuple[np.ndarray, np.ndarray]:
    """Slow twin of :func:`rasterize_uv` for tests: per-texel loop, 2×2 linear solves.

    Returns:
        (covered_by [H, W] list-of-face-index sets encoded as an object array,
        barycentric weights dict keyed by (row, col, face)) — every triangle that
        contains each texel centre (weights ≥ −1e-9), computed independently of the
        edge-function formula used by the fast path.
    """
    height, width = _resolution(resolution)
    uv = np.asarray(uv, np.float64)
    faces_uv = np.asarray(faces_uv, np.int64)
    centers = texel_centers(height, width)
    covered = np.empty((height, width), object)
    weights = {}
    for r in range(height):
        for c in range(width):
            p = centers[r, c]
            hits = set()
            for fi, (a, b, q) in enumerate(faces_uv):
                m = np.array([[uv[b, 0] - uv[a, 0], uv[q, 0] - uv[a, 0]],
                              [uv[b, 1] - uv[a, 1], uv[q, 1] - uv[a, 1]]])
                if abs(np.linalg.det(m)) < 1e-14:
                    continue
                s, t = np.linalg.solve(m, p - uv[a])
                w = np.array([1 - s - t, s, t])
                if w.min() >= -1e-9:
                    hits.add(fi)
                    weights[(r, c, fi)] = w
            covered[r, c] = hits
    return covered, weights


# ---------------------------------------------------------------- seam-aware lookups
#
# A bilinear lookup reads the 2×2 texels around a sample.  Near a chart's border some of
# them belong to another chart, packed beside it in UV but far away on the surface (the
# built-in hand's thumb chart borders the palm's): at 32² texels the thumb's front read
# its neighbours' shading and drew a hollow thumb (issue 53).  A seam-aware lookup keeps
# only the taps inside the sample's own chart and renormalises their weights, as
# seam-aware texture filtering does in production renderers; where none of the four is
# in that chart (a sliver narrower than a texel) it falls back to the plain taps.


def uv_charts(faces_uv: np.ndarray) -> np.ndarray:
    """[F] int64 chart of each triangle: triangles that share a UV vertex (an index of
    ``faces_uv``) are one chart, so a seam — the same mesh edge with different UV
    indices on its two sides — separates charts.  Charts are numbered by their first
    triangle."""
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components
    faces_uv = np.asarray(faces_uv, np.int64).reshape(-1, 3)
    f = len(faces_uv)
    if f == 0:
        return np.zeros(0, np.int64)
    n = int(faces_uv.max()) + 1
    rows = np.repeat(np.arange(f), 3)
    graph = sparse.coo_matrix((np.ones(3 * f, np.int8), (rows, f + faces_uv.ravel())),
                              shape=(f + n, f + n))
    _, labels = connected_components(graph, directed=False)
    _, first = np.unique(labels[:f], return_index=True)
    order = np.argsort(first)                       # charts in order of their first triangle
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    _, dense = np.unique(labels[:f], return_inverse=True)
    return rank[dense]


def texel_charts(raster: UVRaster, face_chart: np.ndarray) -> np.ndarray:
    """[H, W] int64 chart of each texel: an inside texel's triangle's chart; a texel
    outside the charts (the gutter) belongs to the chart of its nearest inside texel, as
    the renderer's maps fill it from there and a learned map may use it to shade its
    chart's border (−1 everywhere when no texel is inside)."""
    from scipy.ndimage import distance_transform_edt
    inside = raster.inside
    if not inside.any():
        return np.full(inside.shape, -1, np.int64)
    charts = np.asarray(face_chart, np.int64)[np.maximum(raster.face, 0)]
    _, (iy, ix) = distance_transform_edt(~inside, return_indices=True)
    return charts[iy, ix]


def bilinear_taps(uv: np.ndarray, height: int, width: int):
    """The four texels and weights of a bilinear lookup at ``uv`` [S, 2] (clamped
    borders, texel centres at ((c + ½)/W, 1 − (r + ½)/H)): ``(rows [S, 4], cols [S, 4],
    weights [S, 4] float64)``, exactly :func:`relight_cli.render.appearance.bilinear`'s
    and ``grid_sample``'s (align_corners=False, border padding)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    x = np.clip(uv[:, 0] * width - 0.5, 0, width - 1)
    y = np.clip((1 - uv[:, 1]) * height - 0.5, 0, height - 1)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    x1 = np.minimum(x0 + 1, width - 1)
    y1 = np.minimum(y0 + 1, height - 1)
    fx, fy = x - x0, y - y0
    rows = np.stack([y0, y0, y1, y1], 1)
    cols = np.stack([x0, x1, x0, x1], 1)
    weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    return rows, cols, weights


#: a sample whose own chart holds less of its bilinear weight than this keeps the plain
#: taps: at a texel centre the three other weights are rounding (1e-16), and renormalising
#: them would read a neighbour instead of the texel
SEAM_MIN_WEIGHT = 1e-9


def seam_taps(uv: np.ndarray, sample_chart: np.ndarray, chart_map: np.ndarray):
    """:func:`bilinear_taps` at ``uv`` [S, 2] with the taps outside each sample's chart
    (``sample_chart`` [S]: the chart of the triangle the sample lies on; ``chart_map``
    [H, W]: :func:`texel_charts`) given weight 0 and the rest renormalised to sum 1.  A
    sample none of whose four taps lies in its chart (their weight ≤
    :data:`SEAM_MIN_WEIGHT`) keeps the plain weights.  Returns
    ``(rows, cols, weights)`` as :func:`bilinear_taps`."""
    chart_map = np.asarray(chart_map)
    rows, cols, weights = bilinear_taps(uv, *chart_map.shape[:2])
    same = chart_map[rows, cols] == np.asarray(sample_chart, np.int64).reshape(-1, 1)
    kept = weights * same
    total = kept.sum(1)
    ok = total > SEAM_MIN_WEIGHT
    weights = np.where(ok[:, None], kept / np.where(ok, total, 1.0)[:, None], weights)
    return rows, cols, weights


def gather_taps(image: np.ndarray, taps) -> np.ndarray:
    """Σ weights · image[rows, cols]: [S] or [S, C] float64 from an [H, W] or [H, W, C] map."""
    rows, cols, weights = taps
    img = np.asarray(image)
    values = img[rows, cols].astype(np.float64, copy=False)           # [S, 4(, C)]
    w = weights if img.ndim == 2 else weights[..., None]
    return (values * w).sum(1)


class UVLayout:
    """A mesh's UV layout (``uv`` [T, 2], ``faces_uv`` [F, 3]) with its charts and, per
    map size, the chart of every texel — what a seam-aware lookup needs.  One instance
    per distinct layout (:meth:`of`, keyed by its bytes), so every posed copy of a mesh
    and every G-buffer share one rasterization per map size."""

    _cache: dict = {}
    _CACHE_SIZE = 16

    def __init__(self, uv: np.ndarray, faces_uv: np.ndarray):
        self.uv = np.asarray(uv, np.float64)
        self.faces_uv = np.asarray(faces_uv, np.int64)
        self._face_chart = None
        self._maps = {}

    @classmethod
    def of(cls, uv, faces_uv) -> "UVLayout":
        import hashlib
        uv = np.ascontiguousarray(uv, np.float64)
        faces_uv = np.ascontiguousarray(faces_uv, np.int64)
        key = hashlib.blake2b(uv.tobytes() + b"|" + faces_uv.tobytes(), digest_size=16).digest()
        layout = cls._cache.get(key)
        if layout is None:
            if len(cls._cache) >= cls._CACHE_SIZE:
                cls._cache.pop(next(iter(cls._cache)))
            layout = cls._cache[key] = cls(uv, faces_uv)
        return layout

    @property
    def face_chart(self) -> np.ndarray:
        """[F] chart of each triangle (:func:`uv_charts`)."""
        if self._face_chart is None:
            self._face_chart = uv_charts(self.faces_uv)
        return self._face_chart

    def chart_map(self, height: int, width: int, raster: UVRaster | None = None) -> np.ndarray:
        """[H, W] chart of every texel of an H×W map (:func:`texel_charts`)."""
        key = (int(height), int(width))
        if key not in self._maps:
            if raster is None or (raster.height, raster.width) != key:
                raster = rasterize_uv(self.uv, self.faces_uv, key)
            self._maps[key] = texel_charts(raster, self.face_chart)
        return self._maps[key]

    def taps(self, uv: np.ndarray, faces: np.ndarray, height: int, width: int):
        """:func:`seam_taps` of samples at ``uv`` [S, 2] on triangles ``faces`` [S]."""
        return seam_taps(uv, self.face_chart[np.asarray(faces, np.int64)],
                         self.chart_map(height, width))
