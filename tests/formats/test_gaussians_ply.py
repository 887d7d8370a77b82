"""Gaussians PLY I/O: round trips, the INRIA f_rest order, activations, bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import plyfile
import pytest
from scipy.spatial.transform import Rotation

from relight_cli.errors import DataError
from relight_cli.formats.gaussians_ply import (SH_C0, Gaussians, concatenate, matrix_to_quaternion,
                                               quaternion_to_matrix, read_gaussians, rgb_to_sh_dc,
                                               write_gaussians)

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
DONUT = DATA / "gaussians" / "donut-fused.ply"


def random_gaussians(n=50, degree=2, seed=0, normals=False) -> Gaussians:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    return Gaussians(means=rng.normal(size=(n, 3)),
                     scales=np.exp(rng.uniform(-5, -1, size=(n, 3))),
                     rotations=Rotation.random(n, random_state=seed).as_quat()[:, [3, 0, 1, 2]],
                     opacities=rng.uniform(0.01, 0.99, n),
                     sh=rng.normal(size=(n, k, 3)), sh_degree=degree,
                     normals=rng.normal(size=(n, 3)) if normals else None)


def write_raw(path, columns: dict, obj_info=()):
    data = np.empty(len(next(iter(columns.values()))), dtype=[(k, "<f4") for k in columns])
    for k, v in columns.items():
        data[k] = v
    plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")], obj_info=list(obj_info)).write(
        str(path))


def raw_columns(n=4, degree=0, seed=1):
    rng = np.random.default_rng(seed)
    cols = {a: rng.normal(size=n) for a in "xyz"}
    for c in range(3):
        cols[f"f_dc_{c}"] = rng.normal(size=n)
    for i in range(3 * ((degree + 1) ** 2 - 1)):
        cols[f"f_rest_{i}"] = rng.normal(size=n)
    cols["opacity"] = rng.normal(size=n)
    for i in range(3):
        cols[f"scale_{i}"] = rng.uniform(-6, -2, n)
    for i in range(4):
        cols[f"rot_{i}"] = rng.normal(size=n)
    return cols


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip(tmp_path, degree):
    g = random_gaussians(degree=degree, normals=degree == 1)
    path = tmp_path / "g.ply"
    write_gaussians(str(path), g, {"format": "relight/gaussians", "version": 1})
    h = read_gaussians(str(path))
    assert h.sh_degree == degree and len(h) == len(g)
    # float32 storage: relative precision 2^-24 ≈ 6e-8 of values of order ≤ 4.
    np.testing.assert_allclose(h.means, g.means, atol=1e-6)
    np.testing.assert_allclose(h.sh, g.sh, atol=1e-6)
    np.testing.assert_allclose(h.scales, g.scales, rtol=1e-6)   # exp(float32 log): rel. error ~1e-7·|log|
    np.testing.assert_allclose(h.opacities, g.opacities, atol=1e-6)
    np.testing.assert_allclose(np.abs(np.sum(h.rotations * g.rotations, 1)), 1, atol=1e-6)
    if g.normals is None:
        assert h.normals is None
    else:
        np.testing.assert_allclose(h.normals, g.normals, atol=1e-6)
    assert h.provenance == {"format": "relight/gaussians", "version": 1}
    assert not list(tmp_path.glob(".*tmp*")), "temporary file left behind"


def test_inria_rest_order_and_activations(tmp_path):
    cols = raw_columns(n=5, degree=2)
    path = tmp_path / "raw.ply"
    write_raw(path, cols)
    g = read_gaussians(str(path), colour_space="linear")   # the layout: colours as stored
    assert g.sh_degree == 2
    # INRIA: features_rest [N, 8, 3] is saved transposed as [N, 3, 8]: f_rest_{c·8+j} = sh[:, 1+j, c].
    f32 = lambda a: np.asarray(a, np.float32).astype(np.float64)  # noqa: E731
    for c in range(3):
        for j in range(8):
            np.testing.assert_array_equal(g.sh[:, 1 + j, c], f32(cols[f"f_rest_{c * 8 + j}"]))
    np.testing.assert_allclose(g.opacities, 1 / (1 + np.exp(-f32(cols["opacity"]))), rtol=1e-12)
    np.testing.assert_allclose(g.scales[:, 1], np.exp(f32(cols["scale_1"])), rtol=1e-12)
    q = np.stack([f32(cols[f"rot_{i}"]) for i in range(4)], 1)
    np.testing.assert_allclose(g.rotations, q / np.linalg.norm(q, axis=1, keepdims=True), atol=1e-12)


def test_covariance_against_scipy():
    g = random_gaussians(n=20, degree=0)
    # Independent reference: scipy's quaternion convention is scalar-last.
    R = Rotation.from_quat(g.rotations[:, [1, 2, 3, 0]]).as_matrix()
    ref = R @ np.stack([np.diag(s ** 2) for s in g.scales]) @ R.transpose(0, 2, 1)
    np.testing.assert_allclose(g.covariances(), ref, atol=1e-14)
    np.testing.assert_allclose(quaternion_to_matrix(g.rotations), R, atol=1e-14)
    q = matrix_to_quaternion(R)
    np.testing.assert_allclose(np.abs(np.sum(q * g.rotations, 1)), 1, atol=1e-12)


def test_colors_and_dc():
    rgb = np.array([[0.2, 0.5, 0.9], [1.5, 0.0, 0.3]])
    g = Gaussians(np.zeros((2, 3)), np.ones((2, 3)), [[1, 0, 0, 0]] * 2, [0.5, 0.5],
                  rgb_to_sh_dc(rgb)[:, None, :], 0)
    np.testing.assert_allclose(g.colors(), rgb, atol=1e-15)
    np.testing.assert_allclose(g.sh[:, 0] * SH_C0 + 0.5, rgb, atol=1e-15)
    both = concatenate([g, random_gaussians(n=3, degree=1)])
    assert both.sh_degree == 1 and len(both) == 5 and np.all(both.sh[:2, 1:] == 0)


def test_donut_loads():
    if not DONUT.exists():
        pytest.skip(f"shared data not present: {DONUT}")
    g = read_gaussians(str(DONUT))
    assert len(g) == 45624 and g.sh_degree == 0 and g.normals is None
    assert np.all((g.opacities > 0) & (g.opacities < 1))
    np.testing.assert_allclose(np.linalg.norm(g.rotations, axis=1), 1, atol=1e-12)
    assert g.scales.max() < 0.1  # a ~20 cm donut: no splat wider than 10 cm
    assert np.isfinite(g.covariances()).all()


def test_mapped_read_is_the_plain_read_and_outlives_the_file(tmp_path):
    """read_gaussians maps the file copy-on-write (plyfile's fast path; its mmap=False
    reads vertex by vertex in Python, 30x slower on a 90k-Gaussian capture): the values
    are plyfile's own unmapped ones, and the arrays stay valid once the file is gone."""
    import shutil
    src = DONUT if DONUT.exists() else None
    path = tmp_path / "g.ply"
    if src is not None:
        shutil.copy(src, path)
    else:
        rng = np.random.default_rng(0)
        write_gaussians(str(path), Gaussians(rng.normal(size=(50, 3)), np.full((50, 3), 0.01),
                                             np.tile([1.0, 0, 0, 0], (50, 1)), np.full(50, 0.5),
                                             rng.normal(size=(50, 4, 3)), 1))
    g = read_gaussians(str(path), colour_space="linear")
    plain = plyfile.PlyData.read(str(path), mmap=False)["vertex"].data
    path.unlink()
    np.testing.assert_array_equal(g.means, np.stack([plain[a] for a in "xyz"], 1))
    np.testing.assert_array_equal(g.sh[:, 0], np.stack([plain[f"f_dc_{c}"] for c in range(3)], 1))
    assert np.isfinite(g.covariances()).all()


@pytest.mark.parametrize("case, message", [
    ("missing", "missing 3DGS field(s) opacity"),
    ("nan", "field scale_1 has 1 non-finite value(s) (first at Gaussian 2)"),
    ("zero_quat", "zero quaternion(s) (first at Gaussian 1)"),
    ("rest_count", "f_rest_* fields must be"),
    ("newer", "version 2 is newer"),
    ("overflow", "overflows exp()"),
])
def test_bad_input(tmp_path, case, message):
    cols = raw_columns(n=4)
    info = ()
    if case == "missing":
        del cols["opacity"]
    elif case == "nan":
        cols["scale_1"][2] = np.nan
    elif case == "zero_quat":
        for i in range(4):
            cols[f"rot_{i}"][1] = 0.0
    elif case == "rest_count":
        cols["f_rest_0"] = np.zeros(4)
    elif case == "newer":
        info = ("relight.format relight/gaussians 2",)
    elif case == "overflow":
        cols["scale_0"][0] = 1000.0
    path = tmp_path / "bad.ply"
    write_raw(path, cols, info)
    with pytest.raises(DataError) as exc:
        read_gaussians(str(path))
    assert message in str(exc.value) and str(path) in str(exc.value)


def test_not_a_ply(tmp_path):
    path = tmp_path / "x.ply"
    path.write_text("hello\n")
    with pytest.raises(DataError, match="not a readable PLY"):
        read_gaussians(str(path))
    with pytest.raises(DataError, match="no such file"):
        read_gaussians(str(tmp_path / "absent.ply"))


def test_write_refuses_nan(tmp_path):
    g = random_gaussians(n=3, degree=0)
    g.means[1, 0] = np.nan
    with pytest.raises(DataError, match="means"):
        write_gaussians(str(tmp_path / "o.ply"), g)
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------ colour space

# The sRGB EOTF (IEC 61966-2-1) at known points: the breakpoint, mid grey, 8-bit codes.
SRGB_TABLE = [(0.0, 0.0), (0.04045, 0.0031308049535603713), (0.2, 0.033104766570885055),
              (0.5, 0.21404114048223255), (128 / 255, 0.21586050011389926),
              (0.8, 0.6038273388553378), (1.0, 1.0)]


def test_srgb_eotf_known_values_and_oiio():
    from relight_cli.formats.gaussians_ply import srgb_eotf
    v, ref = np.array(SRGB_TABLE).T
    np.testing.assert_allclose(srgb_eotf(v), ref, rtol=1e-12, atol=1e-15)
    # OpenImageIO's own sRGB → linear (an OCIO LUT-backed transform: ~1e-4 agreement)
    import OpenImageIO as oiio
    x = np.linspace(0, 1, 101, dtype=np.float32)
    buf = oiio.ImageBuf(np.repeat(x.reshape(1, -1, 1), 3, axis=2))
    lin = oiio.ImageBufAlgo.colorconvert(buf, "sRGB", "linear").get_pixels(oiio.FLOAT)[0, :, 0]
    np.testing.assert_allclose(srgb_eotf(x), lin, atol=1e-4)
    # negative values clamp at 0 (no NaN); above 1 continues the power segment (HDR)
    assert srgb_eotf(np.array([-0.3]))[0] == 0.0
    assert srgb_eotf(np.array([1.5]))[0] == pytest.approx((1.555 / 1.055) ** 2.4, rel=1e-12)


def test_srgb_sh_degree0_exact_and_negative_dc_no_nan():
    from relight_cli.formats.gaussians_ply import srgb_eotf, srgb_to_linear_sh
    rgb = np.array([[0.5, 0.2, 0.9], [1.3, 0.01, -0.4]])     # HDR, linear segment, negative
    lin = srgb_to_linear_sh(rgb_to_sh_dc(rgb)[:, None, :])
    assert np.isfinite(lin).all()
    np.testing.assert_allclose(0.5 + SH_C0 * lin[:, 0], srgb_eotf(np.maximum(rgb, 0)),
                               atol=1e-14)
    assert 0.5 + SH_C0 * lin[1, 0, 2] == pytest.approx(0.0, abs=1e-14)


def _fibonacci(m):
    i = np.arange(m) + 0.5
    z = 1 - 2 * i / m
    phi = i * math.pi * (3 - 5 ** 0.5)
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def _band_errors(sh, degree):
    """RMS error (over 4000 directions) of the linearised SH against the decoded colour
    max(EOTF(c(d)), 0), and of the brute-force least-squares SH fit of the same degree."""
    from relight_cli.formats.gaussians_ply import srgb_eotf, srgb_to_linear_sh
    from relight_cli.sh import sh_basis
    d = _fibonacci(4000)
    B = sh_basis(d, degree)
    truth = srgb_eotf(0.5 + np.einsum("mk,nkc->nmc", B, sh))
    fit, *_ = np.linalg.lstsq(B, (truth - 0.5).transpose(1, 0, 2).reshape(len(d), -1), rcond=None)
    best = 0.5 + (B @ fit).reshape(len(d), len(sh), 3).transpose(1, 0, 2)
    approx = 0.5 + np.einsum("mk,nkc->nmc", B, srgb_to_linear_sh(sh))
    rms = lambda a: float(np.sqrt(((np.maximum(a, 0) - truth) ** 2).mean()))  # noqa: E731
    return rms(approx), rms(best), float(np.sqrt((truth ** 2).mean()))


def test_srgb_sh_bands_against_brute_force():
    """Bands of moderate view dependence (±0.15 around mid colours), degree 3: the
    linearisation's RMS error is 0.0047 (1.3 % of the colour's RMS), against 0.0033 for
    the best degree-3 least-squares fit and 3× less than leaving the bands undecoded."""
    rng = np.random.default_rng(3)
    n, degree = 300, 3
    sh = rng.normal(scale=0.15 / 3, size=(n, (degree + 1) ** 2, 3))
    sh[:, 0] = rgb_to_sh_dc(rng.uniform(0.15, 0.9, size=(n, 3)))
    approx, best, scale = _band_errors(sh, degree)
    assert approx < 1.6 * best and approx / scale < 0.02, (approx, best, scale)
    # not decoding the bands at all is clearly worse
    from relight_cli.formats.gaussians_ply import srgb_to_linear_sh
    dc_only = srgb_to_linear_sh(sh)
    dc_only[:, 1:] = sh[:, 1:]
    from relight_cli.sh import sh_basis
    d = _fibonacci(4000)
    B = sh_basis(d, degree)
    from relight_cli.formats.gaussians_ply import srgb_eotf
    truth = srgb_eotf(0.5 + np.einsum("mk,nkc->nmc", B, sh))
    naive = float(np.sqrt(((0.5 + np.einsum("mk,nkc->nmc", B, dc_only) - truth) ** 2).mean()))
    assert approx < naive / 3, (approx, naive)


def test_srgb_sh_bands_real_robot():
    """The real SH-degree-2 robot (strong view dependence): error measured in
    formats/gaussians_ply.md (600 Gaussians: RMS 0.057, the best degree-2 fit 0.035,
    12 % and 7 % of the colour's RMS 0.47)."""
    robot_path = DATA / "gaussians" / "playbot-lod3.ply"
    if not robot_path.exists():
        pytest.skip(f"shared data not present: {robot_path}")
    robot = read_gaussians(str(robot_path), colour_space="linear")     # as stored (sRGB)
    sub = robot.sh[np.random.default_rng(0).choice(len(robot), 600, replace=False)]
    approx, best, scale = _band_errors(sub, 2)
    assert approx < 1.8 * best and approx / scale < 0.14, (approx, best, scale)


def test_colour_space_detection(tmp_path):
    """A plain 3DGS PLY reads as sRGB (decoded); a PLY this tool wrote reads back linear,
    says so in its header, and a read → write → read keeps the linear colours."""
    from relight_cli.formats.gaussians_ply import srgb_to_linear_sh
    cols = raw_columns(n=6, degree=1)
    foreign = tmp_path / "trained.ply"
    write_raw(foreign, cols)
    raw = read_gaussians(str(foreign), colour_space="linear")
    g = read_gaussians(str(foreign))
    assert g.source_colour_space == "srgb" and raw.source_colour_space == "linear"
    np.testing.assert_allclose(g.sh, srgb_to_linear_sh(raw.sh), atol=1e-12)
    assert np.isfinite(g.sh).all()                    # raw DCs include negative colours
    ours = tmp_path / "ours.ply"
    write_gaussians(str(ours), g, {"format": "relight/gaussians", "version": 1})
    assert b"obj_info relight.colour-space linear\n" in ours.read_bytes()[:2000]
    back = read_gaussians(str(ours))
    assert back.source_colour_space == "linear"
    np.testing.assert_allclose(back.sh, g.sh, rtol=1e-6, atol=1e-6)
    # an older file of ours (format line, no colour-space line) is linear too
    older = tmp_path / "older.ply"
    write_raw(older, cols, ["relight.format relight/gaussians 1"])
    assert read_gaussians(str(older)).source_colour_space == "linear"
    # the header line wins over the guess; the argument wins over both
    tagged = tmp_path / "tagged.ply"
    write_raw(tagged, cols, ["relight.colour-space srgb"])
    assert read_gaussians(str(tagged)).source_colour_space == "srgb"
    np.testing.assert_allclose(read_gaussians(str(ours), colour_space="srgb").sh,
                               srgb_to_linear_sh(back.sh), atol=1e-12)
    with pytest.raises(ValueError):
        read_gaussians(str(ours), colour_space="rgb")


def test_damaged_colour_space_line(tmp_path):
    path = tmp_path / "bad.ply"
    write_raw(path, raw_columns(n=3), ["relight.colour-space rec2020"])
    with pytest.raises(DataError, match="damaged 'relight.colour-space' header line"):
        read_gaussians(str(path))


def test_real_file_reads_srgb_and_darker():
    if not DONUT.exists():
        pytest.skip(f"shared data not present: {DONUT}")
    g, raw = read_gaussians(str(DONUT)), read_gaussians(str(DONUT), colour_space="linear")
    assert g.source_colour_space == "srgb" and np.isfinite(g.sh).all()
    assert g.colors().mean() < 0.8 * raw.colors().mean()        # mid tones decode darker
