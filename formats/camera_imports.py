"""Cameras from other tools: COLMAP text models and nerfstudio ``transforms.json``
(and from relight's own JSON files that hold cameras: camera rigs, capture indexes).

Spec: ``formats/camera.md`` (section *Imports*).  Both tools put the centre of the
top-left pixel at (0.5, 0.5); ``relight/camera`` puts it at (0, 0) (OpenCV), so the
principal point moves by −½ pixel on import.  Lens distortion cannot be kept by a
pinhole camera: a model with non-zero distortion is refused unless the caller asks
for it to be dropped.  Readers take text or parsed JSON; the path versions are
one-line wrappers, so tests round-trip through strings.
"""

from __future__ import annotations

import math
import os

import numpy as np

from relight_cli.errors import DataError

from .camera import Camera, camera_from_json, nearest_rotation

# COLMAP and nerfstudio: centre of the top-left pixel at (0.5, 0.5); ours at (0, 0).
PIXEL_CENTRE_SHIFT = -0.5

# COLMAP camera models: name -> parameter names (src/colmap/sensor/models.h).
COLMAP_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}
# Models whose distortion is not a small polynomial correction of a pinhole: refused
# even with drop_distortion (a fisheye without its distortion is a different camera).
COLMAP_NOT_PINHOLE = ("OPENCV_FISHEYE", "FOV", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE",
                      "THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE")
NERFSTUDIO_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def _intrinsics(fx, fy, cx, cy, width, height, name, path, where) -> Camera:
    """A camera with identity pose from tool intrinsics (their pixel convention)."""
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)):
        raise DataError(f"{where}: intrinsics hold NaN/Inf", path)
    if fx <= 0 or fy <= 0:
        raise DataError(f"{where}: focal lengths must be positive, got {fx:g}, {fy:g}", path)
    if not (0 < width <= 65536 and 0 < height <= 65536):
        raise DataError(f"{where}: image size must be positive (at most 65536), got "
                        f"{width}x{height}", path)
    K = [[fx, 0.0, cx + PIXEL_CENTRE_SHIFT], [0.0, fy, cy + PIXEL_CENTRE_SHIFT], [0.0, 0.0, 1.0]]
    return camera_from_json({"K": K, "R": np.eye(3).tolist(), "t": [0.0, 0.0, 0.0],
                             "width": width, "height": height, "name": name}, path)


def _refuse_distortion(model: str, values: dict, drop: bool, path: str, where: str) -> None:
    nonzero = {k: v for k, v in values.items() if v != 0}
    if nonzero and not drop:
        terms = ", ".join(f"{k}={v:g}" for k, v in nonzero.items())
        raise DataError(f"{where}: camera model {model} has lens distortion ({terms}) that a "
                        f"pinhole camera cannot keep", path,
                        hint="undistort the images first (colmap image_undistorter), or give "
                             "--drop-distortion to ignore it")


# ----------------------------------------------------------------------------- COLMAP


def _data_lines(text: str):
    """(line number, stripped line) of a COLMAP text file, comments dropped, blanks kept."""
    for number, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line.startswith("#"):
            yield number, line


def _floats(tokens, path, number, what):
    try:
        values = [float(v) for v in tokens]
    except ValueError:
        raise DataError(f"line {number}: {what} must be numbers", path) from None
    if not all(math.isfinite(v) for v in values):
        raise DataError(f"line {number}: {what} hold NaN/Inf", path)
    return values


def _int(token, path, number, what) -> int:
    try:
        return int(token)
    except ValueError:
        raise DataError(f"line {number}: {what} must be an integer, got {token!r}", path) from None


def parse_colmap_cameras(text: str, path: str = "cameras.txt", drop_distortion: bool = False):
    """COLMAP ``cameras.txt`` (CAMERA_ID MODEL WIDTH HEIGHT PARAMS…) → {id: Camera}
    with identity poses, principal point in relight's pixel convention."""
    cameras = {}
    for number, line in _data_lines(text):
        if not line:
            continue
        tokens = line.split()
        if len(tokens) < 4:
            raise DataError(f"line {number}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...",
                            path)
        cam_id = _int(tokens[0], path, number, "CAMERA_ID")
        model = tokens[1]
        width = _int(tokens[2], path, number, "WIDTH")
        height = _int(tokens[3], path, number, "HEIGHT")
        where = f"line {number} (camera {cam_id})"
        if model in COLMAP_NOT_PINHOLE:
            raise DataError(f"{where}: camera model {model} is not a pinhole camera and "
                            f"cannot be imported", path,
                            hint="undistort the images first (colmap image_undistorter)")
        if model not in COLMAP_MODELS:
            raise DataError(f"{where}: unknown COLMAP camera model {model!r}", path)
        names = COLMAP_MODELS[model]
        params = _floats(tokens[4:], path, number, "PARAMS")
        if len(params) != len(names):
            raise DataError(f"{where}: model {model} takes {len(names)} parameters "
                            f"({' '.join(names)}), got {len(params)}", path)
        p = dict(zip(names, params))
        _refuse_distortion(model, {k: v for k, v in p.items()
                                   if k not in ("f", "fx", "fy", "cx", "cy")},
                           drop_distortion, path, where)
        fx, fy = (p["f"], p["f"]) if "f" in p else (p["fx"], p["fy"])
        if cam_id in cameras:
            raise DataError(f"{where}: CAMERA_ID {cam_id} appears twice", path)
        cameras[cam_id] = _intrinsics(fx, fy, p["cx"], p["cy"], width, height, "", path, where)
    return cameras


def _is_points_line(line: str) -> bool:
    """A POINTS2D line: (X Y POINT3D_ID) triples, possibly none."""
    tokens = line.split()
    if len(tokens) % 3:
        return False
    try:
        for i in range(0, len(tokens), 3):
            float(tokens[i]), float(tokens[i + 1]), int(tokens[i + 2])
    except ValueError:
        return False
    return True


def quaternion_to_rotation(qw: float, qx: float, qy: float, qz: float) -> np.ndarray:
    """[3, 3] rotation of the unit Hamilton quaternion (w, x, y, z)."""
    return np.array([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
        [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
        [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)]])


def parse_colmap_images(text: str, path: str = "images.txt"):
    """COLMAP ``images.txt`` → [(name, camera_id, R [3, 3], t [3])], world→camera.

    Each image is two lines: IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then its
    POINTS2D (possibly empty).  Blank lines before an image line are skipped; a
    missing POINTS2D line (files whose empty lines were stripped) is tolerated.
    A quaternion must have norm 1 to 1e-3; it is then normalised.
    """
    lines = list(_data_lines(text))
    images, names = [], set()
    i = 0
    while i < len(lines):
        number, line = lines[i]
        i += 1
        if not line:
            continue
        tokens = line.split()
        if len(tokens) < 10:
            raise DataError(f"line {number}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID "
                            f"NAME", path)
        image_id = _int(tokens[0], path, number, "IMAGE_ID")
        values = _floats(tokens[1:8], path, number, "QW QX QY QZ TX TY TZ")
        camera_id = _int(tokens[8], path, number, "CAMERA_ID")
        name = " ".join(tokens[9:])
        q = np.asarray(values[:4])
        norm = float(np.linalg.norm(q))
        if abs(norm - 1) > 1e-3:
            raise DataError(f"line {number} (image {image_id}): quaternion QW QX QY QZ has "
                            f"norm {norm:.6g}, not 1", path)
        R = quaternion_to_rotation(*(q / norm))
        if name in names:
            raise DataError(f"line {number}: image name {name!r} appears twice", path)
        names.add(name)
        images.append((name, camera_id, R, np.asarray(values[4:7])))
        if i < len(lines) and _is_points_line(lines[i][1]):
            i += 1   # this image's POINTS2D
    return images


def cameras_from_colmap(cameras_text: str, images_text: str, drop_distortion: bool = False,
                        cameras_path: str = "cameras.txt",
                        images_path: str = "images.txt") -> list[Camera]:
    """One ``relight/camera`` per registered image, named after it, sorted by name."""
    intrinsics = parse_colmap_cameras(cameras_text, cameras_path, drop_distortion)
    images = parse_colmap_images(images_text, images_path)
    if not images:
        raise DataError("the model has no images", images_path)
    out = []
    for name, camera_id, R, t in sorted(images, key=lambda item: item[0]):
        if camera_id not in intrinsics:
            raise DataError(f"image {name!r} uses CAMERA_ID {camera_id}, which is not in "
                            f"{os.path.basename(cameras_path)}", images_path)
        base = intrinsics[camera_id]
        out.append(Camera(base.K.copy(), R, t, base.width, base.height, name))
    return out


def colmap_model_files(path: str) -> tuple[str, str]:
    """(cameras.txt, images.txt) of a COLMAP text model: a folder holding both, or
    either file (the other beside it)."""
    folder = path if os.path.isdir(path) else os.path.dirname(path) or "."
    cameras, images = (os.path.join(folder, n) for n in ("cameras.txt", "images.txt"))
    for needed in (cameras, images):
        if not os.path.isfile(needed):
            binary = needed[:-4] + ".bin"
            hint = ("this is a binary model: convert it with colmap model_converter "
                    "--output_type TXT" if os.path.exists(binary) else
                    "this is a relight capture: give its capture.json"
                    if os.path.isfile(os.path.join(folder, "capture.json")) else None)
            raise DataError(f"a COLMAP text model needs {os.path.basename(needed)}", needed,
                            hint=hint)
    return cameras, images


def read_colmap_model(path: str, drop_distortion: bool = False) -> list[Camera]:
    """Cameras of a COLMAP text model (folder, cameras.txt or images.txt)."""
    cameras_path, images_path = colmap_model_files(path)
    return cameras_from_colmap(_read_text(cameras_path), _read_text(images_path),
                               drop_distortion, cameras_path, images_path)


def _read_text(path: str) -> str:
    try:
        with open(path, encoding="utf-8") as f:
            return f.read()
    except UnicodeDecodeError:
        raise DataError("not a text file (UTF-8)", path) from None
    except OSError as exc:
        raise DataError(f"cannot read: {exc.strerror}", path) from None


# ----------------------------------------------------------------------------- nerfstudio


# OpenGL/Blender camera axes (x right, y up, looking down −z) → OpenCV's (y down, z forward).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
                   "camera_model") + NERFSTUDIO_DISTORTION


# A field of view a pinhole camera can have: in (0, π) radians, kept 1° from π (where the
# focal length goes to 0: π itself gives 10⁻¹⁴ pixels) and 10⁻⁶ rad from 0 (where it
# goes to infinity).
ANGLE_RANGE = (1e-6, math.pi - math.radians(1.0))


def _angle(p: dict, key: str, where: str, path: str) -> float:
    """A nerfstudio field of view (radians), checked against :data:`ANGLE_RANGE`."""
    value = float(p[key])
    lo, hi = ANGLE_RANGE
    if not (math.isfinite(value) and lo <= value <= hi):
        raise DataError(f"{where}: '{key}' must be a field of view in radians, in (0, π) with a "
                        f"margin: from {lo:g} to {hi:.4f} (179°), got {value:g}", path)
    return value


def _focal(p: dict, key: str, where: str, path: str) -> float:
    """A nerfstudio focal length in pixels: finite and positive."""
    value = float(p[key])
    if not (math.isfinite(value) and value > 0):
        raise DataError(f"{where}: '{key}' (focal length in pixels) must be a positive "
                        f"number, got {value:g}", path)
    return value


def is_nerfstudio(obj) -> bool:
    """A transforms.json: frames, and no relight format tag (a capture index has frames too)."""
    return (isinstance(obj, dict) and "frames" in obj
            and not str(obj.get("format", "")).startswith("relight/"))


def cameras_from_nerfstudio(obj, path: str = "transforms.json",
                            drop_distortion: bool = False) -> list[Camera]:
    """One ``relight/camera`` per frame of a nerfstudio (or instant-ngp) transforms.json.

    Intrinsics ``fl_x fl_y cx cy w h`` (or ``camera_angle_x``/``_y`` in radians) are
    global or per frame (a frame's own win); ``transform_matrix`` is camera→world with
    OpenGL camera axes; names are the frames' ``file_path``, in file order.  The world
    frame is the file's (an ``applied_transform`` is not undone).
    """
    from ._common import is_number
    if not is_nerfstudio(obj):
        raise DataError("not a nerfstudio transforms.json (no 'frames')", path)
    frames = obj["frames"]
    if not isinstance(frames, list) or not frames:
        raise DataError("'frames' must be a non-empty list", path)
    shared = {k: obj[k] for k in _INTRINSIC_KEYS if k in obj}
    out, names = [], set()
    for i, frame in enumerate(frames):
        where = f"frames[{i}]"
        if not isinstance(frame, dict):
            raise DataError(f"{where} must be an object", path)
        p = dict(shared, **{k: frame[k] for k in _INTRINSIC_KEYS if k in frame})
        model = p.get("camera_model", "OPENCV")
        if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
            raise DataError(f"{where}: camera_model {model!r} is not a pinhole camera and "
                            f"cannot be imported", path)
        for key in ("w", "h"):
            if not (isinstance(p.get(key), int) and not isinstance(p.get(key), bool)):
                raise DataError(f"{where}: '{key}' (image size in pixels) must be an integer",
                                path)
        for key, value in p.items():
            if key not in ("camera_model", "w", "h") and not is_number(value):
                raise DataError(f"{where}: '{key}' must be a number, got {value!r}"[:160], path)
        w, h = p["w"], p["h"]
        if not (0 < w <= 65536 and 0 < h <= 65536):
            raise DataError(f"{where}: 'w' and 'h' (image size) must be positive (at most "
                            f"65536), got {w}x{h}", path)
        if "fl_x" in p:
            fx = _focal(p, "fl_x", where, path)
            fy = _focal(p, "fl_y", where, path) if "fl_y" in p else fx
        elif "camera_angle_x" in p:
            fx = 0.5 * w / math.tan(0.5 * _angle(p, "camera_angle_x", where, path))
            fy = (0.5 * h / math.tan(0.5 * _angle(p, "camera_angle_y", where, path))
                  if "camera_angle_y" in p else fx)
        else:
            raise DataError(f"{where}: no focal length (fl_x or camera_angle_x)", path)
        _refuse_distortion(model, {k: float(p[k]) for k in NERFSTUDIO_DISTORTION if k in p},
                           drop_distortion, path, where)
        base = _intrinsics(fx, fy, float(p.get("cx", w / 2)), float(p.get("cy", h / 2)), w, h,
                           "", path, where)
        from ._common import number_array
        M = number_array(frame.get("transform_matrix"), f"{where}.transform_matrix", path)
        if M.shape not in ((4, 4), (3, 4)):
            raise DataError(f"{where}.transform_matrix must be 4×4 (or 3×4), got shape "
                            f"{M.shape}", path)
        if not np.isfinite(M).all():
            raise DataError(f"{where}.transform_matrix holds NaN/Inf", path)
        if M.shape == (4, 4) and np.abs(M[3] - [0, 0, 0, 1]).max() > 1e-6:
            raise DataError(f"{where}.transform_matrix's last row must be [0, 0, 0, 1]", path)
        rotation = nearest_rotation(M[:3, :3], f"{where}.transform_matrix's rotation", path)
        R = (rotation @ _GL_TO_CV).T                      # world→camera, OpenCV axes
        t = -R @ M[:3, 3]
        name = frame.get("file_path", f"frame{i:05d}")
        if not isinstance(name, str):
            raise DataError(f"{where}.file_path must be a string", path)
        if name in names:
            raise DataError(f"{where}: file_path {name!r} appears twice", path)
        names.add(name)
        out.append(Camera(base.K, R, t, base.width, base.height, name))
    return out


# ----------------------------------------------------------------------------- any JSON


def cameras_from_any_json(obj, path: str, drop_distortion: bool = False):
    """(cameras, kind) of a parsed JSON file holding cameras: a nerfstudio/instant-ngp
    transforms.json, a ``relight/capture`` index (its rig) or a ``relight/camera`` file."""
    from .camera import cameras_from_json
    if is_nerfstudio(obj):
        return cameras_from_nerfstudio(obj, path, drop_distortion), "nerfstudio"
    from . import capture
    if isinstance(obj, dict) and obj.get("format") == capture.FORMAT:
        return capture.capture_from_json(obj, path).cameras, capture.FORMAT
    return cameras_from_json(obj, path), "relight/camera"
