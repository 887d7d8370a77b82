"""Cameras: OpenCV/COLMAP pinhole cameras in JSON (spec: ``formats/camera.md``).

A camera is ``{"K": 3×3, "R": 3×3, "t": [3], "width": W, "height": H}`` with
x_cam = R·x_world + t (world→camera), pixel = K·x_cam / z (x right, y down,
z forward).  A JSON list of such objects is a rig.
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
        """An OpenCV camera at ``eye`` looking at ``target`` with world ``up`` (+Y)."""
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
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float64)
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


def read_cameras(path: str) -> list[Camera]:
    """Read one camera (object) or a rig (list, or {"cameras": [...]}) from JSON."""
    from ._common import read_json
    obj = read_json(path)
    if isinstance(obj, dict) and "cameras" in obj:
        obj = obj["cameras"]
    if isinstance(obj, list):
        if not obj:
            raise DataError("camera list is empty", path)
        return [camera_from_json(o, path, i) for i, o in enumerate(obj)]
    return [camera_from_json(obj, path)]


def read_camera(path: str) -> Camera:
    """Read exactly one camera."""
    cams = read_cameras(path)
    if len(cams) != 1:
        raise DataError(f"expected one camera, file holds {len(cams)}", path)
    return cams[0]


def write_cameras(path: str, cameras: list[Camera]) -> None:
    from relight_cli.provenance import write_text_atomic
    payload = cameras[0].to_json() if len(cameras) == 1 else [c.to_json() for c in cameras]
    write_text_atomic(path, json.dumps(payload, indent=2) + "\n")
