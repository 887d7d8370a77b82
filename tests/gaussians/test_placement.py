"""Placing Gaussian objects: similarity transforms (means, covariances, SH), robust fit/on-floor,
the placement spec language, multi-occluder DGSMs, and the CLI (dgsm-build OCCLUDER..., relight --object)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import run_relight, shared_path
from relight_cli.formats.camera import Camera, write_cameras
from relight_cli.formats.dgsm_exr import read_dgsm, write_dgsm
from relight_cli.formats.gaussians_ply import (Gaussians, concatenate, read_gaussians,
                                               rgb_to_sh_dc, write_gaussians)
from relight_cli.formats.lights_json import Lights, write_lights
from relight_cli.formats.sh_probe_json import ShProbe, write_probe
from relight_cli.gaussians import dgsm as D
from relight_cli.gaussians import placement as PL
from relight_cli.gaussians.splat import gaussian_colors, render
from relight_cli.sh import sh_basis


def random_gaussians(n=60, degree=3, seed=0, centre=(0, 0, 0), spread=0.1):
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    sh = rng.normal(scale=0.3, size=(n, k, 3))
    sh[:, 0] = rgb_to_sh_dc(rng.uniform(0.2, 0.8, (n, 3)))
    return Gaussians(rng.normal(size=(n, 3)) * spread + np.asarray(centre),
                     rng.uniform(0.005, 0.03, (n, 3)), Rotation.random(n, random_state=seed)
                     .as_quat()[:, [3, 0, 1, 2]], rng.uniform(0.3, 0.95, n), sh, degree,
                     rng.normal(size=(n, 3)))


def some_similarity(seed=1, scale=1.7):
    rot = Rotation.random(random_state=seed).as_matrix()
    return PL.Similarity(scale, rot, np.array([0.3, -0.2, 0.5]))


# ------------------------------------------------------------------ transforms


def test_covariances_transform_exactly():
    g = random_gaussians()
    sim = some_similarity()
    out = PL.transform_gaussians(g, sim)
    Q, s = sim.rotation, sim.scale
    expected = s ** 2 * np.einsum("ij,njk,lk->nil", Q, g.covariances(), Q)   # s² Q Σ Qᵀ
    # R' S'² R'ᵀ recomputed from the stored quaternion/scales: float64 round-off only.
    np.testing.assert_allclose(out.covariances(), expected, atol=1e-15, rtol=1e-12)
    np.testing.assert_allclose(out.means, s * g.means @ Q.T + sim.translation, atol=1e-14)
    np.testing.assert_allclose(out.normals, g.normals @ Q.T, atol=1e-14)
    np.testing.assert_array_equal(out.opacities, g.opacities)
    np.testing.assert_array_equal(g.scales, random_gaussians().scales)      # input untouched


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_sh_rotation_is_colour_in_rotated_direction(degree):
    """c'(d) = c(Qᵀ d) for every direction d (band l is closed under rotation)."""
    g = random_gaussians(n=5, degree=degree)
    Q = Rotation.random(random_state=7).as_matrix()
    rotated = PL.rotate_sh(g.sh, Q)
    d = np.random.default_rng(3).normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    new = np.einsum("mk,nkc->nmc", sh_basis(d, degree), rotated)
    old = np.einsum("mk,nkc->nmc", sh_basis(d @ Q, degree), g.sh)           # rows Qᵀ d
    np.testing.assert_allclose(new, old, atol=1e-11)   # least-squares blocks: round-off only
    for X in PL.sh_rotation_blocks(Q, degree):
        np.testing.assert_allclose(X @ X.T, np.eye(len(X)), atol=1e-11)     # orthogonal


def test_transformed_gaussians_render_as_a_transformed_camera():
    """Moving the object by x' = sQx + t and the camera with it gives the same image."""
    g = random_gaussians(n=80, degree=2, centre=(0, 0, 0), spread=0.08)
    cam = Camera.look_at([0.25, 0.2, 0.35], [0, 0, 0], width=48, height=40, fov_y_deg=50)
    sim = some_similarity(seed=4, scale=2.5)
    moved = PL.transform_gaussians(g, sim)
    # world→camera of the moved scene: x_c·s = R Qᵀ x' − R Qᵀ t + s t_c (projection ignores s)
    R2 = cam.R @ sim.rotation.T
    t2 = sim.scale * cam.t - R2 @ sim.translation
    cam2 = Camera(cam.K, R2, t2, cam.width, cam.height)
    a = render(g, cam, background=(0.1, 0.2, 0.3), near=1e-3)
    b = render(moved, cam2, background=(0.1, 0.2, 0.3), near=1e-3)
    assert a.alpha.max() > 0.5                                    # the object is in view
    np.testing.assert_allclose(b.image, a.image, atol=1e-9)      # round-off of the transforms
    np.testing.assert_allclose(b.alpha, a.alpha, atol=1e-9)
    np.testing.assert_allclose(b.depth, sim.scale * a.depth, atol=1e-8)
    # and view-dependent colours agree per Gaussian
    np.testing.assert_allclose(gaussian_colors(moved, cam2.center), gaussian_colors(g, cam.center),
                               atol=1e-11)


def test_scale_and_translate_compose():
    g = random_gaussians(degree=1)
    a, b = some_similarity(1, 0.5), some_similarity(2, 3.0)
    twice = PL.transform_gaussians(PL.transform_gaussians(g, a), b)
    once = PL.transform_gaussians(g, a.then(b))
    np.testing.assert_allclose(twice.means, once.means, atol=1e-13)
    np.testing.assert_allclose(twice.covariances(), once.covariances(), atol=1e-15, rtol=1e-11)
    np.testing.assert_allclose(twice.sh, once.sh, atol=1e-11)
    # spec order is fixed: scale, then rotation, then translate, whatever the order written
    p1 = PL.parse_placement("translate=1,2,3;rotate-y=90;scale=2")
    p2 = PL.parse_placement("scale=2;rotate-y=90;translate=1,2,3")
    s1, s2 = PL.resolve(p1, g), PL.resolve(p2, g)
    np.testing.assert_allclose(s1.apply(g.means), s2.apply(g.means), atol=1e-14)
    x = np.array([[1.0, 0, 0]])
    np.testing.assert_allclose(s1.apply(x), [[1.0, 2.0, 1.0]], atol=1e-14)   # 2·(0,0,−1)+(1,2,3)
    np.testing.assert_allclose(PL.place(g, PL.parse_placement("scale=3")).scales, 3 * g.scales)


@pytest.mark.parametrize("bad", [
    PL.Similarity(0.0, np.eye(3), np.zeros(3)),
    PL.Similarity(float("nan"), np.eye(3), np.zeros(3)),
    PL.Similarity(-1.0, np.eye(3), np.zeros(3)),
    PL.Similarity(1.0, np.diag([1.0, 1.0, -1.0]), np.zeros(3)),     # a mirror
    PL.Similarity(1.0, 2 * np.eye(3), np.zeros(3)),                 # not orthonormal
    PL.Similarity(1.0, np.eye(3), np.array([0, np.inf, 0])),
])
def test_bad_similarities_are_refused(bad):
    with pytest.raises(ValueError):
        PL.transform_gaussians(random_gaussians(n=3, degree=0), bad)


# ------------------------------------------------------------------ robust bounds, fit, floor


def test_weighted_percentile_matches_numpy_for_equal_weights():
    v = np.random.default_rng(0).normal(size=101)
    for q in (1, 25, 50, 99):
        assert PL.weighted_percentile(v, np.ones_like(v), q) == pytest.approx(
            np.percentile(v, q, method="hazen"), abs=1e-12)


def test_fit_on_floor_ignores_faint_floaters():
    rng = np.random.default_rng(5)
    body = random_gaussians(n=2000, degree=0, centre=(3, 5, -2), spread=1.0)
    body.means = rng.uniform([2, 4, -3], [4, 5, -2.5], (2000, 3))   # box 2 × 1 × 0.5
    body.opacities[:] = 0.9
    floaters = random_gaussians(n=10, degree=0, centre=(50, -40, 9), spread=5.0)
    floaters.opacities[:] = 0.02                                   # faint: 0.01 % of the mass
    g = concatenate([body, floaters])
    placed = PL.place(g, PL.parse_spec("x.ply:fit=0.5;on-floor;translate=0.1,0,-0.2")[1])
    lo, hi = PL.robust_bounds(placed)
    # the 1–99 % box of a uniform 2 m side covers 0.98 of it: the fitted side is exactly 0.5
    assert (hi - lo).max() == pytest.approx(0.5, abs=1e-12)
    assert lo[1] == pytest.approx(0.0, abs=1e-12)                  # resting on y = 0
    np.testing.assert_allclose(((lo + hi) / 2)[[0, 2]], [0.1, -0.2], atol=1e-12)


def test_real_donut_fits_on_the_floor():
    path = shared_path("gaussians", "donut-fused.ply")
    g = read_gaussians(str(path))
    placed = PL.place(g, PL.parse_placement("fit=0.15;rotate-x=-90;on-floor"))
    lo, hi = PL.robust_bounds(placed)
    assert (hi - lo).max() == pytest.approx(0.15, abs=1e-9)
    assert lo[1] == pytest.approx(0.0, abs=1e-9)
    assert hi[1] - lo[1] < 0.08        # lying flat: its thin axis (file z) now points up


# ------------------------------------------------------------------ spec language


def test_split_spec():
    assert PL.split_spec("builtin:hand") == ("builtin:hand", None)
    assert PL.split_spec("builtin:hand:scale=2") == ("builtin:hand", "scale=2")
    assert PL.split_spec("a/b.ply:on-floor") == ("a/b.ply", "on-floor")
    assert PL.split_spec("a.ply") == ("a.ply", None)
    p = PL.parse_placement("fit=0.15;rotate-x=-90;rotate-y=30;on-floor;translate=1,0,2")
    assert p.fit == 0.15 and p.rotations == [("x", -90.0), ("y", 30.0)] and p.on_floor
    assert p.translate == (1.0, 0.0, 2.0)


@pytest.mark.parametrize("text, reason", [
    ("scale=0", "must be > 0"), ("scale=nan", "must be finite"), ("scale=-2", "must be > 0"),
    ("fit=inf", "must be finite"), ("translate=1,2", "3 finite numbers"),
    ("translate=a,b,c", "X,Y,Z numbers"), ("spin=3", "unknown placement key"),
    ("on-floor=1", "takes no value"), ("scale=", "needs a value"), ("scale=1;scale=2", "twice"),
    ("rotate-y=x", "must be a number"),
])
def test_bad_placements(text, reason):
    with pytest.raises(ValueError, match=reason):
        PL.parse_placement(text)


# ------------------------------------------------------------------ several occluders in one DGSM


def _blob(centre, n=150, seed=0, scale=0.03):
    rng = np.random.default_rng(seed)
    return Gaussians(rng.normal(size=(n, 3)) * 0.06 + centre, np.full((n, 3), scale),
                     np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.8),
                     rgb_to_sh_dc(np.full((n, 3), 0.6))[:, None, :], 0)


def _floor(n=20, half=1.0):
    xs, zs = np.meshgrid(np.linspace(-half, half, n), np.linspace(-half, half, n))
    m = xs.size
    return Gaussians(np.column_stack([xs.ravel(), np.zeros(m), zs.ravel()]),
                     np.tile([0.04, 0.002, 0.04], (m, 1)), np.tile([1.0, 0, 0, 0], (m, 1)),
                     np.full(m, 0.9), rgb_to_sh_dc(np.full((m, 3), 0.6))[:, None, :], 0)


def test_multi_occluder_dgsm_equals_concatenated():
    a, b = _blob([0, 1.0, 0], seed=1), _blob([0.25, 0.5, 0.1], seed=2)
    lights = np.array([[0.1, 2.5, 0.2], [-1.0, 2.0, 0.5]])
    kw = dict(size=(24, 24), bins=12, t_max=3.5, roi=False)
    grouped = D.build_dgsm_groups([a, b], lights, None, **kw)
    whole = D.build_dgsm(concatenate([a, b]), lights, None, **kw)
    # τ adds over disjoint sets, so T multiplies; float32 per-pair terms and culling ε = 1e-7:
    np.testing.assert_allclose(grouped.transmittance, whole.transmittance, atol=1e-5)
    assert grouped.transmittance.min() < 0.2                     # something is really shadowed
    np.testing.assert_allclose(grouped.others(0).transmittance, grouped.groups[1], atol=0)
    np.testing.assert_allclose(grouped.others(1).transmittance, grouped.groups[0], atol=0)
    # with the receiver ROI (default t_max from receivers): lookups where receivers are agree
    floor = _floor()
    pts = floor.means
    g2 = D.build_dgsm_groups([a, b], lights, pts, [a.means, b.means], size=(48, 48), bins=32)
    w2 = D.build_dgsm(concatenate([a, b]), lights, pts, size=(48, 48), bins=32,
                      t_max=g2.t_max)
    # the product of bilinear lookups vs the lookup of the product: same table values, only
    # the interpolation of a product differs (penumbra texels); measured ≈ 1e-3 here.
    np.testing.assert_allclose(D.sample_transmittance(g2, pts), D.sample_transmittance(w2, pts),
                               atol=2e-2)
    # the blob b sits under a: b's Gaussians are shadowed by a's table, not by their own
    exact = np.stack([D.exact_transmittance(D.TR.from_gaussians(a), l, b.means) for l in lights])
    assert exact[0].min() < 0.2
    errors = []
    for n in (128, 256):
        gn = D.build_dgsm_groups([a, b], lights, pts, [a.means, b.means], size=(n, n), bins=32)
        errors.append(np.abs(D.sample_transmittance(gn.others(1), b.means) - exact))
    # trilinear lookups of 3 cm Gaussians' hard-edged shadows: measured mean 0.013 → 0.004,
    # max 0.14 → 0.06; the error must shrink with the atlas as a table of the true T does.
    assert errors[1].mean() < 0.01 and errors[1].max() < 0.1
    assert errors[1].mean() < 0.5 * errors[0].mean()


def test_grouped_dgsm_exr_round_trip(tmp_path):
    a, b = _blob([0, 1.0, 0], seed=1), _blob([0.25, 0.5, 0.1], seed=2)
    m = D.build_dgsm_groups([a, b], [[0.1, 2.5, 0.2]], None, names=["a.ply", "b.ply:scale=2"],
                            size=(8, 8), bins=4, t_max=3.0, roi=False)
    from relight_cli.formats.dgsm_exr import FORMAT, VERSION
    from relight_cli.provenance import provenance
    write_dgsm(str(tmp_path / "g.exr"), m, provenance(FORMAT, VERSION))
    back = read_dgsm(str(tmp_path / "g.exr"))
    assert back.group_names == ["a.ply", "b.ply:scale=2"]
    np.testing.assert_array_equal(back.groups, m.groups)
    np.testing.assert_array_equal(back.transmittance, m.transmittance)


# ------------------------------------------------------------------ CLI


@pytest.fixture()
def files(tmp_path):
    write_gaussians(str(tmp_path / "a.ply"), _blob([0, 0, 0], seed=1))
    write_gaussians(str(tmp_path / "floor.ply"), _floor())
    write_lights(str(tmp_path / "lights.json"), Lights([[0.1, 2.5, 0.2]], [[1, 1, 1]], [5.0]))
    c = np.zeros((1, 3))
    c[0] = math.sqrt(4 * math.pi)                                # uniform radiance 1
    write_probe(str(tmp_path / "p.json"), ShProbe(c, 0))
    write_cameras(str(tmp_path / "cam.json"),
                  [Camera.look_at([0.8, 1.2, 1.2], [0, 0.3, 0], width=40, height=30)])
    return tmp_path


def test_cli_two_placed_occluders_shadow_room_and_each_other(run_cli, files):
    upper = f"{files / 'a.ply'}:scale=1.5;translate=0,1.0,0"
    lower = f"{files / 'a.ply'}:rotate-y=45;translate=0.05,0.45,0.05"
    r = run_cli("dgsm-build", upper, lower, "--receivers", files / "floor.ply", "--lights",
                files / "lights.json", "--size", "32", "--bins", "16", "-o", files / "s.exr",
                "--occluders-out", files / "occ.ply", "-q")
    assert r.exit_code == 0, r.output
    m = read_dgsm(str(files / "s.exr"))
    assert m.groups.shape[:2] == (2, 1) and m.group_names == [upper, lower]
    assert len(read_gaussians(str(files / "occ.ply"))) == 300
    r = run_cli("relight", upper, "--object", lower, "--probe", files / "p.json", "--dgsm",
                files / "s.exr", "--receivers", files / "floor.ply", "--receivers-out",
                files / "floor-out.ply", "--footprint", "centre", "--shadow-strength", "1",
                "-o", files / "relit.ply", "-q")
    assert r.exit_code == 0, r.output
    relit = read_gaussians(str(files / "relit.ply"))
    top, bottom = relit.subset(np.arange(150)), relit.subset(np.arange(150, 300))
    # uniform probe of radiance 1: unshadowed colour = albedo 0.6; the lower blob sits in the
    # upper one's shadow, the upper one (nothing above it) is not darkened by itself
    # (1e-4: the lower blob's Gaussian tails reach a few upper Gaussians' lookups, ~2e-6)
    np.testing.assert_allclose(top.colors(), 0.6, atol=1e-4)
    assert bottom.colors()[:, 0].mean() < 0.45
    floor_out = read_gaussians(str(files / "floor-out.ply"))
    assert floor_out.colors()[:, 0].min() < 0.3                   # both cast onto the floor
    # --direct-light (auto strength): albedo × (probe + Σ_l E_l T_l / π), E_l = I max(n·ω, 0)/r²,
    # T_l through the OTHER object only: each light's term shadowed, exactly
    r = run_cli("relight", upper, "--object", lower, "--probe", files / "p.json", "--dgsm",
                files / "s.exr", "--receivers", files / "floor.ply", "--footprint", "centre",
                "--direct-light", "-o", files / "lit.ply", "-q")
    assert r.exit_code == 0, r.output
    lit = read_gaussians(str(files / "lit.ply"))
    for j, rows in enumerate((np.arange(150), np.arange(150, 300))):
        g = lit.subset(rows)
        v = np.array([0.1, 2.5, 0.2]) - g.means
        dist = np.linalg.norm(v, axis=1)
        e = 5.0 * np.maximum((v * g.normals).sum(axis=1) / dist, 0) / dist ** 2
        T = D.sample_transmittance(m.others(j), g.means, g.scales, g.rotations,
                                   footprint="centre")[0]
        np.testing.assert_allclose(g.colors()[:, 0], 0.6 * (1 + e * T / math.pi), rtol=2e-5,
                                   atol=1e-6)
    assert np.mean(T) < 0.5                 # the lower blob does sit in the upper one's shadow
    # a render of everything, and a mismatch between objects and groups
    r = run_cli("relight", upper, "--object", lower, "--probe", files / "p.json", "--dgsm",
                files / "s.exr", "--receivers", files / "floor.ply", "--camera",
                files / "cam.json", "-o", files / "v.exr", "--preview", files / "v.png", "-q")
    assert r.exit_code == 0, r.output
    assert (files / "v.png").exists()
    r = run_cli("relight", upper, "--probe", files / "p.json", "--dgsm", files / "s.exr",
                "--receivers", files / "floor.ply", "-o", files / "one.ply")
    assert r.exit_code == 1 and "2 occluder groups" in r.output and "1 object(s)" in r.output
    assert not (files / "one.ply").exists()


@pytest.mark.parametrize("spec, message", [
    ("a.ply:scale=0", "scale must be > 0"),
    ("a.ply:scale=nan", "scale must be finite"),
    ("a.ply:translate=1,2", "translate must be 3"),
    ("a.ply:wobble=1", "unknown placement key 'wobble'"),
])
def test_cli_bad_placement_is_a_one_line_usage_error(run_cli, files, monkeypatch, spec, message):
    monkeypatch.chdir(files)
    r = run_cli("dgsm-build", "a.ply", spec, "--receivers", "floor.ply", "--lights",
                "lights.json", "-o", "s.exr")
    assert r.exit_code == 2, r.output
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0] and lines[0].startswith("relight dgsm-build:")
    assert not (files / "s.exr").exists()


def test_subprocess_placed_builtin(files):
    r = run_relight("dgsm-build", "builtin:sphere:fit=0.3;on-floor;translate=0,0.2,0",
                    "--receivers", files / "floor.ply", "--lights", files / "lights.json",
                    "--size", "16", "--bins", "8", "-o", files / "s.exr", "--occluders-out",
                    files / "sphere.ply", "-q")
    assert r.returncode == 0, r.stderr
    lo, hi = PL.robust_bounds(read_gaussians(str(files / "sphere.ply")))
    assert lo[1] == pytest.approx(0.2, abs=1e-5) and (hi - lo).max() == pytest.approx(0.3, abs=1e-5)


def test_placement_keeps_the_source_colour_space():
    """A placed sRGB-sourced object still says where its (decoded, linear) colours came from."""
    g = random_gaussians(n=10, degree=1)
    g.source_colour_space = "srgb"
    placed = PL.place(g, PL.parse_placement("rotate-y=30;translate=1,0,0"))
    assert placed.source_colour_space == "srgb"


# ------------------------------------------------------------------ crop and prune (issue 53, 7)


def _grid_scene():
    """125 Gaussians on the integer grid {0..4}³ (index = 25x + 5y + z); opacity 0.9 and
    largest scale 0.01 except: opacity 0.04 at (2, 2, 2) and (4, 4, 4), a 0.5 needle
    (largest std dev, on x) at (1, 2, 3) and (0, 0, 0)."""
    axis = np.arange(5.0)
    xs, ys, zs = np.meshgrid(axis, axis, axis, indexing="ij")
    means = np.column_stack([xs.ravel(), ys.ravel(), zs.ravel()])
    n = len(means)
    index = {tuple(p): i for i, p in enumerate(means.astype(int).tolist())}
    scales = np.tile([0.01, 0.004, 0.002], (n, 1))
    opacities = np.full(n, 0.9)
    for p in ((2, 2, 2), (4, 4, 4)):
        opacities[index[p]] = 0.04
    for p in ((1, 2, 3), (0, 0, 0)):
        scales[index[p]] = [0.5, 0.004, 0.002]
    g = Gaussians(means, scales, np.tile([1.0, 0, 0, 0], (n, 1)), opacities,
                  rgb_to_sh_dc(np.full((n, 3), 0.5))[:, None, :], 0, np.tile([0, 1.0, 0], (n, 1)))
    return g, index


def _kept_points(g):
    return sorted(map(tuple, np.rint(g.means).astype(int).tolist()))


def test_parse_crop_and_prune_keys():
    p = PL.parse_placement("crop=-1,0,-2.5,1,2,2.5;min-opacity=0.1;max-scale=0.05;fit=0.3")
    assert p.crop == (-1.0, 0.0, -2.5, 1.0, 2.0, 2.5) and p.min_opacity == 0.1
    assert p.max_scale == 0.05 and p.fit == 0.3 and p.prunes() and not p.is_identity()
    only = PL.parse_placement("min-opacity=0.5")
    assert only.prunes() and only.is_identity()       # pruning only: the similarity is I
    assert not PL.parse_placement("fit=1").prunes()
    assert PL.split_spec("desk.ply:min-opacity=0.2") == ("desk.ply", "min-opacity=0.2")


@pytest.mark.parametrize("text, reason", [
    ("crop=0,0,0,1,1", "6 finite numbers"), ("crop=0,0,0,1,1,1,1", "6 finite numbers"),
    ("crop=0,0,a,1,1,1", "X0,Y0,Z0,X1,Y1,Z1 numbers"), ("crop=0,0,0,1,inf,1", "6 finite"),
    ("crop=1,0,0,1,1,1", "X0 = 1 must be < X1 = 1"), ("crop=0,2,0,1,1,1", "Y0 = 2 must be"),
    ("crop=0,0,0.5,1,1,-0.5", "Z0 = 0.5 must be < Z1 = -0.5"), ("crop=", "needs a value"),
    ("crop=0,0,0,1,1,1;crop=0,0,0,2,2,2", "twice"),
    ("min-opacity=1.5", r"in \[0, 1\]"), ("min-opacity=-0.1", r"in \[0, 1\]"),
    ("min-opacity=nan", "must be finite"), ("min-opacity=x", "must be a number"),
    ("max-scale=0", "must be > 0"), ("max-scale=-1", "must be > 0"),
    ("max-scale=inf", "must be finite"), ("min-opacity", "needs a value"),
])
def test_bad_prune_keys(text, reason):
    with pytest.raises(ValueError, match=reason):
        PL.parse_placement(text)


def test_prune_keeps_exactly_the_known_set():
    g, index = _grid_scene()
    # crop bounds are inclusive: the 3×3×3 block 1..3 on every axis
    kept = PL.prune(g, PL.parse_placement("crop=1,1,1,3,3,3"))
    expected = [(x, y, z) for x in (1, 2, 3) for y in (1, 2, 3) for z in (1, 2, 3)]
    assert _kept_points(kept) == expected
    # + min-opacity drops (2,2,2) (0.04 < 0.05; (4,4,4) is outside anyway), max-scale (1,2,3)
    kept = PL.prune(g, PL.parse_placement("crop=1,1,1,3,3,3;min-opacity=0.05;max-scale=0.2"))
    assert _kept_points(kept) == [p for p in expected if p not in ((2, 2, 2), (1, 2, 3))]
    # every array follows the selection (normals included, colours and order kept)
    rows = [index[p] for p in _kept_points(kept)]
    np.testing.assert_array_equal(kept.scales, g.scales[rows])
    np.testing.assert_array_equal(kept.normals, g.normals[rows])
    np.testing.assert_array_equal(kept.sh, g.sh[rows])
    # the thresholds themselves are kept (opacity ≥ A, largest scale ≤ S)
    assert len(PL.prune(g, PL.parse_placement("min-opacity=0.04"))) == 125
    assert len(PL.prune(g, PL.parse_placement("min-opacity=0.0400001"))) == 123
    assert len(PL.prune(g, PL.parse_placement("max-scale=0.5"))) == 125
    assert len(PL.prune(g, PL.parse_placement("max-scale=0.4999"))) == 123
    # a box in the source's own frame, before the placement's transform: the same set
    placed = PL.place(g, PL.parse_placement("crop=1,1,1,3,3,3;rotate-y=90;translate=10,0,0"))
    assert len(placed) == 27
    np.testing.assert_allclose(np.sort(placed.means[:, 0]), np.sort(10 + _z_of(expected)))


def _z_of(points):
    """x' = z after rotate-y=90 (x' = cos·x + sin·z)."""
    return np.array([p[2] for p in points], np.float64)


def test_fit_and_on_floor_measure_what_is_kept():
    """A 0.2 m object at the origin and a bright 4 m slab of 'desk' beside it: cropped to
    the object, fit=1 makes the object's robust box 1 m and on-floor rests the object."""
    obj = _blob([0, 0.5, 0], n=400, seed=3)
    rng = np.random.default_rng(4)
    desk = Gaussians(np.column_stack([rng.uniform(-2, 2, 600), rng.uniform(-0.1, 0, 600),
                                      rng.uniform(-2, 2, 600)]), np.full((600, 3), 0.02),
                     np.tile([1.0, 0, 0, 0], (600, 1)), np.full(600, 0.9),
                     rgb_to_sh_dc(np.full((600, 3), 0.3))[:, None, :], 0)
    scene = concatenate([obj, desk])
    spec = "crop=-0.5,0.1,-0.5,0.5,1,0.5;fit=1;on-floor"
    placed = PL.place(scene, PL.parse_placement(spec))
    assert len(placed) == 400
    expected = PL.place(obj, PL.parse_placement("fit=1;on-floor"))     # the object alone
    np.testing.assert_allclose(placed.means, expected.means, atol=1e-12)
    lo, hi = PL.robust_bounds(placed)
    assert (hi - lo).max() == pytest.approx(1.0, abs=1e-9) and lo[1] == pytest.approx(0, abs=1e-9)
    # without the crop the desk sets the size: the object would be a fraction of 1 m
    whole = PL.place(scene, PL.parse_placement("fit=1;on-floor"))
    assert np.ptp(whole.means[:400], axis=0).max() < 0.3 * np.ptp(placed.means, axis=0).max()
    # resolve (used for meshes and clips) sees the same kept set
    sim = PL.resolve(PL.parse_placement(spec), scene)
    np.testing.assert_allclose(sim.apply(obj.means), expected.means, atol=1e-12)


def test_prune_to_nothing_says_what_each_key_dropped():
    g, _ = _grid_scene()
    with pytest.raises(ValueError, match=r"no Gaussians left after pruning \(of 125: 124 "
                                         r"outside the crop box, 2 below min-opacity 0\.5, 2 "
                                         r"above max-scale 0\.1\)"):
        PL.place(g, PL.parse_placement("crop=3.5,3.5,3.5,5,5,5;min-opacity=0.5;max-scale=0.1"))


def test_cli_crop_and_prune(run_cli, files, monkeypatch):
    """dgsm-build writes exactly the kept occluders; an empty result is one data error."""
    g, index = _grid_scene()
    write_gaussians(str(files / "grid.ply"), g)
    monkeypatch.chdir(files)
    spec = "grid.ply:crop=1,1,1,3,3,3;min-opacity=0.05;max-scale=0.2;fit=0.2;translate=0,1,0"
    r = run_cli("dgsm-build", spec, "--receivers", "floor.ply", "--lights", "lights.json",
                "--size", "8", "--bins", "4", "-o", "s.exr", "--occluders-out", "occ.ply", "-q")
    assert r.exit_code == 0, r.output
    occ = read_gaussians("occ.ply")
    assert len(occ) == 25
    # the kept block, 2 m across, fitted to 0.2 m (a scale of 0.1), centred, then lifted
    np.testing.assert_allclose(occ.means.min(0), [-0.1, 0.9, -0.1], atol=1e-6)
    np.testing.assert_allclose(occ.scales.max(), 0.001, rtol=1e-6)
    r = run_cli("dgsm-build", "grid.ply:crop=10,10,10,11,11,11", "--receivers", "floor.ply",
                "--lights", "lights.json", "-o", "empty.exr")
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert r.exit_code == 1 and len(lines) == 1, r.output
    assert lines[0].startswith("relight dgsm-build: error: cannot place it: no Gaussians left")
    assert "125 outside the crop box" in lines[0] and "grid.ply" in lines[0]
    assert not (files / "empty.exr").exists()
    r = run_cli("dgsm-build", "grid.ply:crop=1,1,1,0,3,3", "--receivers", "floor.ply",
                "--lights", "lights.json", "-o", "bad.exr")
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert r.exit_code == 2 and len(lines) == 1 and "X0 = 1 must be < X1 = 0" in lines[0]
    assert not (files / "bad.exr").exists()


def test_clip_prunes_every_frame(tmp_path):
    """A per-frame pattern: each frame pruned by the same keys (its own kept set), placed
    by the one similarity resolved on the first frame's kept Gaussians."""
    from relight_cli.gaussians.sequence import GaussianSource
    g, _ = _grid_scene()
    write_gaussians(str(tmp_path / "f_0.ply"), g)
    shifted = g.subset(np.arange(len(g)))
    shifted.means = shifted.means + [0.5, 0, 0]          # frame 1: moved by +0.5 on x
    write_gaussians(str(tmp_path / "f_1.ply"), shifted)
    source = GaussianSource(str(tmp_path / "f_{frame}.ply") + ":crop=1,1,1,3,3,3;centre")
    first, second = source.frame(0), source.frame(1)
    assert len(first) == 27 and len(second) == 18     # frame 1 keeps x = 1.5, 2.5 only
    np.testing.assert_allclose(first.means.mean(0), 0, atol=1e-6)          # centred
    # frame 0's centre (2, 2, 2) taken off frame 1 too: x = 1.5, 2.5 → -0.5, 0.5
    np.testing.assert_allclose(np.unique(second.means[:, 0]), [-0.5, 0.5], atol=1e-6)


def test_real_capture_crop_and_min_opacity(shared):
    """A real trained capture: the kept count equals a count made from the PLY's raw
    columns (sigmoid of the opacity logit, exp of the log scales), independently."""
    from plyfile import PlyData
    path = shared("gaussians", "statue-massa.ply")
    v = PlyData.read(str(path))["vertex"]
    xyz = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    alpha = 1 / (1 + np.exp(-np.asarray(v["opacity"], np.float64)))
    largest = np.exp(np.column_stack([v[f"scale_{i}"] for i in range(3)]).astype(np.float64)
                     ).max(axis=1)
    box = np.array([-0.4, -1.8, -0.4, 0.4, -0.8, 0.4])       # the bust (+Y down as captured)
    inside = np.all((xyz >= box[:3]) & (xyz <= box[3:]), axis=1)
    expected = int((inside & (alpha >= 0.2) & (largest <= 0.05)).sum())
    from relight_cli.gaussians.from_mesh import load_gaussians
    g = load_gaussians(str(path))
    spec = "crop=-0.4,-1.8,-0.4,0.4,-0.8,0.4;min-opacity=0.2;max-scale=0.05;fit=0.3;rotate-x=180"
    placed = PL.place(g, PL.parse_placement(spec))
    assert 1000 < expected < len(g) // 2 and len(placed) == expected
    lo, hi = PL.robust_bounds(placed)
    # fit is measured before rotate-x=180; the capture's quantised y has ties, so the
    # percentile box of −y differs from that of y by ~2e-6 m (midpoint weighted CDF)
    assert (hi - lo).max() == pytest.approx(0.3, abs=1e-5)
