"""Shared foundation: SH basis, cameras, atomic outputs and provenance, EXR I/O."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
from scipy import integrate, special

from relight_cli import sh
from relight_cli.errors import DataError, UsageProblem
from relight_cli.formats.camera import Camera, read_camera, read_cameras
from relight_cli.formats.exr import check_format, read_exr, write_exr
from relight_cli.provenance import atomic_path, output_transaction, provenance


def _unit(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_sh_basis_matches_scipy_complex_harmonics():
    """Real SH from scipy's complex Y_l^m (which includes the Condon–Shortley phase)."""
    d = _unit(np.random.default_rng(0), 64)
    theta, phi = np.arccos(d[:, 2]), np.arctan2(d[:, 1], d[:, 0])
    basis = sh.sh_basis(d, 7)
    for l in range(8):
        for m in range(-l, l + 1):
            y = special.sph_harm_y(l, abs(m), theta, phi)
            ref = math.sqrt(2) * (y.real if m > 0 else y.imag) if m else y.real
            np.testing.assert_allclose(basis[:, l * l + l + m], ref, atol=1e-12)


def test_sh_degree1_is_the_3dgs_convention():
    d = _unit(np.random.default_rng(1), 10)
    c1 = math.sqrt(3 / (4 * math.pi))
    np.testing.assert_allclose(sh.sh_basis(d, 1)[:, 1:],
                               np.stack([-c1 * d[:, 1], c1 * d[:, 2], -c1 * d[:, 0]], 1), atol=1e-15)


def test_sh_poles_are_finite():
    b = sh.sh_basis(np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 0, 0.0]]), 10)
    assert np.isfinite(b).all()


def test_lambert_band_factors_match_quadrature():
    """Â_l = 2π ∫₀^{π/2} cos θ P_l(cos θ) sin θ dθ (Funk–Hecke)."""
    factors = sh.lambert_band_factors(8)
    for l in range(9):
        ref, _ = integrate.quad(lambda t: math.cos(t) * special.eval_legendre(l, math.cos(t))
                                * math.sin(t), 0, math.pi / 2)
        assert factors[l] == pytest.approx(2 * math.pi * ref, abs=1e-12)


def test_fit_sh_recovers_coefficients_on_a_grid():
    from relight_cli import envmap as E
    dirs = E.latlong_directions(64, 128).reshape(-1, 3)
    omega = E.latlong_solid_angles(64, 128).reshape(-1)
    truth = np.random.default_rng(2).normal(size=(9, 3))
    values = sh.sh_basis(dirs, 2) @ truth
    np.testing.assert_allclose(sh.fit_sh(dirs, values, omega, 2), truth, atol=1e-9)


def test_camera_look_at_projects_target_to_principal_point():
    cam = Camera.look_at([0.3, 0.2, 1.0], [0, 0, 0], width=200, height=100)
    x = cam.R @ np.zeros(3) + cam.t
    u, v, w = cam.K @ x
    assert w > 0 and abs(u / w - 99.5) < 1e-9 and abs(v / w - 49.5) < 1e-9   # image centre
    np.testing.assert_allclose(cam.center, [0.3, 0.2, 1.0], atol=1e-12)
    # +Y (up) in the world appears above the target (smaller v: y points down).
    u2, v2, w2 = cam.K @ (cam.R @ np.array([0, 0.1, 0]) + cam.t)
    assert v2 / w2 < 49.5


def test_camera_json_round_trip_and_errors(tmp_path):
    cam = Camera.look_at([0, 0, 1], [0, 0, 0], width=64, height=48, name="c0")
    path = tmp_path / "cam.json"
    path.write_text(json.dumps(cam.to_json()))
    back = read_camera(str(path))
    np.testing.assert_allclose(back.K, cam.K)
    np.testing.assert_allclose(back.R, cam.R)
    assert back.name == "c0"
    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps([cam.to_json(), cam.to_json()]))
    assert len(read_cameras(str(rig))) == 2
    bad = dict(cam.to_json(), R=[[1, 0, 0], [0, 1, 0], [0, 0, 2]])
    path.write_text(json.dumps(bad))
    with pytest.raises(DataError, match="rotation"):
        read_camera(str(path))
    path.write_text("{not json")
    with pytest.raises(DataError, match="JSON"):
        read_camera(str(path))
    path.write_text(json.dumps({"K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}))
    with pytest.raises(DataError, match="missing"):
        read_camera(str(path))


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            open(tmp, "w").write("half")
            raise RuntimeError("boom")
    assert os.listdir(tmp_path) == []
    with atomic_path(target) as tmp:
        open(tmp, "w").write("whole")
    assert target.read_text() == "whole"
    assert oct(target.stat().st_mode & 0o777) != oct(0o600)  # not mkstemp's private mode


def test_output_transaction_is_all_or_nothing(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    with pytest.raises(ValueError):
        with output_transaction():
            with atomic_path(a) as tmp:
                open(tmp, "w").write("a")
            assert not a.exists()  # staged until the whole command succeeds
            raise ValueError("second output failed")
    assert os.listdir(tmp_path) == []
    with output_transaction():
        for p in (a, b):
            with atomic_path(p) as tmp:
                open(tmp, "w").write(p.name)
    assert a.read_text() == "a.txt" and b.read_text() == "b.txt"


def test_atomic_path_missing_folder_is_usage_error(tmp_path):
    with pytest.raises(UsageProblem):
        with atomic_path(tmp_path / "nope" / "x.exr"):
            pass


def test_exr_named_channels_attributes_and_format_check(tmp_path):
    path = tmp_path / "x.exr"
    rng = np.random.default_rng(3)
    chans = {"diffuse.R": rng.random((5, 7)), "diffuse.G": rng.random((5, 7)),
             "diffuse.B": rng.random((5, 7)), "mask.Y": np.ones((5, 7))}
    prov = provenance("relight/test", 2, settings={"k": 1})
    write_exr(str(path), chans, attributes={"relight.shininess": [16, 32], "relight.note": "hi"},
              provenance=prov)
    img = read_exr(str(path))
    np.testing.assert_array_equal(img.layer("diffuse"), np.stack(
        [chans[f"diffuse.{c}"].astype(np.float32) for c in "RGB"], -1))
    assert img.attributes["relight.shininess"] == [16.0, 32.0]
    assert img.provenance()["settings"] == {"k": 1}
    assert check_format(img, "relight/test", 2) == 2
    with pytest.raises(DataError, match="newer"):
        check_format(img, "relight/test", 1)
    with pytest.raises(DataError, match="not a relight/other"):
        check_format(img, "relight/other", 1)
    with pytest.raises(DataError, match="missing channel"):
        img.layer("specular")


def test_half_exr_clamps_instead_of_overflowing(tmp_path):
    path = tmp_path / "h.exr"
    write_exr(str(path), {"Y": np.array([[1e6, 1.0]])}, half=True)
    y = read_exr(str(path)).channels["Y"]
    assert np.isfinite(y).all() and y[0, 0] == 65504.0


def test_an_input_replaced_during_a_run_does_not_make_its_old_inode_an_input(tmp_path):
    """Inputs are compared with outputs by what their paths are *now*: an input rewritten
    atomically by another process mid-run leaves its old inode free, and a file this run
    writes later may get that inode number (a checkpoint save of a long ``distill`` was
    refused as "also an input" that way).  Moving the old inode onto the output path is
    the deterministic version of that reuse; the input's path itself is still refused."""
    from relight_cli.errors import UsageProblem
    from relight_cli.provenance import atomic_path, declare_input, output_transaction
    config, saved = tmp_path / "config.json", tmp_path / "student.pt"
    config.write_text("{}")
    with output_transaction():
        declare_input(str(config))
        os.rename(config, saved)               # the old inode now sits at the output path
        config.write_text('{"rewritten": true}')
        with atomic_path(saved) as tmp:
            open(tmp, "w").write("checkpoint")
        with pytest.raises(UsageProblem, match="also an input"):
            with atomic_path(config) as tmp:
                open(tmp, "w").write("clobber")
    assert saved.read_text() == "checkpoint" and config.read_text() == '{"rewritten": true}'
