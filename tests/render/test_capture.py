"""The synthetic light stage (relight_cli/render/capture.py): dome and light groups, fully lit
irradiance, the multiplexed plan, two interacting hands, nails and regions, held-out env renders
against brute force and the sum of far LEDs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from relight_cli.render import capture as S


# ---------------------------------------------------------------- engine


def test_fibonacci_dome_and_light_groups():
    d = S.fibonacci_sphere(400)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, atol=1e-12)
    assert np.abs(d.mean(0)).max() < 0.01                  # evenly spread: centroid ≈ 0
    cams = S.dome_cameras(12, [0, 0.1, 0], 1.0, 16, 20)
    for cam in cams:
        np.testing.assert_allclose(np.linalg.norm(cam.center - [0, 0.1, 0]), 1.0, atol=1e-9)
        # The optical axis passes through the centre.
        p = cam.R @ np.array([0, 0.1, 0]) + cam.t
        assert abs(p[0]) < 1e-9 and abs(p[1]) < 1e-9 and p[2] > 0
    lights, names = S.dome_lights(100, [0, 0, 0], 1.2)
    group = S.light_group(lights.positions, 5, np.random.default_rng(0))
    assert len(group) == 5
    # A group is one light and its 4 nearest neighbours.
    assert any(sorted(np.argsort(np.linalg.norm(lights.positions - lights.positions[m], axis=1),
                                 kind="stable")[:5].tolist()) == group for m in group)


def test_fully_lit_stage_irradiance():
    """All LEDs on: irradiance on any unoccluded surface is ≈ π (see dome_lights)."""
    lights, _ = S.dome_lights(400, [0, 0, 0], 1.2)
    rng = np.random.default_rng(1)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    l = lights.positions / np.linalg.norm(lights.positions, axis=1, keepdims=True)
    e = (np.clip(n @ l.T, 0, None) / 1.2 ** 2) @ lights.radiant_intensity()[:, 0]
    # 400 lights sample the cosine lobe: quadrature error ~1%.
    np.testing.assert_allclose(e, math.pi, rtol=0.03)


def test_plan_is_deterministic_and_multiplexed():
    from relight_cli.hand.model import builtin_hand
    hand = builtin_hand()
    settings = S.StageSettings(cameras=3, lights=20, group=5, frames=7, full_every=3, res=8)
    a, b = S.plan_capture(hand, settings), S.plan_capture(hand, settings)
    assert a.key == b.key
    np.testing.assert_array_equal(a.motion.poses, b.motion.poses)
    assert [f.lit for f in a.frames] == ["full", "group", "group"] * 2 + ["full"]
    for f in a.frames:
        assert len(f.lights_on) == (20 if f.lit == "full" else 5)
    assert [f.lights_on for f in a.frames] == [f.lights_on for f in b.frames]
    other = S.plan_capture(hand, S.StageSettings(cameras=3, lights=20, frames=7, seed=1, res=8))
    assert other.key != a.key and not np.allclose(other.motion.poses, a.motion.poses)
    # Slerp motion: consecutive frames are close, key poses differ.
    step = np.abs(np.diff(a.motion.poses, axis=0)).max()
    assert 0 < step < 0.5


# ---------------------------------------------------------------- two interacting hands


def _surface_distance(a, b) -> float:
    """Exact smallest distance from a vertex of mesh ``a`` to the triangles of mesh ``b``
    (slow twin of the stage's vertex–vertex distance): for each of a's vertices near b, the
    closest point on every triangle of b that can hold it (a triangle whose corners lie
    within the nearest-vertex distance + the largest triangle diameter)."""
    import trimesh
    from scipy.spatial import cKDTree

    tree = cKDTree(b.vertices)
    d, _ = tree.query(a.vertices, k=1)
    tri = b.vertices[b.faces]
    diameter = np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=2).max()
    faces_of = [[] for _ in range(len(b.vertices))]
    for f, corners in enumerate(b.faces):
        for v in corners:
            faces_of[v].append(f)
    best = np.inf
    for i in np.nonzero(d < d.min() + 0.003)[0]:
        faces = np.unique(np.concatenate([faces_of[v] for v in
                                          tree.query_ball_point(a.vertices[i], d[i] + diameter)]))
        closest = trimesh.triangles.closest_point(tri[faces], np.repeat(a.vertices[i][None],
                                                                        len(faces), 0))
        best = min(best, float(np.linalg.norm(closest - a.vertices[i], axis=1).min()))
    return best


@pytest.fixture(scope="module")
def two_motion():
    from relight_cli.hand.model import builtin_hand
    from relight_cli.hand.scene import two_hands
    return S.hand_motion(two_hands(builtin_hand("right")), 12, seed=5, keyframe_every=4)


def test_two_hands_move_close_but_apart(two_motion):
    from relight_cli.hand.scene import handedness, posed_meshes
    motion = two_motion
    assert handedness(motion) == ["right", "left"] and len(motion.hands) == 2
    # both hands move: their own finger poses (not mirrors of each other) change over time
    for inst in motion.hands:
        assert np.abs(np.diff(inst.poses[:, 1:], axis=0)).max() > 1e-3
    from relight_cli.hand.skinning import mirror_pose
    assert not np.allclose(mirror_pose(motion.hands[0].poses[:, 1:]), motion.hands[1].poses[:, 1:])
    for f in range(0, 12, 3):
        m0, m1 = posed_meshes(motion, f, "fine")
        gap = min(_surface_distance(m0, m1), _surface_distance(m1, m0))
        # never touching (the documented margin), but interacting: a few centimetres at most
        assert S.TWO_HAND_MARGIN <= gap <= S.TWO_HAND_GAP[1] + 1e-3, (f, gap)
        assert S.hand_distance(motion, f) >= S.TWO_HAND_GAP[0] - 1e-9
    # held-out poses of a pair: every frame its own key pose, still apart
    held = S.hand_motion(motion, 3, seed=9, keyframe_every=1)
    assert all(S.hand_distance(held, f) >= S.TWO_HAND_GAP[0] - 1e-9 for f in range(3))
    assert not np.allclose(held.hands[1].translations, held.hands[1].translations[0])


def test_two_hands_shadow_occlude_and_light_each_other(two_motion):
    """What makes a pair harder than two single hands: with the other hand present, some
    texels lose LEDs (cast shadows), some camera samples see the other hand instead
    (occlusion), and one bounce brings light from the other hand's skin."""
    from relight_cli.hand.scene import posed_meshes
    from relight_cli.render.appearance import hand_materials
    from relight_cli.render.gbuffer import render_gbuffer
    from relight_cli.render.shading import HandRenderer, RenderSettings

    settings = S.StageSettings(cameras=8, lights=24, frames=12, res=24, tex_res=48)
    plan = S.plan_capture(two_motion, settings, motion=two_motion)
    meshes = posed_meshes(two_motion, 6, "fine")
    materials = hand_materials(two_motion, "fine", 64)
    rs = RenderSettings(tex_res=48, aa=1, sss=False, specular=False, direct="texel", bounce=True)
    both = HandRenderer(meshes, materials, rs)
    alone = HandRenderer(meshes[:1], materials[:1], rs)
    vis_both = both.light_visibility(0, positions=plan.lights.positions)
    vis_alone = alone.light_visibility(0, positions=plan.lights.positions)
    assert not (vis_both & ~vis_alone).any()                  # the other hand only takes light
    assert (vis_alone & ~vis_both).mean() > 0.002             # … and it does: cast shadows
    occluded = 0
    for cam in plan.cameras:
        gb_both = render_gbuffer(meshes, cam, 1)
        gb_alone = render_gbuffer(meshes[:1], cam, 1)
        occluded += int(((gb_alone.hand == 0) & (gb_both.hand == 1)).sum())
    assert occluded > 0
    lights = plan.lights
    bounce_both = both._bounce(both.light(lights).direct)[0]
    bounce_alone = alone._bounce(alone.light(lights).direct)[0]
    assert (bounce_both - bounce_alone).max() > 0.01 * bounce_alone.max()


def test_left_hand_skin_is_the_left_hand_of_the_pair():
    """One subject: the left hand of a two-hand scene has exactly the skin of a left-hand
    capture, the right that of a right-hand one (so per-hand teachers apply to the pair)."""
    from relight_cli.hand.model import builtin_hand
    from relight_cli.hand.scene import two_hands
    from relight_cli.render.appearance import hand_materials
    pair = hand_materials(two_hands(builtin_hand("right")), "fine", 64, seed=3)
    right = hand_materials(builtin_hand("right"), "fine", 64, seed=3)[0]
    left = hand_materials(builtin_hand("left"), "fine", 64, seed=3)[0]
    np.testing.assert_array_equal(pair[0].albedo, right.albedo)
    np.testing.assert_array_equal(pair[1].albedo, left.albedo)
    np.testing.assert_array_equal(pair[1].roughness, left.roughness)
    assert np.abs(left.albedo - right.albedo).max() > 0.01          # two different hands


def test_nails_and_regions_are_in_the_images():
    """The stage renders the procedural skin: pixels on nails are whiter (higher G/R) than
    pixels on finger skin in a fully lit frame, so a capture without region materials
    (a flat colour) would fail here."""
    from relight_cli.hand.model import FINGER, NAIL, builtin_hand
    from relight_cli.render.appearance import hand_materials
    from relight_cli.uvraster import rasterize_uv
    hand = builtin_hand(pose="relaxed")
    settings = S.StageSettings(cameras=6, lights=32, frames=1, res=96, tex_res=128, aa=1)
    plan = S.plan_capture(hand, settings, motion=hand)
    renderer = S.FrameRenderer(plan, hand_materials(plan.motion, "fine", 256), settings)
    fine = hand.fine
    raster = rasterize_uv(fine.uv, fine.faces_uv, 256)
    labels = raster.interpolate(np.eye(5)[fine.labels], fine.faces, fill=None)
    from relight_cli.render.appearance import bilinear
    ratio = {NAIL: [], FINGER: []}
    for cam, result in renderer.frame(plan.frames[0]):
        gb = result.gbuffer
        hit = gb.hit
        lab = np.argmax(bilinear(labels, gb.uv[hit]), 1)
        rad = result.samples[hit]
        for region in ratio:
            sel = (lab == region) & (rad[:, 0] > 0.05)
            ratio[region].extend(rad[sel, 1] / rad[sel, 0])
    assert len(ratio[NAIL]) > 20
    assert np.mean(ratio[NAIL]) > np.mean(ratio[FINGER]) + 0.05


# ---------------------------------------------------------------- held-out env maps


def test_stage_env_render_matches_brute_force():
    """An HDR through the stage: resampled once to the working grid (power kept; the
    resampling's exactness is tests/engine/test_envmap.py's), then the ground truth's texel
    irradiance = Σ over the grid's directions of L·h·max(n·ω, 0)·Δω, with h from
    brute-force ray–triangle tests (independent of embree and of features.py)."""
    from relight_cli import envmap as E
    from relight_cli.formats.envmap import EnvMap
    from relight_cli.raytrace import occluded_reference
    from relight_cli.render.appearance import constant_material
    from relight_cli.render.shading import HandRenderer, RenderSettings
    from render_scenes import uv_quad

    rng = np.random.default_rng(3)
    src = rng.exponential(0.5, (32, 64, 3)).astype(np.float32)
    src[5, 40] = 2000.0                                         # a small sun
    env = S.stage_envmap(EnvMap(src, "latlong", "hdr"), (8, 16))
    assert (env.height, env.width) == (8, 16)
    np.testing.assert_allclose(E.power(env), E.power(EnvMap(src, "latlong")), rtol=1e-6)
    assert S.stage_envmap(env, (8, 16)) is env                  # already on the grid: kept

    floor = uv_quad(0.2)
    blocker = uv_quad(0.08, z=0.03)                              # shades part of the floor
    blocker.vertices[:, 0] += 0.03
    white = constant_material(albedo=(1.0, 1.0, 1.0))
    renderer = HandRenderer([floor, blocker], [white, white],
                            RenderSettings(tex_res=12, aa=1, specular=False, sss=False,
                                           env_res=(8, 16), env_space="texels", direct="texel"))
    ours = renderer.light(env=env).direct[0]                    # [K, 3] floor texels
    surf = renderer.surfaces[0]
    dirs = E.latlong_directions(8, 16).reshape(-1, 3)
    dw = E.latlong_solid_angles(8, 16).reshape(-1)
    rad = env.radiance.reshape(-1, 3).astype(np.float64)
    verts = np.concatenate([floor.vertices, blocker.vertices])
    faces = np.concatenate([floor.faces, blocker.faces + len(floor.vertices)])
    cos = surf.normals @ dirs.T                                  # [K, M]
    ii, mm = np.nonzero(cos > 0)
    origins = surf.points[ii] + renderer.offsets[0] * surf.normals[ii]
    blocked = occluded_reference(verts, faces, origins, dirs[mm])
    expected = np.zeros_like(ours)
    np.add.at(expected, ii, (~blocked * cos[ii, mm] * dw[mm])[:, None] * rad[mm])
    assert blocked.any() and not blocked.all()
    np.testing.assert_allclose(ours, expected, rtol=1e-9, atol=1e-12 * expected.max())


def test_stage_env_render_is_the_sum_of_far_leds():
    """Superposition, the property every model of LED frames relies on (RelightableHands
    Eq. 2): with ``env_space="texels"`` (the stage's default since ``eval_env_space``) an
    env map of a few lit directions renders, SSS and GGX included, as the sum of far LEDs
    in those directions (r = 100 m, intensity r²·L Δω: the distant-light limit of the
    LEDs' own shading), through a camera.  The older per-vertex transport does not."""
    from relight_cli.envmap import DiscreteEnv, latlong_directions, latlong_solid_angles
    from relight_cli.hand.scene import posed_meshes
    from relight_cli.cli.inputs import load_hand
    from relight_cli.formats.lights_json import Lights
    from relight_cli.render.appearance import hand_materials
    from relight_cli.render.shading import HandRenderer, RenderSettings

    hand = load_hand("builtin:right")
    meshes = posed_meshes(hand, 0, "fine")
    materials = hand_materials(hand, "fine", 256, 0)
    centre = meshes[0].vertices.mean(0)
    camera = S.dome_cameras(3, centre, 1.0, 32, 30.0)[1]
    dirs = latlong_directions(8, 16).reshape(-1, 3)
    dw = latlong_solid_angles(8, 16).reshape(-1)
    far = 100.0

    def relative(space, cells, weights):
        r = HandRenderer(meshes, materials, RenderSettings(tex_res=64, aa=2, sss=True,
                                                           direct="texel", env_res=(8, 16),
                                                           env_space=space))
        rad = np.zeros((len(dirs), 3))
        rad[cells] = weights / dw[cells, None]                  # L Δω = weight
        env = r.render(camera, r.light(env=DiscreteEnv(dirs, dw, rad, 8, 16))).image
        leds = Lights.from_radiant_intensity(centre + far * dirs[cells], far * far * weights)
        led = r.render(camera, r.light(leds)).image
        assert led.sum() > 0
        return float(np.sum((env - led) ** 2) / np.sum(led ** 2))

    # one at a time (a backlit grazing one, 37, has the sharpest lobe), then three at once
    singles = [20, 37, 50, 70, 90]
    weights = np.array([[1.0, 0.8, 0.6], [0.3, 0.3, 0.3], [2.0, 2.0, 1.5]])
    for c in singles:
        assert relative("texels", [c], weights[:1]) < 1e-3, c
    assert relative("texels", [20, 37, 90], weights) < 1e-3
    assert max(relative("vertices", [c], weights[:1]) for c in singles) > 1e-2
