"""Cameras: look-at, rigs, COLMAP / nerfstudio imports, OpenEXR header matrices, and the
``relight camera`` command.

References are independent of the code under test: pixels computed by hand, COLMAP and
nerfstudio files written here from a known camera with scipy's quaternions and each
tool's own pixel convention (centre of the top-left pixel at (0.5, 0.5)), and renders
whose features (a small fronto-parallel square, one round Gaussian) sit at known points.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import run_relight
from relight_cli import cameras as C
from relight_cli.errors import DataError
from relight_cli.formats import camera_imports as I
from relight_cli.formats.camera import (Camera, camera_from_openexr, openexr_matrices,
                                        read_camera, read_cameras, write_cameras)


def project(cam: Camera, X) -> np.ndarray:
    """[N, 2] pixels of world points [N, 3] in relight's convention (camera.md)."""
    p = np.atleast_2d(X) @ cam.R.T + cam.t
    uvw = p @ cam.K.T
    return uvw[:, :2] / uvw[:, 2:]


def known_camera(width=64, height=48) -> Camera:
    """A camera with an arbitrary rotation, skew-free intrinsics fx ≠ fy, off-centre cx, cy."""
    R = Rotation.from_euler("xyz", [20, -35, 170], degrees=True).as_matrix()
    K = np.array([[70.0, 0, 30.25], [0, 65.0, 25.75], [0, 0, 1]])
    return Camera(K, R, np.array([0.1, -0.2, 1.5]), width, height, "img_001.png")


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


# ----------------------------------------------------------------------------- COLMAP


def colmap_text(cam: Camera, model="PINHOLE", extra=(), image_id=3, camera_id=7):
    """cameras.txt and images.txt of ``cam``, written as COLMAP does: pixel centres at +0.5,
    quaternion (w, x, y, z) of the world→camera rotation (scipy's is (x, y, z, w))."""
    fx, fy = cam.K[0, 0], cam.K[1, 1]
    cx, cy = cam.K[0, 2] + 0.5, cam.K[1, 2] + 0.5
    params = {"PINHOLE": [fx, fy, cx, cy], "SIMPLE_PINHOLE": [fx, cx, cy],
              "SIMPLE_RADIAL": [fx, cx, cy], "OPENCV": [fx, fy, cx, cy]}[model] + list(extra)
    cameras = ("# Camera list with one line of data per camera:\n"
               "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
               f"{camera_id} {model} {cam.width} {cam.height} "
               + " ".join(repr(float(p)) for p in params) + "\n")
    x, y, z, w = (float(v) for v in Rotation.from_matrix(cam.R).as_quat())
    tx, ty, tz = (float(v) for v in cam.t)
    images = ("# Image list with two lines of data per image:\n"
              "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
              "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
              f"{image_id} {w!r} {x!r} {y!r} {z!r} {tx!r} {ty!r} {tz!r} "
              f"{camera_id} {cam.name}\n"
              "\n")
    return cameras, images


def test_colmap_round_trip_and_half_pixel_shift():
    cam = known_camera()
    cams_txt, imgs_txt = colmap_text(cam)
    # a second image with a POINTS2D line, and one after it whose POINTS2D line is empty
    cams_txt += f"8 SIMPLE_PINHOLE 10 20 5.0 5.5 10.5\n"
    imgs_txt += ("4 1 0 0 0 0 0 1 8 b.png\n12.5 3.25 -1 4.0 5.0 17\n"
                 "5 1 0 0 0 0 0 2 8 a.png\n\n")
    got = I.cameras_from_colmap(cams_txt, imgs_txt)
    assert [c.name for c in got] == ["a.png", "b.png", "img_001.png"]     # sorted by name
    back = got[2]
    np.testing.assert_allclose(back.K, cam.K, atol=1e-12)
    np.testing.assert_allclose(back.R, cam.R, atol=1e-12)
    np.testing.assert_allclose(back.t, cam.t, atol=1e-15)
    np.testing.assert_allclose(got[0].K, [[5, 0, 5], [0, 5, 10], [0, 0, 1]])   # SIMPLE_PINHOLE
    # A point projected both ways: COLMAP's pixel (hand-written pinhole with COLMAP's cx)
    # sits 0.5 px right/down of ours, and both name the same pixel index.
    X = np.array([[0.05, 0.02, 0.1], [-0.2, 0.1, -0.1]])
    p = X @ cam.R.T + cam.t
    colmap_uv = np.stack([70.0 * p[:, 0] / p[:, 2] + 30.75, 65.0 * p[:, 1] / p[:, 2] + 26.25], 1)
    ours = project(back, X)
    np.testing.assert_allclose(ours, colmap_uv - 0.5, atol=1e-9)
    np.testing.assert_array_equal(np.floor(colmap_uv), np.round(ours))


def test_colmap_images_without_their_empty_points_lines():
    """Files whose empty POINTS2D lines were stripped (blank-line-dropping editors) parse."""
    cams_txt = "1 PINHOLE 8 8 4 4 4 4\n"
    imgs_txt = "1 1 0 0 0 0 0 1 1 a.png\n2 1 0 0 0 0 0 2 1 b.png\n"
    assert [c.name for c in I.cameras_from_colmap(cams_txt, imgs_txt)] == ["a.png", "b.png"]


def test_colmap_distortion_refused_unless_dropped():
    cam = known_camera()
    cams_txt, imgs_txt = colmap_text(cam, "SIMPLE_RADIAL", extra=[0.01])
    with pytest.raises(DataError, match="SIMPLE_RADIAL has lens distortion") as err:
        I.cameras_from_colmap(cams_txt, imgs_txt)
    assert "--drop-distortion" in str(err.value) and "\n" not in str(err.value)
    dropped = I.cameras_from_colmap(cams_txt, imgs_txt, drop_distortion=True)[0]
    assert dropped.K[0, 0] == dropped.K[1, 1] == 70.0
    zero = colmap_text(cam, "OPENCV", extra=[0, 0, 0, 0])     # no distortion: nothing lost
    np.testing.assert_allclose(I.cameras_from_colmap(*zero)[0].K, cam.K)
    fisheye = cams_txt.replace("SIMPLE_RADIAL", "OPENCV_FISHEYE")
    with pytest.raises(DataError, match="not a pinhole"):
        I.cameras_from_colmap(fisheye, imgs_txt, drop_distortion=True)


@pytest.mark.parametrize("change, message", [
    (lambda c, i: (c.replace("70.0", "nan", 1), i), "NaN"),
    (lambda c, i: (c, i.replace(" 1.5 ", " inf ", 1)), "NaN/Inf"),
    (lambda c, i: (c, i.replace(" 7 img", " 9 img")), "CAMERA_ID 9"),
    (lambda c, i: (c.replace("PINHOLE", "WEIRD"), i), "unknown COLMAP camera model"),
    (lambda c, i: (c + c, i), "appears twice"),
    (lambda c, i: (c, "\n".join(line if line.startswith("#") or not line else
                                "3 2 0 0 0 0 0 1 7 x.png" for line in i.splitlines())),
     "norm 2"),
    (lambda c, i: (c, "# nothing\n"), "no images"),
])
def test_colmap_bad_files(change, message):
    cams_txt, imgs_txt = change(*colmap_text(known_camera()))
    with pytest.raises(DataError, match=message):
        I.cameras_from_colmap(cams_txt, imgs_txt)


# ----------------------------------------------------------------------------- nerfstudio


def nerfstudio_frame(cam: Camera) -> list:
    """Its camera→world matrix in the OpenGL convention (y up, looking down −z)."""
    c2w = np.eye(4)
    c2w[:3, :3] = cam.R.T @ np.diag([1.0, -1.0, -1.0])    # OpenCV axes → OpenGL axes
    c2w[:3, 3] = cam.center
    return c2w.tolist()


def test_nerfstudio_round_trip_and_projection():
    cam = known_camera()
    doc = {"camera_model": "OPENCV", "fl_x": 70.0, "fl_y": 65.0, "cx": 30.75, "cy": 26.25,
           "w": 64, "h": 48, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
           "frames": [{"file_path": "images/frame_00001.png",
                       "transform_matrix": nerfstudio_frame(cam)},
                      {"file_path": "images/frame_00002.png", "fl_x": 90.0, "w": 100,
                       "transform_matrix": nerfstudio_frame(cam)}]}
    got = I.cameras_from_nerfstudio(doc)
    assert [c.name for c in got] == ["images/frame_00001.png", "images/frame_00002.png"]
    np.testing.assert_allclose(got[0].K, cam.K, atol=1e-12)
    np.testing.assert_allclose(got[0].R, cam.R, atol=1e-12)
    np.testing.assert_allclose(got[0].t, cam.t, atol=1e-12)
    assert got[1].K[0, 0] == 90.0 and got[1].width == 100 and got[1].K[1, 1] == 65.0
    # the other way: OpenGL camera coordinates, nerfstudio's pinhole (x/−z, −y/−z), its cx
    X = np.array([[0.05, 0.02, 0.1], [-0.2, 0.1, -0.1]])
    gl = (np.linalg.inv(np.array(doc["frames"][0]["transform_matrix"]))
          @ np.c_[X, np.ones(2)].T).T
    ns_uv = np.stack([70.0 * gl[:, 0] / -gl[:, 2] + 30.75, 65.0 * -gl[:, 1] / -gl[:, 2] + 26.25], 1)
    np.testing.assert_allclose(project(got[0], X), ns_uv - 0.5, atol=1e-9)


def test_nerfstudio_instant_ngp_angle_and_tiny_rotation_noise():
    cam = known_camera()
    matrix = np.array(nerfstudio_frame(cam))
    matrix[:3, :3] += 1e-5 * np.random.default_rng(0).normal(size=(3, 3))   # 5-digit files
    doc = {"camera_angle_x": 2 * math.atan(32 / 70.0), "w": 64, "h": 48,
           "frames": [{"file_path": "r_0", "transform_matrix": matrix.tolist()}]}
    got, = I.cameras_from_nerfstudio(doc)
    np.testing.assert_allclose(got.K, [[70, 0, 31.5], [0, 70, 23.5], [0, 0, 1]], atol=1e-9)
    np.testing.assert_allclose(got.R @ got.R.T, np.eye(3), atol=1e-14)   # made exact
    np.testing.assert_allclose(got.R, cam.R, atol=1e-4)


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(k1=0.1), "OPENCV has lens distortion"),
    (lambda d: d.update(camera_model="OPENCV_FISHEYE"), "not a pinhole"),
    (lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(0, 1.1), "not a rotation"),
    (lambda d: d["frames"][0].__setitem__(
        "transform_matrix", (np.array(d["frames"][0]["transform_matrix"])
                             @ np.diag([1, 1, -1, 1])).tolist()), "mirrored"),
    (lambda d: d.pop("w"), "'w'"),
    (lambda d: d.pop("fl_x"), "no focal length"),
    (lambda d: d.update(frames=[]), "non-empty"),
    (lambda d: d["frames"].append(dict(d["frames"][0])), "appears twice"),
    (lambda d: d["frames"][0].__setitem__("transform_matrix", np.eye(3).tolist()), "4×4"),
])
def test_nerfstudio_bad_files(change, message):
    doc = {"fl_x": 70.0, "fl_y": 65.0, "cx": 30.75, "cy": 26.25, "w": 64, "h": 48,
           "frames": [{"file_path": "a.png", "transform_matrix": nerfstudio_frame(known_camera())}]}
    change(doc)
    with pytest.raises(DataError, match=message):
        I.cameras_from_nerfstudio(doc)


def test_nerfstudio_distortion_dropped_on_request():
    doc = {"fl_x": 70.0, "fl_y": 65.0, "cx": 30.75, "cy": 26.25, "w": 64, "h": 48, "k1": -0.2,
           "frames": [{"file_path": "a.png", "transform_matrix": nerfstudio_frame(known_camera())}]}
    got, = I.cameras_from_nerfstudio(doc, drop_distortion=True)
    np.testing.assert_allclose(got.K, known_camera().K)


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


# ----------------------------------------------------------------------------- the command


def test_cli_look_at_orbit_select_and_stdout(tmp_path, run_cli):
    out = tmp_path / "cam.json"
    r = run_cli("camera", "--eye", "0.45,0.55,0.6", "--target", "0,0.15,0", "--fov", "45",
                "--size", "320x240", "--name", "room", "-o", out)
    assert r.exit_code == 0, r.output
    doc = json.loads(out.read_text())
    assert doc["format"] == "relight/camera" and doc["version"] == 1 and doc["name"] == "room"
    assert doc["provenance"]["settings"]["mode"] == "look-at"
    cam = read_camera(str(out))
    assert (cam.width, cam.height) == (320, 240)
    np.testing.assert_allclose(cam.center, [0.45, 0.55, 0.6], atol=1e-12)
    np.testing.assert_allclose(project(cam, [0, 0.15, 0]), [[159.5, 119.5]], atol=1e-9)
    r = run_cli("camera", "--orbit", "6", "--radius", "0.8", "--elevation", "15,45", "-o",
                tmp_path / "rig.json", "-q")
    assert r.exit_code == 0 and len(read_cameras(str(tmp_path / "rig.json"))) == 12
    r = run_cli("camera", "--from", tmp_path / "rig.json", "--select", "cam007,cam002", "-o", "-")
    assert r.exit_code == 0, r.output
    picked = json.loads(r.stdout)
    assert [c["name"] for c in picked["cameras"]] == ["cam007", "cam002"]
    r = run_cli("camera", "--from", tmp_path / "rig.json", "--select", "cam003", "-o",
                tmp_path / "c3.json")
    assert read_camera(str(tmp_path / "c3.json")).name == "cam003"


def test_cli_imports_colmap_folder_and_nerfstudio_from_stdin(tmp_path):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    cam = known_camera()
    cams_txt, imgs_txt = colmap_text(cam)
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(cams_txt)
    (model / "images.txt").write_text(imgs_txt)
    for source in (model, model / "images.txt"):
        r = CliRunner().invoke(cli, ["camera", "--from", str(source), "-o",
                                     str(tmp_path / "c.json")])
        assert r.exit_code == 0, r.output
        back = read_camera(str(tmp_path / "c.json"))
        np.testing.assert_allclose(back.K, cam.K, atol=1e-12)
        doc = json.loads((tmp_path / "c.json").read_text())
        assert set(doc["provenance"]["inputs"]) == {"colmap_cameras", "colmap_images"}
        (tmp_path / "c.json").unlink()
    doc = {"fl_x": 70.0, "fl_y": 65.0, "cx": 30.75, "cy": 26.25, "w": 64, "h": 48,
           "frames": [{"file_path": "a.png", "transform_matrix": nerfstudio_frame(cam)}]}
    text = json.dumps(doc)
    r = CliRunner().invoke(cli, ["camera", "--from", "-", "-o", "-"], input=text)
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    np.testing.assert_allclose(out["R"], cam.R, atol=1e-12)
    import hashlib
    assert (out["provenance"]["inputs"]["source"]["sha256"]
            == hashlib.sha256(text.encode()).hexdigest())


def test_cli_output_is_byte_identical(tmp_path, run_cli):
    args = ["camera", "--dome", "5", "--radius", "1", "--elevation", "10"]
    assert run_cli(*args, "-o", tmp_path / "a.json").exit_code == 0
    assert run_cli(*args, "-o", tmp_path / "a2.json", "-q").exit_code == 0
    a, b = (tmp_path / "a.json").read_text(), (tmp_path / "a2.json").read_text()
    assert a.replace("a.json", "a2.json").replace(' -q"', '"') == b


def test_console_script_writes_a_camera_and_relight_renders_with_it(tmp_path):
    r = run_relight("camera", "--eye", "0,0.06,0.5", "--target", "0,0.06,0", "--fov", "30",
                    "--size", "16x12", "-o", tmp_path / "cam.json")
    assert r.returncode == 0 and r.stdout == "" and "wrote" in r.stderr, r.stderr
    r = run_relight("relight", "builtin:right", "builtin:uniform", "--camera", tmp_path / "cam.json",
                    "--tex-res", "16", "--aa", "1", "--env-res", "8x4", "-o", tmp_path / "h.exr",
                    "-q")
    assert r.returncode == 0, r.stderr
    r = run_relight("camera", "--eye", "0,0,0", "-o", tmp_path / "x.json")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "same point" in r.stderr
    assert not (tmp_path / "x.json").exists()


def _write_bad(tmp_path):
    (tmp_path / "nan.json").write_text('{"fl_x": NaN, "w": 4, "h": 4, "frames": []}')
    (tmp_path / "ns.json").write_text(json.dumps(
        {"fl_x": 7.0, "w": 8, "h": 8, "k1": 0.3,
         "frames": [{"file_path": "a", "transform_matrix": np.eye(4).tolist()}]}))
    (tmp_path / "scaled.json").write_text(json.dumps(
        {"fl_x": 7.0, "w": 8, "h": 8,
         "frames": [{"file_path": "a", "transform_matrix": np.diag([2.0, 2, 2, 1]).tolist()}]}))
    model = tmp_path / "colmap"
    model.mkdir()
    (model / "cameras.txt").write_text("1 PINHOLE 8 8 nan 4 4 4\n")
    (model / "images.txt").write_text("1 1 0 0 0 0 0 1 1 a.png\n\n")
    binary = tmp_path / "binary"
    binary.mkdir()
    (binary / "cameras.bin").write_bytes(b"\0" * 8)
    (tmp_path / "notes.txt").write_text("hello")
    write_cameras(str(tmp_path / "rig.json"), C.orbit(2, 1.0))
    from relight_cli.formats.exr import write_exr
    write_exr(str(tmp_path / "plain.exr"), {"R": np.ones((2, 2), np.float32)})


@pytest.mark.parametrize("args, code, words", [
    (["--eye", "1,1,1", "--target", "1,1,1"], 2, ["same point"]),
    (["--eye", "0,3,0"], 2, ["parallel", "--up"]),
    (["--eye", "0,1,nan"], 2, ["--eye"]),
    (["--fov", "180", "--eye", "0,0,1"], 2, ["--fov"]),
    ([], 2, ["exactly one of"]),
    (["--from", "rig.json", "--eye", "0,0,1"], 2, ["exactly one of"]),
    (["--from", "rig.json", "--fov", "30"], 2, ["--fov", "--from"]),
    (["--orbit", "4"], 2, ["--radius"]),
    (["--orbit", "4", "--radius", "1", "--up", "0,0,1"], 2, ["--up"]),
    (["--orbit", "4", "--radius", "1", "--elevation", "95"], 2, ["--elevation"]),
    (["--dome", "4", "--radius", "1", "--elevation", "10,20"], 2, ["--dome"]),
    (["--eye", "0,0,1", "--radius", "1"], 2, ["--radius"]),
    (["--eye", "0,0,1", "--drop-distortion"], 2, ["--drop-distortion"]),
    (["--from", "rig.json", "--select", "cam009"], 2, ["cam009", "cam000"]),
    (["--from", "notes.txt"], 2, ["--from takes"]),
    (["--from", "missing.json"], 1, ["no such file", "missing.json"]),
    (["--from", "nan.json"], 1, ["NaN", "nan.json"]),
    (["--from", "ns.json"], 1, ["lens distortion", "ns.json"]),
    (["--from", "scaled.json"], 1, ["not a rotation", "scaled.json"]),
    (["--from", "colmap"], 1, ["NaN", "cameras.txt"]),
    (["--from", "binary"], 1, ["model_converter"]),
    (["--from", "plain.exr"], 1, ["worldToCamera", "plain.exr"]),
])
def test_cli_bad_input(tmp_path, monkeypatch, args, code, words):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    _write_bad(tmp_path)
    monkeypatch.chdir(tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    r = CliRunner().invoke(cli, ["camera", *args, "-o", "out.json"])
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.exit_code == code, r.output
    assert len(lines) == 1 and "Traceback" not in r.output, r.output
    assert "camera: error:" in lines[0]       # click's own errors name the program as invoked
    for w in words:
        assert w in lines[0], lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_relight_render_option_is_renamed(tmp_path, run_cli):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    r = CliRunner().invoke(cli, ["relight", "builtin:sphere", "--probe", "p.json", "--render",
                                 "cam.json", "-o", str(tmp_path / "v.exr")])
    assert r.exit_code == 2 and "--render was renamed --camera" in r.stderr
    assert r.stderr.count("\n") == 1
    assert "  --render" not in CliRunner().invoke(cli, ["relight", "--help"]).output   # hidden


def test_cli_cameras_of_a_capture(tmp_path, run_cli):
    """`--from capture.json --select cam001`: one camera of a synthetic light stage's rig,
    exactly as the capture stores it (the README's example uses it)."""
    r = run_cli("synth-capture", "-o", tmp_path / "cap", "--cameras", "2", "--leds", "2",
                "--group", "1", "--frames", "1", "--size", "8", "--tex-res", "8", "--aa", "1",
                "--eval-poses", "0", "--eval-cameras", "1", "-q")
    assert r.exit_code == 0, r.output
    r = run_cli("camera", "--from", tmp_path / "cap" / "capture.json", "--select", "cam001",
                "-o", tmp_path / "c.json", "-q")
    assert r.exit_code == 0, r.output
    stored = json.loads((tmp_path / "cap" / "capture.json").read_text())["cameras"][1]
    cam = read_camera(str(tmp_path / "c.json"))
    assert cam.name == "cam001"
    np.testing.assert_array_equal(cam.K, stored["K"])
    np.testing.assert_array_equal(cam.R, stored["R"])
    # and its image carries the same camera in its header
    from relight_cli.formats.exr import read_exr
    attrs = read_exr(str(tmp_path / "cap" / "images" / "000000" / "cam001.exr")).attributes
    np.testing.assert_array_equal(np.asarray(attrs["worldToNDC"], np.float32),
                                  openexr_matrices(cam)[1])
