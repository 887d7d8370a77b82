"""Surface-aligned flat 3D Gaussians from a triangle mesh.

One Gaussian per triangle (after optional subdivision to a maximum edge
length): centred at the centroid, its in-plane covariance that of the uniform
distribution over the triangle, Σ_tri = (1/12) Σ_i (v_i − c)(v_i − c)ᵀ, scaled
by ``scale_factor``² so neighbours overlap (1.5 leaves no pin-holes at shared
vertices for α = 0.99: six fans each at Mahalanobis ≈ 1.9 sum to τ ≈ 4.6), and a
thin normal axis ``thickness`` × the smaller in-plane scale.  The smallest axis
is the face normal, which is also stored as the Gaussian's normal.

Colours come from a texture (sampled bilinearly at each face's centroid UV,
v = 0 at the bottom row as in OBJ/OpenGL), from per-face or per-vertex colours,
or from a constant; they become degree-0 SH (``0.5 + C0·f_dc`` = colour).
"""

from __future__ import annotations

import numpy as np

from relight_cli.formats.gaussians_ply import Gaussians, matrix_to_quaternion, rgb_to_sh_dc


def gaussians_from_mesh(vertices, faces, face_colors=None, opacity: float = 0.99,
                        scale_factor: float = 1.5, thickness: float = 0.05,
                        max_edge: float | None = None) -> Gaussians:
    """Flat Gaussians covering a triangle mesh.

    Args:
        vertices: [V, 3] float, metres, world.
        faces: [F, 3] int.
        face_colors: None (mid grey), an RGB triple, or [F, 3] linear RGB in [0, 1]
            per face (after subdivision, give colours via :func:`gaussians_from_trimesh`).
        opacity: peak opacity α of every Gaussian, in (0, 1).
        scale_factor: in-plane std devs relative to the triangle's own (≥ 1 fills gaps).
        thickness: normal-axis std dev relative to the smaller in-plane one.
        max_edge: subdivide triangles until no edge is longer (metres); None = as is.
    Returns:
        :class:`~relight_cli.formats.gaussians_ply.Gaussians` with normals, SH degree 0.
        Degenerate (zero-area) triangles are skipped.
    """
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    colors = _broadcast_colors(face_colors, len(f))
    if max_edge is not None:
        import trimesh.remesh
        v, f, idx = trimesh.remesh.subdivide_to_size(v, f, max_edge=max_edge, return_index=True)
        colors = colors[idx]
    if not (0 < opacity < 1):
        raise ValueError(f"opacity must be in (0, 1), got {opacity}")
    tri = v[f]                                                     # [F, 3, 3]
    centre = tri.mean(axis=1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(normal, axis=1)
    scale_ref = np.maximum(np.abs(tri).max(axis=(1, 2)), 1.0)
    good = area2 > 1e-12 * scale_ref ** 2
    tri, centre, normal, area2, colors = tri[good], centre[good], normal[good], area2[good], colors[good]
    normal = normal / area2[:, None]
    rel = tri - centre[:, None, :]
    cov = np.einsum("fki,fkj->fij", rel, rel) / 12.0               # uniform-triangle covariance
    evals, evecs = np.linalg.eigh(cov)                              # ascending; evals[:, 0] ≈ 0
    # principal frame: columns (major, minor, normal), right-handed
    e1 = evecs[:, :, 2]
    e3 = normal
    e1 = e1 - (e1 * e3).sum(1, keepdims=True) * e3                 # exactly in-plane
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(e3, e1)
    R = np.stack([e1, e2, e3], axis=2)
    s1 = np.sqrt(np.maximum(evals[:, 2], 0)) * scale_factor
    s2 = np.sqrt(np.maximum(evals[:, 1], 0)) * scale_factor
    s3 = np.maximum(thickness * s2, 1e-9)
    n = len(centre)
    return Gaussians(means=centre, scales=np.stack([s1, s2, s3], 1),
                     rotations=matrix_to_quaternion(R), opacities=np.full(n, float(opacity)),
                     sh=rgb_to_sh_dc(colors)[:, None, :], sh_degree=0, normals=normal)


def gaussians_from_trimesh(mesh, color=None, **kwargs) -> Gaussians:
    """:func:`gaussians_from_mesh` for a ``trimesh.Trimesh``, colours from its visuals.

    Texture (``TextureVisuals`` with UVs and an image): bilinear sample at each
    (subdivided) face's centroid UV, sRGB texels converted to linear.  Face or
    vertex colours (``ColorVisuals``): per face (vertex colours averaged), sRGB →
    linear.  ``color`` (an RGB triple, linear) overrides the visuals.
    """
    import trimesh

    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    max_edge = kwargs.pop("max_edge", None)
    uv = None
    colors = None
    if color is not None:
        colors = _broadcast_colors(color, len(f))
    else:
        visual = mesh.visual
        if isinstance(visual, trimesh.visual.texture.TextureVisuals) and visual.uv is not None \
                and getattr(visual.material, "image", None) is not None:
            uv = np.asarray(visual.uv, np.float64)
            image = np.asarray(visual.material.image.convert("RGB"), np.float64) / 255.0
        elif isinstance(visual, trimesh.visual.color.ColorVisuals) and visual.kind is not None:
            rgb = np.asarray(visual.face_colors, np.float64)[:, :3] / 255.0
            colors = _srgb_to_linear(rgb)
    if max_edge is not None:
        import trimesh.remesh
        out = trimesh.remesh.subdivide_to_size(v, f, max_edge=max_edge, return_index=True)
        v, f, idx = out[0], out[1], out[2]
        if colors is not None:
            colors = colors[idx]
        if uv is not None:
            # uv of new vertices: barycentric interpolation of the source face's uv
            uv = _resample_uv(mesh.vertices, mesh.faces, uv, v, f, idx)
    if uv is not None:
        centre_uv = uv[f].mean(axis=1)
        colors = _srgb_to_linear(_bilinear(image, centre_uv))
    return gaussians_from_mesh(v, f, colors, **kwargs)


def _resample_uv(v0, f0, uv0, v, f, idx):
    """Per-vertex UVs of a subdivided mesh (new faces keep their source face's UV chart)."""
    v0 = np.asarray(v0, np.float64)
    f0 = np.asarray(f0, np.int64)
    src = f0[idx]                                                   # [F', 3] source vertex ids
    a, b, c = v0[src[:, 0]], v0[src[:, 1]], v0[src[:, 2]]
    out = np.zeros((len(v), 2))
    for corner in range(3):
        p = v[f[:, corner]]
        w = _barycentric(p, a, b, c)
        out[f[:, corner]] = (w[:, :, None] * uv0[src]).sum(axis=1)
    return out


def _barycentric(p, a, b, c):
    v0, v1, v2 = b - a, c - a, p - a
    d00 = (v0 * v0).sum(1); d01 = (v0 * v1).sum(1); d11 = (v1 * v1).sum(1)
    d20 = (v2 * v0).sum(1); d21 = (v2 * v1).sum(1)
    den = np.where(np.abs(d00 * d11 - d01 ** 2) > 0, d00 * d11 - d01 ** 2, 1.0)
    wb = (d11 * d20 - d01 * d21) / den
    wc = (d00 * d21 - d01 * d20) / den
    return np.stack([1 - wb - wc, wb, wc], axis=1)


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """[N, C] bilinear texture samples at uv ∈ [0,1]² (v = 0 bottom row; wraps)."""
    h, w = image.shape[:2]
    x = (uv[:, 0] % 1.0) * w - 0.5
    y = (1 - (uv[:, 1] % 1.0)) * h - 0.5
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x0m, x1m = x0 % w, (x0 + 1) % w
    y0c, y1c = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    return ((1 - fx) * (1 - fy) * image[y0c, x0m] + fx * (1 - fy) * image[y0c, x1m]
            + (1 - fx) * fy * image[y1c, x0m] + fx * fy * image[y1c, x1m])


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    from relight_cli.formats.gaussians_ply import srgb_eotf
    return srgb_eotf(np.clip(c, 0, 1))


def _broadcast_colors(colors, n: int) -> np.ndarray:
    if colors is None:
        return np.full((n, 3), 0.5)
    c = np.asarray(colors, np.float64)
    if c.shape == (3,):
        return np.tile(c, (n, 1))
    if c.shape != (n, 3):
        raise ValueError(f"face colours must be an RGB triple or [{n}, 3], got {c.shape}")
    return c


BUILTINS = ("hand", "room", "sphere")


def builtin_gaussians(name: str) -> Gaussians:
    """Small built-in Gaussian assets (for demos and tests), metres, +Y up.

    * ``hand``: the procedural right hand (relight_cli.hand, fine mesh, relaxed
      pose) as flat Gaussians, skin colour; about 20 cm, near the origin.
    * ``room``: a 2 m × 2 m floor at y = 0 (x, z ∈ [−1, 1]) with a back wall
      (z = −1) and a left wall (x = −1), 1.5 m high, as flat Gaussians
      (≈ 4 cm triangles); warm grey floor, off-white walls.
    * ``sphere``: a 10 cm radius sphere at the origin.
    """
    import trimesh

    if name == "hand":
        from relight_cli.hand.model import builtin_hand
        from relight_cli.hand.scene import posed_meshes
        pm = posed_meshes(builtin_hand(), 0, "fine")[0]
        return gaussians_from_mesh(pm.vertices, pm.faces, (0.62, 0.38, 0.28))
    if name == "sphere":
        s = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
        return gaussians_from_mesh(s.vertices, s.faces, (0.7, 0.7, 0.7))
    if name == "room":
        from relight_cli.formats.gaussians_ply import concatenate

        def quad(corners, color):
            v = np.asarray(corners, np.float64)
            return gaussians_from_mesh(v, [[0, 1, 2], [0, 2, 3]], color, max_edge=0.04)

        floor = quad([[-1, 0, -1], [-1, 0, 1], [1, 0, 1], [1, 0, -1]], (0.45, 0.40, 0.35))
        back = quad([[-1, 0, -1], [1, 0, -1], [1, 1.5, -1], [-1, 1.5, -1]], (0.75, 0.75, 0.72))
        left = quad([[-1, 0, 1], [-1, 0, -1], [-1, 1.5, -1], [-1, 1.5, 1]], (0.70, 0.72, 0.75))
        return concatenate([floor, back, left])
    raise ValueError(f"unknown built-in Gaussians {name!r}; choose from {', '.join(BUILTINS)}")


def hand_gaussians(hand, frame: int = 0, opacity: float = 0.99, colors=None) -> Gaussians:
    """A posed hand (HandData, every hand of it) as flat Gaussians on its fine mesh.

    One Gaussian per triangle of the skinned fine mesh at ``frame``
    (:func:`gaussians_from_mesh`), coloured by the hand's albedo (its procedural
    per-region material, or its image maps) at the triangle's UV centroid, with
    the triangle's normal stored: the bridge from the hand half of the toolkit
    (hand.npz) to the Gaussian half (dgsm-build, relight --object).  ``colors``:
    :func:`hand_colors` computed before (a sequence's frames share them).
    """
    from relight_cli.formats.gaussians_ply import concatenate
    from relight_cli.hand.scene import posed_meshes

    if not 0 <= frame < hand.n_frames:
        raise ValueError(f"frame {frame} is out of range: the hand has {hand.n_frames} "
                         f"frame(s)")
    meshes = posed_meshes(hand, frame, "fine")
    if colors is None:
        colors = hand_colors(hand)
    parts = [gaussians_from_mesh(pm.vertices, pm.faces, c, opacity=opacity)
             for pm, c in zip(meshes, colors)]
    return concatenate(parts)


def hand_colors(hand) -> list:
    """Per hand of ``hand``, the [F, 3] albedo of each fine triangle at its UV centroid:
    the same for every frame (the UVs do not move), so a sequence computes it once
    (:func:`hand_gaussians` ``colors``)."""
    from relight_cli.hand.scene import posed_meshes
    from relight_cli.render.appearance import hand_materials

    out = []
    for pm, material in zip(posed_meshes(hand, 0, "fine"), hand_materials(hand, "fine")):
        uv_centroid = pm.uv[pm.faces_uv].mean(axis=1)
        out.append(np.clip(material.albedo_at(uv_centroid), 0.0, 1.0))
    return out


MESH_SUFFIXES = (".obj", ".glb", ".gltf", ".stl", ".off")


def load_gaussians(spec: str, frame: int | None = None,
                   colour_space: str = "auto") -> Gaussians:
    """Gaussians from ``builtin:NAME``, a mesh file (.obj .glb .gltf .stl .off → flat
    Gaussians with texture/face colours), a hand .npz (its pose at ``frame``, default
    0, by :func:`hand_gaussians`) or a 3DGS PLY.  Raises DataError.

    Colours come back linear.  ``colour_space`` ("auto" | "srgb" | "linear") is the
    space a PLY's colours are stored in (auto: linear for files this toolkit wrote,
    sRGB otherwise; see :func:`~relight_cli.formats.gaussians_ply.read_gaussians`);
    built-in objects, meshes and hands are made linear and ignore it."""
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.gaussians_ply import read_gaussians

    if frame is not None and not spec.lower().endswith(".npz"):
        raise UsageProblem("frame=K applies to a hand .npz source only", spec)
    if spec.lower().endswith(".npz"):
        from relight_cli.formats.hand_npz import read_hand
        hand = read_hand(spec)
        try:
            return hand_gaussians(hand, 0 if frame is None else frame)
        except ValueError as exc:
            raise DataError(str(exc), spec) from None
    if spec.startswith("builtin:"):
        name = spec.split(":", 1)[1]
        if name not in BUILTINS:  # a misspelt name is a usage error, as for builtin env maps
            raise UsageProblem(f"unknown built-in Gaussians {name!r}; choose from "
                               f"{', '.join('builtin:' + b for b in BUILTINS)}", spec)
        return builtin_gaussians(name)
    if spec.lower().endswith(MESH_SUFFIXES):
        import trimesh
        try:
            mesh = trimesh.load(spec, force="mesh", process=False)
        except Exception as exc:  # trimesh raises many types on damaged files
            raise DataError(f"cannot read mesh: {type(exc).__name__}: {str(exc)[:120]}",
                            spec) from None
        if len(getattr(mesh, "faces", [])) == 0:
            raise DataError("mesh has no faces", spec)
        if not np.isfinite(np.asarray(mesh.vertices)).all():
            raise DataError("mesh vertices hold NaN/Inf", spec)
        g = gaussians_from_trimesh(mesh)
        if len(g) == 0:
            raise DataError("mesh has only degenerate (zero-area) faces", spec)
        return g
    return read_gaussians(spec, colour_space=colour_space)
