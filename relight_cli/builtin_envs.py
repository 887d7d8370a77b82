"""Built-in procedural environments, so the main job needs no data.

``builtin:sky`` (sun + sky + ground), ``builtin:studio`` (key, fill and rim
area lights over a dim ambient), ``builtin:uniform`` (L = 1 everywhere) and
``builtin:point`` (one small bright source).  All are lat-long, +Y up, and
deterministic.  Small sources are integrated over each texel by supersampling
and scaled so their power is exactly the stated value at any resolution.
"""

from __future__ import annotations

import math

import numpy as np

from relight_cli import envmap as E
from relight_cli.errors import UsageProblem
from relight_cli.formats.envmap import EnvMap

NAMES = ("sky", "studio", "uniform", "point")
DEFAULT_SIZE = (256, 128)  # (width, height)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _disc_coverage(height: int, width: int, centre, radius_deg: float, n: int = 8) -> np.ndarray:
    """[H, W] solid angle of each texel covered by a cone (sub-cell integration)."""
    cos_r = math.cos(math.radians(radius_deg))
    out = np.zeros(height * width)
    for d, omega, idx in E._subcells("latlong", height, width, n):
        inside = (d @ centre) >= cos_r
        out += np.bincount(idx[inside], weights=omega[inside], minlength=height * width)
    return out.reshape(height, width)


def _add_source(rgb, coverage, colour, total_power):
    covered = coverage.sum()
    if covered > 0:
        # radiance so that Σ L·(covered Ω) equals total_power exactly
        omega = E.latlong_solid_angles(*rgb.shape[:2])
        rgb += (coverage / omega)[..., None] * (np.asarray(colour) * total_power / covered)


def builtin_envmap(name: str, width: int | None = None, height: int | None = None) -> EnvMap:
    """The named built-in environment as a lat-long EnvMap ([H, W, 3] float32)."""
    key = name.split(":", 1)[1] if name.startswith("builtin:") else name
    if key not in NAMES:
        raise UsageProblem(f"unknown built-in environment {name!r}; choose one of "
                           + ", ".join("builtin:" + n for n in NAMES))
    w, h = (width or DEFAULT_SIZE[0]), (height or DEFAULT_SIZE[1])
    dirs = E.latlong_directions(h, w)
    rgb = np.zeros((h, w, 3))
    if key == "uniform":
        rgb[:] = 1.0
    elif key == "sky":
        y = dirs[..., 1]
        up = np.clip(y, 0, 1)[..., None]
        zenith = np.array([0.25, 0.45, 0.95])
        horizon = np.array([0.85, 0.9, 1.0])
        sky = horizon + (zenith - horizon) * up ** 0.6
        ground = np.array([0.18, 0.15, 0.12]) * 0.8
        rgb = np.where(y[..., None] >= 0, sky, ground)
        sun = _unit([0.45, 0.6, 0.66])  # elevation ≈ 37°
        glow = np.exp((dirs @ sun - 1) * 40)[..., None] * np.array([1.0, 0.9, 0.7]) * 1.5
        rgb = rgb + glow * (y[..., None] >= 0)
        _add_source(rgb, _disc_coverage(h, w, sun, 1.5), [1.0, 0.95, 0.85], 20.0)
    elif key == "studio":
        rgb[:] = 0.05
        lights = [(_unit([-0.6, 0.55, 0.6]), 12.0, [1.0, 0.97, 0.92], 8.0),   # key
                  (_unit([0.8, 0.2, 0.5]), 18.0, [0.85, 0.9, 1.0], 3.0),      # fill
                  (_unit([0.1, 0.5, -0.85]), 8.0, [1.0, 1.0, 1.0], 4.0)]      # rim
        for centre, radius, colour, watts in lights:
            _add_source(rgb, _disc_coverage(h, w, centre, radius, n=4), colour, watts)
    elif key == "point":
        _add_source(rgb, _disc_coverage(h, w, _unit([0.3, 0.8, 0.5]), 1.0), [1.0, 1.0, 1.0], 10.0)
    return EnvMap(rgb.astype(np.float32), "latlong", "builtin:" + key)
