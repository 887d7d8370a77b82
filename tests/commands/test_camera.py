"""``relight camera`` (commands/camera.py): look-at, orbits, selection, imports from COLMAP,
nerfstudio, captures and renders, stdout, byte identity, the console script, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import run_relight
from relight_cli import cameras as C
from relight_cli.formats.camera import Camera, openexr_matrices, read_camera, read_cameras, write_cameras


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


# ----------------------------------------------------------------------------- nerfstudio


def nerfstudio_frame(cam: Camera) -> list:
    """Its camera→world matrix in the OpenGL convention (y up, looking down −z)."""
    c2w = np.eye(4)
    c2w[:3, :3] = cam.R.T @ np.diag([1.0, -1.0, -1.0])    # OpenCV axes → OpenGL axes
    c2w[:3, 3] = cam.center
    return c2w.tolist()


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
                "--group", "1", "--n-frames", "1", "--size", "8", "--tex-res", "8", "--aa", "1",
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
