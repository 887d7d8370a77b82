"""Camera rigs: a checked look-at camera, rings of cameras around a target, a dome.

Cameras are ``relight_cli.formats.camera.Camera`` (OpenCV: x right, y down, z
forward; world→camera R, t; pixel centres at integers).  Positions are metres,
world (+Y up); angles are degrees.  A camera at azimuth φ and elevation θ sits at
target + r·(cos θ sin φ, sin θ, cos θ cos φ): azimuth 0 is in front (+Z), 90° is
+X, elevation 90° straight above.  Everything here is deterministic.
"""

from __future__ import annotations

import math

import numpy as np

from relight_cli.formats.camera import Camera

# Below this |sin| of the angle between --up and the view direction, look-at is refused:
# the image's roll would be decided by rounding.
MIN_UP_SINE = 1e-6


def look_at(eye, target, up=(0.0, 1.0, 0.0), fov_y_deg: float = 40.0, width: int = 256,
            height: int = 256, name: str = "") -> Camera:
    """A camera at ``eye`` [3] looking at ``target`` [3], image up along ``up`` [3].

    ``fov_y_deg`` is the vertical field of view from the top edge of the image to the
    bottom edge; the principal point is the image centre.  Raises ValueError when eye
    and target coincide or when ``up`` is (nearly) parallel to the view direction.
    """
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    forward = target - eye
    distance = float(np.linalg.norm(forward))
    if not distance > 1e-12 * max(1.0, float(np.abs(eye).max())):
        raise ValueError("the eye and the target are the same point: no view direction")
    if not float(np.linalg.norm(up)) > 0:
        raise ValueError("the up vector is zero")
    sine = np.linalg.norm(np.cross(forward / distance, up / np.linalg.norm(up)))
    if sine < MIN_UP_SINE:
        raise ValueError("the up vector is parallel to the view direction (looking straight "
                         "up or down?): give another up, e.g. 0,0,-1 for a camera looking "
                         "down with -Z at the top of the image")
    return Camera.look_at(eye, target, up, fov_y_deg, width, height, name)


def _on_sphere(target, radius: float, azimuth_deg: float, elevation_deg: float,
               fov_y_deg: float, width: int, height: int, name: str) -> Camera:
    """A camera on the sphere around ``target`` looking at it.  Its image up is the
    direction of increasing elevation, which is world +Y's projection away from the
    poles and stays defined at them (at 90° the top of the image is −Z at azimuth 0)."""
    phi, theta = math.radians(azimuth_deg), math.radians(elevation_deg)
    outward = np.array([math.cos(theta) * math.sin(phi), math.sin(theta),
                        math.cos(theta) * math.cos(phi)])
    up = np.array([-math.sin(theta) * math.sin(phi), math.cos(theta),
                   -math.sin(theta) * math.cos(phi)])
    forward = -outward
    right = np.cross(forward, up)
    R = np.stack([right, -up, forward])
    eye = np.asarray(target, np.float64) + radius * outward
    f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    return Camera(K, R, -R @ eye, int(width), int(height), name)


def orbit(n: int, radius: float, elevations_deg=(0.0,), target=(0.0, 0.0, 0.0),
          azimuth_deg: float = 0.0, fov_y_deg: float = 40.0, width: int = 256,
          height: int = 256, prefix: str = "cam") -> list[Camera]:
    """Rings of ``n`` cameras each, evenly spaced in azimuth from ``azimuth_deg``, one
    ring per elevation (in the order given), named prefix000, prefix001, …"""
    cams = []
    for elevation in elevations_deg:
        for k in range(n):
            cams.append(_on_sphere(target, radius, azimuth_deg + 360.0 * k / n, elevation,
                                   fov_y_deg, width, height, f"{prefix}{len(cams):03d}"))
    return cams


def dome(n: int, radius: float, min_elevation_deg: float = 0.0, target=(0.0, 0.0, 0.0),
         azimuth_deg: float = 0.0, fov_y_deg: float = 40.0, width: int = 256,
         height: int = 256, prefix: str = "cam") -> list[Camera]:
    """``n`` cameras spread evenly (a Fibonacci lattice: equal-area bands in height,
    golden-angle turns) over the part of the sphere above ``min_elevation_deg``,
    from the top down, named prefix000, …"""
    from relight_cli.render.capture import fibonacci_sphere
    directions = fibonacci_sphere(n, min_y=math.sin(math.radians(min_elevation_deg)))
    cams = []
    for k, (x, y, z) in enumerate(directions):
        elevation = math.degrees(math.asin(max(-1.0, min(1.0, y))))
        azimuth = (azimuth_deg + math.degrees(math.atan2(x, z))) % 360.0
        cams.append(_on_sphere(target, radius, azimuth, elevation, fov_y_deg, width, height,
                               f"{prefix}{k:03d}"))
    return cams


def select(cameras: list[Camera], names: list[str]) -> list[Camera]:
    """The cameras named ``names``, in that order; KeyError naming the first unknown."""
    by_name = {c.name: c for c in cameras}
    missing = [n for n in names if n not in by_name]
    if missing:
        raise KeyError(missing[0])
    return [by_name[n] for n in names]
