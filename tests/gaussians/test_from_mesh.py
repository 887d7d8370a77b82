"""Flat Gaussians from meshes: geometry, colours (texture/faces/constant), coverage."""

from __future__ import annotations

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")

from relight_cli.gaussians import transmittance as TR  # noqa: E402
from relight_cli.gaussians.from_mesh import gaussians_from_mesh, gaussians_from_trimesh  # noqa: E402


def test_single_triangle_covariance_and_frame():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0.2, 0.7, 0]])
    g = gaussians_from_mesh(v, [[0, 1, 2]], scale_factor=1.0, thickness=0.1)
    assert len(g) == 1
    np.testing.assert_allclose(g.means[0], v.mean(0), atol=1e-12)
    # Monte-Carlo covariance of the uniform triangle (the definition, not the formula)
    rng = np.random.default_rng(0)
    a, b = rng.uniform(size=(2, 400_000))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    pts = v[0] + a[:, None] * (v[1] - v[0]) + b[:, None] * (v[2] - v[0])
    cov_mc = np.cov(pts.T)
    cov = g.covariances()[0]
    thin = g.scales[0, 2] ** 2
    # in-plane block matches to MC noise (~1e-3 relative at 4e5 samples)
    np.testing.assert_allclose(cov[:2, :2], cov_mc[:2, :2], atol=3e-4)
    assert abs(cov[2, 2] - thin) < 1e-12 and g.scales[0, 2] < g.scales[0, 1] <= g.scales[0, 0]
    np.testing.assert_allclose(np.abs(g.normals[0]), [0, 0, 1], atol=1e-12)


def test_sphere_normals_outward_and_thin_axis_is_normal():
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    g = gaussians_from_trimesh(mesh, color=(0.8, 0.2, 0.1))
    assert len(g) == len(mesh.faces)
    assert np.all((g.normals * g.means).sum(1) > 0)
    R = g.rotation_matrices()
    np.testing.assert_allclose(np.abs((R[:, :, 2] * g.normals).sum(1)), 1, atol=1e-9)
    np.testing.assert_allclose(g.colors(), np.tile([0.8, 0.2, 0.1], (len(g), 1)), atol=1e-12)


def test_gaussian_sphere_casts_a_solid_shadow():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    g = gaussians_from_trimesh(mesh)
    # peak reproduces each splat's opacity along any ray through it: the shell is solid
    mix = TR.from_gaussians(g, "peak")
    light = np.array([0.0, 3.0, 0.0])
    inside = np.array([[0.0, -1.0, 0.0], [0.1, -1.0, 0.05], [-0.15, -1.0, -0.1]])
    outside = np.array([[0.6, -1.0, 0.0], [0.0, -1.0, -0.7]])
    assert TR.transmittance_between(mix, light, inside).max() < 1e-3
    assert TR.transmittance_between(mix, light, outside).min() > 0.999
    # the paper's avg (the default) gives a flat splat only τ*/√3 face-on (tr(A)/3 ≈ 1/(3s_z²)),
    # so two walls of the shell let through T ≈ (1 − α)^(2/√3): darker than 1 %, not 0.1 %
    avg = TR.from_gaussians(g)
    assert TR.transmittance_between(avg, light, inside).max() < 1e-2
    assert TR.transmittance_between(avg, light, outside).min() > 0.999


def test_texture_and_face_colours():
    # a unit quad with a 2×2 texture: bottom-left red, bottom-right green, top row blue
    v = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uv = v[:, :2].copy()
    from PIL import Image
    img = np.zeros((2, 2, 3), np.uint8)
    img[1, 0] = (255, 0, 0)      # bottom row (v = 0 bottom), left
    img[1, 1] = (0, 255, 0)
    img[0, :] = (0, 0, 255)
    tex = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(img))
    mesh = trimesh.Trimesh(v, f, visual=tex, process=False)
    g = gaussians_from_trimesh(mesh, scale_factor=1.0)
    # face 0's centroid uv (0.67, 0.33) is nearer the green texel, face 1's (0.33, 0.67) the blue
    c = g.colors()
    assert c[0, 1] > c[0, 0] and c[0, 1] > 0.2
    assert c[1, 2] > c[1, 0] and c[1, 2] > c[1, 1]
    # subdivision keeps texture lookups consistent
    gs = gaussians_from_trimesh(mesh, max_edge=0.2)
    assert len(gs) > 20 and np.all(np.isfinite(gs.colors()))
    # per-face colours
    fc = trimesh.Trimesh(v, f, face_colors=[[255, 0, 0, 255], [0, 0, 255, 255]], process=False)
    gc = gaussians_from_trimesh(fc)
    np.testing.assert_allclose(gc.colors(), [[1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_degenerate_faces_are_skipped_and_round_trip_ply(tmp_path):
    from relight_cli.formats.gaussians_ply import read_gaussians, write_gaussians
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]])
    g = gaussians_from_mesh(v, [[0, 1, 2], [0, 1, 3]])   # second face has zero area
    assert len(g) == 1
    path = tmp_path / "g.ply"
    write_gaussians(str(path), g)
    back = read_gaussians(str(path))
    np.testing.assert_allclose(back.means, g.means, atol=1e-6)
    with pytest.raises(ValueError):
        gaussians_from_mesh(v, [[0, 1, 2]], opacity=1.0)


# ------------------------------------------------------------------ a posed hand.npz as Gaussians


def _two_fists(tmp_path, two=True):
    from relight_cli.formats.hand_npz import write_hand
    from relight_cli.hand.model import builtin_hand
    from relight_cli.hand.scene import two_hands
    hand = builtin_hand("right", "fist")
    if two:
        hand = two_hands(hand)
    path = tmp_path / "hands.npz"
    write_hand(str(path), hand)
    return hand, str(path)


def test_hand_npz_gaussians_shadow_like_the_mesh(tmp_path):
    """The Gaussians of a posed hand .npz block light where the fine mesh does
    (embree against the same posed mesh), and let it through where the mesh misses."""
    from relight_cli.gaussians.from_mesh import hand_gaussians, load_gaussians
    from relight_cli.hand.scene import posed_meshes
    from relight_cli.raytrace import RayScene

    hand, path = _two_fists(tmp_path, two=False)
    g = load_gaussians(path)
    assert len(g) == sum(len(pm.faces) for pm in posed_meshes(hand, 0, "fine"))
    np.testing.assert_array_equal(g.means, hand_gaussians(hand, 0).means)
    meshes = posed_meshes(hand, 0, "fine")
    scene = RayScene([(pm.vertices, pm.faces) for pm in meshes])
    light = np.array([0.0, 2.0, 0.0])
    lo, hi = g.means.min(0), g.means.max(0)
    xs, zs = np.meshgrid(np.linspace(lo[0] - 0.02, hi[0] + 0.02, 24),
                         np.linspace(lo[2] - 0.02, hi[2] + 0.02, 16))
    floor = np.column_stack([xs.ravel(), np.full(xs.size, lo[1] - 0.05), zs.ravel()])
    d = light - floor
    dist = np.linalg.norm(d, axis=1)
    blocked = scene.occluded(floor, d / dist[:, None], dist)
    # a point counts as inside/outside the mesh shadow only if its 4 neighbours 3 mm away agree
    robust = np.ones(len(floor), bool)
    for off in ([3e-3, 0, 0], [-3e-3, 0, 0], [0, 0, 3e-3], [0, 0, -3e-3]):
        q = floor + off
        dq = light - q
        nq = np.linalg.norm(dq, axis=1)
        robust &= scene.occluded(q, dq / nq[:, None], nq) == blocked
    T = TR.transmittance_between(TR.from_gaussians(g, "peak"), light, floor)
    assert blocked[robust].any() and (~blocked[robust]).any()
    assert T[robust & blocked].max() < 0.05
    assert T[robust & ~blocked].min() > 0.95


def test_hand_npz_gaussians_colours_and_frames(tmp_path):
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.gaussians.from_mesh import hand_gaussians, load_gaussians
    from relight_cli.render.appearance import hand_materials

    hand, path = _two_fists(tmp_path)
    g = hand_gaussians(hand, 0)
    albedo = hand_materials(hand, "fine")[0].albedo
    rgb = g.colors()
    assert np.isfinite(rgb).all() and rgb.min() >= 0 and rgb.max() <= 1
    # per-region albedo, not one flat colour: the spread matches the material's own
    assert rgb.std(0).mean() > 0.2 * albedo.reshape(-1, 3).std(0).mean()
    with pytest.raises(DataError, match="out of range"):
        load_gaussians(path, frame=5)
    with pytest.raises(UsageProblem, match="hand .npz"):
        load_gaussians("builtin:hand", frame=0)
