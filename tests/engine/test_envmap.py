"""Environment-map geometry, resampling and I/O against independent references."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from conftest import shared_path
from relight_cli import envmap as E
from relight_cli.builtin_envs import builtin_envmap
from relight_cli.errors import DataError
from relight_cli.formats.envmap import EnvMap, handle_nonfinite, read_envmap, write_envmap

AXES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)


@pytest.mark.parametrize("h,w", [(2, 2), (3, 5), (16, 32), (17, 31), (500, 1000)])
def test_latlong_solid_angles_sum_to_4pi(h, w):
    assert abs(E.latlong_solid_angles(h, w).sum() - 4 * math.pi) < 1e-12


@pytest.mark.parametrize("n", [1, 2, 3, 8, 65])
def test_cube_solid_angles_sum_to_4pi(n):
    assert abs(E.cube_solid_angles(n).sum() - 4 * math.pi) < 1e-12


def test_latlong_cell_solid_angle_matches_quadrature():
    """Cell of texel (y, x) = ∫∫ cos φ dφ dλ over its (clipped) lat/long bounds."""
    h, w = 9, 14
    omega = E.latlong_solid_angles(h, w)
    for y, x in [(0, 0), (4, 7), (8, 13), (3, 1)]:
        lat_hi = min(math.pi / 2, math.pi / 2 - math.pi * (y - 0.5) / (h - 1))
        lat_lo = max(-math.pi / 2, math.pi / 2 - math.pi * (y + 0.5) / (h - 1))
        lon_hi = min(math.pi, math.pi - 2 * math.pi * (x - 0.5) / (w - 1))
        lon_lo = max(-math.pi, math.pi - 2 * math.pi * (x + 0.5) / (w - 1))
        ref, _ = integrate.dblquad(lambda phi, lam: math.cos(phi), lon_lo, lon_hi, lat_lo, lat_hi)
        assert omega[y, x] == pytest.approx(ref, rel=1e-10)


def test_cube_cell_solid_angle_matches_quadrature():
    """On a unit-distance face, dω = da db / (1 + a² + b²)^(3/2)."""
    n = 5
    omega = E.cube_solid_angles(n)
    _, px, py = E._cube_position_in_face(n)
    for r, c in [(0, 0), (2, 2), (13, 4), (29, 1)]:
        a0, a1 = [v.item() for v in E._cube_cell_bounds(np.array([px[r, c]]), n)]
        b0, b1 = [v.item() for v in E._cube_cell_bounds(np.array([py[r, c]]), n)]
        ref, _ = integrate.dblquad(lambda b, a: (1 + a * a + b * b) ** -1.5, a0, a1, b0, b1)
        assert omega[r, c] == pytest.approx(ref, rel=1e-9)


def test_latlong_directions_follow_openexr():
    h, w = 9, 17  # odd sizes put pixel centres exactly on the axes
    d = E.latlong_directions(h, w)
    np.testing.assert_allclose(d[0, 3], [0, 1, 0], atol=1e-12)            # top row: +Y
    np.testing.assert_allclose(d[h - 1, 5], [0, -1, 0], atol=1e-12)       # bottom row: −Y
    np.testing.assert_allclose(d[4, 8], [0, 0, 1], atol=1e-12)            # centre: +Z
    np.testing.assert_allclose(d[4, 4], [1, 0, 0], atol=1e-12)            # quarter from left: +X
    np.testing.assert_allclose(d[4, 12], [-1, 0, 0], atol=1e-12)          # three quarters: −X
    lon = np.arctan2(d[4, :, 0], d[4, :, 2])
    assert lon[1] > lon[-2]  # longitude decreases left to right (+π … −π)


def test_cube_face_centres_and_round_trip():
    n = 9
    d = E.cube_directions(n)
    for face, axis in enumerate(AXES):
        np.testing.assert_allclose(d[face * n + n // 2, n // 2], axis, atol=1e-12)
    # Interior texels (not on face edges, which two faces share) map back to themselves.
    rows, cols = np.mgrid[0:6 * n, 0:n]
    interior = ((rows % n) > 0) & ((rows % n) < n - 1) & (cols > 0) & (cols < n - 1)
    p = E.cube_pixel(d[interior], n)
    np.testing.assert_allclose(p, np.stack([cols[interior], rows[interior]], 1), atol=1e-9)


def test_cube_orientation_matches_imfenvmap_pixel_position():
    """Spot values of OpenEXR's CubeMap::pixelPosition (worked by hand from ImfEnvmap.cpp)."""
    n = 4  # face coordinate a = pif / (n − 1) · 2 − 1, so pif 1 ↔ −1/3, pif 2 ↔ +1/3
    # +Y, positionInFace (1, 0): direction (−1/3, 1, −1); pixel (min.x + 1, max.y − 0) = (1, 11).
    np.testing.assert_allclose(E.cube_pixel(np.array([[-1 / 3, 1, -1]]), n), [[1, 11]], atol=1e-9)
    # +Z, positionInFace (1, 2): direction (−1/3, 1/3, 1); pixel (max.x − 1, max.y − 2) = (2, 17).
    np.testing.assert_allclose(E.cube_pixel(np.array([[-1 / 3, 1 / 3, 1]]), n), [[2, 17]], atol=1e-9)
    # −Y, positionInFace (2, 1): direction (1/3, −1, −1/3); pixel (min.x + 2, min.y + 1) = (2, 13).
    np.testing.assert_allclose(E.cube_pixel(np.array([[1 / 3, -1, -1 / 3]]), n), [[2, 13]], atol=1e-9)
    # +X, positionInFace (2, 1): direction (1, 1/3, −1/3); pixel (min.x + 1, max.y − 2) = (1, 1).
    np.testing.assert_allclose(E.cube_pixel(np.array([[1, 1 / 3, -1 / 3]]), n), [[1, 1]], atol=1e-9)


def _random_env(h, w, seed=0, layout="latlong"):
    rng = np.random.default_rng(seed)
    return EnvMap(rng.gamma(0.5, 2.0, size=(h, w, 3)).astype(np.float32), layout)


@pytest.mark.parametrize("size", [(16, 32), (8, 16), (64, 128), (13, 29), (200, 400)])
def test_latlong_resampling_preserves_power(size):
    env = _random_env(50, 100)
    out = E.resample(env, "latlong", *size)
    np.testing.assert_allclose(E.power(out), E.power(env), rtol=1e-6)


@pytest.mark.parametrize("degrees", [0.0, 37.5, 90.0, -180.0])
def test_rotation_preserves_power(degrees):
    env = _random_env(20, 40, seed=1)
    out = E.resample(env, "latlong", 20, 40, rotation=E.rotation_y(degrees))
    np.testing.assert_allclose(E.power(out), E.power(env), rtol=1e-6)


def test_rotation_moves_z_towards_x():
    env = builtin_envmap("builtin:point")
    src_dir = np.array(E.info(env)["dominant_direction"])
    out = E.resample(env, "latlong", 64, 128, rotation=E.rotation_y(90))
    got = np.array(E.info(out)["dominant_direction"])
    np.testing.assert_allclose(got, E.rotation_y(90) @ src_dir, atol=0.03)


def test_single_bright_texel_is_neither_lost_nor_nan():
    """A 1e6 'sun' in one texel keeps its power through every resampling path:
    exact lat-long, splatting (coarser targets) and gathering (finer targets)."""
    for src_h, layout, h, w in [(256, "latlong", 16, 32), (256, "latlong", 8, 16),
                                (256, "cube", 6 * 16, 16), (256, "cube", 6 * 64, 64),
                                (64, "cube", 6 * 64, 64), (64, "latlong", 256, 512)]:
        rad = np.full((src_h, 2 * src_h, 3), 0.5, np.float32)
        y, x = int(src_h * 0.27), int(src_h * 1.17)
        rad[y, x] = 1e6
        env = EnvMap(rad, "latlong")
        out = E.resample(env, layout, h, w)
        assert np.isfinite(out.radiance).all()
        # Peaks keep their power exactly on every path; the 0.5 background is
        # smooth, so the total is preserved to ~1e-5 (float32 storage and the
        # background's sub-cell discretization).
        np.testing.assert_allclose(E.power(out), E.power(env), rtol=1e-5)
        # Not smeared: the sun's power sits in about as many target texels as
        # its source texel overlaps (a few, times the upsampling area factor).
        omega = E.solid_angles(out)
        sun_power = 1e6 * E.latlong_solid_angles(src_h, 2 * src_h)[y, x]
        texel_power = np.sort((out.radiance[..., 0] * omega).ravel())[::-1]
        spread = max(1.0, h * w / (2 * src_h * src_h))
        assert texel_power[:int(np.ceil(6 * spread))].sum() > 0.9 * sun_power


def test_cube_latlong_round_trip():
    env = builtin_envmap("builtin:studio", 128, 64)
    cube = E.resample(env, "cube", 6 * 32, 32)
    back = E.resample(cube, "latlong", 64, 128)
    np.testing.assert_allclose(E.power(cube), E.power(env), rtol=2e-3)
    np.testing.assert_allclose(E.power(back), E.power(env), rtol=2e-3)
    # Per-texel agreement on a smooth environment (box filtering blurs sharp
    # light edges by design, so those are checked through power only).
    d = E.latlong_directions(64, 128)
    smooth = EnvMap((1.5 + 0.5 * d[..., [0, 1, 2]] + 0.3 * d[..., [1, 2, 0]] ** 2).astype(np.float32))
    cube_s = E.resample(smooth, "cube", 6 * 32, 32)
    back_s = E.resample(cube_s, "latlong", 64, 128)
    cube_s2 = E.resample(back_s, "cube", 6 * 32, 32)
    truth = 1.5 + 0.5 * E.cube_directions(32) + 0.3 * E.cube_directions(32)[..., [1, 2, 0]] ** 2
    assert np.abs(cube_s.radiance - truth).mean() < 0.01 * truth.mean()
    assert np.abs(cube_s2.radiance - cube_s.radiance).mean() < 0.01 * truth.mean()


def test_uniform_irradiance_is_pi():
    env = builtin_envmap("builtin:uniform", 32, 16)
    rng = np.random.default_rng(2)
    normals = rng.normal(size=(20, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # Cells are not split at the tangent plane, so the discretization error is ~1/H.
    np.testing.assert_allclose(E.irradiance(env, normals), math.pi, rtol=0.02)
    assert abs(E.power(env)[0] - 4 * math.pi) < 1e-9


@pytest.mark.parametrize("name", ["builtin:sky", "builtin:studio", "builtin:uniform", "builtin:point"])
def test_builtins_are_finite_and_positive(name):
    env = builtin_envmap(name, 64, 32)
    assert np.isfinite(env.radiance).all() and (env.radiance >= 0).all()
    assert E.power(env).min() > 0


def test_builtin_point_power_is_resolution_independent():
    for w, h in [(64, 32), (256, 128), (512, 256)]:
        # float32 storage of the radiance limits the match to ~1e-7
        np.testing.assert_allclose(E.power(builtin_envmap("builtin:point", w, h)), 10.0, rtol=1e-6)


def test_nonfinite_policies():
    rad = np.ones((4, 8, 3), np.float32)
    rad[0, 0, 0] = np.nan
    rad[1, 1, :] = np.inf
    rad[2, 2, 1] = -np.inf
    with pytest.raises(DataError, match="3 pixel"):
        handle_nonfinite(rad, "x.exr")
    assert handle_nonfinite(rad, "x.exr", "zero")[1, 1, 0] == 0
    clamped = handle_nonfinite(rad, "x.exr", "clamp")
    assert np.isfinite(clamped).all() and clamped[1, 1, 0] == 1.0


def test_exr_round_trip_is_exact(tmp_path):
    env = _random_env(6, 12, seed=3)
    for layout, e in [("latlong", env), ("cube", _random_env(12, 2, seed=4, layout="cube"))]:
        path = tmp_path / f"{layout}.exr"
        write_envmap(str(path), e, provenance={"format": "relight/envmap", "version": 1})
        back = read_envmap(str(path))
        assert back.layout == layout
        np.testing.assert_array_equal(back.radiance, e.radiance)


# ------------------------------------------------------------- real data


def test_openexr_orientation_cube_to_latlong():
    """OpenEXR's own pair: our cube → lat-long conversion must reproduce their lat-long."""
    lat = read_envmap(str(shared_path("envmaps", "OrientationLatLong.exr")))
    cube = read_envmap(str(shared_path("envmaps", "OrientationCube.exr")))
    assert (lat.layout, cube.layout) == ("latlong", "cube")
    converted = E.resample(cube, "latlong", lat.height, lat.width)
    mae = np.abs(converted.radiance - lat.radiance).mean()
    assert lat.radiance.mean() == pytest.approx(0.92, abs=0.05)
    assert mae <= 0.03, mae
    # The check can fail: a mirrored longitude is clearly worse.
    dirs = E.latlong_directions(lat.height, lat.width).reshape(-1, 3) * np.array([-1, 1, 1])
    mirrored = E.lookup(cube, dirs).reshape(lat.radiance.shape)
    assert np.abs(mirrored - lat.radiance).mean() > 2 * mae


def test_openexr_orientation_axis_labels_sit_on_our_axes():
    """The black axis glyphs of the lat-long file cluster at +X, +Z, −X (quarter, half, three quarters)."""
    lat = read_envmap(str(shared_path("envmaps", "OrientationLatLong.exr")))
    h, w = lat.height, lat.width
    band = lat.radiance[int(0.35 * h):int(0.65 * h)]
    dark = (band.max(axis=-1) < 0.05).any(axis=0)           # [W] columns holding glyph pixels
    cols = np.nonzero(dark)[0]
    dirs = E.latlong_directions(h, w)[h // 2]
    for axis in ([1, 0, 0], [0, 0, 1], [-1, 0, 0]):
        x_axis = int(np.argmax(dirs @ np.array(axis, float)))
        near = cols[np.abs(cols - x_axis) < w / 8]
        assert near.size > 5, axis
        assert abs(near.mean() - x_axis) < w / 16, (axis, near.mean(), x_axis)


def test_stage_env_cube_and_latlong_agree():
    lat = read_envmap(str(shared_path("envmaps", "StageEnvLatLong.exr")))
    cube = read_envmap(str(shared_path("envmaps", "StageEnvCube.exr")))
    assert lat.radiance.max() > 1000  # real HDR
    np.testing.assert_allclose(E.power(cube), E.power(lat), rtol=0.02)
    small_lat = E.resample(lat, "latlong", 64, 128)
    small_cube = E.resample(cube, "latlong", 64, 128)
    np.testing.assert_allclose(E.irradiance(small_cube, AXES), E.irradiance(small_lat, AXES), rtol=0.02)


def test_radiance_hdr_reads_as_latlong(tmp_path):
    """Non-EXR environments go through OpenImageIO as lat-long.

    RGBE shares one exponent per pixel, so each channel is exact only to
    2⁻⁷ of the pixel's largest channel."""
    import OpenImageIO as oiio
    rad = (np.random.default_rng(5).random((8, 16, 3)) * 100 + 0.01).astype(np.float32)
    path = str(tmp_path / "env.hdr")
    out = oiio.ImageOutput.create(path)
    assert out.open(path, oiio.ImageSpec(16, 8, 3, oiio.FLOAT))
    assert out.write_image(rad)
    out.close()
    env = read_envmap(path)
    assert env.layout == "latlong" and env.radiance.shape == (8, 16, 3)
    assert (np.abs(env.radiance - rad) <= rad.max(axis=-1, keepdims=True) * 2 ** -7).all()


# ---------------------------------------------------------------- bright sources (issue 50)


SUN = np.array([0.45, 0.6, 0.66]) / np.linalg.norm([0.45, 0.6, 0.66])   # builtin:sky's sun
SUN_POWER = 20.0 * E.luminance(np.array([1.0, 0.95, 0.85]))   # its disc's luminance power


def _angle_deg(a, b):
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1, 1))))


def test_sun_of_the_sky_is_kept_at_its_direction_and_power():
    """The generator's own sun (builtin_envs: a 1.5° disc of power 20 at SUN) against the
    default 32×16 grid: on the grid alone its brightest cell sits 6.5° away holding about
    half its power; kept apart it is one direction within 0.2° of the disc's centre carrying
    its power to 1 % (what the disc's anti-aliased rim below the threshold leaves in the
    grid), and the map's total power is unchanged."""
    env = builtin_envmap("builtin:sky")
    plain = E.discretize_env(env, 16, 32)
    lum = E.luminance(plain.radiance) * plain.solid_angle
    j = int(np.argmax(lum))
    assert _angle_deg(plain.directions[j], SUN) > 5.0 and lum[j] < 0.7 * SUN_POWER
    kept = E.discretize_env(env, 16, 32, sources="auto")
    assert kept.sources == 1 and len(kept.directions) == 16 * 32 + 1
    assert _angle_deg(kept.directions[-1], SUN) < 0.2
    sun_power = float(E.luminance(kept.radiance[-1]) * kept.solid_angle[-1])
    assert sun_power == pytest.approx(SUN_POWER, rel=0.01)
    for d in (plain, kept):
        np.testing.assert_allclose((d.radiance * d.solid_angle[:, None]).sum(0), E.power(env),
                                   rtol=1e-6)
        assert d.solid_angle.sum() == pytest.approx(4 * math.pi, rel=1e-12)
        assert np.all(d.solid_angle > 0)


def _irradiance_error(env, discrete, normals):
    """RMS over normals of the relative error of unshadowed irradiance Σ L max(n·ω, 0) Δω
    against the map's own texels (the exact integral of the piecewise-constant map,
    envmap.irradiance)."""
    truth = E.luminance(E.irradiance(env, normals))
    ours = E.luminance(np.clip(normals @ discrete.directions.T, 0, None)
                       @ (discrete.radiance * discrete.solid_angle[:, None]))
    return float(np.sqrt(np.mean(((ours - truth) / truth) ** 2)))


def _normals(n=400, seed=0):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_sources_make_sunlit_irradiance_exact_where_the_grid_is_not():
    """What keeping the sun apart buys a renderer: unshadowed irradiance on 400 random
    normals against the full map.  On the grid alone the sun's cell-centre direction is
    wrong by up to 6.5°, which moves irradiance by several percent on surfaces lit at
    grazing angles; kept apart, what remains is the grid's quadrature of the smooth sky."""
    env = builtin_envmap("builtin:sky")
    normals = _normals()
    plain = _irradiance_error(env, E.discretize_env(env, 16, 32), normals)
    kept = _irradiance_error(env, E.discretize_env(env, 16, 32, sources="auto"), normals)
    assert plain > 0.03 and kept < plain / 3, (plain, kept)


@pytest.mark.parametrize("name", ["venice_sunset_1k.hdr", "forest_slope_1k.hdr",
                                  "empty_warehouse_01_1k.hdr"])
def test_real_sunny_maps_keep_their_power_and_gain_accuracy(name):
    """Poly Haven maps (skipped without ../shared/data): power kept exactly, Σ Δω = 4π, and
    irradiance (RMS relative error over normals) no worse than the grid alone: measured
    0.49 → 0.43 % (venice_sunset), 0.44 → 0.38 % (forest_slope), 2.2 → 1.4 % (the
    warehouse's 8 lamps)."""
    from relight_cli.cli.inputs import load_envmap
    path = shared_path("envmaps", "polyhaven", name)
    env = load_envmap(str(path))
    kept = E.discretize_env(env, 16, 32, sources="auto")
    assert kept.sources >= 1
    np.testing.assert_allclose((kept.radiance * kept.solid_angle[:, None]).sum(0),
                               E.power(env), rtol=1e-6)
    assert kept.solid_angle.sum() == pytest.approx(4 * math.pi, rel=1e-12)
    normals = _normals(seed=1)
    plain = _irradiance_error(env, E.discretize_env(env, 16, 32), normals)
    assert _irradiance_error(env, kept, normals) <= plain * 1.001


def _sun_map(centre, radius_deg=0.6, power=50.0, h=256, w=512, layout="latlong"):
    rng = np.random.default_rng(7)
    sky = 0.2 + 0.05 * rng.random((h, w, 3))
    env = EnvMap(sky.astype(np.float32), "latlong")
    dirs = E.directions(env).reshape(h, w, 3)
    disc = (dirs @ centre) > math.cos(math.radians(radius_deg))
    omega = E.solid_angles(env)
    sky[disc] += power / omega[disc].sum()
    env = EnvMap(sky.astype(np.float32), "latlong")
    return env if layout == "latlong" else E.resample(env, "cube", 6 * 128, 128)


@pytest.mark.parametrize("centre", [[0.0, 1.0, 0.0],                       # on the pole row
                                    [0.0, 0.2, -1.0],                      # on the seam λ = ±π
                                    [0.7, 0.1, 0.7]])
@pytest.mark.parametrize("layout", ["latlong", "cube"])
def test_hard_sun_positions_keep_power_and_direction(centre, layout):
    """A sun on the pole, across the lat-long seam (λ = ±π: its texels fall into two
    regions, each its own source), and in a cube map (faces stacked in storage): every
    source carries its part of the power, and their power-weighted direction is the sun's."""
    centre = np.asarray(centre, np.float64) / np.linalg.norm(centre)
    env = _sun_map(centre, layout=layout)
    kept = E.discretize_env(env, 16, 32, sources="auto")
    assert kept.sources >= 1
    n = 16 * 32
    power = E.luminance(kept.radiance[n:]) * kept.solid_angle[n:]
    mean = power @ kept.directions[n:]
    assert _angle_deg(mean / np.linalg.norm(mean), centre) < 0.5
    assert float(power.sum()) == pytest.approx(50.0, rel=0.02)
    np.testing.assert_allclose((kept.radiance * kept.solid_angle[:, None]).sum(0), E.power(env),
                               rtol=1e-5)


def test_nothing_to_keep_apart():
    """A uniform map, a dark one, a broad bright region (a window larger than half a cell:
    the grid resolves it) and a map already on the grid give no sources; a bad count is a
    ValueError."""
    uniform = EnvMap(np.ones((64, 128, 3), np.float32), "latlong")
    dark = EnvMap(np.zeros((64, 128, 3), np.float32), "latlong")
    window = _sun_map(np.array([0.0, 0.0, 1.0]), radius_deg=25.0, h=64, w=128)
    on_grid = E.resample(builtin_envmap("builtin:sky"), "latlong", 16, 32)
    for env in (uniform, dark, window, on_grid):
        d = E.discretize_env(env, 16, 32, sources="auto")
        assert d.sources == 0 and len(d.directions) == 16 * 32
    with pytest.raises(ValueError, match="sources"):
        E.discretize_env(uniform, 16, 32, sources=-1)


def test_shared_directions_keep_each_maps_power():
    """Two maps with suns in different places on one direction set (bake-features bakes
    several maps on one visibility trace): each keeps its power and its own sun, is dark in
    the other's, and Σ Δω stays 4π; a grid-only map passes through unchanged."""
    a = E.discretize_env(_sun_map(np.array([0.7, 0.1, 0.7]) / math.sqrt(0.99)), 16, 32, "auto")
    b = E.discretize_env(builtin_envmap("builtin:sky"), 16, 32, "auto")
    shared = E.share_directions([a, b])
    assert all(np.array_equal(s.directions, shared[0].directions) for s in shared)
    assert shared[0].solid_angle.sum() == pytest.approx(4 * math.pi, rel=1e-12)
    for old, new in zip((a, b), shared):
        np.testing.assert_allclose((new.radiance * new.solid_angle[:, None]).sum(0),
                                   (old.radiance * old.solid_angle[:, None]).sum(0), rtol=1e-12)
    n = 16 * 32
    assert shared[0].radiance[n + a.sources:].max() == 0
    assert shared[1].radiance[n:n + a.sources].max() == 0
    plain = E.discretize_env(builtin_envmap("builtin:studio"), 16, 32)
    assert E.share_directions([plain])[0] is plain
