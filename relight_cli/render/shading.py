"""Physically based shading of posed hands: Lambert + GGX, shadows, SSS, one bounce.

Radiance leaving a surface point x towards the camera (linear RGB, W·sr⁻¹·m⁻²
up to the global scale of the light units):

    L_o(x) = albedo(x)/π · E_sss(x) + Σ_lights f_s·(n·l) · I / r² · h + Σ_m L(ω_m) h f_s (n·ω_m) Δω_m

* E(x) = Σ_lights I·max(n·l, 0)·h/r² + Σ_m L(ω_m)·h(ω_m)·max(n·ω_m, 0)·Δω_m (+ one bounce)
  is the diffuse irradiance.  Point lights have radiant intensity I [3] and fall off
  with the inverse square of the distance r (near field).  The env map term is
  bake-features' diffuse feature at the env receivers: the env map is discretized to
  the lat-long grid ``env_res`` with exact texel solid angles, its small bright sources
  (a sun, a lamp) kept apart as distant lights at their own direction and power
  (``env_sources``, :func:`relight_cli.envmap.discretize_env`), and the transport is
  bake-features' :class:`~relight_cli.features.FeatureBaker` on those directions, so a
  render is exactly linear in the discretized env map.
* h is binary visibility from embree shadow rays against every hand of the scene.
* f_s is the GGX lobe of :mod:`relight_cli.brdf` (F0 = 0.04) with the exact Smith G
  (``shadowing="smith"``, what Mitsuba 3 renders: tests/render/test_shading_mitsuba.py)
  or URHand Eq. 15's Schlick remap (``"schlick"``, the learned models' lobe).
* E_sss is E diffused in texture space (d'Eon & Luebke's texture-space diffusion)
  with the sum-of-Gaussians skin profile :data:`SKIN_PROFILE` whose RGB weights sum
  to 1, so uniform irradiance is unchanged (energy conserving) and it is linear.

Where things are computed: diffuse irradiance lives in UV texture space
(``tex_res``², one value per texel centre inside the UV charts), where SSS blurs it
and the bounce gathers it.  With ``direct="pixel"`` (default) point-light shadows are
also traced per G-buffer sample (a ray per sample and light) for the specular lobe,
and, when neither SSS nor bounce is on, for the diffuse term, which is then exact
per sample; ``direct="texel"`` looks everything up from the texel maps,
which are camera independent, so a light-stage frame traces its lights once and
renders every camera from them.  An env map's transport is integrated per texel
(``env_space="texels"``, default: visibility and diffuse transport at the texel centres,
the GGX lobe per sample with that visibility looked up, a pixel's samples sharing one
shading point where their normals agree within :data:`SHARE_SPREAD` of the lobe's width)
or per mesh vertex and interpolated (``"vertices"``: cheaper, shadows jagged and
highlights smeared between vertices).  Texels outside the charts, or buried inside another part, copy their
nearest exposed texel, so bilinear lookups never pull in zeros.

Departures from a path tracer such as Mitsuba 3 (``direct`` integrator), which the
cross-check measures (benchmarks/results/mitsuba.md): the env map's smooth part is
integrated on the ``env_res`` grid (cell centres), SSS and the bounce are
texture-space approximations, and shading is looked up bilinearly from texels.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from relight_cli.uvraster import gather_taps
from relight_cli import features as FE
from relight_cli.brdf import MIN_ROUGHNESS, ggx_cosine
from relight_cli.envmap import DEFAULT_GRID, DiscreteEnv, discretize_env
from relight_cli.formats.lights_json import Lights
from relight_cli.geometry import Receivers, view_directions

# d'Eon & Luebke (GPU Gems 3, ch. 14) six-Gaussian fit of a three-layer skin
# profile: (variance in mm², RGB weights).  Each colour's weights sum to 1.
SKIN_PROFILE = (
    (0.0064, (0.233, 0.455, 0.649)),
    (0.0484, (0.100, 0.336, 0.344)),
    (0.187, (0.118, 0.198, 0.000)),
    (0.567, (0.113, 0.007, 0.007)),
    (1.99, (0.358, 0.004, 0.000)),
    (7.41, (0.078, 0.000, 0.000)),
)
# Gaussians narrower than this (in texels) are below the texture's resolution:
# they are applied as the identity (their weight stays, nothing is blurred).
_MIN_SIGMA_TEXELS = 0.25
# Lights per block in per-sample specular ([samples, lights, 3] float64 arrays).
_LIGHT_BLOCK = 16
# A pixel's samples share one shading point for texture-space lobes when their normals lie
# within SHARE_SPREAD × the lobe's width α = ρ² of their mean (HandRenderer._shading_points):
# the box-filtered lobe then moves by ~(SHARE_SPREAD)²/2 of its peak at most.
SHARE_SPREAD = 0.1


@dataclass
class RenderSettings:
    """How to render.

    Attributes:
        tex_res: N of the N×N texture-space lighting maps.
        aa: sub-pixel grid (aa² stratified samples per pixel).
        jitter: jitter samples inside their sub-cells (seeded by ``seed``).
        seed: random seed (jitter only; everything else is deterministic).
        shadows: trace shadow rays (False: h ≡ 1).
        specular: add the GGX lobe.
        sss: texture-space subsurface scattering with :data:`SKIN_PROFILE`.
        sss_scale: multiply the profile's widths (1 = measured skin).
        env_res: (H, W) lat-long grid of env-map integration (bake-features' --env-res).
        bounce: add one bounce of diffuse interreflection between hand surfaces.
        bounce_res: (H, W) direction grid gathering the bounce.
        direct: where point-light shadows are evaluated: "pixel" (exact, a shadow ray per
            G-buffer sample and light, for the specular lobe, and for the diffuse term too
            when neither SSS nor bounce needs texture space) or "texel" (looked up from
            the texture-space maps: camera independent, so a light-stage frame traces
            its lights once).
        env_space: where env-map transport is integrated: "texels" (default: diffuse
            transport, visibility and the GGX lobe towards the eye at the texel centres,
            looked up bilinearly; every direction is shaded as a far point light is with
            ``direct="texel"``, so the render is their sum) or "vertices" of the rendered
            mesh (bake-features' receivers, interpolated to texels: faster, but shadows and
            highlights come out jagged and smeared between vertices).
        env_sources: bright sources (a sun, a lamp) taken out of an env map before it is
            put on the ``env_res`` grid and kept as distant lights at their own direction
            and power (:func:`relight_cli.envmap.discretize_env`): ``"auto"`` or 0 (off).
        shadowing: the GGX lobe's G, ``"smith"`` (exact) or ``"schlick"`` (URHand Eq. 15's
            remap), :mod:`relight_cli.brdf`.
        ray_offset: metres to lift shadow-ray origins; None = 1e-4 × the mesh's diagonal.
    """

    tex_res: int = 256
    aa: int = 2
    jitter: bool = False
    seed: int = 0
    shadows: bool = True
    specular: bool = True
    sss: bool = True
    sss_scale: float = 1.0
    env_res: tuple = DEFAULT_GRID
    bounce: bool = False
    bounce_res: tuple = (8, 16)
    env_space: str = "texels"
    env_sources: object = "auto"
    shadowing: str = "smith"
    direct: str = "pixel"
    ray_offset: float | None = None


@dataclass
class TexelSurface:
    """The texel centres of one posed hand: where texture-space lighting is computed.

    Attributes:
        raster: the UV rasterization (``relight_cli.uvraster.UVRaster``), pose independent.
        inside: [N, N] bool texel centre lies on the surface.
        points: [K, 3] float64 world positions of the inside texels (row-major order).
        normals: [K, 3] float64 unit shading normals there.
        face_normals: [K, 3] float64 unit geometric normals of the triangles under them.
        uv: [K, 2] float64 texel-centre UVs.
        fill_index: ([N, N], [N, N]) row/col of the nearest *exposed* texel of every texel.
        metres_per_uv: world length of one UV unit (√(surface area / UV area)).
        exposed: [N, N] bool inside texels not buried inside another part of the
            scene (the built-in hand's finger tubes start inside the palm); only these
            feed subsurface scattering and lookups (see :meth:`HandRenderer.__init__`).
    """

    raster: object
    inside: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    face_normals: np.ndarray
    uv: np.ndarray
    fill_index: tuple
    metres_per_uv: float
    exposed: np.ndarray | None = None

    def set_buried(self, buried: np.ndarray) -> None:
        """Mark inside texels [K] as buried: lookups and SSS then ignore them."""
        self.exposed = self.inside.copy()
        self.exposed[self.inside] = ~np.asarray(buried, bool)
        self.fill_index = _raster_fill_index(self.exposed if self.exposed.any() else self.inside)

    def to_map(self, values: np.ndarray) -> np.ndarray:
        """Scatter [K, C] inside-texel values to an [N, N, C] map; texels outside the
        charts (or buried) copy their nearest exposed texel, so bilinear lookups near
        chart edges and part intersections stay on the visible surface."""
        values = np.asarray(values)
        n = self.inside.shape[0]
        out = np.zeros((n, self.inside.shape[1]) + values.shape[1:], values.dtype)
        out[self.inside] = values
        iy, ix = self.fill_index
        return out[iy, ix]


def _raster_fill_index(inside: np.ndarray):
    from scipy.ndimage import distance_transform_edt
    if not inside.any():
        return np.indices(inside.shape)
    _, (iy, ix) = distance_transform_edt(~inside, return_indices=True)
    return iy, ix


def texel_surface(mesh, resolution: int, raster=None) -> TexelSurface:
    """The texel centres of a posed mesh (``PosedMesh``) on an N×N UV grid."""
    from relight_cli.uvraster import rasterize_uv, texel_centers

    if raster is None:
        raster = rasterize_uv(mesh.uv, mesh.faces_uv, resolution)
    inside = raster.inside
    points = raster.interpolate(np.asarray(mesh.vertices, np.float64), mesh.faces, fill=None)[inside]
    normals = raster.interpolate(np.asarray(mesh.normals, np.float64), mesh.faces, fill=None)[inside]
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    uv = texel_centers(*inside.shape)[inside]
    tri = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    face_n /= np.maximum(np.linalg.norm(face_n, axis=1, keepdims=True), 1e-300)
    area3 = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    t = np.asarray(mesh.uv, np.float64)[np.asarray(mesh.faces_uv)]
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    area2 = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    scale = math.sqrt(area3 / area2) if area2 > 0 else 1.0
    return TexelSurface(raster, inside, points, normals, face_n[raster.face[inside]], uv,
                        _raster_fill_index(inside), scale)


def sss_diffuse(irradiance_map: np.ndarray, inside: np.ndarray, texel_mm: float,
                scale: float = 1.0, profile=SKIN_PROFILE) -> np.ndarray:
    """Texture-space diffusion of irradiance with a sum-of-Gaussians profile.

    E_sss = Σ_k w_k · (G_σk ⊛ (E·m)) / (G_σk ⊛ m), m the chart mask: a normalized
    convolution, so uniform irradiance stays uniform (energy conserving away from
    chart borders too) and texels outside the charts never pull values in.  It is
    linear in E.

    Args:
        irradiance_map: [N, N, 3] float64, valid where ``inside``.
        inside: [N, N] bool.
        texel_mm: the size of one texel on the surface, millimetres.
        scale: multiplies every Gaussian's standard deviation.
        profile: ((variance mm², (wR, wG, wB)), ...).

    Returns:
        [N, N, 3] float64 (inside texels; outside ones are 0).
    """
    from scipy.ndimage import gaussian_filter

    mask = inside.astype(np.float64)
    out = np.zeros_like(irradiance_map, dtype=np.float64)
    masked = irradiance_map * mask[..., None]
    for variance, weights in profile:
        sigma = math.sqrt(variance) * scale / texel_mm                  # texels
        weights = np.asarray(weights, np.float64)
        if not weights.any():
            continue
        if sigma < _MIN_SIGMA_TEXELS:
            out += masked * weights
            continue
        norm = gaussian_filter(mask, sigma, mode="constant", truncate=3.0)
        for c in range(3):
            if weights[c] == 0:
                continue
            blurred = gaussian_filter(masked[..., c], sigma, mode="constant", truncate=3.0)
            out[..., c] += weights[c] * np.divide(blurred, norm, out=np.zeros_like(blurred),
                                                  where=norm > 1e-12)
    return out * mask[..., None]


@dataclass
class Lighting:
    """Camera-independent lighting of a posed scene (one entry per hand).

    Attributes:
        irradiance: per hand [N, N, 3] float64 diffuse irradiance after SSS (filled).
        direct: per hand [K, 3] irradiance at the inside texels before SSS and bounce.
        visibility: per hand [N, N, L] float32 point-light visibility (filled), or None.
        point_maps: per hand [N, N, 3] point-light direct irradiance before SSS/bounce
            (filled), or None; ``direct="pixel"`` rendering swaps it for exact per-sample
            irradiance and keeps only the SSS/bounce difference from texture space.
        lights: the point lights (``formats.lights_json.Lights``) or None.
        env: the discretized env map (``envmap.DiscreteEnv``) or None.
        stats: seconds per stage and rays traced.
    """

    irradiance: list
    direct: list
    visibility: list | None
    lights: Lights | None
    env: object | None
    stats: dict = field(default_factory=dict)
    point_maps: list | None = None


@dataclass
class RenderResult:
    """A rendered view.

    Attributes:
        image: [H, W, 3] float32 linear radiance (background where no hand).
        mask: [H, W] float32 pixel coverage.
        normal, uv, depth: (properties) [H, W, 3] / [H, W, 2] / [H, W] float32 AOVs, the
            mean over a pixel's samples that hit.
        gbuffer: the :class:`~relight_cli.render.gbuffer.GBuffer`.
        samples: [P, 3] float64 per-sample radiance (before the pixel filter).
        stats: seconds per stage.
    """

    image: np.ndarray
    mask: np.ndarray
    gbuffer: object
    samples: np.ndarray
    stats: dict = field(default_factory=dict)

    @property
    def normal(self) -> np.ndarray:
        return self.gbuffer.average_hits(self.gbuffer.normal).astype(np.float32)

    @property
    def uv(self) -> np.ndarray:
        return self.gbuffer.average_hits(self.gbuffer.uv).astype(np.float32)

    @property
    def depth(self) -> np.ndarray:
        gb = self.gbuffer
        return gb.average_hits(np.where(gb.hit, gb.depth, 0.0)).astype(np.float32)


class HandRenderer:
    """Renders one pose of one or more hands (set up once, light and render many times).

    Args:
        meshes: posed meshes (``PosedMesh``: vertices, faces, uv, faces_uv, normals).
        materials: one :class:`Material` per mesh.
        settings: :class:`RenderSettings`.
        rasters: optional UV rasterizations per mesh (pose independent: reuse them
            across frames; see :func:`relight_cli.uvraster.rasterize_uv`).
    """

    def __init__(self, meshes, materials, settings: RenderSettings | None = None, rasters=None):
        from relight_cli.geometry import scene_diagonal
        from relight_cli.raytrace import RayScene

        self.settings = settings or RenderSettings()
        if len(materials) != len(meshes):
            raise ValueError("give one material per mesh")
        self.meshes = meshes
        self.materials = materials
        self.stats = {}
        t0 = time.perf_counter()
        rasters = rasters or [None] * len(meshes)
        self.surfaces = [texel_surface(m, self.settings.tex_res, r) for m, r in zip(meshes, rasters)]
        self.stats["texels"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        self.scene = RayScene([(m.vertices, m.faces) for m in meshes])
        # Build the BVH now (embree builds on first query) so timings separate it.
        self.scene.occluded(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
        self.stats["scene"] = time.perf_counter() - t0
        offset = self.settings.ray_offset
        self.offsets = [offset if offset is not None
                        else 1e-4 * scene_diagonal([(m.vertices, m.faces)]) for m in meshes]
        self._bakers = {}
        t0 = time.perf_counter()
        self._mark_buried()
        self.stats["buried"] = time.perf_counter() - t0

    def _layout(self, k: int):
        """Hand k's UV layout (:class:`relight_cli.uvraster.UVLayout`), whose charts the
        seam-aware lookups of its maps respect."""
        from relight_cli.uvraster import UVLayout
        return UVLayout.of(self.meshes[k].uv, self.meshes[k].faces_uv)

    def _mark_buried(self):
        """Find texels inside another closed part (e.g. a finger tube's root inside the
        palm): a ray along the normal that first meets a surface from its back side
        (geometric normal along the ray) starts inside a volume.  Such texels are dark
        (everything occludes them) and invisible; without this their darkness would
        bleed through bilinear lookups and SSS into the visible seam."""
        normals = []
        for m in self.meshes:
            tri = np.asarray(m.vertices, np.float64)[np.asarray(m.faces)]
            fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            normals.append(fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300))
        face_normals = np.concatenate(normals) if normals else np.zeros((0, 3))
        for k, surf in enumerate(self.surfaces):
            if not len(surf.points):
                surf.set_buried(np.zeros(0, bool))
                continue
            hits = self.scene.intersect(surf.points + self.offsets[k] * surf.normals, surf.normals)
            back = np.zeros(len(surf.points), bool)
            ok = hits.hit
            back[ok] = np.einsum("ij,ij->i", face_normals[hits.face[ok]], surf.normals[ok]) > 0
            surf.set_buried(back)

    # ---------------------------------------------------------------- lighting

    def _light_ray(self, x, n, origins, position, k: int):
        """Towards one point light from points x [P, 3] with normals n: unit directions
        l [P, 3], n·l [P], squared distance r² [P] and visibility h [P] bool (facing the
        light and, with shadows on, nothing of the scene in between)."""
        d = position[None] - x
        r2 = np.einsum("ij,ij->i", d, d)
        r = np.sqrt(r2)
        l = d / np.maximum(r, 1e-12)[:, None]
        cos = np.einsum("ij,ij->i", n, l)
        h = cos > 0
        if self.settings.shadows and h.any():
            idx = np.nonzero(h)[0]
            # Stop at the light: a shadow is cast by what lies between, not beyond.
            h[idx[self.scene.occluded(origins[idx], l[idx], r[idx] - self.offsets[k])]] = False
        return l, cos, r2, h

    def light_visibility(self, k: int, positions=None, directions=None) -> np.ndarray:
        """[L, K] bool visibility of hand k's inside texels: facing the light and (with
        shadows on) nothing of the scene in between — the renderer's own shadow rule.

        Args:
            positions: [L, 3] point lights (rays stop at the light), or
            directions: [L, 3] unit directions towards distant lights (infinite rays).
        """
        surf = self.surfaces[k]
        x, n = surf.points, surf.normals
        origins = x + self.offsets[k] * n
        if (positions is None) == (directions is None):
            raise ValueError("give positions or directions")
        if positions is not None:
            positions = np.asarray(positions, np.float64).reshape(-1, 3)
            out = np.zeros((len(positions), len(x)), bool)
            for j in range(len(positions)):
                out[j] = self._light_ray(x, n, origins, positions[j], k)[3]
            return out
        directions = np.asarray(directions, np.float64).reshape(-1, 3)
        out = (directions @ n.T) > 0                                          # [L, K] facing
        if self.settings.shadows and out.any():
            jj, ii = np.nonzero(out)
            blocked = self.scene.occluded(origins[ii], directions[jj])
            out[jj[blocked], ii[blocked]] = False
        return out

    def _point_irradiance(self, k: int, lights: Lights):
        """Irradiance [K, 3] and visibility [K, L] of hand k's texels from point lights."""
        intensity = lights.radiant_intensity()                                  # [L, 3]
        surf = self.surfaces[k]
        x, n = surf.points, surf.normals
        irr = np.zeros((len(x), 3))
        vis = np.zeros((len(x), len(lights)), np.float32)
        origins = x + self.offsets[k] * n
        for j in range(len(lights)):
            l, cos, r2, h = self._light_ray(x, n, origins, lights.positions[j], k)
            vis[:, j] = h
            irr += (h * np.clip(cos, 0, None) / np.maximum(r2, 1e-300))[:, None] * intensity[j]
        return irr, vis

    def _env_baker(self, env):
        """Bake-features' :class:`~relight_cli.features.FeatureBaker` (diffuse only) on
        ``env_space``'s receivers (mesh vertices or texel centres) for ``env``'s directions,
        made once per renderer and direction set: its visibility cache then holds every
        (receiver, lit direction) pair facing each other, which the GGX lobe reuses."""
        key = env.directions.tobytes()
        if key not in self._bakers:
            receivers = None
            if self.settings.env_space == "texels":
                receivers = [Receivers(s.points, s.normals, np.ones(len(s.points), bool))
                             for s in self.surfaces]
            fs = FE.FeatureSettings(shininess=(), specular="none",
                                    visibility=self.settings.shadows,
                                    ray_offset=self.settings.ray_offset)
            self._bakers[key] = FE.FeatureBaker(
                [FE.PoseMesh(m.vertices, m.faces, m.normals) for m in self.meshes], fs,
                grid=env, receivers=receivers, scene=self.scene)
        return self._bakers[key]

    def _env_diffuse(self, env) -> list:
        """Per hand [K, 3] env irradiance Σ_m L h max(n·ω, 0) Δω at the inside texels
        (bake-features' diffuse feature at the receivers, interpolated from vertices)."""
        baker = self._env_baker(env)
        per_mesh = baker.bake([env], np.zeros(3))[0]
        out = []
        for k, surf in enumerate(self.surfaces):
            value = per_mesh[k]["diffuse"]
            if self.settings.env_space == "vertices":
                value = surf.raster.interpolate(value, self.meshes[k].faces, fill=None)[surf.inside]
            out.append(value)
        return out

    def _env_specular(self, k: int, env, points, normals, roughness, visibility) -> np.ndarray:
        """[P, 3] GGX radiance Σ_m L h f_s max(n·ω, 0) Δω of ``env`` at hand k's shading
        points: ``points`` = (positions [P, 3], unit views towards the eye [P, 3]),
        ``normals`` [P, 3], ``roughness`` [P]; ``visibility(r)`` gives the points ``r`` (a
        slice)'s [b, M'] visibility towards ``env``'s lit directions (0 where a pair was
        never traced: facing away or unlit).  The lobe is
        :func:`relight_cli.features.ggx_weights` on blocks of points × lit directions,
        spread over the tracing thread pool."""
        from relight_cli.visibility import thread_pool, trace_threads

        positions, view = points
        lit = np.nonzero(env.lit)[0]
        out = np.zeros((len(positions), 3))
        if not len(positions) or not len(lit):
            return out
        dirs = env.directions[lit]
        weighted = env.radiance[lit] * env.solid_angle[lit, None]                # [M', 3]
        rough = np.broadcast_to(np.asarray(roughness, np.float64), (len(positions),))
        f0, shadowing = self.materials[k].f0, self.settings.shadowing
        # blocks of ~2 MiB of float64 weights, each product summed without BLAS (its
        # threads would compete with the pool's: see geometry.dot3)
        step = max(1, (1 << 18) // len(lit))

        def block(start):
            r = slice(start, min(len(positions), start + step))
            vis = visibility(r)
            # only the directions some point of the block sees (points come in screen
            # tiles, so a block's normals are alike and it faces about half the sphere)
            cols = np.flatnonzero(vis.any(0))
            # float64: in float32 the peak's 1 − (n·h)² loses 1.4 % of the lobe at ρ 0.1
            # (0.04 % at 0.45), measured
            w = FE.ggx_weights(normals[r], view[r], dirs[cols], rough[r], f0, shadowing)
            w *= vis[:, cols]
            out[r] = np.einsum("pm,mc->pc", w, weighted[cols])

        starts = range(0, len(positions), step)
        workers = trace_threads()
        if workers > 1 and len(starts) > 1:
            list(thread_pool(workers).map(block, starts))
        else:
            for start in starts:
                block(start)
        return out

    def discretize(self, env):
        """An EnvMap (or DiscreteEnv) on bake-features' ``env_res`` grid, bright sources
        kept apart per ``env_sources``."""
        if isinstance(env, DiscreteEnv):
            return env
        return discretize_env(env, *self.settings.env_res, sources=self.settings.env_sources)

    def light(self, lights: Lights | None = None, env=None) -> Lighting:
        """Camera-independent lighting: irradiance maps (SSS applied) and visibility.

        Args:
            lights: point lights (``formats.lights_json.Lights``: positions and
                :meth:`~Lights.radiant_intensity`), or None.
            env: an ``EnvMap`` (discretized to ``env_res``) or a ``envmap.DiscreteEnv``, or None.
        """
        stats = {}
        t0 = time.perf_counter()
        denv = None if env is None else self.discretize(env)
        has_lights = lights is not None and len(lights) > 0
        direct = []
        vis_maps = [] if has_lights else None
        point_maps = [] if has_lights else None
        env_diffuse = None if denv is None else self._env_diffuse(denv)
        for k, surf in enumerate(self.surfaces):
            irr = np.zeros((len(surf.points), 3))
            if has_lights:
                e, vis = self._point_irradiance(k, lights)
                irr += e
                vis_maps.append(surf.to_map(vis))
                point_maps.append(surf.to_map(e))
            if denv is not None:
                irr += env_diffuse[k]
            direct.append(irr)
        stats["direct"] = time.perf_counter() - t0
        total = [d.copy() for d in direct]
        if self.settings.bounce:
            t0 = time.perf_counter()
            for k, extra in enumerate(self._bounce(direct)):
                total[k] += extra
            stats["bounce"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        maps = []
        for k, surf in enumerate(self.surfaces):
            emap = np.zeros(surf.inside.shape + (3,))
            emap[surf.inside] = total[k]
            if self.settings.sss:
                texel_mm = 1000.0 * surf.metres_per_uv / surf.inside.shape[0]
                emap = sss_diffuse(emap, surf.exposed, texel_mm, self.settings.sss_scale)
            maps.append(surf.to_map(emap[surf.inside]))
        stats["sss" if self.settings.sss else "maps"] = time.perf_counter() - t0
        return Lighting(maps, direct, vis_maps, lights, denv, stats, point_maps)

    def _bounce(self, direct):
        """One bounce of diffuse interreflection: [K, 3] extra irradiance per hand.

        From each texel, rays along the ``bounce_res`` lat-long directions above its
        tangent planes find other hand surface; the radiance arriving from there is
        the first-bounce diffuse exitance albedo/π · E_direct at the hit.
        """
        from relight_cli import envmap as E

        h, w = self.settings.bounce_res
        dirs = E.latlong_directions(h, w).reshape(-1, 3)
        omega = np.asarray(E.latlong_solid_angles(h, w)).reshape(-1)
        # Direct irradiance maps; the albedo is applied at each hit's own UV.
        irradiance = [surf.to_map(direct[k]) for k, surf in enumerate(self.surfaces)]
        out = []
        for k, surf in enumerate(self.surfaces):
            cos = surf.normals @ dirs.T                                   # [K, M]
            # Only directions above both the shading and the geometric tangent plane:
            # below the triangle's own plane a ray would find the texel's neighbours
            # (a tessellation artefact, not interreflection), so convex shapes get none.
            ii, mm = np.nonzero((cos > 0) & (surf.face_normals @ dirs.T > 0))
            origins = surf.points[ii] + self.offsets[k] * surf.normals[ii]
            hits = self.scene.intersect(origins, dirs[mm])
            gathered = np.zeros((len(ii), 3))
            ok = hits.hit
            if ok.any():
                offsets = np.asarray(self.scene.face_offsets, np.int64)
                for j, mesh in enumerate(self.meshes):
                    sel = ok & (hits.mesh == j)
                    if not sel.any():
                        continue
                    f = hits.face[sel] - offsets[j]
                    b = hits.barycentric[sel].astype(np.float64)
                    uv = np.einsum("kc,kcd->kd", b, np.asarray(mesh.uv)[np.asarray(mesh.faces_uv)[f]])
                    gathered[sel] = (self.materials[j].albedo_at(uv) / math.pi
                                     * gather_taps(irradiance[j], self._layout(j).taps(
                                         uv, f, *irradiance[j].shape[:2])))
            contrib = gathered * (cos[ii, mm] * omega[mm])[:, None]
            extra = np.zeros((len(surf.points), 3))
            np.add.at(extra, ii, contrib)
            out.append(extra)
        return out

    # ---------------------------------------------------------------- render

    def render(self, camera, lighting: Lighting, background=(0.0, 0.0, 0.0),
               gbuffer=None) -> RenderResult:
        """Render ``camera``'s view under ``lighting`` (from :meth:`light`)."""
        from .gbuffer import render_gbuffer

        s = self.settings
        stats = {}
        t0 = time.perf_counter()
        gb = gbuffer if gbuffer is not None else render_gbuffer(
            self.meshes, camera, s.aa, s.jitter, s.seed, scene=self.scene)
        stats["gbuffer"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        radiance = np.zeros((len(gb.hand), 3))
        for k, mat in enumerate(self.materials):
            sel = np.nonzero(gb.hand == k)[0]
            if not len(sel):
                continue
            irradiance = gb.lookup(lighting.irradiance[k], k)      # seam-aware, as every map
            has_lights = lighting.lights is not None and len(lighting.lights) > 0
            spec = np.zeros((len(sel), 3))
            specular = s.specular and mat.specular > 0
            rough = gb.lookup(mat.roughness, k) if specular else None
            if has_lights and s.direct == "pixel":
                exact, point_spec = self._point_samples(gb, sel, lighting.lights, k, rough,
                                                        mat.f0)
                if specular:
                    spec += point_spec
                if not (s.sss or s.bounce):
                    # Swap the texture-space point-light irradiance for the exact one.  (With
                    # SSS or bounce the diffuse irradiance stays in texture space: adding
                    # their texture-space difference to exact irradiance goes negative where
                    # texel and pixel shadows disagree.)
                    irradiance += exact - gb.lookup(lighting.point_maps[k], k)
            radiance[sel] = gb.lookup(mat.albedo, k) / math.pi * irradiance
            if specular:
                if has_lights and s.direct != "pixel":
                    spec += self._point_specular(gb, sel, rough, mat.f0, lighting, k)
                if lighting.env is not None:
                    spec += self._env_texture_specular(k, lighting.env, gb, sel)
                radiance[sel] += mat.specular * spec
        stats["shade"] = time.perf_counter() - t0
        image = gb.resolve(radiance, background).astype(np.float32)
        return RenderResult(image, gb.mask, gb, radiance, stats)

    def _point_samples(self, gb, sel, lights: Lights, k: int, rough=None, f0=0.04):
        """Exact point-light irradiance [S, 3] at G-buffer samples ``sel`` of hand k (one
        shadow ray per sample and light facing it) and, given ``rough`` [S], the GGX
        radiance [S, 3] with the same rays (else None)."""
        x, n, v = gb.position[sel], gb.normal[sel], gb.view[sel]
        intensity = lights.radiant_intensity()                                  # [L, 3]
        irr = np.zeros((len(sel), 3))
        spec = None if rough is None else np.zeros((len(sel), 3))
        origins = x + self.offsets[k] * n
        for j in range(len(lights)):
            l, cos, r2, h = self._light_ray(x, n, origins, lights.positions[j], k)
            falloff = h / np.maximum(r2, 1e-300)                            # [S] h / r²
            irr += (falloff * np.clip(cos, 0, None))[:, None] * intensity[j]
            if spec is not None:
                spec += (ggx_cosine(n, v, l, rough, f0, self.settings.shadowing)
                         * falloff)[:, None] * intensity[j]
        return irr, spec

    def _env_texture_specular(self, k: int, env, gb, sel) -> np.ndarray:
        """[len(sel), 3] GGX radiance of an env map towards the eye at hand k's G-buffer
        samples ``sel``, with the visibility traced in texture space.

        ``env_space="texels"``: the lobe is evaluated at the shading points of
        :meth:`_shading_points` (a pixel's samples share one where they see one smooth
        patch, else each sample has its own), with each direction's texel visibility looked
        up bilinearly, as a ``direct="texel"`` LED is shaded per sample, so a far LED renders
        as the env map's direction it stands for (tests/render/test_capture.py).
        (Evaluating the lobe per texel and interpolating it instead loses sharp highlights:
        22 % RMS on the fist's specular at ρ = 0.45, tex 256, against per sample; so only
        visibility is interpolated.)  ``env_space="vertices"``: the lobe at every vertex,
        interpolated to texels (the fast, documented approximation)."""
        surf = self.surfaces[k]
        mat = self.materials[k]
        baker = self._env_baker(env)
        lit = np.nonzero(env.lit)[0]
        if self.settings.env_space == "texels":
            index, position, normal, puv, pface = self._shading_points(gb, sel, k, mat)
            lookup = _TexelLookup(surf, puv, self._layout(k), pface)
            visible = lookup.rows_of(baker.cache.visible[baker.slices[k]], lit)
            spec = self._env_specular(k, env, (position, view_directions(position, gb.eye)),
                                      normal, mat.roughness_at(puv),
                                      lambda r: lookup.matrix[r] @ visible)
            return spec[index]
        mesh = self.meshes[k]
        uv_of_vertex = np.zeros((len(mesh.vertices), 2))
        uv_of_vertex[np.asarray(mesh.faces).ravel()] = np.asarray(mesh.uv)[
            np.asarray(mesh.faces_uv).ravel()]
        sl = baker.slices[k]
        points = baker.receivers.points[sl]
        visible = baker.cache.visible[sl][:, lit]
        spec = self._env_specular(k, env, (points, view_directions(points, gb.eye)),
                                  baker.receivers.normals[sl], mat.roughness_at(uv_of_vertex),
                                  lambda r: visible[r])
        spec = surf.raster.interpolate(spec, mesh.faces, fill=None)[surf.inside]
        return gb.lookup(surf.to_map(spec), k)

    def _shading_points(self, gb, sel, k: int, mat):
        """Where hand k's texture-space lobes are evaluated for the samples ``sel``:
        (index [len(sel)] → point, positions [P, 3], unit normals [P, 3], uv [P, 2],
        triangles [P]).

        A pixel whose samples all hit hand k on one smooth patch (shading normals within a
        fraction :data:`SHARE_SPREAD` of the lobe's width α = ρ²
        of their mean, uv within half a texel of the
        lighting maps) is shaded once, at its samples' mean, as multisampling does: the
        lobe's change across the pixel is then second order, and the work per pixel drops
        aa²-fold (4× at the default aa 2).  Other samples are shaded each on its own."""
        spp = gb.spp
        pixel = sel // spp
        count = np.bincount(pixel, minlength=gb.width * gb.height)
        whole = np.nonzero(count[pixel] == spp)[0].reshape(-1, spp)     # positions in sel
        groups = sel[whole]                                               # [G, spp]
        shared = np.zeros(len(groups), bool)
        mean_n = np.zeros((len(groups), 3))
        if len(groups) and spp > 1:
            n = gb.normal[groups]                                         # [G, spp, 3]
            mean_n = n.sum(1)
            mean_n /= np.maximum(np.linalg.norm(mean_n, axis=1, keepdims=True), 1e-300)
            uvs = gb.uv[groups]
            mean_uv = uvs.mean(1)
            rho = np.clip(mat.roughness_at(mean_uv), MIN_ROUGHNESS, 1.0)
            spread = np.einsum("gsk,gk->gs", n, mean_n).min(1)
            shared = ((spread > np.cos(SHARE_SPREAD * rho * rho))
                      & (np.abs(uvs - mean_uv[:, None]).max((1, 2))
                         < 0.5 / self.settings.tex_res))
        own = np.ones(len(sel), bool)
        own[whole[shared].ravel()] = False
        own_at = np.nonzero(own)[0]
        n_shared = int(shared.sum())
        index = np.empty(len(sel), np.int64)
        index[own_at] = n_shared + np.arange(len(own_at))
        index[whole[shared]] = np.arange(n_shared)[:, None]
        g = groups[shared]
        position = np.concatenate([gb.position[g].mean(1), gb.position[sel[own_at]]])
        normal = np.concatenate([mean_n[shared], gb.normal[sel[own_at]]])
        uv = np.concatenate([gb.uv[g].mean(1), gb.uv[sel[own_at]]])
        face = np.concatenate([gb.face[g[:, 0]], gb.face[sel[own_at]]])
        # points in 8×8-pixel screen tiles: neighbours in the arrays see alike
        pix = np.concatenate([g[:, 0], sel[own_at]]) // spp
        tile = (pix // gb.width // 8) * (gb.width // 8 + 1) + (pix % gb.width) // 8
        order = np.argsort(tile, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        return rank[index], position[order], normal[order], uv[order], face[order]

    def _point_specular(self, gb, sel, rough, f0, lighting, k):
        """[len(sel), 3] GGX radiance of point lights at the samples ``sel`` of hand k,
        visibility looked up in the texel maps (``direct="texel"``)."""
        lights = lighting.lights
        intensity = lights.radiant_intensity()                                  # [L, 3]
        x, n, v = gb.position[sel], gb.normal[sel], gb.view[sel]
        vis = gb.lookup(lighting.visibility[k].reshape(*lighting.visibility[k].shape[:2], -1),
                        k).reshape(len(sel), len(lights))                    # [S, L]
        out = np.zeros((len(sel), 3))
        for start in range(0, len(lights), _LIGHT_BLOCK):
            stop = min(len(lights), start + _LIGHT_BLOCK)
            d = lights.positions[None, start:stop] - x[:, None]             # [S, B, 3]
            r2 = np.einsum("sbk,sbk->sb", d, d)
            l = d / np.sqrt(np.maximum(r2, 1e-300))[..., None]
            w = ggx_cosine(n[:, None], v[:, None], l, rough[:, None], f0, self.settings.shadowing)
            w = w * vis[:, start:stop] / np.maximum(r2, 1e-300)
            out += w @ intensity[start:stop]
        return out


class _TexelLookup:
    """The seam-aware bilinear lookup of a texel map at ``uv`` (samples on triangles
    ``faces`` of ``layout``: :func:`relight_cli.uvraster.seam_taps`) as a sparse matrix
    over one hand's inside texels (through the map's fill of outside and buried texels),
    so per-texel rows [K, M] are looked up for M directions by one product."""

    def __init__(self, surf: "TexelSurface", uv, layout, faces):
        from scipy import sparse
        h, w = surf.inside.shape
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        rows, cols, weights = layout.taps(uv, faces, h, w)
        iy, ix = surf.fill_index
        row_of = np.cumsum(surf.inside.ravel()) - 1                  # inside texel → row
        texel = row_of[iy[rows, cols] * w + ix[rows, cols]]          # [S, 4]
        self.rows, local = np.unique(texel.T.ravel(), return_inverse=True)  # texels read
        points = np.tile(np.arange(len(uv)), 4)
        self.matrix = sparse.csr_matrix((weights.T.ravel().astype(np.float32),
                                         (points, local)), shape=(len(uv), len(self.rows)))

    def rows_of(self, per_texel: np.ndarray, columns) -> np.ndarray:
        """float32 [R, len(columns)]: the texels read, of a per-texel [K, M] array."""
        return per_texel[self.rows][:, columns].astype(np.float32)


# ---------------------------------------------------------------- torch path


def lookup_torch(texture, gbuffer, hand: int = 0):
    """Differentiable texture lookup at the G-buffer's samples of one hand.

    Args:
        texture: [N, N, C] torch tensor (UV map of hand ``hand``).
        gbuffer: :class:`~relight_cli.render.gbuffer.GBuffer`.
        hand: which hand's samples.

    Returns:
        [P, C] tensor: the seam-aware bilinear samples of :meth:`GBuffer.taps
        <relight_cli.render.gbuffer.GBuffer.taps>` (the numpy path's
        :meth:`~relight_cli.render.gbuffer.GBuffer.lookup`; plain bilinear, as
        ``grid_sample`` with align_corners=False and border padding, for a G-buffer
        without UV layouts) at the samples of ``hand``, 0 elsewhere.
    """
    import torch

    samples, rows, cols, weights = gbuffer.taps(hand, texture.shape[0], texture.shape[1])
    device = texture.device
    r = torch.as_tensor(rows, device=device)
    c = torch.as_tensor(cols, device=device)
    w = torch.as_tensor(weights, dtype=texture.dtype, device=device)
    values = (texture[r, c] * w[..., None]).sum(1)                           # [S, C]
    out = texture.new_zeros((len(gbuffer.hand), texture.shape[2]))
    return out.index_copy(0, torch.as_tensor(samples, device=device), values)


def resolve_torch(samples, gbuffer, background=0.0):
    """Box-filter per-sample values [P, C] to [H, W, C] (background where samples miss)."""
    import torch

    hit = torch.as_tensor(gbuffer.hit, device=samples.device)[:, None]
    bg = torch.as_tensor(background, dtype=samples.dtype, device=samples.device).reshape(1, -1)
    values = torch.where(hit, samples, bg.expand_as(samples))
    return values.reshape(gbuffer.height, gbuffer.width, gbuffer.spp, -1).mean(2)


def diffuse_image_torch(albedo_textures, irradiance_textures, gbuffer, specular=None,
                        background=0.0):
    """The diffuse image albedo/π · E_sss from UV textures, differentiably (torch).

    The renderer's numpy path computes the same image (:meth:`HandRenderer.render`
    with ``specular=False``); gradients flow to every texture.

    Args:
        albedo_textures: per hand [Na, Na, 3] tensors.
        irradiance_textures: per hand [N, N, 3] tensors (e.g. ``Lighting.irradiance``).
        gbuffer: the view's G-buffer.
        specular: optional [P, 3] per-sample radiance added before the pixel filter.

    Returns:
        [H, W, 3] tensor.
    """
    total = None
    for k, (alb, irr) in enumerate(zip(albedo_textures, irradiance_textures)):
        term = lookup_torch(alb, gbuffer, k) * lookup_torch(irr, gbuffer, k) / math.pi
        total = term if total is None else total + term
    if specular is not None:
        total = total + specular
    return resolve_torch(total, gbuffer, background)
