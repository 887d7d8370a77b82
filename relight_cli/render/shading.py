"""Physically based shading of posed hands: Lambert + GGX, shadows, SSS, one bounce.

Radiance leaving a surface point x towards the camera (linear RGB, W·sr⁻¹·m⁻²
up to the global scale of the light units):

    L_o(x) = albedo(x)/π · E_sss(x) + Σ_lights f_s·(n·l) · I / r² · h + Σ_m L(ω_m) h f_s (n·ω_m) Δω_m

* E(x) = Σ_lights I·max(n·l, 0)·h/r² + Σ_m L(ω_m)·h(ω_m)·max(n·ω_m, 0)·Δω_m (+ one bounce)
  is the diffuse irradiance.  Point lights have radiant intensity I [3] and fall off
  with the inverse square of the distance r (near field).  The env map term is
  *exactly* bake-features' diffuse feature: the env map is discretized to the same
  lat-long grid (``env_res``) with exact texel solid angles by
  :func:`relight_cli.envmap.discretize_env`, and the transport weights come from
  :func:`relight_cli.features.transport_blocks`, so a render is exactly linear in
  the env map and consistent with the features a neural model is given.
* h is binary visibility from embree shadow rays against every hand of the scene.
* f_s is the GGX lobe of URHand (:mod:`relight_cli.brdf`, F0 = 0.04).
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
renders every camera from them.  Point-light GGX is evaluated per sample (sharp
highlights); env-map transport per mesh vertex (bake-features' receivers) or per
texel, for the camera's eye.  Texels outside the charts, or buried inside another
part, copy their nearest exposed texel, so bilinear lookups never pull in zeros.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from .appearance import bilinear
from relight_cli import features as FE
from relight_cli.brdf import ggx_cosine
from relight_cli.envmap import DEFAULT_GRID, DiscreteEnv, discretize_env
from relight_cli.formats.lights_json import Lights
from relight_cli.geometry import Receivers, vertex_normals, view_directions
from relight_cli.visibility import VisibilityCache

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
        env_space: where env-map transport is integrated: "vertices" of the rendered mesh
            (bake-features' receivers; interpolated to texels) or "texels" (diffuse
            transport and visibility at the texel centres, the GGX lobe per G-buffer sample
            with that visibility looked up: every direction shaded as a far point light
            is with ``direct="texel"``, so the render is their sum).
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
    env_space: str = "vertices"
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
        self._env_cache = {}
        t0 = time.perf_counter()
        self._mark_buried()
        self.stats["buried"] = time.perf_counter() - t0

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

    def _env_visibility(self, k: int, env, fs):
        """(receivers, VisibilityCache) of hand k's env transport (``env_space``'s
        receivers), every pair ``fs`` needs of ``env``'s lit directions traced (once per
        renderer: later calls find them traced)."""
        if k not in self._env_cache:
            if self.settings.env_space == "vertices":
                mesh = self.meshes[k]
                normals, defined = vertex_normals(mesh.vertices, mesh.faces, mesh.normals)
                receivers = Receivers(np.asarray(mesh.vertices, np.float64), normals, defined)
            else:
                surf = self.surfaces[k]
                receivers = Receivers(surf.points, surf.normals, np.ones(len(surf.points), bool))
            scene = self.scene if self.settings.shadows else None
            cache = VisibilityCache(scene, receivers, env.directions, self.offsets[k])
            self._env_cache[k] = (receivers, cache)
        receivers, cache = self._env_cache[k]
        if not np.array_equal(cache.directions, env.directions):
            raise ValueError("env maps of one renderer must share the direction grid")
        cache.require(FE.needed_pairs(receivers, None, env.directions, env.lit, fs))
        return receivers, cache

    def _env_transport(self, k: int, env, eye, specular: bool):
        """Bake-features' env transport for hand k, at its texels: {'diffuse', 'ggx'?} [K, 3].

        Receivers are the mesh's vertices (``env_space="vertices"``, bake-features'
        own receivers, results interpolated to texels barycentrically) or the texel
        centres themselves (``"texels"``: per-texel visibility, ~3× more rays).
        """

        surf = self.surfaces[k]
        mesh = self.meshes[k]
        by_vertex = self.settings.env_space == "vertices"
        fs = FE.FeatureSettings(shininess=(), specular="ggx" if specular else "none",
                                f0=self.materials[k].f0, visibility=self.settings.shadows)
        receivers, cache = self._env_visibility(k, env, fs)
        view = view_directions(receivers.points, eye)
        rough = None
        if specular:
            if by_vertex:
                uv_of_vertex = np.zeros((len(receivers.points), 2))
                uv_of_vertex[np.asarray(mesh.faces).ravel()] = np.asarray(mesh.uv)[
                    np.asarray(mesh.faces_uv).ravel()]
                rough = self.materials[k].roughness_at(uv_of_vertex)
            else:
                rough = self.materials[k].roughness_at(surf.uv)
        blocks = FE.transport_blocks(receivers, view, env.directions, env.solid_angle,
                                     cache.visible, fs, rough)
        result = FE.apply_transport(blocks, len(receivers), [env])[0]
        if by_vertex:
            result = {name: surf.raster.interpolate(value, mesh.faces, fill=None)[surf.inside]
                      for name, value in result.items() if name != "visibility"}
        return result

    def discretize(self, env):
        """An EnvMap (or DiscreteEnv) on bake-features' ``env_res`` grid."""
        if isinstance(env, DiscreteEnv):
            return env
        return discretize_env(env, *self.settings.env_res)

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
        for k, surf in enumerate(self.surfaces):
            irr = np.zeros((len(surf.points), 3))
            if has_lights:
                e, vis = self._point_irradiance(k, lights)
                irr += e
                vis_maps.append(surf.to_map(vis))
                point_maps.append(surf.to_map(e))
            if denv is not None:
                irr += self._env_transport(k, denv, np.zeros(3), specular=False)["diffuse"]
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
                                     * bilinear(irradiance[j], uv))
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
            uv = gb.uv[sel]
            irradiance = bilinear(lighting.irradiance[k], uv)
            has_lights = lighting.lights is not None and len(lighting.lights) > 0
            spec = np.zeros((len(sel), 3))
            specular = s.specular and mat.specular > 0
            rough = mat.roughness_at(uv) if specular else None
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
                    irradiance += exact - bilinear(lighting.point_maps[k], uv)
            radiance[sel] = mat.albedo_at(uv) / math.pi * irradiance
            if specular:
                if has_lights and s.direct != "pixel":
                    spec += self._point_specular(gb, sel, rough, mat.f0, lighting, k)
                if lighting.env is not None and s.env_space == "texels":
                    spec += self._env_specular(gb, sel, rough, mat.f0, lighting.env, k)
                elif lighting.env is not None:
                    env_spec = self._env_transport(k, lighting.env, gb.eye, specular=True)["ggx"]
                    spec += bilinear(self.surfaces[k].to_map(env_spec), uv)
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
                spec += (ggx_cosine(n, v, l, rough, f0) * falloff)[:, None] * intensity[j]
        return irr, spec

    def _env_specular(self, gb, sel, rough, f0, env, k):
        """[len(sel), 3] GGX radiance of an env map at the samples ``sel`` of hand k, each
        lit direction ω_m a distant light of RGB weight L_m Δω_m shaded exactly as
        :meth:`_point_specular` shades an LED: the lobe per sample, the visibility h_m
        looked up bilinearly in the texel maps (``env_space="texels"``; traced once by
        :meth:`_env_visibility`, not the diffuse transport again).  So an env render is the sum over its directions of
        what the stage renders for one far LED each (tests/render/test_capture.py)."""
        _, cache = self._env_visibility(k, env, FE.FeatureSettings(
            shininess=(), specular="none", f0=f0, visibility=self.settings.shadows))
        surf = self.surfaces[k]
        n, v, uv = gb.normal[sel], gb.view[sel], gb.uv[sel]
        lit = np.nonzero(env.lit)[0]
        weight = env.radiance[lit] * env.solid_angle[lit, None]                    # [M', 3]
        out = np.zeros((len(sel), 3))
        block = 8 * _LIGHT_BLOCK
        for start in range(0, len(lit), block):
            m = lit[start:start + block]
            vis = bilinear(surf.to_map(cache.visible[:, m].astype(np.float32)), uv)
            vis = vis.reshape(len(sel), len(m))                                   # [S, B]
            w = ggx_cosine(n[:, None], v[:, None], env.directions[m][None], rough[:, None], f0)
            out += (w * vis) @ weight[start:start + block]
        return out

    def _point_specular(self, gb, sel, rough, f0, lighting, k):
        """[len(sel), 3] GGX radiance of point lights at the samples ``sel`` of hand k,
        visibility looked up in the texel maps (``direct="texel"``)."""
        lights = lighting.lights
        intensity = lights.radiant_intensity()                                  # [L, 3]
        x, n, v = gb.position[sel], gb.normal[sel], gb.view[sel]
        vis = bilinear(lighting.visibility[k].reshape(*lighting.visibility[k].shape[:2], -1),
                       gb.uv[sel]).reshape(len(sel), len(lights))           # [S, L]
        out = np.zeros((len(sel), 3))
        for start in range(0, len(lights), _LIGHT_BLOCK):
            stop = min(len(lights), start + _LIGHT_BLOCK)
            d = lights.positions[None, start:stop] - x[:, None]             # [S, B, 3]
            r2 = np.einsum("sbk,sbk->sb", d, d)
            l = d / np.sqrt(np.maximum(r2, 1e-300))[..., None]
            w = ggx_cosine(n[:, None], v[:, None], l, rough[:, None], f0)   # [S, B]
            w = w * vis[:, start:stop] / np.maximum(r2, 1e-300)
            out += w @ intensity[start:stop]
        return out


# ---------------------------------------------------------------- torch path


def lookup_torch(texture, gbuffer, hand: int = 0):
    """Differentiable texture lookup at the G-buffer's samples of one hand.

    Args:
        texture: [N, N, C] torch tensor (UV map of hand ``hand``).
        gbuffer: :class:`~relight_cli.render.gbuffer.GBuffer`.
        hand: which hand's samples.

    Returns:
        [P, C] tensor: bilinear samples (``grid_sample``, align_corners=False, border
        padding; identical to :func:`relight_cli.render.appearance.bilinear`) at the
        samples of ``hand``, 0 elsewhere.
    """
    import torch

    sel = torch.as_tensor(gbuffer.hand == hand, device=texture.device)
    uv = torch.as_tensor(gbuffer.uv, dtype=texture.dtype, device=texture.device)
    grid = torch.stack([2 * uv[:, 0] - 1, 1 - 2 * uv[:, 1]], -1)            # v = 0 at the bottom
    img = texture.permute(2, 0, 1)[None]                                     # [1, C, N, N]
    out = torch.nn.functional.grid_sample(img, grid[None, None], mode="bilinear",
                                          padding_mode="border", align_corners=False)
    values = out[0, :, 0].T                                                  # [P, C]
    return values * sel[:, None].to(values.dtype)


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
