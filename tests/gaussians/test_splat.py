"""CPU EWA splatting: tiled fast path vs the per-pixel twin, and closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from relight_cli.formats.camera import Camera
from relight_cli.formats.gaussians_ply import SH_C0, Gaussians
from relight_cli.gaussians.splat import render, render_reference
from relight_cli.sh import sh_basis

# The fast path evaluates the same float64 formulas as the twin in another
# order (vectorized products, cumprod), so they agree to a few ulps; 1e-12
# leaves room for that while any logic difference (a skipped Gaussian, a wrong
# cut-off) would show up as ≥ 1/255 · colour.
TOL = 1e-12


def random_scene(n, seed, degree=1, spread=0.5, log_scale=(-4, -1.5), opacity=(0.05, 1.0)):
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    return Gaussians(rng.uniform(-spread, spread, (n, 3)), np.exp(rng.uniform(*log_scale, (n, 3))),
                     Rotation.random(n, random_state=seed).as_quat()[:, [3, 0, 1, 2]],
                     rng.uniform(*opacity, n), rng.normal(size=(n, k, 3)) * 0.5, degree)


def assert_twins(g, cam, **kw):
    fast = render(g, cam, background=(0.1, 0.2, 0.3), **kw)
    slow = render_reference(g, cam, background=(0.1, 0.2, 0.3))
    np.testing.assert_allclose(fast.image, slow.image, atol=TOL, rtol=0)
    np.testing.assert_allclose(fast.alpha, slow.alpha, atol=TOL, rtol=0)
    np.testing.assert_allclose(fast.depth, slow.depth, atol=TOL, rtol=0)
    return fast


@pytest.mark.parametrize("seed, tile, chunk", [(0, 16, 64), (1, 8, 3), (2, 5, 1)])
def test_fast_matches_twin_random(seed, tile, chunk):
    g = random_scene(40, seed, degree=2)
    cam = Camera.look_at([0.3, 0.2, 2.0], [0, 0, 0], width=37, height=29, fov_y_deg=40)
    out = assert_twins(g, cam, tile=tile, chunk=chunk)
    assert 0.05 < out.alpha.mean() < 0.95  # the scene actually covers part of the view


def test_fast_matches_twin_hard_cases():
    """Saturating opaque stacks (T < 1e-4 stop), flat/zero-scale splats, Gaussians behind the
    camera, straddling the near plane, huge ones off-screen whose footprint crosses the view."""
    rng = np.random.default_rng(5)
    parts = []
    # 1) 30 nearly opaque Gaussians stacked on the axis: pixels saturate and must stop.
    m = np.column_stack([rng.normal(0, 0.02, 30), rng.normal(0, 0.02, 30), np.linspace(-0.5, 0.5, 30)])
    parts.append((m, np.full((30, 3), 0.2), np.full(30, 0.995)))
    # 2) flat Gaussians (one zero scale) at random orientations.
    s = np.exp(rng.uniform(-4, -2, (10, 3)))
    s[:, 2] = 0.0
    parts.append((rng.uniform(-0.4, 0.4, (10, 3)), s, rng.uniform(0.3, 1, 10)))
    # 3) behind the camera and at the near plane (camera at z = 2 looking at −z).
    parts.append((np.array([[0, 0, 2.5], [0.01, 0, 1.995], [0, 0.01, 1.985]]), np.full((3, 3), 0.05),
                  np.full(3, 0.8)))
    # 4) large Gaussians whose centres are far outside the view.
    parts.append((np.array([[3.0, 0, 0], [0, -2.5, 0.5]]), np.array([[1.0, 0.5, 0.5], [0.3, 1.2, 0.3]]),
                  np.full(2, 0.6)))
    # 5) faint Gaussians below the 1/255 threshold everywhere.
    parts.append((rng.uniform(-0.3, 0.3, (5, 3)), np.full((5, 3), 0.1), np.full(5, 0.003)))
    means = np.concatenate([p[0] for p in parts])
    scales = np.concatenate([p[1] for p in parts])
    opac = np.concatenate([p[2] for p in parts])
    n = len(means)
    g = Gaussians(means, scales, Rotation.random(n, random_state=3).as_quat()[:, [3, 0, 1, 2]], opac,
                  rng.normal(size=(n, 4, 3)) * 0.4, 1)
    cam = Camera.look_at([0.0, 0.0, 2.0], [0, 0, 0], width=33, height=27, fov_y_deg=60)
    out = assert_twins(g, cam, tile=8, chunk=4)
    assert out.alpha.max() > 1 - 2e-4  # the opaque stack saturated (T stops near 1e-4)


def test_single_isotropic_gaussian_closed_form():
    """An isotropic Gaussian on the optical axis: Σ' = ((f σ / z)² + 0.3) I exactly (J at the axis)."""
    sigma, z, o = 0.05, 2.0, 0.7
    g = Gaussians([[0.0, 0.0, 0.0]], [[sigma] * 3], [[1, 0, 0, 0]], [o], np.zeros((1, 1, 3)), 0)
    W = H = 41
    cam = Camera.look_at([0, 0, z], [0, 0, 0], width=W, height=H, fov_y_deg=30)
    cam.K[0, 2] = cam.K[1, 2] = 20.0           # principal point on the centre pixel
    f = cam.K[0, 0]
    var = (f * sigma / z) ** 2 + 0.3
    out = render(g, cam)
    ys, xs = np.mgrid[0:H, 0:W]
    alpha = o * np.exp(-0.5 * ((xs - 20) ** 2 + (ys - 20) ** 2) / var)
    alpha = np.where(alpha >= 1 / 255, alpha, 0.0)
    np.testing.assert_allclose(out.alpha, alpha, atol=1e-12)
    np.testing.assert_allclose(out.image, np.repeat(0.5 * alpha[..., None], 3, axis=2), atol=1e-12)   # f_dc = 0 → grey 0.5
    np.testing.assert_allclose(out.depth, z * alpha, atol=1e-12)


def test_front_to_back_order():
    """Two overlapping Gaussians: C = c_near α_near + c_far α_far (1 − α_near), whatever the index order."""
    rgb = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])   # far red, near blue
    g = Gaussians([[0, 0, -0.5], [0, 0, 0.5]], [[0.3] * 3] * 2, [[1, 0, 0, 0]] * 2, [0.6, 0.5],
                  ((rgb - 0.5) / SH_C0)[:, None, :], 0)
    cam = Camera.look_at([0, 0, 3.0], [0, 0, 0], width=9, height=9, fov_y_deg=20)
    cam.K[0, 2] = cam.K[1, 2] = 4.0
    out = render(g, cam)
    a_near, a_far = 0.5, 0.6                          # both centred on pixel (4, 4)
    expected = rgb[1] * a_near + rgb[0] * a_far * (1 - a_near)
    np.testing.assert_allclose(out.image[4, 4], expected, atol=1e-12)


def test_sh_colour_follows_view_direction():
    """Degree-1 SH with only the Y_1^0 (= C1·z) coefficient: colour = 0.5 + c·C1·d_z."""
    c = 0.8
    sh = np.zeros((1, 4, 3))
    sh[0, 2, :] = c
    g = Gaussians([[0.0, 0.0, 0.0]], [[0.2] * 3], [[1, 0, 0, 0]], [0.98], sh, 1)
    for eye in ([0, 0, 3.0], [0, 0, -3.0], [3.0, 0, 1.0]):
        cam = Camera.look_at(eye, [0, 0, 0], width=5, height=5, fov_y_deg=10)
        cam.K[0, 2] = cam.K[1, 2] = 2.0
        d = -np.asarray(eye) / np.linalg.norm(eye)   # camera → Gaussian
        colour = 0.5 + c * sh_basis(d[None], 1)[0, 2]
        assert math.isclose(sh_basis(d[None], 1)[0, 2], math.sqrt(3 / (4 * math.pi)) * d[2])
        out = render(g, cam)
        np.testing.assert_allclose(out.image[2, 2], colour * 0.98, atol=1e-12)


def test_empty_and_all_behind():
    g = random_scene(5, 0)
    cam = Camera.look_at([0, 0, -5.0], [0, 0, -10.0], width=8, height=6)   # looking away
    out = render(g, cam, background=(1.0, 2.0, 3.0))
    assert np.all(out.alpha == 0) and np.all(out.image == np.array([1.0, 2.0, 3.0]))
