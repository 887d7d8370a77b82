"""relight/camera (formats/camera.py): look-at, rigs, JSON round trip, OpenEXR header matrices, and
renders whose features sit where their header's camera says.  References are computed by hand."""

from __future__ import annotations

import math
import json

import numpy as np
import pytest

from relight_cli import cameras as C
from relight_cli.errors import DataError
from relight_cli.formats.camera import (Camera, camera_from_openexr, openexr_matrices, read_camera,
                                        read_cameras, write_cameras)


def project(cam: Camera, X) -> np.ndarray:
    """[N, 2] pixels of world points [N, 3] in relight's convention (camera.md)."""
    p = np.atleast_2d(X) @ cam.R.T + cam.t
    uvw = p @ cam.K.T
    return uvw[:, :2] / uvw[:, 2:]


# ----------------------------------------------------------------------------- look-at, rigs


def test_look_at_projects_hand_computed_pixels():
    # eye on +Z looking at the origin, 90° vertical fov over 51 rows: f = 25.5 / tan 45° = 25.5,
    # principal point at the centre (50, 25) of a 101×51 image.
    cam = C.look_at([0, 0, 2], [0, 0, 0], fov_y_deg=90, width=101, height=51)
    np.testing.assert_allclose(cam.K, [[25.5, 0, 50], [0, 25.5, 25], [0, 0, 1]], atol=1e-12)
    # (0.5, 0.25, 0): camera x = 0.5 (right), y = −0.25 (up is −y), z = 2
    np.testing.assert_allclose(project(cam, [0.5, 0.25, 0.0]),
                               [[50 + 25.5 * 0.25, 25 - 25.5 * 0.125]], atol=1e-12)
    np.testing.assert_allclose(cam.R, np.diag([1.0, -1.0, -1.0]), atol=1e-12)   # camera.md


def test_look_at_refuses_degenerate_views():
    with pytest.raises(ValueError, match="same point"):
        C.look_at([1, 2, 3], [1, 2, 3])
    with pytest.raises(ValueError, match="parallel"):
        C.look_at([0, 2, 0], [0, 0, 0])                # straight down, up = +Y
    down = C.look_at([0, 2, 0], [0, 0, 0], up=[0, 0, -1])   # the documented way out
    u, v = project(down, [[0, 0, -0.5], [0.5, 0, 0]]).T
    assert v[0] < down.K[1, 2] and u[1] > down.K[0, 2]  # −Z at the top, +X to the right


def test_orbit_positions_names_and_up():
    cams = C.orbit(4, 2.0, [0.0], target=[0, 1, 0], fov_y_deg=50, width=33, height=17)
    assert [c.name for c in cams] == ["cam000", "cam001", "cam002", "cam003"]
    # azimuth 0 = +Z, 90 = +X, elevation 0: hand-computed centres
    expected = [[0, 1, 2], [2, 1, 0], [0, 1, -2], [-2, 1, 0]]
    np.testing.assert_allclose([c.center for c in cams], expected, atol=1e-12)
    for c in cams:
        np.testing.assert_allclose(project(c, [0, 1, 0]), [[16, 8]], atol=1e-9)
        assert project(c, [0, 1.3, 0])[0, 1] < 8            # world up is image up
        assert abs(np.linalg.det(c.R) - 1) < 1e-12
    rings = C.orbit(3, 1.0, [10.0, 60.0])
    assert len(rings) == 6 and rings[5].name == "cam005"
    np.testing.assert_allclose(rings[4].center[1], math.sin(math.radians(60)), atol=1e-12)


def test_orbit_straight_above_has_minus_z_up():
    """Elevation 90: the up vector is the direction of increasing elevation (no
    degenerate world up): −Z at the top of the image at azimuth 0."""
    cam, = C.orbit(1, 2.0, [90.0], width=9, height=9)
    np.testing.assert_allclose(cam.center, [0, 2, 0], atol=1e-12)
    (u_far, v_far), (u_right, v_right) = project(cam, [[0, 0, -0.3], [0.3, 0, 0]])
    assert v_far < 4 and abs(u_far - 4) < 1e-9
    assert u_right > 4 and abs(v_right - 4) < 1e-9
    # and it is the limit of the ring cameras below it (the image does not flip)
    near, = C.orbit(1, 2.0, [89.999], width=9, height=9)
    np.testing.assert_allclose(near.R, cam.R, atol=1e-4)


def test_dome_is_deterministic_and_above_its_lowest_elevation():
    a = C.dome(25, 1.5, min_elevation_deg=-20, target=[0, 0.1, 0])
    b = C.dome(25, 1.5, min_elevation_deg=-20, target=[0, 0.1, 0])
    assert [c.name for c in a] == [f"cam{k:03d}" for k in range(25)]
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.R, y.R)
    offsets = np.array([c.center for c in a]) - [0, 0.1, 0]
    np.testing.assert_allclose(np.linalg.norm(offsets, axis=1), 1.5, atol=1e-12)
    assert (offsets[:, 1] / 1.5 >= math.sin(math.radians(-20)) - 1e-12).all()
    for c in a:   # each looks at the target
        np.testing.assert_allclose(project(c, [0, 0.1, 0]), [[127.5, 127.5]], atol=1e-9)


# ----------------------------------------------------------------------------- OpenEXR matrices


def test_openexr_matrices_hand_computed():
    """Camera at z = 2 looking down −z: OpenEXR camera space (x right, y up, z forward)
    is (x, y, 2 − z); row vectors: [x y z 1]·M.  NDC (0, 0)/(1, 1) are the image's
    outer corners, so the principal point (1.5, 0.5) of a 4×2 image is NDC (½, ½)."""
    cam = Camera(np.array([[2.0, 0, 1.5], [0, 2.0, 0.5], [0, 0, 1]]), np.diag([1.0, -1.0, -1.0]),
                 np.array([0, 0, 2.0]), 4, 2)
    to_camera, to_ndc = openexr_matrices(cam)
    assert to_camera.dtype == np.float32 and to_camera.flags["C_CONTIGUOUS"]
    np.testing.assert_array_equal(to_camera, [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0],
                                              [0, 0, 2, 1]])
    for X, (u, v) in (([0, 0, 0], (1.5, 0.5)), ([0.5, -0.25, 1.0], (1.5 + 1.0, 0.5 + 0.5))):
        h = np.array([*X, 1.0]) @ to_ndc
        np.testing.assert_allclose(h[:2] / h[3], [(u + 0.5) / 4, (v + 0.5) / 2], atol=1e-7)
        np.testing.assert_allclose(project(cam, X), [[u, v]], atol=1e-12)
    back = camera_from_openexr(to_camera, to_ndc, 4, 2)
    np.testing.assert_allclose(back.K, cam.K, atol=1e-6)
    np.testing.assert_allclose(back.R, cam.R, atol=1e-7)


def header_pixels(path, X) -> np.ndarray:
    """[N, 2] pixels of world points read from an EXR's worldToNDC alone (OpenEXR's rules:
    row vectors, divide by w, NDC corners = image corners; ours: centres at integers)."""
    from relight_cli.formats.exr import read_exr
    image = read_exr(str(path))
    M = np.asarray(image.attributes["worldToNDC"], np.float64)
    h = np.c_[np.atleast_2d(X), np.ones(len(np.atleast_2d(X)))] @ M
    ndc = h[:, :2] / h[:, 3:]
    return ndc * [image.width, image.height] - 0.5


def test_hand_renderer_puts_a_point_where_the_header_says(tmp_path):
    """A fronto-parallel square centred on X, exactly 4 pixels wide, seen by the G-buffer
    with 16×16 samples per pixel: the centroid of its coverage is X's image.  A plane
    parallel to the image projects without perspective distortion; with an integer
    width the partial pixels at opposite edges cancel exactly in the pixel-level
    centroid, which leaves the sub-sample quantisation, at most half a sample spacing
    (1/32 px).  A half-pixel convention error would show as 0.5."""
    from render_scenes import uv_quad
    from relight_cli.formats.exr import write_exr
    from relight_cli.render.gbuffer import render_gbuffer
    cam = C.look_at([0.02, 0.03, 0.5], [0.02, 0.03, 0.0], fov_y_deg=20, width=40, height=30)
    X = np.array([0.031, 0.022, 0.0])
    quad = uv_quad(4 * 0.5 / cam.K[0, 0])               # 4 px at 0.5 m
    quad.vertices = quad.vertices + X
    mask = render_gbuffer([quad], cam, aa=16).mask
    rows, cols = np.mgrid[0:30, 0:40]
    centroid = np.array([(mask * cols).sum(), (mask * rows).sum()]) / mask.sum()
    write_exr(str(tmp_path / "q.exr"), {"A": mask}, camera=cam)
    np.testing.assert_allclose(header_pixels(tmp_path / "q.exr", X)[0], centroid,
                               atol=1 / 32 + 1e-4)   # + float32 header matrices


def test_splat_renderer_puts_a_gaussian_where_the_header_says(tmp_path, run_cli):
    """One round opaque Gaussian at X through `relight --camera`: its alpha centroid."""
    from relight_cli.formats.gaussians_ply import Gaussians, write_gaussians
    X = np.array([0.013, -0.021, 0.04])
    write_gaussians(str(tmp_path / "g.ply"), Gaussians(X[None], np.full((1, 3), 0.004),
                                                       np.array([[1.0, 0, 0, 0]]), np.array([0.9]),
                                                       np.zeros((1, 1, 3)), 0))
    write_cameras(str(tmp_path / "cam.json"),
                  [C.look_at([0.1, 0.05, 0.5], [0, 0, 0], fov_y_deg=25, width=48, height=36)])
    assert run_cli("sh-probe", "builtin:uniform", "--degree", "0", "-o", tmp_path / "p.json",
                   "-q").exit_code == 0
    r = run_cli("relight", tmp_path / "g.ply", "--probe", tmp_path / "p.json", "--camera",
                tmp_path / "cam.json", "-o", tmp_path / "g.exr", "-q")
    assert r.exit_code == 0, r.output
    from relight_cli.formats.exr import read_exr
    alpha = read_exr(str(tmp_path / "g.exr")).channels["A"].astype(np.float64)
    rows, cols = np.mgrid[0:36, 0:48]
    centroid = np.array([(alpha * cols).sum(), (alpha * rows).sum()]) / alpha.sum()
    # σ ≈ 1 px: the sampled Gaussian's centroid is its mean to ~1e-3 px (float16-free EXR)
    np.testing.assert_allclose(header_pixels(tmp_path / "g.exr", X)[0], centroid, atol=5e-3)


def test_hand_render_header_is_its_camera(tmp_path, run_cli):
    """`relight` hand mode: worldToCamera/worldToNDC are those of --camera, and `relight
    camera IMAGE.exr` gives the camera back (float32 precision)."""
    cam = C.look_at([0.05, 0.1, 0.45], [0, 0.06, 0], fov_y_deg=30, width=24, height=20)
    write_cameras(str(tmp_path / "cam.json"), [cam])
    r = run_cli("relight", "builtin:right", "builtin:uniform", "--camera", tmp_path / "cam.json",
                "--tex-res", "16", "--aa", "1", "--env-res", "8x4", "-o", tmp_path / "h.exr", "-q")
    assert r.exit_code == 0, r.output
    from relight_cli.formats.exr import read_exr
    attrs = read_exr(str(tmp_path / "h.exr")).attributes
    to_camera, to_ndc = openexr_matrices(cam)
    np.testing.assert_array_equal(np.asarray(attrs["worldToCamera"], np.float32), to_camera)
    np.testing.assert_array_equal(np.asarray(attrs["worldToNDC"], np.float32), to_ndc)
    r = run_cli("camera", "--from", tmp_path / "h.exr", "-o", tmp_path / "back.json", "-q")
    assert r.exit_code == 0, r.output
    back = read_camera(str(tmp_path / "back.json"))
    np.testing.assert_allclose(back.K, cam.K, rtol=1e-5)
    np.testing.assert_allclose(back.R, cam.R, atol=1e-6)
    np.testing.assert_allclose(back.t, cam.t, atol=1e-6)


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
