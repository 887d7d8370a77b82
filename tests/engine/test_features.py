"""Shading features: exact cases, the slow twin, Monte Carlo, hard cases, reuse.

Meshes are synthetic (icospheres, a closed box with a cavity, two touching
spheres) so every expected value is known independently of the hand model.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from relight_cli import envmap as E
from relight_cli.envmap import DiscreteEnv, discretize_env
from relight_cli.features import (FeatureBaker, FeatureSettings, PoseMesh, feature_names,
                                  ggx_weights, vertex_features_reference)
from relight_cli.geometry import scene_diagonal, vertex_normals
from relight_cli.formats.envmap import EnvMap

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"


def sphere(centre=(0, 0, 0), radius=0.05, sub=2, inward=False) -> PoseMesh:
    import trimesh
    s = trimesh.creation.icosphere(subdivisions=sub)
    faces = s.faces[:, ::-1] if inward else s.faces
    normals = -s.vertices if inward else s.vertices.copy()
    return PoseMesh(s.vertices * radius + np.asarray(centre, float), faces, normals, "sphere")


def box(extent=0.3) -> PoseMesh:
    import trimesh
    b = trimesh.creation.box(extents=[extent] * 3)
    return PoseMesh(b.vertices, b.faces, None, "box")


def grid_env(height, width, func) -> DiscreteEnv:
    """A DiscreteEnv whose radiance is ``func(directions)`` ([..., 3] → [...] or [..., 3])."""
    d = E.latlong_directions(height, width).reshape(-1, 3)
    value = np.asarray(func(d), np.float64)
    if value.ndim == 1:
        value = np.repeat(value[:, None], 3, axis=1)
    return DiscreteEnv(d, E.latlong_solid_angles(height, width).reshape(-1).copy(), value,
                       height, width, "analytic")


def smooth_sky(d):
    return 1.0 + 0.8 * d[..., 1] + 0.5 * d[..., 0] ** 2


ALL = FeatureSettings(shininess=(16, 32, 64), specular="both", roughness=0.4)


# ---------------------------------------------------------------- exact cases


def test_uniform_env_on_sphere_gives_pi_L():
    # Convex mesh, L = 2 everywhere: d = L·Σ max(n·ω,0)Δω → π·L.  At 64×128 the pixel-centre
    # quadrature of the clamped cosine is within 3e-4 of π for the sphere's normals
    # (the kink at the horizon dominates; 32×64 reaches 1.3e-3 near the poles, 16×32 3e-3),
    # so the 1e-3 relative bound holds with margin.
    env = grid_env(64, 128, lambda d: np.full(len(d), 2.0))
    baker = FeatureBaker([sphere(sub=2)], ALL, grid=env)
    f = baker.bake([env], eye=[0, 0, 1])[0][0]
    np.testing.assert_allclose(f["diffuse"], 2.0 * math.pi, rtol=1e-3)
    np.testing.assert_allclose(f["visibility"], 1.0, atol=1e-12)  # nothing occludes a convex mesh


def test_closed_cavity_gets_zero():
    # Receivers on a sphere facing inward inside a closed box: every ray hits a wall.
    cavity = sphere(radius=0.05, inward=True)
    env = grid_env(8, 16, lambda d: np.full(len(d), 7.0))
    baker = FeatureBaker([box(), cavity], ALL, grid=env)
    outer, inner = baker.bake([env], eye=[0.0, 0.0, 0.02])[0]
    for name in feature_names(ALL):
        assert np.all(inner[name] == 0), name
    # ... while the outside of the box sees light (the test could fail).
    assert outer["diffuse"].min() > 0
    # Rays were really traced for the inner receivers (not skipped).
    assert baker.stats.rays_traced > 0


def test_single_bright_texel():
    # One lit texel, unoccluded: d = L·Δω·cos θ, s(α) = (α+2)/(2π)·L·Δω·(r·ω)^α exactly.
    h, w = 8, 16
    texel = 2 * w + 5
    env = grid_env(h, w, lambda d: np.where(np.arange(len(d)) == texel, 3.0, 0.0))
    omega = env.solid_angle[texel]
    light = env.directions[texel]
    mesh = sphere(sub=2)
    eye = np.array([0.2, 0.1, 0.3])
    baker = FeatureBaker([mesh], ALL, grid=env)
    f = baker.bake([env], eye=eye)[0][0]
    n, _ = vertex_normals(mesh.vertices, mesh.faces, mesh.normals)
    cos = n @ light
    facing = cos > 1e-3       # well above the tangent plane: the sphere cannot occlude
    expect = 3.0 * omega * np.clip(cos, 0, None)
    np.testing.assert_allclose(f["diffuse"][facing, 0], expect[facing], rtol=1e-12)
    v = eye - mesh.vertices
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    r = 2 * np.sum(n * v, 1, keepdims=True) * n - v
    rc = np.clip(r @ light, 0, None)
    for alpha in (16, 32, 64):
        e = (alpha + 2) / (2 * math.pi) * 3.0 * omega * rc ** alpha
        sel = facing & (rc > 0.5)  # keep values far above the 1e-30 lobe truncation
        np.testing.assert_allclose(f[f"phong{alpha}"][sel, 1], e[sel], rtol=1e-12)


def test_no_visibility_equals_unshadowed_irradiance():
    # The --no-visibility ablation: diffuse is exactly envmap.irradiance (independent code).
    env_map = EnvMap(np.random.default_rng(0).random((8, 16, 3)).astype(np.float32))
    mesh = sphere(sub=1)
    occluder = sphere(centre=(0.06, 0, 0), radius=0.03)
    baker = FeatureBaker([mesh, occluder], FeatureSettings(visibility=False), env_res=(8, 16))
    f = baker.bake([env_map], eye=[0, 0, 1])[0][0]
    n, _ = vertex_normals(mesh.vertices, mesh.faces, mesh.normals)
    np.testing.assert_allclose(f["diffuse"], E.irradiance(env_map, n), rtol=1e-10)
    assert baker.stats.rays_traced == 0
    np.testing.assert_allclose(f["visibility"], 1.0)


def _rotation(axis, degrees):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = math.radians(degrees)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


def test_rotating_scene_and_env_together_changes_nothing():
    # Rotate the meshes, the eye AND the env directions by one arbitrary R: the discrete
    # sums have exactly the same terms, so only float32 ray rounding can differ.
    meshes = [sphere((-0.05, 0, 0)), sphere((0.05, 0, 0))]           # touching spheres
    env = grid_env(8, 16, smooth_sky)
    eye = np.array([0.1, 0.3, 0.4])
    base = FeatureBaker(meshes, ALL, grid=env).bake([env], eye)[0]
    R = _rotation([0.3, 1.0, -0.5], 37.0)
    rot_meshes = [PoseMesh(m.vertices @ R.T, m.faces, m.normals @ R.T) for m in meshes]
    rot_env = DiscreteEnv(env.directions @ R.T, env.solid_angle, env.radiance, 8, 16)
    rotated = FeatureBaker(rot_meshes, ALL, grid=rot_env).bake([rot_env], R @ eye)[0]
    for a, b in zip(base, rotated):
        for name in feature_names(ALL):
            # Summation order is the same; 1e-9 covers float64 rounding of rotated dot
            # products, plus at most a few ray flips at the contact point (each ≤ one
            # texel's term), checked by the looser per-vertex bound on 2 % of vertices.
            close = np.isclose(a[name], b[name], rtol=1e-9, atol=1e-12)
            close = close.all(axis=-1) if close.ndim > 1 else close
            assert close.mean() >= 0.98, name


# ---------------------------------------------------------------- twins and Monte Carlo


def test_fast_equals_slow_twin():
    # Two touching spheres + a sky with a sun texel, every feature, off-axis eye.
    meshes = [sphere((-0.05, 0, 0), sub=1), sphere((0.05, 0.0, 0), sub=1)]
    env = grid_env(6, 12, lambda d: smooth_sky(d) + 40.0 * (np.arange(len(d)) == 20))
    settings = FeatureSettings(shininess=(8, 32), specular="both", roughness=0.35)
    eye = [0.05, 0.2, 0.3]
    fast = FeatureBaker(meshes, settings, grid=env).bake([env], eye)[0]
    slow = vertex_features_reference(meshes, env, eye, settings)
    max_term = env.radiance.max() * env.solid_angle.max() * (32 + 2) / (2 * math.pi)
    for a, b in zip(fast, slow):
        for name in feature_names(settings):
            diff = np.abs(a[name] - b[name]).reshape(len(a[name]), -1).max(axis=1)
            scale = np.abs(b[name]).reshape(len(b[name]), -1).max(axis=1) + 1e-12
            exact = diff <= 1e-9 * scale
            # embree (float32) and trimesh (float64) may disagree on a ray grazing an edge
            # at the contact point; allow that on ≤ 3 % of vertices, and by ≤ 2 terms.
            assert exact.mean() >= 0.97, (name, exact.mean())
            assert diff.max() <= 2 * max_term, name


def test_culling_traces_fewer_rays_and_changes_nothing():
    # Directions below every tangent plane and unlit texels are skipped ...
    meshes = [sphere((-0.05, 0, 0), sub=2), sphere((0.05, 0, 0), sub=2)]
    half_dark = grid_env(8, 16, lambda d: np.where(d[:, 1] > 0, 1.0, 0.0))
    settings = FeatureSettings(shininess=(16,), specular="phong")
    baker = FeatureBaker(meshes, settings, grid=half_dark)
    culled = baker.bake([half_dark], eye=[0, 0, 1])[0]
    n_pairs = sum(len(m.vertices) for m in meshes) * len(half_dark.directions)
    assert baker.stats.rays_traced < 0.75 * n_pairs
    # ... and tracing everything gives the same features.
    full = FeatureBaker(meshes, settings, grid=half_dark)
    full.cache.require(np.ones(full.cache.traced.shape, bool))
    everything = full.bake([half_dark], eye=[0, 0, 1])[0]
    for a, b in zip(culled, everything):
        for name in feature_names(settings):
            np.testing.assert_array_equal(a[name], b[name])


def test_independent_monte_carlo_within_error_bars():
    # Continuous cosine-weighted Monte Carlo with the analytic sky (no texels at all) vs the
    # engine at 64×128.  Bound: 4 standard errors of the MC mean plus the engine's own
    # discretization error, estimated as its change from 32×64 to 64×128.
    from relight_cli.raytrace import RayScene
    meshes = [sphere((-0.05, 0, 0)), sphere((0.05, 0, 0))]
    settings = FeatureSettings(specular="none")
    coarse = grid_env(32, 64, smooth_sky)
    fine = grid_env(64, 128, smooth_sky)
    d_coarse = FeatureBaker(meshes, settings, grid=coarse).bake([coarse], [0, 0, 1])[0][0]
    d_fine = FeatureBaker(meshes, settings, grid=fine).bake([fine], [0, 0, 1])[0][0]
    scene = RayScene([(m.vertices, m.faces) for m in meshes])
    rng = np.random.default_rng(1234)
    m0 = meshes[0]
    offset = 1e-4 * scene_diagonal([(m0.vertices, m0.faces)])  # the engine's rule: own mesh
    n_samples = 20000
    for i in range(0, len(m0.vertices), 13):
        nrm = m0.normals[i] / np.linalg.norm(m0.normals[i])
        u1, u2 = rng.random(n_samples), rng.random(n_samples)
        r, phi = np.sqrt(u1), 2 * math.pi * u2
        helper = np.array([1.0, 0, 0]) if abs(nrm[0]) < 0.9 else np.array([0, 1.0, 0])
        t1 = np.cross(nrm, helper)
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(nrm, t1)
        dirs = (r * np.cos(phi))[:, None] * t1 + (r * np.sin(phi))[:, None] * t2 \
            + np.sqrt(1 - u1)[:, None] * nrm
        visible = ~scene.occluded(np.repeat((m0.vertices[i] + offset * nrm)[None], n_samples, 0),
                                  dirs)
        samples = math.pi * smooth_sky(dirs) * visible      # pdf = cos/π
        mean = samples.mean()
        stderr = samples.std() / math.sqrt(n_samples)
        disc = abs(d_fine["diffuse"][i, 0] - d_coarse["diffuse"][i, 0])
        assert abs(d_fine["diffuse"][i, 0] - mean) <= 4 * stderr + disc, (i, mean, stderr)


def test_ggx_albedo_is_physical():
    # White furnace: unoccluded GGX lobe integrated over a uniform env is the directional
    # albedo, which must lie in (0, 1) for F0 = 0.04 (energy conservation, independent check).
    env = grid_env(64, 128, lambda d: np.ones(len(d)))
    n = np.array([[0.0, 1.0, 0.0]] * 3)
    views = np.array([[0, 1, 0], [0.6, 0.8, 0], [0.995, math.sqrt(1 - 0.995 ** 2), 0]])
    for rough in (0.2, 0.5, 1.0):
        w = ggx_weights(n, views, env.directions, np.full(3, rough))
        albedo = w @ env.solid_angle
        assert np.all(albedo > 0.01) and np.all(albedo < 1.0), (rough, albedo)


# ---------------------------------------------------------------- reuse


def test_multi_env_reuses_visibility():
    meshes = [sphere((-0.05, 0, 0)), sphere((0.05, 0, 0))]
    envs = [grid_env(8, 16, smooth_sky), grid_env(8, 16, lambda d: 1 + d[:, 0]),
            grid_env(8, 16, lambda d: np.full(len(d), 0.5))]
    together = FeatureBaker(meshes, ALL, grid=envs[0])
    both = together.bake(envs, eye=[0, 0.2, 1])
    rays_once = together.stats.rays_traced
    separate = FeatureBaker(meshes, ALL, grid=envs[0])
    for k, env in enumerate(envs):
        single = separate.bake([env], eye=[0, 0.2, 1])[0]
        for a, b in zip(both[k], single):
            for name in feature_names(ALL):
                np.testing.assert_allclose(a[name], b[name], rtol=1e-12, atol=1e-15)
    # Every env lights every texel here, so the later bakes traced nothing new.
    assert separate.stats.rays_traced == rays_once
    before = separate.stats.rays_traced
    separate.bake([envs[1]], eye=[0, 0.2, 1])
    assert separate.stats.rays_traced == before


def test_env_discretization_preserves_power():
    rng = np.random.default_rng(3)
    env = EnvMap(rng.random((24, 48, 3)).astype(np.float32) * 10)
    d = discretize_env(env, 8, 16)
    np.testing.assert_allclose(d.radiance.T @ d.solid_angle, E.power(env), rtol=1e-6)


# ---------------------------------------------------------------- hard cases


def test_million_sun_no_overflow_no_nan():
    sun = 5 * 16 + 3
    env = grid_env(16, 32, lambda d: 0.5 + 1e6 * (np.arange(len(d)) == sun))
    meshes = [sphere((-0.05, 0, 0)), sphere((0.05, 0, 0))]
    f = FeatureBaker(meshes, ALL, grid=env).bake([env], eye=[0, 0, 1])[0]
    for mesh_feats in f:
        for name, v in mesh_feats.items():
            assert np.isfinite(v).all() and np.isfinite(v.astype(np.float32)).all(), name
            assert (v >= 0).all(), name
    # The sun dominates: the brightest diffuse is about 1e6·Δω (plus the dim sky).
    omega = env.solid_angle[sun]
    assert 0.5 * 1e6 * omega < f[0]["diffuse"].max() <= 1e6 * omega + 0.5 * 2 * math.pi


def test_real_hdr_stage_env():
    path = DATA / "envmaps" / "StageEnvLatLong.exr"
    if not path.exists():
        pytest.skip(f"shared data not present: {path}")
    from relight_cli.formats.envmap import read_envmap
    env = read_envmap(str(path))
    meshes = [sphere((-0.05, 0, 0)), sphere((0.05, 0, 0))]
    baker = FeatureBaker(meshes, ALL, env_res=(16, 32))
    f = baker.bake([env], eye=[0, 0, 1])[0]
    free = FeatureBaker(meshes, replace(ALL, visibility=False), env_res=(16, 32))
    unshadowed = free.bake([env], eye=[0, 0, 1])[0]
    for shadowed, bare in zip(f, unshadowed):
        for name, v in shadowed.items():
            assert np.isfinite(v).all(), name
            # h ≤ 1 term by term, so shadowed features never exceed unshadowed ones
            # (1e-12 relative: the same sums, only fewer terms).
            assert (v <= bare[name] * (1 + 1e-12) + 1e-300).all(), name
    # The touching spheres really shadow each other somewhere.
    assert (f[0]["diffuse"] < 0.99 * unshadowed[0]["diffuse"]).any()
    # Power of the 16×32 discretization equals the source's (the lamps are not lost).
    d = discretize_env(env, 16, 32)
    np.testing.assert_allclose(d.radiance.T @ d.solid_angle, E.power(env), rtol=1e-5)


def test_grazing_normals_and_views():
    # Normals exactly in the horizon plane of grid directions and views at 90°: finite features.
    env = grid_env(8, 16, smooth_sky)
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1], [0, 1e-9, 0.5]], float) * 0.1
    faces = np.array([[0, 2, 1], [0, 3, 2]])
    normals = np.array([[0, 1, 0], [0, 1, 0], [1, 0, 0], [0, 0, 1]], float)
    mesh = PoseMesh(verts, faces, normals)
    eye = np.array([10.0, 0.0, 0.0])   # in every receiver's tangent plane or behind it
    f = FeatureBaker([mesh], ALL, grid=env).bake([env], eye)[0][0]
    for name, v in f.items():
        assert np.isfinite(v).all(), name
    # Shading math at grazing angles against the twin (visibility off: rays skimming a
    # plane are legitimately ambiguous between float32 embree and the float64 twin).
    bare = replace(ALL, visibility=False)
    fast = FeatureBaker([mesh], bare, grid=env).bake([env], eye)[0][0]
    ref = vertex_features_reference([mesh], env, eye, bare)[0]
    for name in feature_names(ALL):
        np.testing.assert_allclose(fast[name], ref[name], rtol=1e-9, atol=1e-12)


def test_zero_area_faces_and_undefined_normals():
    s = sphere(sub=1)
    nv = len(s.vertices)
    verts = np.concatenate([s.vertices, [[0.0, 0.2, 0.0]]])          # an isolated vertex
    faces = np.concatenate([s.faces, [[0, 0, 1], [2, 2, 2]]])         # zero-area faces
    normals = np.concatenate([s.normals, [[np.nan, 0, 0]]])
    normals[3] = 0                                                     # repaired from faces
    mesh = PoseMesh(verts, faces, normals)
    env = grid_env(8, 16, smooth_sky)
    f = FeatureBaker([mesh], ALL, grid=env).bake([env], eye=[0, 0, 1])[0][0]
    for name, v in f.items():
        assert np.isfinite(v).all(), name
        assert np.all(v[nv] == 0), name                                # undefined normal → 0
    assert f["diffuse"][3].min() > 0                                   # repaired normal works
    n, ok = vertex_normals(verts, faces, normals)
    assert ok[:nv].all() and not ok[nv]
    np.testing.assert_allclose(n[3], s.normals[3] / np.linalg.norm(s.normals[3]), atol=0.1)


def test_settings_validation():
    with pytest.raises(ValueError):
        FeatureSettings(specular="blinn")
    with pytest.raises(ValueError):
        FeatureSettings(shininess=(-1,))
    assert feature_names(FeatureSettings(shininess=(16, 2.5), specular="both")) == \
        ["diffuse", "phong16", "phong2.5", "ggx", "visibility"]


def test_cached_transport_extends_when_new_texels_light_up():
    # A dark-below env first, then one lit below: the Phong lobes now need rays below
    # the tangent planes, so the cache must trace more and still match a fresh baker.
    meshes = [sphere((-0.05, 0, 0)), sphere((0.05, 0, 0))]
    top = grid_env(8, 16, lambda d: np.where(d[:, 1] > 0, 1.0, 0.0))
    everywhere = grid_env(8, 16, lambda d: 1.0 + 0 * d[:, 1])
    eye = [0.0, -0.3, 0.2]
    baker = FeatureBaker(meshes, ALL, grid=top)
    baker.bake([top], eye)
    first = baker.stats.rays_traced
    again = baker.bake([everywhere], eye)[0]
    assert baker.stats.rays_traced > first
    fresh = FeatureBaker(meshes, ALL, grid=top).bake([everywhere], eye)[0]
    for a, b in zip(again, fresh):
        for name in feature_names(ALL):
            np.testing.assert_allclose(a[name], b[name], rtol=1e-12, atol=1e-15)


# ---------------------------------------------------------------- threads and chunking


def test_row_chunks_cover_every_row_once():
    from relight_cli.visibility import _row_chunks
    rng = np.random.default_rng(3)
    for n, workers in ((1, 1), (7, 2), (500, 2), (3000, 4)):
        per_row = rng.integers(0, 400, n)
        chunks = _row_chunks(per_row, workers)
        rows = np.concatenate([np.arange(c.start, c.stop) for c in chunks])
        np.testing.assert_array_equal(rows, np.arange(n))      # contiguous, ordered, no gaps


def test_threaded_trace_equals_one_flat_embree_call(monkeypatch):
    # The threaded, chunked, tiled ray building must trace exactly the rays a single
    # flat RayScene.occluded call on the (receiver, direction) pairs traces.  Tiny chunk
    # and tile sizes force many chunks and sub-tiles on a small scene.
    from relight_cli import visibility as V
    from relight_cli.raytrace import RayScene
    monkeypatch.setattr(V, "_MIN_CHUNK", 64)
    monkeypatch.setattr(V, "_TILE", 700)       # not a multiple of M: ragged sub-tiles
    meshes = [sphere((-0.05, 0, 0), sub=2), sphere((0.05, 0, 0), sub=2)]
    env = grid_env(8, 16, smooth_sky)
    need = np.random.default_rng(5).random((sum(len(m.vertices) for m in meshes), 128)) < 0.6
    results = []
    for threads in (1, 2, 3):
        baker = FeatureBaker(meshes, ALL, grid=env, threads=threads)
        count = baker.cache.require(need)
        assert count == need.sum() == baker.cache.rays_traced == baker.cache.scene.rays_traced - 1
        results.append(baker.cache.visible.copy())
    cache = baker.cache
    ii, mm = np.nonzero(need)
    flat = RayScene([(m.vertices, m.faces) for m in meshes]).occluded(
        cache.ray_origins()[ii], cache.directions.astype(np.float32)[mm])
    expect = np.zeros_like(need)
    expect[ii, mm] = ~flat
    for visible in results:
        np.testing.assert_array_equal(visible, expect)
    assert expect.any() and (need & ~expect).any()              # both outcomes occur


def test_bake_does_not_depend_on_threads(monkeypatch):
    # The per-pose pipeline over receiver chunks (cull, trace, transport, shade per chunk)
    # gives bit-identical features and ray counts for any thread count, and for an extra
    # env map shaded from the cached transport on the pool.
    from relight_cli import features as F
    monkeypatch.setattr(F, "_BLOCK", 16 * 128)                  # 16 receivers per block
    meshes = [sphere((-0.05, 0, 0), sub=2), sphere((0.05, 0, 0), sub=2)]
    envs = [grid_env(8, 16, smooth_sky), grid_env(8, 16, lambda d: 1 + d[:, 0])]
    out, rays = [], []
    for threads in (1, 2, 4):
        baker = FeatureBaker(meshes, ALL, grid=envs[0], threads=threads)
        first = baker.bake(envs[:1], eye=[0, 0.2, 1])
        second = baker.bake(envs[1:], eye=[0, 0.2, 1])              # cached transport
        out.append(first + second)
        rays.append(baker.stats.rays_traced)
    assert len(set(rays)) == 1
    for other in out[1:]:
        for env_a, env_b in zip(out[0], other):
            for a, b in zip(env_a, env_b):
                for name in feature_names(ALL):
                    np.testing.assert_array_equal(a[name], b[name])


def test_phong_odd_and_fractional_exponents_match_slow_twin():
    # The stacked transport folds h into the lobe before the powers ((h·x)^α = h·x^α
    # for α > 0); odd α multiplies several squarings, non-integer α takes np.power.
    meshes = [sphere((-0.05, 0, 0), sub=1), sphere((0.05, 0.0, 0), sub=1)]
    env = grid_env(6, 12, smooth_sky)
    settings = FeatureSettings(shininess=(1, 2.5, 7), specular="phong")
    eye = [0.05, 0.2, 0.3]
    fast = FeatureBaker(meshes, settings, grid=env).bake([env], eye)[0]
    slow = vertex_features_reference(meshes, env, eye, settings)
    for a, b in zip(fast, slow):
        for name in feature_names(settings):
            diff = np.abs(a[name] - b[name]).reshape(len(a[name]), -1).max(axis=1)
            scale = np.abs(b[name]).reshape(len(b[name]), -1).max(axis=1) + 1e-12
            # same float32-vs-float64 contact-ray allowance as test_fast_equals_slow_twin
            assert (diff <= 1e-9 * scale).mean() >= 0.97, name


def test_dot3_equals_matrix_product():
    from relight_cli.geometry import dot3
    rng = np.random.default_rng(2)
    v, d = rng.normal(size=(1001, 3)), rng.normal(size=(77, 3))
    # row blocks of BLAS products vs one product: the same sums, rounding only
    np.testing.assert_allclose(dot3(v, d), v @ d.T, rtol=1e-13, atol=1e-14)
