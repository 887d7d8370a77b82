"""Environment maps: lat-long or cube EXR (OpenEXR's ImfEnvmap convention), and
Radiance .hdr or any other OpenImageIO format read as lat-long.

Spec: ``formats/envmap.md``.  This module reads and validates pixels; the
geometry (directions, solid angles, resampling) lives in ``relight_cli.envmap``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from relight_cli.errors import DataError, UsageProblem

FORMAT = "relight/envmap"
VERSION = 1
LAYOUTS = ("latlong", "cube")


@dataclass
class EnvMap:
    """Linear radiance on the sphere.

    Attributes:
        radiance: [H, W, 3] float32, linear RGB (W/m²/sr up to a global scale).
            lat-long: H×W with W = 2H typical.  cube: six N×N faces stacked
            vertically (W = N, H = 6N) in the order +X −X +Y −Y +Z −Z.
        layout: "latlong" or "cube".
        name: where it came from (a path or a ``builtin:`` name).
    """

    radiance: np.ndarray
    layout: str = "latlong"
    name: str = ""

    def __post_init__(self):
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {self.layout!r}")
        r = self.radiance
        if r.ndim != 3 or r.shape[2] != 3:
            raise ValueError(f"radiance must be [H, W, 3], got {r.shape}")
        if self.layout == "cube" and (r.shape[0] != 6 * r.shape[1]):
            raise ValueError(f"cube maps are N wide and 6N tall, got {r.shape[1]}x{r.shape[0]}")

    @property
    def height(self) -> int:
        return self.radiance.shape[0]

    @property
    def width(self) -> int:
        return self.radiance.shape[1]


def _rgb_from_channels(channels: dict[str, np.ndarray], path: str) -> np.ndarray:
    if all(c in channels for c in "RGB"):
        return np.stack([channels["R"], channels["G"], channels["B"]], axis=-1)
    if "Y" in channels:
        return np.repeat(channels["Y"][..., None], 3, axis=-1)
    # A single layer with R/G/B, e.g. 'radiance.R'.
    prefixes = sorted({k.rsplit(".", 1)[0] for k in channels if k.endswith((".R", ".G", ".B"))})
    for p in prefixes:
        if all(f"{p}.{c}" in channels for c in "RGB"):
            return np.stack([channels[f"{p}.{c}"] for c in "RGB"], axis=-1)
    raise DataError("no R, G, B (or Y) channels; has " + ", ".join(sorted(channels)[:8]), path)


def handle_nonfinite(radiance: np.ndarray, path: str, policy: str = "error") -> np.ndarray:
    """Refuse (default), zero or clamp NaN/±Inf pixels.

    ``clamp`` sends NaN to 0 and ±Inf to the largest finite value of the map
    (0 if there is none); ``zero`` sends every non-finite value to 0.
    """
    bad = ~np.isfinite(radiance)
    if not bad.any():
        return radiance
    n_pixels = int(bad.any(axis=-1).sum())
    if policy == "error":
        raise DataError(f"{n_pixels} pixel(s) hold NaN or Inf values", path,
                        hint="--nonfinite zero or --nonfinite clamp replaces them")
    out = radiance.copy()
    if policy == "zero":
        out[bad] = 0.0
    elif policy == "clamp":
        finite = radiance[np.isfinite(radiance)]
        top = float(finite.max()) if finite.size else 0.0
        low = float(finite.min()) if finite.size else 0.0
        out[np.isnan(radiance)] = 0.0
        out[np.isposinf(radiance)] = top
        out[np.isneginf(radiance)] = low
    else:
        raise UsageProblem(f"unknown non-finite policy {policy!r}")
    return out


def check_negative(radiance: np.ndarray, path: str) -> None:
    """DataError when ``radiance`` ([H, W, 3]) holds negative values: how many pixels, how
    negative against the map's mean, and the way forward (``relight envmap --negative
    clamp``)."""
    low = radiance < 0
    if not low.any():
        return
    n = int(low.any(axis=-1).sum())
    deepest = float(radiance.min())
    mean = float(radiance.mean(dtype=np.float64))
    raise DataError(f"{n} of {radiance.shape[0] * radiance.shape[1]} pixel(s) have negative "
                    f"radiance, down to {deepest:.4g} (the map's mean is {mean:.4g})", path,
                    hint="relight envmap IN --negative clamp -o OUT.exr writes a copy with "
                         "them set to 0")


def read_envmap(path: str, nonfinite: str = "error", layout: str | None = None,
                negative: str = "error") -> EnvMap:
    """Read an environment map file.

    The EXR ``envmap`` attribute decides the layout (absent: lat-long); other
    formats go through OpenImageIO as lat-long.  ``layout`` overrides it.
    Negative radiance is refused (it is never physical and breaks sampling) unless
    ``negative`` is ``keep``: the caller handles it (``relight envmap --negative clamp``).
    """
    if negative not in ("error", "keep"):
        raise UsageProblem(f"unknown negative-radiance policy {negative!r}")
    path = str(path)
    if not os.path.exists(path):
        raise DataError("no such file", path)
    if os.path.isdir(path):
        raise DataError("is a directory, expected an environment map", path)
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic == b"\x76\x2f\x31\x01":
        from .exr import read_exr
        image = read_exr(path)
        _check_version(image, path)
        radiance = _rgb_from_channels(image.channels, path)
        found_layout = image.envmap or "latlong"
    else:
        radiance = read_image_oiio(path)
        found_layout = "latlong"
    layout = layout or found_layout
    radiance = handle_nonfinite(np.ascontiguousarray(radiance, dtype=np.float32), path, nonfinite)
    h, w = radiance.shape[:2]
    if layout == "cube":
        if h != 6 * w:
            raise DataError(f"cube map must be N wide and 6N tall (faces stacked), got {w}x{h}", path)
    elif h < 2 or w < 2:
        raise DataError(f"lat-long map is too small ({w}x{h})", path)
    if negative == "error":
        check_negative(radiance, path)
    return EnvMap(radiance=radiance, layout=layout, name=path)


def _check_version(image, path: str) -> None:
    """Env maps from other tools carry no relight header and are read as they are;
    one that says it is a relight/envmap (or carries a relight.version) must be a
    version this relight understands."""
    from ._common import check_format_version
    from .exr import FORMAT_KEY, VERSION_KEY
    found = image.attributes.get(FORMAT_KEY)
    if found == FORMAT or (found is None and VERSION_KEY in image.attributes):
        check_format_version(FORMAT, image.attributes.get(VERSION_KEY), FORMAT, VERSION, path)


def read_image_oiio(path: str) -> np.ndarray:
    """Level 0 of any OpenImageIO-readable image as [H, W, 3] float32 (RGB), through
    :func:`relight_cli.formats.image.read_image` (so a PNG cut short is refused and
    libpng's own stderr lines are silenced, as for every image relight reads)."""
    from .image import read_image

    pixels, _names = read_image(path)
    if pixels.shape[2] == 1:
        pixels = np.repeat(pixels, 3, axis=2)
    elif pixels.shape[2] == 2:       # grey + alpha
        pixels = np.repeat(pixels[..., :1], 3, axis=2)
    return pixels[..., :3]


def write_envmap(path: str, env: EnvMap, provenance: dict | None = None,
                 attributes: dict | None = None, half: bool = False) -> None:
    """Write an env map as an RGB EXR with OpenEXR's ``envmap`` attribute, atomically."""
    from .exr import write_exr
    channels = {c: env.radiance[..., i] for i, c in enumerate("RGB")}
    write_exr(path, channels, attributes=attributes, half=half, envmap=env.layout,
              provenance=provenance)
