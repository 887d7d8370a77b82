"""UV rasterization: against a per-texel brute-force twin, exact coverage cases, dilation."""

from __future__ import annotations

import numpy as np
import pytest

from relight_cli.uvraster import (dilate, rasterize_uv, rasterize_uv_reference,
                                  texel_centers)


def _grid_mesh(n: int, jitter: float = 0.0, seed: int = 0, margin: float = 0.0):
    """A n×n grid of quads split into triangles covering [margin, 1−margin]², optionally jittered."""
    rng = np.random.default_rng(seed)
    t = np.linspace(margin, 1 - margin, n + 1)
    uu, vv = np.meshgrid(t, t)
    uv = np.stack([uu.ravel(), vv.ravel()], 1)
    interior = (uu.ravel() > margin) & (uu.ravel() < 1 - margin) & \
               (vv.ravel() > margin) & (vv.ravel() < 1 - margin)
    uv[interior] += rng.uniform(-jitter, jitter, (interior.sum(), 2)) / n
    faces = []
    for i in range(n):
        for j in range(n):
            a = i * (n + 1) + j
            b, c, d = a + 1, a + n + 1, a + n + 2
            faces += [[a, b, d], [a, d, c]]
    return uv, np.array(faces)


def test_texel_centres_v_up():
    c = texel_centers(4, 2)
    # Row 0 is the top: largest v.  Bottom row centre v = 1/8.
    assert c[0, 0, 1] == pytest.approx(7 / 8)
    assert c[-1, 0, 1] == pytest.approx(1 / 8)
    assert c[0, 1, 0] == pytest.approx(3 / 4)


def test_bottom_triangle_lands_in_bottom_rows():
    # A triangle in the lower-left corner of UV space (v small) must occupy the bottom-left texels.
    uv = np.array([[0.0, 0.0], [0.5, 0.0], [0.0, 0.5]])
    r = rasterize_uv(uv, [[0, 1, 2]], 8)
    rows, cols = np.nonzero(r.inside)
    assert rows.min() >= 4 and cols.max() <= 3
    assert r.inside[7, 0] and not r.inside[0, 0]


def test_fast_matches_brute_force_twin():
    uv, faces = _grid_mesh(3, jitter=0.3, seed=1, margin=0.07)
    res = (11, 13)
    fast = rasterize_uv(uv, faces, res)
    covered, weights = rasterize_uv_reference(uv, faces, res)
    for r in range(res[0]):
        for c in range(res[1]):
            hits = covered[r, c]
            f = fast.face[r, c]
            if not hits:
                assert f == -1
                continue
            assert f in hits
            # Barycentrics agree to rounding (2×2 solve vs edge functions; both ~1e-15,
            # the fast path clamps tiny negatives on edges, hence 1e-9).
            np.testing.assert_allclose(fast.barycentric[r, c], weights[(r, c, f)], atol=1e-9)


def test_full_square_covers_every_texel_once():
    # Diagonals pass exactly through texel centres here: no texel may fall between triangles.
    uv, faces = _grid_mesh(4)
    r = rasterize_uv(uv, faces, 16)
    assert r.inside.all()
    assert not r.overlap.any()
    assert r.overlap_fraction() == 0.0
    np.testing.assert_allclose(r.barycentric.sum(-1), 1.0, atol=1e-12)


def test_overlap_detected():
    uv, faces = _grid_mesh(2, margin=0.1)
    # A second copy of the first triangle, stacked on top of the layout.
    uv2 = np.concatenate([uv, uv])
    faces2 = np.concatenate([faces, faces[:1] + len(uv)])
    r = rasterize_uv(uv2, faces2, 32)
    assert r.overlap.any()
    assert 0 < r.overlap_fraction() < 0.5
    assert not rasterize_uv(uv, faces, 32).overlap.any()


def test_zero_area_and_out_of_range_faces():
    uv = np.array([[0.1, 0.1], [0.9, 0.1], [0.1, 0.9], [0.5, 0.5], [2.0, 2.0], [3.0, 2.0], [2.0, 3.0]])
    # Face 1 is degenerate (a repeated vertex), face 2 lies outside [0,1]²: neither covers a texel.
    r = rasterize_uv(uv, [[0, 1, 2], [3, 3, 0], [4, 5, 6]], 16)
    assert set(np.unique(r.face)) == {-1, 0}
    with pytest.raises(ValueError):
        rasterize_uv(uv, [[0, 1, 99]], 8)
    empty = rasterize_uv(uv, np.zeros((0, 3), int), 8)
    assert not empty.inside.any()


def test_interpolation_reproduces_linear_function():
    # Per-vertex values linear in (u, v) must be reproduced exactly at every texel centre.
    uv, faces = _grid_mesh(5, jitter=0.25, seed=3, margin=0.05)
    r = rasterize_uv(uv, faces, 24)
    values = np.stack([2 * uv[:, 0] - uv[:, 1] + 0.5, uv[:, 1] * 3], 1)
    img = r.interpolate(values, faces, fill=None)
    centres = texel_centers(24, 24)
    expect = np.stack([2 * centres[..., 0] - centres[..., 1] + 0.5, centres[..., 1] * 3], -1)
    np.testing.assert_allclose(img[r.inside], expect[r.inside], atol=1e-12)
    assert (img[~r.inside] == 0).all()
    # With separate geometric indices: permuted vertex table, same triangles.
    perm = np.random.default_rng(0).permutation(len(uv))
    inv = np.argsort(perm)
    img2 = r.interpolate(values[perm], inv[faces], fill=None)
    np.testing.assert_allclose(img2, img, atol=1e-12)


def test_dilation_fills_everything_and_keeps_inside():
    uv, faces = _grid_mesh(2, margin=0.3)
    r = rasterize_uv(uv, faces, 32)
    values = np.full(len(uv), 5.0)
    img = r.interpolate(values, faces)               # default fill="dilate"
    # A constant stays constant everywhere: no zeros are pulled in at chart borders.
    np.testing.assert_allclose(img, 5.0)
    noisy = np.random.default_rng(0).normal(size=(32, 32, 2))
    out = dilate(noisy, r.inside, rings=2)
    np.testing.assert_array_equal(out[r.inside], noisy[r.inside])
    assert np.isfinite(out).all()
    # Values outside lie within the range of inside values (averages and copies only).
    assert out.min() >= noisy[r.inside].min() - 1e-12
    assert out.max() <= noisy[r.inside].max() + 1e-12


def test_bilinear_lookup_at_seam_never_pulls_zero():
    # Bilinear sampling right on a chart border must see only filled texels.
    import torch
    uv, faces = _grid_mesh(1, margin=0.25)
    r = rasterize_uv(uv, faces, 16)
    img = r.interpolate(np.ones(len(uv)), faces)
    t = torch.from_numpy(img)[None, None]
    # grid_sample: x = 2u − 1, y = 1 − 2v (image rows go down, v goes up).
    u = torch.tensor([0.25, 0.75, 0.25], dtype=torch.float64)
    v = torch.tensor([0.25, 0.75, 0.75], dtype=torch.float64)
    grid = torch.stack([2 * u - 1, 1 - 2 * v], -1)[None, None]
    s = torch.nn.functional.grid_sample(t, grid, mode="bilinear", align_corners=False)
    np.testing.assert_allclose(s.numpy().ravel(), 1.0, atol=1e-12)


# ---------------------------------------------------------------- seam-aware lookups


def _two_charts():
    """Two unit squares side by side in UV (x ∈ [0, ½] and [½, 1]), separate UV vertices
    (a seam): chart 0 left, chart 1 right."""
    uv = np.array([[0, 0], [0.5, 0], [0.5, 1], [0, 1],
                   [0.5, 0], [1, 0], [1, 1], [0.5, 1]], np.float64)
    faces_uv = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    return uv, faces_uv


def test_uv_charts_split_at_seams_not_at_shared_positions():
    from relight_cli.uvraster import uv_charts
    uv, faces_uv = _two_charts()
    assert uv_charts(faces_uv).tolist() == [0, 0, 1, 1]
    # one UV table shared by all four triangles: one chart
    assert uv_charts(np.array([[0, 1, 2], [0, 2, 3], [1, 5, 6], [1, 6, 2]])).tolist() == [0] * 4
    assert uv_charts(np.zeros((0, 3), np.int64)).shape == (0,)


def test_seam_taps_read_only_the_samples_chart():
    """A map holding 1 on chart 0's texels and 5 on chart 1's: a sample of chart 0 within
    half a texel of the seam reads exactly 1 seam-aware, a mix (3 at the seam) plain; far
    from the seam both agree with plain bilinear to rounding; weights sum to 1."""
    from relight_cli.uvraster import UVLayout, bilinear_taps, gather_taps, seam_taps
    uv, faces_uv = _two_charts()
    layout = UVLayout(uv, faces_uv)
    n = 8
    charts = layout.chart_map(n, n)
    assert (charts[:, :4] == 0).all() and (charts[:, 4:] == 1).all()
    # a gutter texel belongs to its nearest chart
    apart = uv * [0.8, 1.0] + np.array([[0.0, 0]] * 4 + [[0.2, 0]] * 4)   # x: [0, .4], [.6, 1]
    gap = UVLayout(apart, faces_uv).chart_map(10, 10)
    assert gap[0].tolist() == [0] * 4 + [0, 1] + [1] * 4
    image = np.where(charts == 0, 1.0, 5.0)
    pts = np.array([[0.499, 0.5], [0.47, 0.31], [0.501, 0.5], [0.2, 0.6], [0.999, 0.999]])
    faces = np.array([1, 0, 2, 1, 2])
    taps = layout.taps(pts, faces, n, n)
    got = gather_taps(image, taps)
    np.testing.assert_allclose(got, [1, 1, 5, 1, 5], rtol=0, atol=1e-12)
    plain = gather_taps(image, bilinear_taps(pts, n, n))
    from relight_cli.render.appearance import bilinear
    np.testing.assert_allclose(plain, bilinear(image, pts), rtol=1e-12)
    assert abs(plain[0] - 3.0) < 0.1 and abs(plain[2] - 3.0) < 0.1     # the leak it removes
    np.testing.assert_allclose(taps[2].sum(1), 1.0, rtol=1e-12)
    # a sample whose four taps are all of another chart keeps the plain weights
    alone = seam_taps(pts[:1], np.array([7]), charts)
    np.testing.assert_allclose(alone[2], bilinear_taps(pts[:1], n, n)[2])


def test_torch_lookup_is_the_seam_aware_one_with_gradients():
    import torch

    from relight_cli.render.gbuffer import GBuffer
    from relight_cli.render.shading import lookup_torch
    from relight_cli.uvraster import UVLayout, gather_taps
    uv, faces_uv = _two_charts()
    layout = UVLayout(uv, faces_uv)
    rng = np.random.default_rng(3)
    p = 12
    suv = rng.uniform(0.02, 0.98, (p, 2))
    face = np.where(suv[:, 0] < 0.5, 0, 2)
    hand = np.where(np.arange(p) % 5 == 4, -1, 0)
    gb = GBuffer(p, 1, 1, hand, face, np.zeros((p, 3)), suv, np.zeros((p, 3)),
                 np.zeros((p, 3)), np.ones(p), np.zeros((p, 3)), np.zeros(3), [layout])
    tex = torch.rand(6, 6, 2, dtype=torch.float64, requires_grad=True)
    got = lookup_torch(tex, gb).detach().numpy()
    want = np.zeros((p, 2))
    want[hand == 0] = gather_taps(tex.detach().numpy(), gb.taps(0, 6, 6)[1:])
    np.testing.assert_allclose(got, want, rtol=1e-12)
    np.testing.assert_allclose(gb.lookup(tex.detach().numpy(), 0), want[hand == 0], rtol=1e-12)
    assert torch.autograd.gradcheck(lambda t: lookup_torch(t, gb), (tex,))
