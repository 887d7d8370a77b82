"""Texel G-buffers of posed hands: what the teacher sees per light and per camera.

For every hand of a posed scene, the texel centres of its N×N UV map
(:class:`relight_cli.render.shading.TexelSurface`) carry a position x, a shading
normal n and a tangent frame R = [t, b, n] built from the UV derivatives of the
fine mesh (t ∥ ∂x/∂u, b ∥ ∂x/∂v, Gram–Schmidt against n).  RelightableHands
expresses light and view directions in each primitive's frame (Eq. 3–4,
``R_kᵀ (l − p) / ‖l − p‖``); on a mesh R_k is the texel's tangent frame (URHand supp.
10.1 re-implements RelightableHands on a mesh the same way), so the inputs do not
change when a finger bends: only the geometry *around* the texel does.

Per light i and texel k the teacher gets:
  * the local light direction R_kᵀ ω_i(x_k) (point light: towards its position;
    directional light: its fixed direction);
  * the binary visibility h_i(x_k): facing the light and no hand of the scene in
    between (embree shadow rays, the renderer's own rule,
    :meth:`~relight_cli.render.shading.HandRenderer.light_visibility`);
  * the irradiance falloff 1/r² (1 for a directional light), applied analytically
    outside the network (see :mod:`relight_cli.neural.models`).
Per camera: the local view direction R_kᵀ (eye − x_k)/‖eye − x_k‖.

Maps are texel-major [K, ...] at the inside texels; :meth:`PoseTexels.to_maps` scatters
them to [..., C, N, N] maps whose outside texels copy their nearest exposed texel,
so the bilinear lookups of rendering never pull in undefined values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def hand_records(hand) -> list:
    """Per hand of ``hand`` (HandData): {"side": its handedness, "uv_chart": digest of the
    fine mesh's UV chart with each face's corners sorted (the same for a hand and its
    mirror image, whose faces only wind the other way)} — what a checkpoint records of the
    hands it learned, so each hand of a scene can find its own model."""
    from relight_cli.hand.scene import handedness
    fine = hand.mesh("fine")
    chart = _digest(fine.uv, np.sort(np.asarray(fine.faces_uv, np.int64), axis=1))
    return [{"side": handedness(hand, inst), "uv_chart": chart} for inst in hand.hands]


def _digest(uv, faces_uv) -> str:
    import hashlib
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(np.asarray(uv, np.float64)).tobytes())
    h.update(np.ascontiguousarray(np.asarray(faces_uv, np.int64)).tobytes())
    return h.hexdigest()[:16]


def uv_layout_digest(mesh) -> str:
    """16-hex fingerprint of a mesh's UV layout (uv, faces_uv): a learned texture only
    means something on the layout it was learned on."""
    return _digest(mesh.uv, mesh.faces_uv)


def uv_layout_digests(mesh) -> tuple:
    """:func:`uv_layout_digest` of ``mesh`` as it is and of its mirror image (each face's
    corners in the other winding): a layout learned on a hand matches its mirror too."""
    faces_uv = np.asarray(mesh.faces_uv, np.int64)
    return _digest(mesh.uv, faces_uv), _digest(mesh.uv, faces_uv[:, [0, 2, 1]])


def uv_tangents(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray,
                faces_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-UV-vertex ∂x/∂u and ∂x/∂v ([T, 3] each, unnormalized, area weighted).

    For a triangle with edges e1, e2 (world) and UV edges (Δu1, Δv1), (Δu2, Δv2):
    ∂x/∂u = (e1 Δv2 − e2 Δv1)/det, ∂x/∂v = (e2 Δu1 − e1 Δu2)/det, det = Δu1 Δv2 − Δu2 Δv1.
    Each face contributes its derivatives times its UV area |det|/2 to its three UV
    corners (faces with det ≈ 0 contribute nothing), so seams in UV keep separate
    frames on either side and tiny slivers do not dominate.
    """
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]       # [F, 3, 3]
    tex = np.asarray(uv, np.float64)[np.asarray(faces_uv, np.int64)]          # [F, 3, 2]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d1, d2 = tex[:, 1] - tex[:, 0], tex[:, 2] - tex[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]                          # [F]
    ok = np.abs(det) > 1e-14
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    du = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * inv[:, None]
    dv = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * inv[:, None]
    weight = 0.5 * np.abs(det) * ok
    n_uv = len(uv)
    out_u = np.zeros((n_uv, 3))
    out_v = np.zeros((n_uv, 3))
    fuv = np.asarray(faces_uv, np.int64)
    for c in range(3):
        np.add.at(out_u, fuv[:, c], du * weight[:, None])
        np.add.at(out_v, fuv[:, c], dv * weight[:, None])
    return out_u, out_v


def tangent_frames(normals: np.ndarray, du: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """Orthonormal frames [K, 3, 3] (rows t, b, n) from normals and UV derivatives.

    t = normalize(∂x/∂u − (∂x/∂u·n) n); b = ±n × t with the sign of (n × t)·∂x/∂v, so a
    mirrored hand (UV layout flipped in the world) gets a left-handed frame and its
    local directions mirror the right hand's.  Where ∂x/∂u vanishes (degenerate UV) t
    is any unit vector perpendicular to n.
    """
    n = np.asarray(normals, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    t = du - np.sum(du * n, 1, keepdims=True) * n
    length = np.linalg.norm(t, axis=1)
    bad = ~(length > 1e-10 * np.maximum(np.linalg.norm(du, axis=1), 1e-300)) | ~(length > 0)
    if bad.any():
        # any perpendicular: cross with the axis least aligned with n
        axis = np.eye(3)[np.argmin(np.abs(n[bad]), axis=1)]
        alt = np.cross(n[bad], axis)
        t[bad] = alt
        length[bad] = np.linalg.norm(alt, axis=1)
    t = t / length[:, None]
    b = np.cross(n, t)
    sign = np.where(np.sum(b * dv, 1) < 0, -1.0, 1.0)
    return np.stack([t, b * sign[:, None], n], axis=1)


def to_local(frames: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """R_kᵀ d: world directions [..., K, 3] in the texels' frames [K, 3, 3] (rows t, b, n)."""
    return np.einsum("kij,...kj->...ki", frames, directions)


@dataclass
class LightInputs:
    """Per-light teacher inputs at one hand's inside texels.

    Attributes:
        local_light: [L, K, 3] float32 unit light directions in the texel frames.
        visibility: [L, K] float32 binary visibility (1: lit, unoccluded).
        falloff: [L, K] float32 1/r² (m⁻²) for point lights, 1 for directional ones.
    """

    local_light: np.ndarray
    visibility: np.ndarray
    falloff: np.ndarray


class PoseTexels:
    """The texel G-buffer of one posed scene (one or more hands).

    Args:
        meshes: posed fine meshes (``PosedMesh``), world space.
        tex_res: N of the N×N UV maps.
        rasters: optional per-mesh UV rasterizations (pose independent; share them).
        shadows: trace visibility (False: h = 1 wherever the texel faces the light).
    """

    def __init__(self, meshes, tex_res: int, rasters=None, shadows: bool = True):
        from relight_cli.render.shading import HandRenderer, RenderSettings

        self.meshes = meshes
        self.tex_res = int(tex_res)
        self.shadows = shadows
        self.scene_index = list(range(len(meshes)))   # hand k is the renderer's hand scene_index[k]
        settings = RenderSettings(tex_res=self.tex_res, aa=1, shadows=shadows, specular=False,
                                  sss=False, direct="texel")
        # The renderer owns texel surfaces, the embree scene, ray offsets and buried texels;
        # no materials are needed for visibility.
        self.renderer = HandRenderer(meshes, [None] * len(meshes), settings, rasters=rasters)
        self.surfaces = self.renderer.surfaces
        self.frames = []
        # [K, 2, 3] ∂x/∂u, ∂x/∂v (metres per UV unit) in each texel's frame: URHand's
        # displacement (Eq. 2) turns into refined normals through them
        self.uv_derivatives = []
        for mesh, surf in zip(meshes, self.surfaces):
            du, dv = uv_tangents(mesh.vertices, mesh.faces, mesh.uv, mesh.faces_uv)
            raster = surf.raster
            du_t = raster.interpolate(du, mesh.faces_uv, fill=None)[surf.inside]
            dv_t = raster.interpolate(dv, mesh.faces_uv, fill=None)[surf.inside]
            self.frames.append(tangent_frames(surf.normals, du_t, dv_t))
            # uv_tangents sums area-weighted derivatives: divide by the summed weights
            tex = np.asarray(mesh.uv, np.float64)[np.asarray(mesh.faces_uv, np.int64)]
            d1, d2 = tex[:, 1] - tex[:, 0], tex[:, 2] - tex[:, 0]
            area = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1])
            total = np.zeros(len(mesh.uv))
            for c in range(3):
                np.add.at(total, np.asarray(mesh.faces_uv, np.int64)[:, c], area)
            w_t = raster.interpolate(total[:, None], mesh.faces_uv, fill=None)[surf.inside]
            mean = np.stack([du_t, dv_t]) / np.maximum(w_t, 1e-30)[None]
            self.uv_derivatives.append(to_local(self.frames[-1], mean)
                                       .transpose(1, 0, 2).astype(np.float32))

    @property
    def n_hands(self) -> int:
        return len(self.meshes)

    def select(self, k: int) -> "PoseTexels":
        """A view of hand k alone (its hand 0), visibility still traced against the whole
        scene: what a model of one hand is given when each hand has its own model."""
        import copy
        view = copy.copy(self)
        for name in ("meshes", "surfaces", "frames", "uv_derivatives", "scene_index"):
            setattr(view, name, [getattr(self, name)[k]])
        return view

    def point_lights(self, k: int, positions: np.ndarray, visibility: bool = True) -> LightInputs:
        """Inputs of point lights at ``positions`` [L, 3] (metres, world) for hand k."""
        surf = self.surfaces[k]
        positions = np.asarray(positions, np.float64).reshape(-1, 3)
        d = positions[:, None, :] - surf.points[None]                          # [L, K, 3]
        r2 = np.sum(d * d, -1)
        l = d / np.sqrt(np.maximum(r2, 1e-300))[..., None]
        vis = (self.renderer.light_visibility(self.scene_index[k], positions=positions)
               if visibility
               else np.einsum("lki,ki->lk", l, surf.normals) > 0)
        return LightInputs(to_local(self.frames[k], l).astype(np.float32),
                           vis.astype(np.float32), (1.0 / np.maximum(r2, 1e-300)).astype(np.float32))

    def directional_lights(self, k: int, directions: np.ndarray,
                           visibility: bool = True) -> LightInputs:
        """Inputs of distant lights arriving from unit ``directions`` [M, 3] for hand k."""
        surf = self.surfaces[k]
        directions = np.asarray(directions, np.float64).reshape(-1, 3)
        K = len(surf.points)
        l = np.broadcast_to(directions[:, None, :], (len(directions), K, 3))
        vis = (self.renderer.light_visibility(self.scene_index[k], directions=directions)
               if visibility
               else (directions @ surf.normals.T) > 0)
        return LightInputs(to_local(self.frames[k], l).astype(np.float32),
                           vis.astype(np.float32), np.ones((len(directions), K), np.float32))

    def local_view(self, k: int, eye) -> np.ndarray:
        """[K, 3] float32 unit directions towards ``eye`` in hand k's texel frames."""
        surf = self.surfaces[k]
        v = np.asarray(eye, np.float64)[None] - surf.points
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)
        return to_local(self.frames[k], v).astype(np.float32)

    def to_maps(self, k: int, values: np.ndarray) -> np.ndarray:
        """Scatter texel-major values to channel-first maps: [K, C] → [C, N, N], [L, K, C]
        → [L, C, N, N].  Texels outside the charts (and buried ones) copy their nearest
        exposed texel."""
        surf = self.surfaces[k]
        values = np.asarray(values)
        single = values.ndim == 2
        if single:
            values = values[None]
        L, K, C = values.shape
        n = surf.inside.shape[0]
        full = np.zeros((n, surf.inside.shape[1], L, C), values.dtype)
        full[surf.inside] = np.transpose(values, (1, 0, 2))
        iy, ix = surf.fill_index
        maps = np.ascontiguousarray(np.transpose(full[iy, ix], (2, 3, 0, 1)))     # [L, C, N, N]
        return maps[0] if single else maps

    def inside(self, k: int) -> np.ndarray:
        """[N, N] bool texels on exposed surface of hand k (where L_neg and T̄ count)."""
        surf = self.surfaces[k]
        return surf.exposed if surf.exposed is not None else surf.inside
