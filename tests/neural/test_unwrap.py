"""Unwrapping photos into the UV layout (relight_cli.neural.unwrap, relight personalize):
a known texture painted into synthetic photos comes back; irradiance under a uniform sky
meets its closed form; dividing it out gives the albedo of a Lambertian surface."""

from __future__ import annotations

import numpy as np
import pytest

from relight_cli.hand.model import builtin_hand
from relight_cli.jobs import personalize as P
from relight_cli.jobs.phone_scan import scan_cameras


def _texture(uv):
    """A smooth known RGB texture of (u, v)."""
    u, v = uv[..., 0], uv[..., 1]
    return np.stack([0.5 + 0.3 * np.sin(2 * np.pi * u), 0.4 + 0.2 * np.cos(2 * np.pi * v),
                     0.3 + 0.1 * np.sin(2 * np.pi * (u + v))], -1)


@pytest.fixture(scope="module")
def painted():
    """Six 160² photos of the relaxed hand whose pixels are the known texture at the UV
    the camera sees (the G-buffer's), masks where the hand is."""
    from relight_cli.bake import pose_scene
    from relight_cli.hand.poses import named_pose
    from relight_cli.render.gbuffer import render_gbuffer
    hand = builtin_hand()
    hand.hands[0].poses = named_pose("relaxed", "right", hand.rest_joints)[None]
    meshes = pose_scene(hand, 0, "fine")
    center = meshes[0].vertices.mean(0)
    views = []
    for cam in scan_cameras(center, 6, 0.3, 160):
        g = render_gbuffer(meshes, cam, aa=1)
        hit = (g.hand >= 0).reshape(160, 160)
        image = np.where(hit[..., None], _texture(g.uv).reshape(160, 160, 3), 0.0)
        views.append(P.ScanView(cam.name, cam, image, hit, 0))
    return hand, views


def test_a_painted_texture_unwraps_back(painted):
    from scipy.ndimage import binary_erosion
    hand, views = painted
    n = 64
    radiance, _, weight, inside = P._unwrap(hand, views, None, P.PersonalizeOptions(tex_res=n))
    c = (np.arange(n) + 0.5) / n
    u, v = np.meshgrid(c, 1 - c)                 # row 0 at v = 1 (uvraster.py)
    truth = _texture(np.stack([u, v], -1))
    seen = binary_erosion((weight > 0) & inside, iterations=2)   # away from chart edges
    assert seen.sum() > 0.4 * inside.sum()
    err = np.abs(radiance - truth)[seen]
    assert np.median(err) < 0.01 and np.percentile(err, 95) < 0.05, \
        (np.median(err), np.percentile(err, 95))
    # holes copy their nearest seen texel: the map is finite and within the texture's range
    assert np.isfinite(radiance).all() and radiance.min() >= 0 and radiance.max() <= 0.81


def test_uniform_sky_irradiance_is_pi_l_where_unoccluded():
    """Under a uniform sky of radiance L, E = π L on a texel that sees the whole
    hemisphere, less where the hand hides part of it — never more."""
    from relight_cli.bake import pose_scene
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.envmap import discretize_env
    from relight_cli.neural.geometry import PoseTexels
    from relight_cli.neural.unwrap import env_irradiance
    hand = builtin_hand()
    texels = PoseTexels(pose_scene(hand, 0, "fine"), 32)
    env = builtin_envmap("builtin:uniform")
    level = float(env.radiance[..., 0].mean())
    e = env_irradiance(texels, 0, discretize_env(env, 32, 64))[texels.inside(0)]
    np.testing.assert_allclose(np.percentile(e[:, 0], 99), np.pi * level, rtol=0.03)
    assert e.max() <= np.pi * level * 1.03
    assert np.median(e[:, 0]) < np.pi * level          # fingers hide part of the sky
    # a Lambertian texel of albedo a shows L = a E / π: dividing E out returns a / π
    albedo = 0.6
    from relight_cli.neural.unwrap import divide
    e_map = env_irradiance(texels, 0, discretize_env(env, 32, 64))
    inside = texels.inside(0)
    t = divide(albedo * e_map / np.pi, e_map, inside)
    lit = inside & (e_map[..., 0] > 0.25 * np.median(e_map[..., 0][inside]))
    np.testing.assert_allclose(t[lit], albedo / np.pi, rtol=1e-9)


def test_shading_map_keeps_broad_shading_and_leaves_fine_texture():
    """supp. 9's shading map: a broad shading ramp × a fine checker (skin detail): the map
    follows the ramp and leaves the checker in radiance / S."""
    from relight_cli.neural.unwrap import shading_map
    n = 48
    y, x = np.mgrid[0:n, 0:n]
    ramp = 0.4 + 0.8 * x / (n - 1)
    checker = 1 + 0.1 * np.where((x // 2 + y // 2) % 2 == 0, 1, -1)
    colour = np.array([0.5, 0.35, 0.3])
    radiance = (ramp * checker)[..., None] * colour
    s = shading_map(radiance, np.ones((n, n), bool), colour)
    inner = (slice(4, -4), slice(4, -4))
    assert np.abs(s[inner] / ramp[inner] - 1).max() < 0.05
    texture = radiance / s[..., None]
    fine = texture[..., 0] / colour[0]
    assert 0.17 < fine[inner].std() * 2 < 0.23         # the checker's ±10 % survives
