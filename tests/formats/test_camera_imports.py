"""Camera imports (formats/camera_imports.py): COLMAP and nerfstudio files written here from a known
camera with scipy's quaternions and each tool's own pixel convention (centre of the top-left
pixel at (0.5, 0.5)), read back; distortion and bad files refused."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from relight_cli.errors import DataError
from relight_cli.formats import camera_imports as I
from relight_cli.formats.camera import Camera


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
