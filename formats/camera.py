"""Cameras: OpenCV/COLMAP pinhole cameras in JSON (spec: ``formats/camera.md``).

A camera is ``{"K": 3×3, "R": 3×3, "t": [3], "width": W, "height": H}`` with
x_cam = R·x_world + t (world→camera), pixel = K·x_cam / z (x right, y down,
z forward); the centre of the top-left pixel is (0, 0).  A JSON list of such
objects (or ``{"cameras": [...]}``) is a rig.  Also here: the camera as OpenEXR's
standard header matrices ``worldToCamera`` and ``worldToNDC`` and back, with its
name from relight's ``relight.camera`` attribute.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from relight_cli.errors import DataError

FORMAT = "relight/camera"
VERSION = 1


@dataclass
class Camera:
    """A pinhole camera.

    Attributes:
        K: [3, 3] float64 intrinsics (pixels).
        R: [3, 3] float64 world→camera rotation.
        t: [3] float64 world→camera translation (metres).
        width, height: image size in pixels.
        name: optional label (e.g. the camera id of a capture rig).
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    name: str = ""

    @property
    def center(self) -> np.ndarray:
        """[3] camera centre in world coordinates, −Rᵀt."""
        return -self.R.T @ self.t

    def to_json(self) -> dict:
        out = {"K": self.K.tolist(), "R": self.R.tolist(), "t": self.t.tolist(),
               "width": int(self.width), "height": int(self.height)}
        if self.name:
            out["name"] = self.name
        return out

    @staticmethod
    def look_at(eye, target, up=(0.0, 1.0, 0.0), fov_y_deg: float = 40.0,
                width: int = 256, height: int = 256, name: str = "") -> "Camera":
        """An OpenCV camera at ``eye`` looking at ``target`` with world ``up`` (+Y).

        ``fov_y_deg`` spans the image from its top edge to its bottom edge; the
        principal point is the image centre ((W − 1)/2, (H − 1)/2), so ``target``
        lands there.  When ``up`` is parallel to the view direction, any right
        vector is picked (callers that care refuse that case first).
        """
        eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
        forward = target - eye
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, up)
        if np.linalg.norm(right) < 1e-9:  # looking straight along up: pick any right
            right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R = np.stack([right, down, forward])  # rows: camera x, y, z axes in world
        t = -R @ eye
        f = 0.5 * height / np.tan(np.radians(fov_y_deg) / 2)
        K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], np.float64)
        return Camera(K, R, t, int(width), int(height), name)


def camera_from_json(obj, path: str = "", index: int | None = None) -> Camera:
    where = f"camera {index}: " if index is not None else ""
    if not isinstance(obj, dict):
        raise DataError(f"{where}expected a JSON object with K, R, t, width, height", path)
    missing = [k for k in ("K", "R", "t", "width", "height") if k not in obj]
    if missing:
        raise DataError(f"{where}missing field(s) {', '.join(missing)}", path)
    from ._common import is_int, number_array
    K = number_array(obj["K"], f"{where}K", path)
    R = number_array(obj["R"], f"{where}R", path)
    t = number_array(obj["t"], f"{where}t", path).reshape(-1)
    if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
        raise DataError(f"{where}K and R must be 3×3 and t length 3, got "
                        f"{K.shape}, {R.shape}, {t.shape}", path)
    if not (np.isfinite(K).all() and np.isfinite(R).all() and np.isfinite(t).all()):
        raise DataError(f"{where}K, R or t holds NaN/Inf", path)
    if abs(np.linalg.det(R) - 1) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
        raise DataError(f"{where}R is not a rotation matrix (orthonormal, det +1)", path)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1) > 1e-9 or np.any(K[2, :2] != 0):
        raise DataError(f"{where}K must have positive focal lengths and last row [0, 0, 1]", path)
    w, h = obj["width"], obj["height"]
    if not (is_int(w) and is_int(h) and 0 < w <= 65536 and 0 < h <= 65536):
        raise DataError(f"{where}width and height must be positive integers", path)
    return Camera(K, R, t, w, h, str(obj.get("name", "")))


def cameras_from_json(obj, path: str = "") -> list[Camera]:
    """One camera (object) or a rig (list, or ``{"cameras": [...]}``) from parsed JSON.

    ``format``/``version`` are checked when present (files before the tag have none).
    """
    if isinstance(obj, dict) and ("format" in obj or "version" in obj):
        from ._common import check_format_version
        check_format_version(obj.get("format"), obj.get("version"), FORMAT, VERSION, path)
    if isinstance(obj, dict) and "cameras" in obj:
        obj = obj["cameras"]
    if isinstance(obj, list):
        if not obj:
            raise DataError("camera list is empty", path)
        return [camera_from_json(o, path, i) for i, o in enumerate(obj)]
    return [camera_from_json(obj, path)]


def read_cameras(path: str) -> list[Camera]:
    """Read one camera (object) or a rig (list, or {"cameras": [...]}) from JSON."""
    from ._common import read_json
    return cameras_from_json(read_json(path), path)


def read_camera(path: str) -> Camera:
    """Read exactly one camera."""
    cams = read_cameras(path)
    if len(cams) != 1:
        raise DataError(f"expected one camera, file holds {len(cams)} (pick one with "
                        f"relight camera --from RIG.json --select NAME)", path)
    return cams[0]


def dumps_cameras(cameras: list[Camera], provenance: dict | None = None) -> str:
    """The JSON text of one camera (an object) or a rig (``{"cameras": [...]}``).

    Tagged with ``format``/``version``; each matrix row on one line; floats as
    Python's repr, which round-trips exactly.
    """
    def camera_lines(cam: Camera, indent: str) -> list[str]:
        obj = cam.to_json()
        for key in ("K", "R", "t"):   # + 0.0 turns −0.0 into 0.0
            obj[key] = (np.asarray(obj[key], np.float64) + 0.0).tolist()
        rows = [f'{indent}"name": {json.dumps(obj["name"])}'] if "name" in obj else []
        for key in ("K", "R"):
            inner = f",\n{indent}      ".join(json.dumps(r) for r in obj[key])
            rows.append(f'{indent}"{key}": [{inner}]')
        rows += [f'{indent}"t": {json.dumps(obj["t"])}', f'{indent}"width": {obj["width"]}',
                 f'{indent}"height": {obj["height"]}']
        return rows

    head = [f'  "format": "{FORMAT}"', f'  "version": {VERSION}']
    if len(cameras) == 1:
        body = camera_lines(cameras[0], "  ")
    else:
        blocks = ["    {\n" + ",\n".join(camera_lines(c, "      ")) + "\n    }" for c in cameras]
        body = ['  "cameras": [\n' + ",\n".join(blocks) + "\n  ]"]
    tail = []
    if provenance is not None:
        text = json.dumps(provenance, indent=2, sort_keys=True, allow_nan=False)
        tail = ['  "provenance": ' + text.replace("\n", "\n  ")]
    return "{\n" + ",\n".join(head + body + tail) + "\n}\n"


def write_cameras(path: str, cameras: list[Camera], provenance: dict | None = None) -> None:
    """Write one camera or a rig atomically ('-' for stdout)."""
    from relight_cli.fileio import write_text_atomic
    for cam in cameras:
        values = np.concatenate([np.ravel(cam.K), np.ravel(cam.R), np.ravel(cam.t)])
        if not np.isfinite(values).all():
            raise DataError(f"camera {cam.name or 0} holds NaN/Inf", path)
    write_text_atomic(path, dumps_cameras(cameras, provenance))


def nearest_rotation(A, what: str, path: str = "", tolerance: float = 1e-3) -> np.ndarray:
    """The rotation closest to ``A`` [3, 3] (SVD), when A is one to ``tolerance``
    (max |AᵀA − I|, det > 0): imported files store rotations to a few digits.
    Anything farther (a scale, a shear, a mirror) is a DataError naming ``what``."""
    A = np.asarray(A, np.float64)
    if not np.isfinite(A).all():
        raise DataError(f"{what} holds NaN/Inf", path)
    error = float(np.abs(A.T @ A - np.eye(3)).max())
    if error > tolerance or np.linalg.det(A) <= 0:
        raise DataError(f"{what} is not a rotation (max |RᵀR − I| = {error:.2g}, det "
                        f"{np.linalg.det(A):.3g}): scaled, sheared or mirrored poses are refused",
                        path)
    u, _, vt = np.linalg.svd(A)
    return u @ vt


# ----------------------------------------------------------------------------- OpenEXR


# OpenEXR's camera space is x right, y up, z forward (left-handed, RenderMan's); ours
# (OpenCV) has y down: the two differ by a flip of y.
_FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])


def openexr_matrices(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """``worldToCamera`` and ``worldToNDC`` as OpenEXR defines them: [4, 4] float32 each.

    OpenEXR (Imath) multiplies row vectors: ``[x y z 1] · M``, then divides by the
    last component.  Camera space is x right, y up, z along the view (OpenCV's with
    y flipped).  NDC is x right, y down, (0, 0) the top-left corner and (1, 1) the
    bottom-right corner of the image (pixel edges, as RenderMan's), so a point at our
    pixel (u, v) (pixel centres at integers) has NDC ((u + ½)/W, (v + ½)/H).  NDC z is
    1/z_cam (OpenEXR says to discard it; this keeps the matrix invertible).
    """
    world_to_cv = np.eye(4)
    world_to_cv[:3, :3] = cam.R
    world_to_cv[:3, 3] = cam.t
    K = np.asarray(cam.K, np.float64)
    pixel_to_ndc = np.array([[1 / cam.width, 0, 0.5 / cam.width],
                             [0, 1 / cam.height, 0.5 / cam.height],
                             [0, 0, 1.0]])
    A = pixel_to_ndc @ K                                  # camera (OpenCV) → NDC·z
    cv_to_ndc = np.array([[A[0, 0], A[0, 1], A[0, 2], 0],
                          [A[1, 0], A[1, 1], A[1, 2], 0],
                          [0, 0, 0, 1],                   # → z_ndc = 1 / z_cam
                          [0, 0, 1, 0]])                  # w = z_cam
    to_camera = _FLIP_Y @ world_to_cv
    to_ndc = cv_to_ndc @ world_to_cv
    # C order: the OpenEXR bindings copy the array's memory as is (a transposed view
    # would be stored transposed).
    return (np.ascontiguousarray(to_camera.T, np.float32),
            np.ascontiguousarray(to_ndc.T, np.float32))


def openexr_camera_name(value) -> str:
    """The camera's name recorded by relight in an EXR's ``relight.camera`` attribute.

    A render (formats/render_exr.md) stores the whole camera as a JSON object string,
    whose ``name`` is taken; a capture image (formats/capture.md) stores the name
    itself.  ``''`` when the attribute is absent (``None``), names nothing, or is a JSON
    object that cannot be read: the name is a label, the header matrices are the camera.
    """
    if value is None:
        return ""
    if isinstance(value, dict):
        obj = value
    else:
        text = str(value)
        if not text.lstrip().startswith("{"):
            return text.strip()
        try:
            obj = json.loads(text)
        except ValueError:
            return ""
    name = obj.get("name", "") if isinstance(obj, dict) else ""
    return name if isinstance(name, str) else ""


def camera_from_openexr(world_to_camera, world_to_ndc, width: int, height: int,
                        path: str = "", name: str = "") -> Camera:
    """The pinhole camera of an EXR's ``worldToCamera`` and ``worldToNDC`` (row-vector
    [4, 4] matrices, see :func:`openexr_matrices`) and its image size.  Raises
    DataError when they do not describe a pinhole camera (rotation and upper-triangular
    intrinsics, to float32 precision)."""
    C = np.asarray(world_to_camera, np.float64).reshape(4, 4).T     # column-vector form
    P = np.asarray(world_to_ndc, np.float64).reshape(4, 4).T
    if not (np.isfinite(C).all() and np.isfinite(P).all()):
        raise DataError("worldToCamera or worldToNDC holds NaN/Inf", path)
    world_to_cv = _FLIP_Y @ C
    R, t = world_to_cv[:3, :3], world_to_cv[:3, 3]
    if np.abs(world_to_cv[3] - [0, 0, 0, 1]).max() > 1e-6:
        raise DataError("worldToCamera is not a rigid transform", path)
    ndc_to_pixel = np.array([[width, 0, -0.5], [0, height, -0.5], [0, 0, 1.0]])
    projection = ndc_to_pixel @ P[[0, 1, 3]]             # [3, 4]: pixel·w from world
    scale = float(np.linalg.norm(projection[2, :3]))
    if scale == 0:
        raise DataError("worldToNDC has no perspective row", path)
    K = (projection[:, :3] / scale) @ R.T
    if np.abs(K[2] - [0, 0, 1]).max() > 1e-4 or abs(K[1, 0]) > 1e-4 * abs(K[1, 1]):
        raise DataError("worldToNDC is not a pinhole projection of worldToCamera's camera",
                        path)
    K[1, 0], K[2] = 0.0, [0.0, 0.0, 1.0]
    if abs(K[0, 1]) < 1e-6 * abs(K[0, 0]):   # float32 noise, not a skew
        K[0, 1] = 0.0
    R = nearest_rotation(R, "worldToCamera", path)
    return camera_from_json({"K": K.tolist(), "R": R.tolist(), "t": t.tolist(),
                             "width": int(width), "height": int(height), "name": name}, path)
