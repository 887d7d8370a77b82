"""The procedural hand on the 25-joint WebXR/OpenXR skeleton.

Rest pose of the right hand (model space, metres, +Y up): wrist at the origin,
fingers straight along ≈ +Y, palm facing +Z, thumb towards +X; the left hand is
its mirror image across x = 0.  Wrist to middle fingertip is ≈ 0.186 m.

The surface is six closed parametric tubes (palm with the wrist stub, thumb and
four fingers), each a superellipse cross-section swept along the bone chain
and closed by rounded caps; the finger tubes start inside the palm, so the
union is closed (every part is watertight; parts overlap at the knuckles).
Each part is one rectangular UV chart (u around, arc-length parameterized;
v along), packed without overlaps into [0, 1]².  The coarse proxy and the
fine mesh sample the *same* parametric map on nested grids (the fine grid
halves both spacings), so they share one UV parameterization and every coarse
vertex is a fine vertex; only the fine mesh carries the palmar flexion creases.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from .skeleton import (FINGER_SPECS, FINGERS, JOINT_NAMES, N_JOINTS, PARENTS,
                       THUMB_LENGTHS, THUMB_META_DIR, THUMB_PHAL_DIR, THUMB_RADII, rest_skeleton,
                       unit)

LABEL_NAMES = ("palm", "dorsum", "finger", "nail", "crease")
PALM, DORSUM, FINGER, NAIL, CREASE = range(5)

# Coarse grid per part: (columns around, interior rows along).  The coarse mesh
# has 5·(16·28+2) + (40·22+2) = 3,132 vertices; the fine one 4.1× that.
_FINGER_GRID = (16, 28)
_PALM_GRID = (40, 22)
_CREASE_DEPTH = 0.0004   # metres; palmar flexion creases on the fine mesh only
_CREASE_WIDTH = 0.0007   # metres (Gaussian sigma along the finger)

# Palm: knots along y (metres) of half-width, half-thickness, centre x, centre z.
_PALM_Y = np.array([-0.030, 0.000, 0.030, 0.060, 0.086])
_PALM_A = np.array([0.027, 0.029, 0.037, 0.040, 0.041])
_PALM_B = np.array([0.019, 0.0175, 0.0155, 0.0140, 0.0125])
_PALM_CX = np.array([0.001, 0.002, 0.000, -0.002, -0.003])
_PALM_CZ = np.array([0.000, 0.000, 0.001, 0.001, 0.000])


# ----------------------------------------------------------------------------- tubes

class _Tube:
    """A closed tube: superellipse sections swept along a polyline, capped at both ends.

    Knots are given along the body arc length s ∈ [0, L]; the meridian
    parameter t ∈ [0, 1] runs pole → cap0 → body → cap1 → pole, proportional
    to approximate meridian arc length.
    """

    def __init__(self, centers, half_width, half_thickness, lateral, exponent, cap0, cap1):
        self.centers = np.asarray(centers, np.float64)            # [K, 3]
        seg = np.linalg.norm(np.diff(self.centers, axis=0), axis=1)
        self.s_knots = np.concatenate([[0.0], np.cumsum(seg)])     # [K]
        self.length = float(self.s_knots[-1])
        self.a = np.asarray(half_width, np.float64)
        self.b = np.asarray(half_thickness, np.float64)
        self.lateral = np.asarray(lateral, np.float64)             # [3] reference e1
        self.exponent = exponent
        self.cap0, self.cap1 = cap0, cap1
        r0 = math.sqrt(self.a[0] * self.b[0])
        r1 = math.sqrt(self.a[-1] * self.b[-1])
        # Quarter-ellipse arc lengths (Ramanujan's mean is plenty here).
        self.arc0 = math.pi / 4 * (cap0 + r0)
        self.arc1 = math.pi / 4 * (cap1 + r1)
        self.meridian = self.arc0 + self.length + self.arc1

    def _center(self, s):
        return np.stack([np.interp(s, self.s_knots, self.centers[:, k]) for k in range(3)], -1)

    def _tangent(self, s, delta=0.004):
        lo = np.clip(s - delta, 0, self.length)
        hi = np.clip(s + delta, 0, self.length)
        return unit(self._center(hi) - self._center(lo))

    def body_coordinates(self, t):
        """Meridian t [R] → (body s [R], axial offset past the body end [R], radial scale [R])."""
        ell = np.asarray(t, np.float64) * self.meridian
        s = np.clip(ell - self.arc0, 0.0, self.length)
        offset = np.zeros_like(ell)
        radial = np.ones_like(ell)
        in0 = ell < self.arc0
        beta0 = (math.pi / 2) * (1.0 - ell[in0] / self.arc0)
        offset[in0] = -self.cap0 * np.sin(beta0)
        radial[in0] = np.cos(beta0)
        in1 = ell > self.arc0 + self.length
        beta1 = (math.pi / 2) * (ell[in1] - self.arc0 - self.length) / self.arc1
        offset[in1] = self.cap1 * np.sin(beta1)
        radial[in1] = np.cos(beta1)
        return s, offset, radial

    def frames(self, s):
        """(centre [R, 3], tangent, e1 lateral, e2 = e1 × tangent) at body coordinates s [R]."""
        c = self._center(s)
        T = self._tangent(s)
        e1 = unit(self.lateral - (T @ self.lateral)[:, None] * T)
        e2 = np.cross(e1, T)
        return c, T, e1, e2

    def section_angles(self, s, u):
        """φ [R, M] giving arc-length-uniform samples u ∈ [0, 1) of each row's section."""
        a = np.interp(s, self.s_knots, self.a)
        b = np.interp(s, self.s_knots, self.b)
        phi = np.linspace(0.0, 2 * math.pi, 257)
        x = a[:, None] * _spow(np.cos(phi), 2 / self.exponent)
        z = b[:, None] * _spow(np.sin(phi), 2 / self.exponent)
        arc = np.concatenate([np.zeros((len(s), 1)),
                              np.cumsum(np.hypot(np.diff(x, axis=1), np.diff(z, axis=1)), 1)], 1)
        arc /= arc[:, -1:]
        return np.stack([np.interp(u, arc[r], phi) for r in range(len(s))]), a, b

    def sample(self, n_columns, n_rows):
        """Evaluate the surface on the grid u = c/M, t = i/(R+1), i = 1..R.

        Returns a dict with positions [R, M, 3], the two poles [3] each, the
        row parameters t [R], body coordinate s [R], the per-vertex section
        cosines toward e1 (``lat``) and e2 (``palmar``) [R, M], and outward
        radial directions [R, M, 3].
        """
        t = np.arange(1, n_rows + 1) / (n_rows + 1)
        u = np.arange(n_columns) / n_columns
        s, offset, radial = self.body_coordinates(t)
        c, T, e1, e2 = self.frames(s)
        phi, a, b = self.section_angles(s, u)
        fx = _spow(np.cos(phi), 2 / self.exponent)                       # [R, M]
        fz = _spow(np.sin(phi), 2 / self.exponent)
        centre = c + offset[:, None] * T                                 # [R, 3]
        pos = (centre[:, None, :]
               + (radial * a)[:, None, None] * fx[..., None] * e1[:, None, :]
               + (radial * b)[:, None, None] * fz[..., None] * e2[:, None, :])
        out_dir = unit(fx[..., None] * b[:, None, None] * e1[:, None, :]
                        + fz[..., None] * a[:, None, None] * e2[:, None, :] + 1e-12)
        c_ends, T_ends, _, _ = self.frames(np.array([0.0, self.length]))
        pole0 = c_ends[0] - self.cap0 * T_ends[0]
        pole1 = c_ends[1] + self.cap1 * T_ends[1]
        return dict(pos=pos, pole0=pole0, pole1=pole1, t=t, s=s, offset=offset,
                    lat=np.cos(phi), palmar=np.sin(phi), out_dir=out_dir)


def _spow(x, e):
    return np.sign(x) * np.abs(x) ** e


def _grid_topology(M, R):
    """Faces [F, 3] and UV faces of the capped grid; vertex 0 and V−1 are poles."""
    def vid(r, c):
        return 1 + r * M + (c % M)

    pole1 = 1 + R * M
    cols = np.arange(M)
    faces = [np.stack([np.zeros(M, np.int64), vid(0, cols), vid(0, cols + 1)], 1)]
    uv_row = lambda r, c: M + r * (M + 1) + c                             # noqa: E731
    faces_uv = [np.stack([cols, uv_row(0, cols), uv_row(0, cols + 1)], 1)]
    for r in range(R - 1):
        a, b = vid(r, cols), vid(r, cols + 1)
        c, d = vid(r + 1, cols + 1), vid(r + 1, cols)
        faces += [np.stack([a, d, c], 1), np.stack([a, c, b], 1)]
        ua, ub = uv_row(r, cols), uv_row(r, cols + 1)
        uc, ud = uv_row(r + 1, cols + 1), uv_row(r + 1, cols)
        faces_uv += [np.stack([ua, ud, uc], 1), np.stack([ua, uc, ub], 1)]
    faces.append(np.stack([vid(R - 1, cols + 1), vid(R - 1, cols), np.full(M, pole1)], 1))
    pole1_uv = M + R * (M + 1)
    faces_uv.append(np.stack([uv_row(R - 1, cols + 1), uv_row(R - 1, cols), pole1_uv + cols], 1))
    return np.concatenate(faces).astype(np.int64), np.concatenate(faces_uv).astype(np.int64)


def _grid_uv(M, R, t):
    """Chart-local UVs [T, 2] in [0, 1]² matching :func:`_grid_topology`."""
    cols = np.arange(M)
    pole0 = np.stack([(cols + 0.5) / M, np.zeros(M)], 1)
    uu, vv = np.meshgrid(np.arange(M + 1) / M, t)
    rows = np.stack([uu.ravel(), vv.ravel()], 1)
    pole1 = np.stack([(cols + 0.5) / M, np.ones(M)], 1)
    return np.concatenate([pole0, rows, pole1])


# ----------------------------------------------------------------------------- parts

def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _chain_weights(s, knots, joints, half_widths):
    """[R, J] weights along a chain: segment k (between knots k−1 and k) → joints[k]."""
    W = np.zeros((len(s), N_JOINTS))
    prev = np.ones_like(s)
    for k, (knot, h) in enumerate(zip(knots, half_widths)):
        step = _smoothstep((s - knot + h) / (2 * h))
        W[:, joints[k]] += prev - step
        prev = step
    W[:, joints[len(knots)]] += prev
    return W


def _finger_parts(J):
    parts = []
    for k, f in enumerate(FINGERS):
        spec = FINGER_SPECS[f]
        base = 5 + 5 * k
        d = unit(spec["dir"])
        r_mcp, r_pip, r_dip, r_tip = spec["radii"]
        start = J[base + 1] - 0.024 * d
        end = J[base + 4] - 0.9 * r_tip * d
        pts = [start, J[base + 1], 0.5 * (J[base + 1] + J[base + 2]), J[base + 2],
               0.5 * (J[base + 2] + J[base + 3]), J[base + 3], end]
        radii = np.array([r_mcp * 0.95, r_mcp * 1.04, 0.5 * (r_mcp + r_pip) * 0.95, r_pip * 1.04,
                          0.5 * (r_pip + r_dip) * 0.95, r_dip * 1.03, r_tip])
        lateral = np.cross(d, [0.0, 0.0, 1.0])
        tube = _Tube(pts, radii, 0.86 * radii, lateral, 2.2, cap0=0.8 * r_mcp, cap1=0.9 * r_tip + 0.001)
        knots_s = tube.s_knots[[1, 3, 5]]
        parts.append(dict(name=f, tube=tube, grid=_FINGER_GRID, kind="finger",
                          joints=[base, base + 1, base + 2, base + 3],
                          knots=knots_s, blend=[0.55 * r_mcp, 0.55 * r_pip, 0.55 * r_dip],
                          crease_s=[knots_s[0] + 0.004, knots_s[1], knots_s[2]],
                          nail_from=knots_s[2] + 0.35 * spec["lengths"][2]))
    return parts


def _thumb_part(J):
    d0, d1 = unit(THUMB_META_DIR), unit(THUMB_PHAL_DIR)
    r_cmc, r_mcp, r_ip, r_tip = THUMB_RADII
    start = J[1] - 0.012 * d0
    end = J[4] - 0.9 * r_tip * d1
    pts = [start, J[1], 0.5 * (J[1] + J[2]), J[2], 0.5 * (J[2] + J[3]), J[3], end]
    radii = np.array([r_cmc * 0.9, r_cmc, 0.5 * (r_cmc + r_mcp), r_mcp * 1.03,
                      0.5 * (r_mcp + r_ip) * 0.96, r_ip * 1.02, r_tip])
    # The thumb is turned ~90° about its axis relative to the fingers: its nail
    # faces sideways, so its lateral (flexion) axis lies mostly along the palm normal.
    palmar = unit(np.array([-0.75, 0.0, 0.65]))
    lateral = np.cross(d1, palmar)
    tube = _Tube(pts, radii, 0.88 * radii, lateral, 2.2, cap0=0.8 * r_cmc, cap1=0.9 * r_tip + 0.001)
    knots_s = tube.s_knots[[1, 3, 5]]
    return dict(name="thumb", tube=tube, grid=_FINGER_GRID, kind="finger",
                joints=[0, 1, 2, 3], knots=knots_s, blend=[0.012, 0.55 * r_mcp, 0.55 * r_ip],
                crease_s=[knots_s[1], knots_s[2]],
                nail_from=knots_s[2] + 0.35 * THUMB_LENGTHS[2])


def _palm_part():
    y0 = _PALM_Y[0]
    pts = np.stack([_PALM_CX, _PALM_Y, _PALM_CZ], 1)
    tube = _Tube(pts, _PALM_A, _PALM_B, np.array([1.0, 0.0, 0.0]), 2.6,
                 cap0=0.012, cap1=0.010)
    return dict(name="palm", tube=tube, grid=_PALM_GRID, kind="palm", y0=y0)


def _palm_weights(p, J):
    """[P, J] weights of palm vertices [P, 3]: wrist → metacarpals → proximal phalanges."""
    W = np.zeros((len(p), N_JOINTS))
    x, y = p[:, 0], p[:, 1]
    to_meta = _smoothstep((y - 0.004) / 0.026)
    share = np.zeros((len(p), 4))
    for k in range(4):
        cmc, mcp = J[5 + 5 * k], J[6 + 5 * k]
        frac = np.clip((y - cmc[1]) / (mcp[1] - cmc[1]), 0.0, 1.2)
        xf = cmc[0] + frac * (mcp[0] - cmc[0])
        share[:, k] = np.exp(-((x - xf) / 0.010) ** 2)
    # Outside the outermost fingers the nearest one takes all.
    share += 1e-30
    share /= share.sum(1, keepdims=True)
    W[:, 0] = 1.0 - to_meta
    for k in range(4):
        mcp_y = J[6 + 5 * k][1]
        to_prox = _smoothstep((y - (mcp_y - 0.006)) / 0.010)
        W[:, 5 + 5 * k] = to_meta * share[:, k] * (1 - to_prox)
        W[:, 6 + 5 * k] = to_meta * share[:, k] * to_prox
    return W


def _part_attributes(part, g, J):
    """Per-vertex (grid rows × columns, flattened with the poles) weights and labels."""
    M = g["pos"].shape[1]
    pos = np.concatenate([g["pole0"][None], g["pos"].reshape(-1, 3), g["pole1"][None]])
    s = np.concatenate([[g["s"][0]], np.repeat(g["s"], M), [g["s"][-1]]])
    palmar = np.concatenate([[0.0], g["palmar"].ravel(), [0.0]])
    in_body = np.concatenate([[False], np.repeat(g["offset"] == 0, M), [False]])
    labels = np.full(len(pos), FINGER, np.uint8)
    if part["kind"] == "palm":
        W = _palm_weights(pos, J)
        labels[:] = np.where(palmar > 0, PALM, DORSUM)
        wrist_crease = (np.abs(pos[:, 1] - 0.004) < 0.0015) & (palmar > 0.5)
        labels[wrist_crease] = CREASE
    else:
        W = _chain_weights(s, part["knots"], part["joints"], part["blend"])
        tip_end = np.concatenate([[False], np.repeat(g["offset"] > 0, M), [True]])
        nail = ((s >= part["nail_from"]) | tip_end) & (palmar < -0.55)
        labels[nail] = NAIL
        for cs in part["crease_s"]:
            labels[(np.abs(s - cs) < 0.0012) & (palmar > 0.5) & in_body] = CREASE
    return pos, W, labels


def _build_part(part, J, fine: bool):
    M, R = part["grid"]
    if fine:
        M, R = 2 * M, 2 * R + 1
    g = part["tube"].sample(M, R)
    if fine and part["kind"] == "finger":
        # Palmar flexion creases: a shallow Gaussian groove across the palmar side.
        depth = np.zeros_like(g["palmar"])
        for cs in part["crease_s"]:
            depth += np.exp(-0.5 * ((g["s"] - cs) / _CREASE_WIDTH) ** 2)[:, None]
        depth *= _CREASE_DEPTH * np.clip(g["palmar"], 0, None) ** 2 * (g["offset"] == 0)[:, None]
        g["pos"] = g["pos"] - depth[..., None] * g["out_dir"]
    pos, W, labels = _part_attributes(part, g, J)
    faces, faces_uv = _grid_topology(M, R)
    uv = _grid_uv(M, R, g["t"])
    return pos, faces, uv, faces_uv, W, labels


def _chart_sizes(parts):
    """(width, height) in metres of each part's UV chart: mean section perimeter × meridian."""
    sizes = []
    for part in parts:
        tube = part["tube"]
        a, b = tube.a, tube.b
        perim = np.pi * (3 * (a + b) - np.sqrt((3 * a + b) * (a + 3 * b)))   # Ramanujan
        sizes.append((float(np.mean(perim)), float(tube.meridian)))
    return sizes


def _pack(sizes, gap):
    """Shelf-pack rectangles (metres) into a square; returns origins and the square's side."""
    order = sorted(range(len(sizes)), key=lambda i: -sizes[i][1])
    best = None
    total_w = sum(w for w, _ in sizes) + gap * (len(sizes) + 1)
    for shelf_width in np.linspace(max(w for w, _ in sizes) + 2 * gap, total_w, 40):
        origins = {}
        x, y, row_h = gap, gap, 0.0
        for i in order:
            w, h = sizes[i]
            if x + w + gap > shelf_width + 1e-12:
                x, y, row_h = gap, y + row_h + gap, 0.0
            origins[i] = (x, y)
            x += w + gap
            row_h = max(row_h, h)
        side = max(max(origins[i][0] + sizes[i][0] for i in origins),
                   y + row_h) + gap
        if best is None or side < best[1]:
            best = ([origins[i] for i in range(len(sizes))], side)
    return best


@functools.lru_cache(maxsize=1)
def _right_hand_arrays():
    J = rest_skeleton()
    parts = [_palm_part(), _thumb_part(J), *_finger_parts(J)]
    sizes = _chart_sizes(parts)
    origins, side = _pack(sizes, gap=0.004)
    meshes = {}
    for fine in (False, True):
        V, F, UV, FUV, W, L = [], [], [], [], [], []
        nv = nuv = 0
        for part, (w, h), (ox, oy) in zip(parts, sizes, origins):
            pos, faces, uv, faces_uv, weights, labels = _build_part(part, J, fine)
            V.append(pos)
            F.append(faces + nv)
            UV.append(np.stack([(ox + uv[:, 0] * w) / side, (oy + uv[:, 1] * h) / side], 1))
            FUV.append(faces_uv + nuv)
            W.append(weights)
            L.append(labels)
            nv += len(pos)
            nuv += len(uv)
        vertices, faces = np.concatenate(V), np.concatenate(F)
        faces_uv = np.concatenate(FUV)
        # Orient every face outward: the tube construction winds them one way;
        # check it once with the signed volume and flip if needed.
        tri = vertices[faces]
        volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
        if volume < 0:
            faces = faces[:, [0, 2, 1]]
            faces_uv = faces_uv[:, [0, 2, 1]]
        weights = np.concatenate(W)
        weights /= weights.sum(1, keepdims=True)
        meshes["fine" if fine else "coarse"] = (vertices, faces, np.concatenate(UV), faces_uv,
                                                weights, np.concatenate(L))
    return J, meshes


def mirror_mesh(vertices, faces, faces_uv):
    """Mirror across x = 0: negate x and flip the winding (faces and UV faces alike)."""
    v = np.array(vertices, np.float64, copy=True)
    v[:, 0] *= -1.0
    return v, np.asarray(faces)[:, [0, 2, 1]].copy(), np.asarray(faces_uv)[:, [0, 2, 1]].copy()


def builtin_hand(side: str = "right", pose: str | None = "relaxed"):
    """The procedural hand as HandData with one frame (``pose``, default relaxed).

    Args:
        side: "right" or "left" (the mirror image).
        pose: a named pose (see relight_cli.hand.poses) or None for the rest pose.
    Returns:
        HandData (model space = world: root identity, zero translation).
    """
    from relight_cli.formats.hand_npz import HandData, HandInstance, HandMesh

    from .poses import named_pose

    if side not in ("right", "left"):
        raise ValueError(f"side must be 'right' or 'left', got {side!r}")
    J, meshes = _right_hand_arrays()
    out = {}
    for which, (v, f, uv, fuv, w, lab) in meshes.items():
        if side == "left":
            v, f, fuv = mirror_mesh(v, f, fuv)
        out[which] = HandMesh(v.copy(), f.copy(), uv.copy(), fuv.copy(), w.copy(), lab.copy())
    rest = J.copy()
    if side == "left":
        rest[:, 0] *= -1
    poses = (np.zeros((1, N_JOINTS, 3)) if pose is None
             else named_pose(pose, side=side)[None].copy())
    inst = HandInstance(side, False, np.eye(4), poses, np.zeros((1, 3)))
    return HandData(joint_names=list(JOINT_NAMES), parents=PARENTS.copy(), rest_joints=rest,
                    coarse=out["coarse"], fine=out["fine"], side=side, hands=[inst],
                    label_names=list(LABEL_NAMES), bone_scales=np.ones(N_JOINTS))
