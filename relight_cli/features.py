"""Visibility-aware shading features on posed meshes (RelightableHands Eq. 8–9, URHand's GGX).

For every receiver i (a mesh vertex, or any point with a normal) and an
environment map discretized to M directions ω_m with exact solid angles Δω_m
(pixel-centre directions of a lat-long map, :mod:`relight_cli.envmap`):

* diffuse      d_i = Σ_m L(ω_m) · h_i(ω_m) · max(n_i·ω_m, 0) · Δω_m
* Phong        s_i(α) = (α+2)/(2π) · Σ_m L(ω_m) · h_i(ω_m) · max(r_i·ω_m, 0)^α · Δω_m,
               r_i = 2(n_i·v_i)n_i − v_i, the view direction v_i reflected about n_i
* GGX          g_i = Σ_m L(ω_m) · h_i(ω_m) · f_s(ω_m, v_i) · max(n_i·ω_m, 0) · Δω_m with the
               Disney/UE4 microfacet lobe URHand uses (see :func:`ggx_weights`)
* visibility   a_i = Σ_m h_i(ω_m) max(n_i·ω_m, 0) Δω_m / Σ_m max(n_i·ω_m, 0) Δω_m
               (cosine-weighted, 1 for an unoccluded receiver, env-independent)

h is binary visibility: a ray from the receiver (offset along n_i) towards ω_m
escapes every mesh of the scene (two hands shadow each other), and ω_m is not below
the receiver's tangent plane (n_i·ω_m > −10⁻⁹): a direction under the plane is
blocked by the surface itself, which is what a ray would find on a closed surface —
without casting it.  (It matters only for Phong, the one lobe Eq. 9 does not clip by
n·ω; with ``visibility=False``, h ≡ 1 and Eq. 9 counts such directions as written.)

Speed: visibility depends on the pose, not the lighting, so :class:`VisibilityCache`
traces it once and every env map, shininess and specular model reuses it.  Only
pairs (i, m) whose weight can be non-zero are traced: ω_m above i's tangent
plane (diffuse, GGX, visibility channel, and Phong lobes, which without visibility
also reach below it: r_i·ω_m inside the lobe's support *and* lit by some env map).  Every stage of a new pose
is local to its receivers, so :meth:`FeatureBaker.bake` runs cull → trace
(embree through :class:`relight_cli.raytrace.RayScene`) → transport → shade per
block of receivers while the block's arrays are in cache, with blocks spread over
a thread pool (embree and numpy release the GIL); results do not depend on the
thread count.  An extra env map reuses the cached transport weights: one small
matrix product per feature.

Where the pieces live: the env map's discretization (:class:`DiscreteEnv`,
:func:`discretize_env`) beside the lat-long geometry in :mod:`relight_cli.envmap`;
receivers, normals and view/mirror directions in :mod:`relight_cli.geometry`; the
traced visibility (:class:`VisibilityCache`) beside the ray tracer in
:mod:`relight_cli.visibility`; this module keeps what turns them into features (culling
by lobe support, transport weights, shading, the per-pose baker) and their twins.

:func:`vertex_features_reference` is the slow twin (per-receiver loop, every
direction traced with trimesh's numpy ray test, no culling) used by tests.
:func:`ggx_specular_torch` is the differentiable torch version of the GGX
feature (visibility fixed) for URHand's physical branch.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from relight_cli.brdf import (MIN_ROUGHNESS, check_shadowing, ggx_cosine_torch,
                               shadowing_denominator)
from relight_cli.envmap import DEFAULT_GRID, DiscreteEnv, discretize_env
from relight_cli.formats.envmap import EnvMap
from relight_cli.geometry import (GEMM_SINGLE, Receivers, matvec, dot3, reflect, scene_diagonal,
                                  vertex_normals, view_directions)
from relight_cli.visibility import VisibilityCache, thread_pool

# Shading works on [receivers, directions] blocks of at most this many entries
# (float64: 8 bytes each, a handful alive at once) to bound memory.
_BLOCK = 1 << 16
# (receiver, direction) entries per chunk of a pose's pipeline (whole blocks): with
# K features, K·8 bytes each is the size of one allocation of kept weights.
_CHUNK = 1 << 18
# Transport weights (N·M per feature, float64) are kept between env maps up to
# this many entries (128 MiB); beyond it they are streamed and recomputed.
_TRANSPORT_CACHE = 1 << 24
SPECULAR_MODELS = ("phong", "ggx", "both", "none")
# Phong lobes are truncated where max(r·ω, 0)^α < 1e-30 (relative to the lobe's
# peak of 1): that bounds the relative error by 1e-30 per texel, far below
# float32 output precision, keeps powers out of the subnormal range (which is
# ~50× slower) and is the lobe's *support* for ray culling.
LOBE_EPSILON = 1e-30


def lobe_cutoff(shininess) -> float:
    """Smallest r·ω kept for Phong exponents ``shininess`` (0 keeps the whole hemisphere)."""
    alphas = [a for a in shininess if a > 0]
    return LOBE_EPSILON ** (1.0 / min(alphas)) if alphas else 0.0


@dataclass
class FeatureSettings:
    """What to compute.

    Attributes:
        shininess: Phong exponents α (one ``phong{α}`` feature each); empty for none.
        specular: "phong", "ggx", "both" or "none".
        roughness: GGX perceptual roughness ρ ∈ (0, 1]: a scalar or [N] per receiver.
        f0: GGX Fresnel reflectance at normal incidence (0.04: dielectric skin).
        shadowing: the GGX lobe's G, ``"smith"`` (exact) or ``"schlick"`` (URHand Eq. 15's
            remap), :mod:`relight_cli.brdf`.
        visibility: False = the no-shadow ablation (h ≡ 1, nothing traced).
        ray_offset: metres to lift ray origins along the normal; None = 1e-4 × the
            bounding-box diagonal of the receiver's own mesh (0.02 mm for a hand), so
            adding a second hand to the scene does not change the first one's rays.
    """

    shininess: tuple = (16, 32, 64)
    specular: str = "phong"
    roughness: float | np.ndarray = 0.5
    f0: float = 0.04
    visibility: bool = True
    ray_offset: float | None = None
    shadowing: str = "smith"

    def __post_init__(self):
        check_shadowing(self.shadowing)
        if self.specular not in SPECULAR_MODELS:
            raise ValueError(f"specular must be one of {SPECULAR_MODELS}, got {self.specular!r}")
        self.shininess = tuple(float(a) for a in self.shininess)
        # α = 0 is no lobe at all (max(r·ω, 0)⁰ is a step whose value on the
        # boundary is undefined), so exponents must be positive.
        if any(not (a > 0 and math.isfinite(a)) for a in self.shininess):
            raise ValueError(f"shininess exponents must be finite and > 0, got {self.shininess}")

    @property
    def phong(self) -> tuple:
        return self.shininess if self.specular in ("phong", "both") else ()

    @property
    def ggx(self) -> bool:
        return self.specular in ("ggx", "both")


def phong_name(alpha: float) -> str:
    """Feature/channel-layer name of a Phong exponent: 16 → ``phong16``, 2.5 → ``phong2.5``."""
    return f"phong{int(alpha)}" if float(alpha).is_integer() else f"phong{alpha:g}"


def feature_names(settings: FeatureSettings) -> list[str]:
    """Feature names in output order: diffuse, phong{α}…, ggx, visibility."""
    names = ["diffuse"] + [phong_name(a) for a in settings.phong]
    if settings.ggx:
        names.append("ggx")
    return names + ["visibility"]


#: n·ω below −BELOW_PLANE: the direction is under the receiver's tangent plane.
BELOW_PLANE = 1e-9


def needed_pairs(receivers: Receivers, reflected: np.ndarray | None, directions: np.ndarray,
                 lit: np.ndarray, settings: FeatureSettings,
                 cosines: np.ndarray | None = None) -> np.ndarray:
    """[N, M] bool: the (receiver, direction) pairs whose visibility can change a feature.

    * n·ω > 0 (above the tangent plane): diffuse, GGX and the visibility channel;
      the latter is env-independent, so every such pair is needed.
    * without visibility (h ≡ 1) also r·ω > c on lit texels (Phong lobes:
      max(r·ω, 0)^α < 1e-30 for r·ω ≤ c = :func:`lobe_cutoff`, and L = 0 on unlit
      texels), which adds pairs below the tangent plane.  With visibility those pairs
      are never traced: a direction below a receiver's tangent plane cannot light it
      (the surface itself blocks it), so h = 0 there by definition — RelightableHands'
      h of Eq. 9 on a closed surface, without the rays (a third of the rays on the
      built-in hand's proxy).
    Receivers with undefined normals need nothing (their features are 0).
    ``cosines`` optionally passes n·ω [N, M] already computed.
    """
    return _needed_pairs(receivers, reflected, directions, lit, settings, cosines)[0]


def _needed_pairs(receivers, reflected, directions, lit, settings, cosines=None):
    """:func:`needed_pairs` and the r·ω [N, M] it computed (None without Phong), which
    :func:`_transport_stacked` reuses."""
    cos = dot3(receivers.normals, directions) if cosines is None else cosines   # [N, M]
    need = cos > 0
    lobes = None
    if settings.phong and reflected is not None:
        lobes = dot3(reflected, directions)
        lobe = (lobes > lobe_cutoff(settings.phong)) & lit[None, :]
        if settings.visibility:
            # a direction below the tangent plane is blocked by the surface itself: h = 0
            # without a ray (an untraced pair is invisible).  Grazing pairs within
            # BELOW_PLANE of the plane are still traced, so rounding of n·ω ≈ 0 (e.g. a
            # rotated scene) never flips a Phong term.
            lobe &= cos > -BELOW_PLANE
        need |= lobe       # h ≡ 1: a Phong lobe below the plane counts (Eq. 9 as written)
    need &= receivers.defined[:, None]
    return need, lobes


# ---------------------------------------------------------------- shading


def ggx_weights(normals: np.ndarray, view: np.ndarray, directions: np.ndarray,
                roughness: np.ndarray, f0: float = 0.04, shadowing: str = "smith",
                cosines: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """[N, M] GGX specular weight f_s(ω_m, v_i) · max(n_i·ω_m, 0): :mod:`relight_cli.brdf`'s lobe.

    f_s = D·F·G / (4 (n·l)(n·v)), perceptual roughness ρ, α = ρ², ``shadowing`` G
    (exact separable Smith or the Schlick–Smith remap of URHand Eq. 15; see
    :mod:`relight_cli.brdf`).  Zero where n·l ≤ 0 or n·v ≤ 0.

    Every pair's half vector enters only through dot products, so the [N, M] work is
    two matrix products (n·ω, v·ω) and a few in-place element operations, with
      |v + ω|² = 2 (1 + v·ω),  n·h = (n·v + n·ω) / |v + ω|,  v·h = √((1 + v·ω)/2),
    and D's denominator (n·h)²(α² − 1) + 1 = (1 − (n·h)²) + (n·h)² α², whose first term is
    (|v + ω|² − (n·v + n·ω)²)/|v + ω|² ≥ 0 (no cancellation to 0 at small α).
    Equals :func:`relight_cli.brdf.ggx_cosine` to rounding (tests).

    Args:
        normals, view: [N, 3] unit.  directions: [M, 3] unit.  roughness: [N] or scalar.
        cosines: optional n·ω [N, M] already computed.  out: optional [N, M] float64 result.
    """
    check_shadowing(shadowing)
    n_rows = len(normals)
    rho = np.clip(np.broadcast_to(np.asarray(roughness, np.float64).reshape(-1), (n_rows,)),
                  MIN_ROUGHNESS, 1.0)[:, None]                                 # [N, 1]
    a2 = rho ** 4
    nv = np.einsum("ij,ij->i", normals, view)[:, None]                         # [N, 1]
    nw = dot3(normals, directions) if cosines is None else cosines             # [N, M]
    w = dot3(view, directions, out=out)                                        # v·ω → ...
    one_vw = np.add(w, 1.0, out=w)                                             # 1 + v·ω
    valid = (nw > 0) & (nv > 0) & (one_vw > 1e-12)
    hl2 = np.multiply(one_vw, 2.0)                                             # |v + ω|²
    nh = np.add(nw, nv)                                                        # n·(v + ω)
    np.multiply(nh, nh, out=nh)
    np.divide(nh, hl2, out=nh, where=valid)                                    # (n·h)²
    # D denominator (1 − nh²) + nh² α², computed from |v+ω|² − (n·(v+ω))² to stay ≥ 0
    den = np.subtract(1.0, nh)
    np.maximum(den, 0.0, out=den)
    den += nh * a2
    np.multiply(den, den, out=den)
    # F = F0 + (1 − F0)(1 − v·h)⁵, v·h = √((1 + v·ω)/2)
    vh = np.multiply(one_vw, 0.5, out=one_vw)
    np.sqrt(vh, out=vh)
    np.subtract(1.0, vh, out=vh)
    np.clip(vh, 0.0, 1.0, out=vh)
    fres = vh * vh
    fres *= fres
    fres *= vh
    fres *= 1 - f0
    fres += f0
    nl = np.maximum(nw, 0.0)
    lam = shadowing_denominator(nl, rho, shadowing)
    lam *= shadowing_denominator(np.maximum(nv, 0.0), rho, shadowing)
    lam *= den
    lam *= math.pi
    # D F (n·l) / (Λ(l) Λ(v)) = α² F (n·l) / (π den² Λ(l) Λ(v))
    np.multiply(fres, nl, out=fres)
    fres *= a2
    np.divide(fres, lam, out=fres, where=valid)
    np.multiply(fres, valid, out=w)           # w's buffer held v·ω, then 1 − v·h: now f_s·cos
    return w


def transport_blocks(receivers: Receivers, view: np.ndarray, directions: np.ndarray,
                     solid_angle: np.ndarray, visible: np.ndarray, settings: FeatureSettings,
                     roughness: np.ndarray | None = None, cosines: np.ndarray | None = None):
    """Yield the env-independent light-transport weights, a block of receivers at a time.

    Every feature is linear in the env map: feature_i = Σ_m W_i,m · L(ω_m)Δω_m.  This
    yields (receiver slice, {name: W [b, M] float64}, visibility [b]) with
      W_diffuse = h·max(n·ω, 0),  W_phongα = (α+2)/(2π)·h·max(r·ω, 0)^α,
      W_ggx = h·f_s·max(n·ω, 0), and the cosine-weighted visibility channel.
    Pairs never traced have zero weight (guaranteed by :func:`needed_pairs`).
    ``cosines`` optionally passes n·ω [N, M] already computed (e.g. by :func:`needed_pairs`).
    """
    for sl, names, stacked, vis in _transport_stacked(receivers, view, directions, solid_angle,
                                                      visible, settings, roughness, cosines):
        yield sl, dict(zip(names, stacked)), vis


def _transport_stacked(receivers, view, directions, solid_angle, visible, settings,
                       roughness=None, cosines=None, lobes=None, out=None):
    """:func:`transport_blocks` with each block's weights stacked: (slice, names, [K, b, M], vis).

    One allocation per block holds every feature, and the in-place arithmetic below
    avoids allocating a fresh [b, M] array per step.
    Bit-identical to the formulas in :func:`transport_blocks`: h ∈ {0, 1}, so
    (h·x)^α = h·x^α for α > 0 and h·x = x or 0 exactly.  ``lobes`` optionally passes r·ω
    [N, M] from :func:`_needed_pairs`; it is used as scratch space.  ``out`` optionally
    gives the [K, N, M] float64 array to write the weights into (blocks are views of it).
    """
    n = len(receivers)
    m = len(directions)
    if roughness is None:
        roughness = np.broadcast_to(np.asarray(settings.roughness, np.float64), (n,))
    reflected = reflect(view, receivers.normals) if settings.phong else None
    cutoff = lobe_cutoff(settings.phong)
    names = feature_names(settings)[:-1]
    phong_at = {a: names.index(phong_name(a)) for a in settings.phong}
    step = max(1, _BLOCK // max(1, m))
    for s in range(0, n, step):
        sl = slice(s, min(n, s + step))
        b = sl.stop - sl.start
        w = np.empty((len(names), b, m)) if out is None else out[:, sl]
        h = visible[sl]                                           # [b, M] bool
        cos = w[0]
        above = None                  # Phong with visibility: h = 0 below the tangent plane
        if cosines is None:
            dot3(receivers.normals[sl], directions, out=cos)
            if settings.phong and settings.visibility:
                above = cos > -BELOW_PLANE
            np.maximum(cos, 0, out=cos)
        else:
            if settings.phong and settings.visibility:
                above = cosines[sl] > -BELOW_PLANE
            np.maximum(cosines[sl], 0, out=cos)
        denom = matvec(cos, solid_angle)
        np.multiply(cos, h, out=cos)                              # W_diffuse = h·max(n·ω, 0)
        vis = np.divide(matvec(cos, solid_angle), denom, out=np.zeros_like(denom), where=denom > 0)
        if settings.phong:
            # [b, M] r·ω (``lobes`` from culling is overwritten in place: a scratch array)
            lobe = dot3(reflected[sl], directions) if lobes is None else lobes[sl]
            support = lobe > cutoff                               # the lobe's support ...
            support &= h                                          # ... where visible
            if above is not None:
                support &= above                                  # ... above the plane
            hl = np.multiply(lobe, support, out=lobe)             # h·max(r·ω, 0), 0 off-lobe
            positive = [a for a in settings.phong if a > 0]
            for alpha, power in zip(positive, _powers(hl, positive)):
                np.multiply(power, (alpha + 2) / (2 * math.pi), out=w[phong_at[alpha]])
            for alpha in settings.phong:
                if alpha <= 0:   # x^0 = 1 even where the lobe is 0 (α ≥ 0 is validated)
                    np.multiply(h, (alpha + 2) / (2 * math.pi), out=w[phong_at[alpha]])
        if settings.ggx:
            g = w[names.index("ggx")]
            ggx_weights(receivers.normals[sl], view[sl], directions, roughness[sl],
                        settings.f0, settings.shadowing, out=g)
            np.multiply(g, h, out=g)
        undefined = ~receivers.defined[sl]
        if undefined.any():
            w[:, undefined] = 0
            vis[undefined] = 0
        yield sl, names, w, vis


def _weighted_radiance(envs: list[DiscreteEnv]) -> np.ndarray:
    """[M, 3E] float64: L(ω_m)·Δω_m of every env map side by side."""
    omega = envs[0].solid_angle
    return np.concatenate([e.radiance * omega[:, None] for e in envs], axis=1)


def _empty_features(names, n: int, count: int) -> list[dict]:
    """``count`` dicts of zeroed outputs: name → [n, 3], ``visibility`` → [n]."""
    out = [{name: np.zeros((n, 3)) for name in names} for _ in range(count)]
    for o in out:
        o["visibility"] = np.zeros(n)
    return out


def _shade_stacked(blocks, weighted: np.ndarray, out: list[dict]):
    """Shade :func:`_transport_stacked` blocks into ``out`` (from :func:`_empty_features`).

    Blocks write only their own rows, so disjoint blocks may be shaded concurrently.
    """
    for sl, names, stacked, vis in blocks:
        k, b, m = stacked.shape
        # Products of at most GEMM_SINGLE multiply-adds: OpenBLAS runs those on one
        # thread, and its thread hand-off costs more than it saves on these memory-bound
        # tall-skinny products (3-10× slower on a busy 2-core machine, measured).
        rows = max(1, GEMM_SINGLE // (m * weighted.shape[1]))
        for i, name in enumerate(names):
            for r in range(0, b, rows):
                res = stacked[i, r:r + rows] @ weighted                         # [r, 3E]
                for j, o in enumerate(out):
                    o[name][sl.start + r:sl.start + r + len(res)] = res[:, 3 * j:3 * j + 3]
        for o in out:
            o["visibility"][sl] = vis


def apply_transport(blocks, n: int, envs: list[DiscreteEnv]) -> list[dict]:
    """Features of each env map from transport blocks (one matrix product per feature).

    Returns:
        One dict per env map: name → [N, 3] float64 (diffuse, phong…, ggx) and
        ``visibility`` → [N] float64.
    """
    omega = envs[0].solid_angle
    weighted = np.concatenate([e.radiance * omega[:, None] for e in envs], axis=1)   # [M, 3K]
    out = [dict() for _ in envs]
    for sl, weights, vis in blocks:
        for name, w in weights.items():
            res = w @ weighted                                    # [b, 3K]
            for j, o in enumerate(out):
                if name not in o:
                    o[name] = np.zeros((n, 3))
                o[name][sl] = res[:, 3 * j:3 * j + 3]
        for o in out:
            o.setdefault("visibility", np.zeros(n))[sl] = vis
    return out


def shade(receivers: Receivers, view: np.ndarray, envs: list[DiscreteEnv], visible: np.ndarray,
          settings: FeatureSettings, roughness: np.ndarray | None = None) -> list[dict]:
    """Features of every receiver under each env map, given visibility.

    Args:
        receivers: N receivers.
        view: [N, 3] unit directions towards the eye.
        envs: env maps sharing one direction grid.
        visible: [N, M] bool h (True where the ray escapes; pairs never traced must
            carry zero weight, which :func:`needed_pairs` guarantees).
        settings: what to compute.
        roughness: [N] GGX roughness (default from settings).

    Returns:
        One dict per env map: name → [N, 3] float64 and ``visibility`` → [N] float64.
    """
    blocks = transport_blocks(receivers, view, envs[0].directions, envs[0].solid_angle,
                              visible, settings, roughness)
    return apply_transport(blocks, len(receivers), envs)


def _powers(base: np.ndarray, exponents) -> list[np.ndarray]:
    """base**α for each α; integer α by repeated squaring (shared squarings: α = 16,
    32, 64 cost six multiplies instead of three transcendental powers)."""
    squares = {1: base}
    out = []
    for alpha in exponents:
        if float(alpha).is_integer() and 0 < alpha <= 1 << 20:
            a = int(alpha)
            result = None
            bit = 1
            while a:
                if bit not in squares:
                    squares[bit] = squares[bit // 2] * squares[bit // 2]
                if a & 1:
                    result = squares[bit] if result is None else result * squares[bit]
                a >>= 1
                bit <<= 1
            out.append(result)
        else:
            out.append(np.power(base, alpha))
    return out


# ---------------------------------------------------------------- the engine


@dataclass
class PoseMesh:
    """One mesh of a posed scene (e.g. one hand).

    Attributes:
        vertices: [V, 3] float, metres, world.
        faces: [F, 3] int.
        normals: [V, 3] or None (computed from faces then).
        name: label (e.g. "right").
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    name: str = ""


@dataclass
class FeatureStats:
    """What the work cost: rays, seconds per stage.

    The per-pose stages (cull, trace, transport, shade) run per block of receivers on
    several threads; their seconds are summed over threads (thread-seconds), so they
    can add up to more than the wall time of the bake.
    """

    rays_traced: int = 0
    rays_possible: int = 0        # N·M for every env grid used (what a naive tracer casts)
    seconds: dict = field(default_factory=dict)

    def add_time(self, stage: str, seconds: float):
        self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds


class FeatureBaker:
    """Per-vertex shading features of a posed scene; visibility traced once per pose.

    Build one per pose (mesh positions), then call :meth:`bake` for any number of
    env maps (in one call or several) and eyes: visibility of pairs already traced
    is reused, new pairs (e.g. a new eye's Phong lobes) are traced on demand.

    Args:
        meshes: the posed meshes; every mesh occludes every receiver.
        settings: what to compute.
        env_res: (H, W) of the lat-long grid env maps are discretized to.
        grid: instead of ``env_res``, use this DiscreteEnv's directions; env maps
            passed to :meth:`bake` must then be DiscreteEnvs with these directions.
        threads: ray-tracing worker threads (None = every CPU available, see
            :func:`trace_threads`); results do not depend on it.
        receivers: optional per mesh :class:`~relight_cli.geometry.Receivers` that receive
            light instead of the mesh's vertices (e.g. the renderer's texel centres); the
            meshes still occlude, and a receiver's ray offset is still its own mesh's.
        scene: optional :class:`~relight_cli.raytrace.RayScene` of ``meshes`` already built
            (the renderer's), used instead of building another.
    """

    def __init__(self, meshes: list[PoseMesh], settings: FeatureSettings | None = None,
                 env_res: tuple[int, int] = DEFAULT_GRID, grid: DiscreteEnv | None = None,
                 threads: int | None = None, receivers: list[Receivers] | None = None,
                 scene=None):
        from relight_cli import envmap as E

        self.meshes = meshes
        self.settings = settings or FeatureSettings()
        self.env_res = (int(env_res[0]), int(env_res[1]))
        self.stats = FeatureStats()
        t0 = time.perf_counter()
        points, normals, defined = [], [], []
        self.slices = []
        start = 0
        if receivers is not None and len(receivers) != len(meshes):
            raise ValueError("give one set of receivers per mesh")
        for k, mesh in enumerate(meshes):
            if receivers is None:
                v = np.asarray(mesh.vertices, np.float64).reshape(-1, 3)
                nrm, ok = vertex_normals(v, mesh.faces, mesh.normals)
            else:
                v = np.asarray(receivers[k].points, np.float64).reshape(-1, 3)
                nrm = np.asarray(receivers[k].normals, np.float64).reshape(-1, 3)
                ok = np.asarray(receivers[k].defined, bool) & np.isfinite(nrm).all(1)
            ok &= np.isfinite(v).all(1)
            points.append(np.where(np.isfinite(v), v, 0.0))
            normals.append(nrm)
            defined.append(ok)
            self.slices.append(slice(start, start + len(v)))
            start += len(v)
        self.receivers = Receivers(np.concatenate(points), np.concatenate(normals),
                                   np.concatenate(defined))
        geometry = [(np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64))
                    for m in meshes]
        offset = self.settings.ray_offset
        if offset is None:
            offset = np.concatenate([np.full(sl.stop - sl.start, 1e-4 * scene_diagonal([g]))
                                     for g, sl in zip(geometry, self.slices)])
        if not self.settings.visibility:
            scene = None
        elif scene is None:
            from relight_cli.raytrace import RayScene
            scene = RayScene(geometry)
            # embree builds its BVH on the first query: do it here so the "scene" stage
            # holds the build and "trace" only ray traversal.
            scene.occluded(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
        self.stats.add_time("scene", time.perf_counter() - t0)
        if grid is None:
            h, w = self.env_res
            self.directions = E.latlong_directions(h, w).reshape(-1, 3)
        else:  # any direction set, e.g. a rotated grid (tests) or a discretized env
            self.env_res = (grid.height, grid.width)
            self.directions = np.asarray(grid.directions, np.float64)
        self.solid_angle = (E.latlong_solid_angles(*self.env_res).reshape(-1) if grid is None
                            else np.asarray(grid.solid_angle, np.float64))
        self.cache = VisibilityCache(scene, self.receivers, self.directions, offset, threads)
        self._cosines = None            # n·ω [N, M]: pose-only, shared by culling and shading
        self._cosines_done = None
        self._transport = None          # cached transport blocks for (eye, roughness)
        self._transport_key = None
        self._lit_covered = np.zeros(len(self.directions), bool)

    def bake(self, envs: list[EnvMap] | list[DiscreteEnv], eye, roughness=None) -> list[list[dict]]:
        """Features for each env map, split per mesh.

        Args:
            envs: EnvMaps (discretized here to ``env_res``) or DiscreteEnvs of that grid.
            eye: [3] viewer position, metres, world.
            roughness: optional [N] per-receiver GGX roughness (all meshes concatenated).

        Returns:
            ``result[env][mesh]`` = dict feature name → per-vertex array ([V, 3] RGB
            features, [V] visibility), float64.
        """
        t0 = time.perf_counter()
        h, w = self.env_res
        discrete = [e if isinstance(e, DiscreteEnv) else discretize_env(e, h, w) for e in envs]
        for d in discrete:
            if d.directions.shape != self.directions.shape or not np.array_equal(
                    d.directions, self.directions):
                raise ValueError("all env maps must use the baker's direction grid")
        self.stats.add_time("env", time.perf_counter() - t0)

        t0 = time.perf_counter()
        eye = np.asarray(eye, np.float64).reshape(3)
        if roughness is not None:
            roughness = np.broadcast_to(np.asarray(roughness, np.float64), (len(self.receivers),))
        key = (eye.tobytes(), None if roughness is None else roughness.tobytes())
        lit = np.zeros(len(self.directions), bool)
        for d in discrete:
            lit |= d.lit
        # Same eye and roughness, and no texel lit that earlier env maps left dark: every
        # needed ray is traced and the transport weights are cached, so an extra env map
        # costs one small matrix product per feature.
        reuse = (self._transport is not None and self._transport_key == key
                 and not (lit & ~self._lit_covered).any())
        names = feature_names(self.settings)[:-1]
        weighted = _weighted_radiance(discrete)
        per_env = _empty_features(names, len(self.receivers), len(discrete))
        workers = self.cache.threads
        if not reuse:
            view = view_directions(self.receivers.points, eye)
            reflected = reflect(view, self.receivers.normals)
            lit_all = lit | (self._lit_covered if self._transport_key == key else False)
            size = len(self.receivers) * len(self.directions) * len(feature_names(self.settings))
            keep = size <= _TRANSPORT_CACHE     # else stream (benchmark references)
            if self._cosines is None and keep:
                self._cosines = np.empty((len(self.receivers), len(self.directions)))
                self._cosines_done = np.zeros(len(self.receivers), bool)
            self.stats.add_time("cull", time.perf_counter() - t0)
            self.cache.ray_origins()
            self.cache.warm_up()
            counted = None if self.cache.scene is None else self.cache.scene.rays_traced
            traced_before = self.cache.rays_traced
            timers = []

            def pose_chunk(rows: slice):
                # Every stage of a new pose is local to its receivers, so each block of
                # receivers goes through cull, trace, transport and shade in one go while
                # its [b, M] arrays are still in cache; chunks of blocks run concurrently on
                # the pool (numpy and embree release the GIL), each writing only its rows.
                kept = []
                spent = np.zeros(4)
                step = max(1, _BLOCK // max(1, len(self.directions)))
                # The chunk's kept weights in one allocation of ≥ 4 MiB, which numpy asks
                # huge pages for: faulting in 64 MB of weights as 2 MiB blocks took
                # ~45 ms, as 8 MiB chunks ~20 ms (measured).
                weights = (np.empty((len(names), rows.stop - rows.start, len(self.directions)))
                           if keep else None)
                for start in range(rows.start, rows.stop, step):
                    sl = slice(start, min(rows.stop, start + step))
                    c0 = time.perf_counter()
                    sub = Receivers(self.receivers.points[sl], self.receivers.normals[sl],
                                    self.receivers.defined[sl])
                    if not keep:
                        cos = dot3(sub.normals, self.directions)
                    else:
                        cos = self._cosines[sl]
                        if not self._cosines_done[sl].all():
                            dot3(sub.normals, self.directions, out=cos)
                            self._cosines_done[sl] = True
                    need, lobes = _needed_pairs(sub, reflected[sl], self.directions, lit_all,
                                                self.settings, cos)
                    c1 = time.perf_counter()
                    self.cache.require_rows(sl, need)
                    c2 = time.perf_counter()
                    blocks = [(slice(b.start + start, b.stop + start), nm, w, vis)
                              for b, nm, w, vis in _transport_stacked(
                                  sub, view[sl], self.directions, self.solid_angle,
                                  self.cache.visible[sl], self.settings,
                                  None if roughness is None else roughness[sl], cos, lobes,
                                  None if weights is None else
                                  weights[:, start - rows.start:sl.stop - rows.start])]
                    c3 = time.perf_counter()
                    _shade_stacked(blocks, weighted, per_env)
                    spent += (c1 - c0, c2 - c1, c3 - c2, time.perf_counter() - c3)
                    if keep:
                        kept += blocks
                timers.append(spent)
                return kept

            chunks = self._row_slices(workers)
            if workers > 1 and len(chunks) > 1:
                results = list(thread_pool(min(workers, len(chunks))).map(pose_chunk, chunks))
            else:
                results = [pose_chunk(rows) for rows in chunks]
            if counted is not None:   # RayScene's counter is not thread-safe: set it once
                self.cache.scene.rays_traced = counted + self.cache.rays_traced - traced_before
            # Stage times summed over workers (thread-seconds; their sum exceeds the wall
            # time when chunks run concurrently).
            for stage, k in (("cull", 0), ("trace", 1), ("transport", 2), ("shade", 3)):
                self.stats.add_time(stage, sum(t[k] for t in timers))
            self.stats.rays_traced = self.cache.rays_traced
            self.stats.rays_possible += len(self.receivers) * len(self.directions) * (
                1 if self.settings.visibility else 0)
            if keep:
                self._transport = [b for blocks in results for b in blocks]
                self._transport_key, self._lit_covered = key, lit_all
            else:
                self._transport, self._transport_key = None, None
        else:
            self.stats.add_time("cull", time.perf_counter() - t0)
            t0 = time.perf_counter()
            blocks = self._transport
            groups = [blocks[i::workers] for i in range(workers)] if workers > 1 else [blocks]
            groups = [g for g in groups if g]
            if len(groups) > 1:
                list(thread_pool(len(groups)).map(lambda g: _shade_stacked(g, weighted, per_env),
                                                  groups))
            else:
                _shade_stacked(blocks, weighted, per_env)
            self.stats.add_time("shade", time.perf_counter() - t0)
        return [[{k: v[sl] for k, v in feats.items()} for sl in self.slices] for feats in per_env]

    def _row_slices(self, workers: int) -> list[slice]:
        """Receiver chunks for the pose pipeline: whole shading blocks, about 4 per worker."""
        n = len(self.receivers)
        step = max(1, _BLOCK // max(1, len(self.directions)))
        blocks = -(-n // step)
        per_chunk = min(max(1, _CHUNK // (step * len(self.directions) or 1)),
                        max(1, -(-blocks // (4 * workers))))
        size = per_chunk * step
        return [slice(s, min(n, s + size)) for s in range(0, n, size)]


# ---------------------------------------------------------------- slow twin


def vertex_features_reference(meshes: list[PoseMesh], env: DiscreteEnv, eye,
                              settings: FeatureSettings) -> list[dict]:
    """Slow, obviously correct twin of :class:`FeatureBaker` for tests.

    Per receiver: every direction of the grid is traced (no culling) with
    a float64 Möller–Trumbore test against every triangle of all meshes, and each feature is
    summed term by term as written in the module docstring (GGX from its
    uncancelled D·F·G / (4 n·l n·v) form).  Same ray offset rule as the fast path.

    Returns:
        One dict per mesh: name → [V, 3] / [V] float64.
    """
    geometry = [(np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)) for m in meshes]
    all_v = np.concatenate([g[0] for g in geometry])
    offsets = np.cumsum([0] + [len(g[0]) for g in geometry])
    all_f = np.concatenate([g[1] + o for g, o in zip(geometry, offsets[:-1])])
    offsets_per_mesh = [settings.ray_offset if settings.ray_offset is not None
                        else 1e-4 * scene_diagonal([g]) for g in geometry]
    eye = np.asarray(eye, np.float64)
    dirs, omega, rad = env.directions, env.solid_angle, env.radiance
    m = len(dirs)
    results = []
    for mesh_index, mesh in enumerate(meshes):
        verts = geometry[mesh_index][0]
        normals, defined = vertex_normals(verts, mesh.faces, mesh.normals)
        rough = np.broadcast_to(np.asarray(settings.roughness, np.float64),
                                (len(all_v),))[offsets[mesh_index]:offsets[mesh_index + 1]]
        out = {name: np.zeros((len(verts), 3)) for name in feature_names(settings)[:-1]}
        out["visibility"] = np.zeros(len(verts))
        for i, (x, nrm) in enumerate(zip(verts, normals)):
            if not defined[i]:
                continue
            if settings.visibility:
                origins = np.repeat((x + offsets_per_mesh[mesh_index] * nrm)[None], m, axis=0)
                # below the tangent plane the surface itself blocks the direction
                h = (~_occluded_brute_force(all_v[all_f], origins[0], dirs)
                     & (dirs @ nrm > -BELOW_PLANE))
            else:
                h = np.ones(m, bool)
            v = eye - x
            v = v / np.linalg.norm(v)
            r = 2 * np.dot(nrm, v) * nrm - v
            num = den = 0.0
            for j in range(m):
                cos = max(float(np.dot(nrm, dirs[j])), 0.0)
                den += cos * omega[j]
                if not h[j]:
                    continue
                num += cos * omega[j]
                out["diffuse"][i] += rad[j] * cos * omega[j]
                rc = max(float(np.dot(r, dirs[j])), 0.0)
                for alpha in settings.phong:
                    out[phong_name(alpha)][i] += ((alpha + 2) / (2 * math.pi) * rad[j]
                                                  * rc ** alpha * omega[j])
                if settings.ggx:
                    out["ggx"][i] += rad[j] * _ggx_brdf_scalar(nrm, v, dirs[j], rough[i],
                                                               settings.f0, settings.shadowing) * cos * omega[j]
            out["visibility"][i] = num / den if den > 0 else 0.0
        results.append(out)
    return results


def _occluded_brute_force(triangles: np.ndarray, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """[M] bool: does the ray origin + t·dir, t > 0, hit any of ``triangles`` [F, 3, 3]?

    Float64 Möller–Trumbore against every triangle (O(F·M)); degenerate triangles
    (zero area) never hit.  The slow, obviously correct twin of embree's query.
    """
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    e1, e2 = b - a, c - a                                          # [F, 3]
    p = np.cross(dirs[:, None, :], e2[None, :, :])                 # [M, F, 3]
    det = np.einsum("mfk,fk->mf", p, e1)
    ok = np.abs(det) > 1e-300
    inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
    s = origin[None, :] - a                                        # [F, 3]
    u = np.einsum("mfk,fk->mf", p, s) * inv
    q = np.cross(s, e1)                                            # [F, 3]
    v = (dirs @ q.T) * inv                                         # [M, F]
    t = np.einsum("fk,fk->f", q, e2)[None, :] * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return hit.any(axis=1)


def _ggx_brdf_scalar(n, v, l, roughness, f0, shadowing="smith"):
    """f_s(l, v) of the GGX lobe, uncancelled form D F G / (4 n·l n·v), one direction (slow
    twin); G1 exact Smith, 2 / (1 + √(1 + α² tan²θ)) (Walter et al. 2007 Eq. 34), or the
    Schlick–Smith remap."""
    nl, nv = float(np.dot(n, l)), float(np.dot(n, v))
    if nl <= 0 or nv <= 0:
        return 0.0
    rho = min(max(float(roughness), MIN_ROUGHNESS), 1.0)
    alpha = rho * rho
    k = (rho + 1) ** 2 / 8
    hv = (l + v) / np.linalg.norm(l + v)
    nh, vh = float(np.dot(n, hv)), float(np.dot(v, hv))
    d = alpha ** 2 / (math.pi * (nh ** 2 * (alpha ** 2 - 1) + 1) ** 2)
    f = f0 + (1 - f0) * (1 - vh) ** 5
    if shadowing == "smith":
        def g1(c):
            return 2 / (1 + math.sqrt(1 + alpha ** 2 * (1 - c * c) / (c * c)))
        g = g1(nl) * g1(nv)
    else:
        g = (nl / (nl * (1 - k) + k)) * (nv / (nv * (1 - k) + k))
    return d * f * g / (4 * nl * nv)


# ---------------------------------------------------------------- torch


def ggx_specular_torch(normals, view, directions, weighted_radiance, visibility, roughness,
                       f0: float = 0.04, shadowing: str = "smith"):
    """Differentiable GGX specular feature g_i (torch), visibility fixed.

    Same lobe as :func:`ggx_weights`; gradients flow to ``normals`` (normalized
    inside, so any non-zero vector works) and ``roughness``.

    Args:
        normals: [N, 3] tensor (need not be unit).
        view: [N, 3] unit tensor towards the eye.
        directions: [M, 3] unit tensor.
        weighted_radiance: [M, C] tensor L(ω_m)·Δω_m.
        visibility: [N, M] tensor h (0/1 or soft), treated as constant.
        roughness: scalar or [N] tensor ρ (clamped to [MIN_ROUGHNESS, 1]).
        f0: Fresnel reflectance at normal incidence.

    Returns:
        [N, C] tensor Σ_m L Δω h f_s max(n·ω, 0).
    """
    import torch

    rho = torch.as_tensor(roughness, dtype=normals.dtype, device=normals.device)
    rho = rho.reshape(-1, 1) if rho.ndim else rho
    w = ggx_cosine_torch(normals[:, None, :], view[:, None, :], directions[None, :, :], rho, f0,
                         shadowing)
    return (visibility.detach() * w) @ weighted_radiance


# ---------------------------------------------------------------- texel maps


def texel_maps(features: dict, faces: np.ndarray, raster) -> dict:
    """Per-vertex features → texel-aligned maps over a mesh's UV rasterization.

    Args:
        features: name → [V, 3] or [V] per-vertex values (one mesh).
        faces: [F, 3] geometric faces (the same triangle order as the rasterized
            ``faces_uv``).
        raster: :class:`relight_cli.uvraster.UVRaster` of the mesh's UV layout.

    Returns:
        name → [H, W, 3] / [H, W] float32 maps, barycentrically interpolated inside
        the charts and dilation-filled outside, plus ``mask`` [H, W] (1 inside).
    """
    names = list(features)
    widths = [np.asarray(features[k]).reshape(len(features[k]), -1).shape[1] for k in names]
    stacked = np.concatenate([np.asarray(features[k], np.float64).reshape(len(features[k]), -1)
                              for k in names], axis=1)
    image = raster.interpolate(stacked, faces, fill="dilate")             # [H, W, ΣC]
    out = {}
    start = 0
    for name, width in zip(names, widths):
        block = image[..., start:start + width].astype(np.float32)
        out[name] = block[..., 0] if np.ndim(features[name]) == 1 else block
        start += width
    out["mask"] = raster.mask
    return out
