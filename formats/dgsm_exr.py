"""Deep Gaussian Shadow Maps in OpenEXR (spec: ``formats/dgsm_exr.md``).

One EXR per build: for light i and bin k the channel ``light{i}.t{k:03d}`` holds
T at the bin centre t_k = (k + ½)·t_max_i / K over the H×W direction atlas.
The table is a :class:`DGSM` (arrays and their metadata); building it and the
geometry (atlas mapping, lookup) live in ``relight_cli.gaussians.dgsm``, the
opacity mappings in ``relight_cli.gaussians.transmittance``; this module holds,
reads, validates and writes it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import numpy as np

from relight_cli.errors import DataError

FORMAT = "relight/dgsm"
VERSION = 2
LAYOUTS = ("octahedral", "cube")
# the opacity→absorption mappings (relight_cli.gaussians.transmittance implements them)
MAPPINGS = ("avg", "simple", "mass", "diag", "peak")
DEFAULT_MAPPING = "avg"
# Version 1 wrote the mapping now called "peak" as "eq5"; its "simple", "mass"
# and "diag" were direction-dependent definitions that version 2 replaced by the
# paper's (Sec. 4.4 B), so they read back under a "v1-" label.
V1_MAPPINGS = {"eq5": "peak", "simple": "v1-simple", "mass": "v1-mass", "diag": "v1-diag"}
PREFIX = "relight.dgsm."
TEXEL_MAPPING = ("octahedral: column x -> u = 2(x+0.5)/W - 1, row y (top 0) -> v = 1 - 2(y+0.5)/H; "
                 "(u,v) -> direction from the light, lower hemisphere (y<=0) = central diamond "
                 "(x,z)/|w|_1; cube: OpenEXR ImfEnvmap cube, faces +X -X +Y -Y +Z -Z stacked")


@dataclass
class DGSM:
    """A built shadow map for L lights.

    Attributes:
        transmittance: [L, K, H, W] float32 T at bin centres t_k (1 outside the ROI).
        lights: [L, 3] light positions, metres, world.
        t_max: [L] radial extent per light, metres; bin k centre = (k + ½) t_max / K.
        layout: "octahedral" or "cube".
        mapping: opacity→absorption mapping used; kappa: its κ.
        roi: per light, a dict with the texel bbox ``pixels`` [x0, y0, x1, y1]
            (inclusive), ``bins`` [k0, k1] (inclusive; [0, −1] when empty),
            ``centroid`` [3], ``radius`` (m or None), ``height`` [lo, hi],
            ``receivers`` (count in the ROI), ``texels`` (count computed).
        build_seconds: wall time of :func:`relight_cli.gaussians.dgsm.build_dgsm`.
        stats: counters (pairs tested/kept, Gaussians after culling ...).
        groups: None, or [J, L, K, H, W] float32 per-occluder-group tables (from
            :func:`relight_cli.gaussians.dgsm.build_dgsm_groups`); then
            ``transmittance`` is their product (optical depths add over disjoint sets
            of Gaussians).
        group_names: J labels of the groups (e.g. the occluder specs).
        intensities: [L] the lights' intensities (relight/lights ``intensity``),
            or None when unknown (DGSM version 1 files); weights each light's
            share of a receiver's direct light (paper Sec. 3.3).
        colors: [L, 3] the lights' linear RGB colours, or None when unknown.
    """

    transmittance: np.ndarray
    lights: np.ndarray
    t_max: np.ndarray
    layout: str = "octahedral"
    mapping: str = DEFAULT_MAPPING
    kappa: float = 1.0
    roi: list = field(default_factory=list)
    build_seconds: float = 0.0
    stats: dict = field(default_factory=dict)
    groups: np.ndarray | None = None
    group_names: list = field(default_factory=list)
    intensities: np.ndarray | None = None
    colors: np.ndarray | None = None

    def others(self, group: int) -> "DGSM":
        """The shadow map of every group except ``group`` (what that group receives).

        Its own table is left out because a Gaussian looked up in the table of
        its own object would be shadowed by itself (half its own optical depth).
        """
        if self.groups is None:
            raise ValueError("this shadow map has no occluder groups")
        rest = [j for j in range(len(self.groups)) if j != group]
        table = (np.prod(self.groups[rest], axis=0, dtype=np.float32) if rest
                 else np.ones_like(self.transmittance))
        return DGSM(table, self.lights, self.t_max, self.layout, self.mapping, self.kappa,
                    self.roi, self.build_seconds, self.stats, intensities=self.intensities,
                    colors=self.colors)

    @property
    def bins(self) -> int:
        return self.transmittance.shape[1]

    @property
    def height(self) -> int:
        return self.transmittance.shape[2]

    @property
    def width(self) -> int:
        return self.transmittance.shape[3]


# ------------------------------------------------------------------ the file


def channel_name(light: int, k: int, group: int | None = None) -> str:
    """``light{i}.t{k:03d}`` (the product over groups), or ``group{j}.light{i}.t{k:03d}``."""
    name = f"light{light}.t{k:03d}"
    return name if group is None else f"group{group}.{name}"


def write_dgsm(path: str, dgsm, provenance: dict | None = None, half: bool = False) -> None:
    """Write a :class:`DGSM` atomically."""
    from relight_cli.formats.exr import write_exr

    table = np.asarray(dgsm.transmittance)
    if not np.isfinite(table).all():
        raise DataError("transmittance table holds NaN/Inf (a bug; nothing written)", path)
    n_lights, K = table.shape[:2]
    intensities = (np.ones(n_lights) if getattr(dgsm, "intensities", None) is None
                   else np.asarray(dgsm.intensities, np.float64).reshape(n_lights))
    colors = (np.ones((n_lights, 3)) if getattr(dgsm, "colors", None) is None
              else np.asarray(dgsm.colors, np.float64).reshape(n_lights, 3))
    channels = {channel_name(i, k): table[i, k] for i in range(n_lights) for k in range(K)}
    groups = getattr(dgsm, "groups", None)
    if groups is not None:
        groups = np.asarray(groups)
        if not np.isfinite(groups).all():
            raise DataError("group transmittance holds NaN/Inf (a bug; nothing written)", path)
        for j in range(len(groups)):
            channels.update({channel_name(i, k, j): groups[j, i, k]
                             for i in range(n_lights) for k in range(K)})
    attributes = {
        PREFIX + "layout": str(dgsm.layout),
        PREFIX + "lights": int(n_lights),
        PREFIX + "bins": int(K),
        PREFIX + "light_positions": json.dumps([[float(v) for v in p] for p in dgsm.lights]),
        PREFIX + "t_max": json.dumps([float(t) for t in dgsm.t_max]),
        PREFIX + "mapping": str(dgsm.mapping),
        PREFIX + "light_intensities": json.dumps([float(v) for v in intensities]),
        PREFIX + "light_colors": json.dumps([[float(v) for v in c] for c in colors]),
        PREFIX + "kappa": float(dgsm.kappa),
        PREFIX + "roi": json.dumps(_jsonable(dgsm.roi), sort_keys=True),
        PREFIX + "texel_mapping": TEXEL_MAPPING,
    }
    if groups is not None:
        names = list(getattr(dgsm, "group_names", []) or [f"group{j}" for j in range(len(groups))])
        attributes[PREFIX + "groups"] = json.dumps([str(n) for n in names])
    write_exr(path, channels, attributes=attributes, half=half, provenance=provenance)


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, (np.floating, np.integer)):
        return _jsonable(value.item())
    return value


def _json_attr(image, key, path):
    text = image.attributes.get(PREFIX + key)
    if not isinstance(text, str):
        raise DataError(f"missing header attribute {PREFIX + key}", path)
    from ._common import parse_json
    try:
        return parse_json(text, path, non_finite="allow")
    except DataError:
        raise DataError(f"damaged header attribute {PREFIX + key}", path) from None


def read_dgsm(path: str):
    """Read and validate a DGSM EXR → :class:`DGSM`."""
    from relight_cli.formats.exr import check_format, read_exr

    image = read_exr(path)
    version = check_format(image, FORMAT, VERSION)
    attrs = image.attributes
    layout = attrs.get(PREFIX + "layout")
    if layout not in LAYOUTS:
        raise DataError(f"unknown atlas layout {layout!r}", path)
    n_lights, K = attrs.get(PREFIX + "lights"), attrs.get(PREFIX + "bins")
    if not isinstance(n_lights, int) or n_lights < 1 or not isinstance(K, int) or K < 1:
        raise DataError("missing or invalid light/bin counts in the header", path)
    lights = np.asarray(_json_attr(image, "light_positions", path), np.float64)
    t_max = np.asarray(_json_attr(image, "t_max", path), np.float64)
    if lights.shape != (n_lights, 3) or t_max.shape != (n_lights,):
        raise DataError("light positions / t_max do not match the light count", path)
    if not (np.isfinite(lights).all() and np.isfinite(t_max).all() and (t_max > 0).all()):
        raise DataError("light positions / t_max must be finite (t_max > 0)", path)
    mapping = attrs.get(PREFIX + "mapping")
    if version == 1:
        if mapping not in V1_MAPPINGS:
            raise DataError(f"unknown opacity mapping {mapping!r}", path)
        mapping = V1_MAPPINGS[mapping]
        intensities = colors = None      # version 1 did not store them
    else:
        if mapping not in MAPPINGS:
            raise DataError(f"unknown opacity mapping {mapping!r}", path)
        intensities = np.asarray(_json_attr(image, "light_intensities", path), np.float64)
        colors = np.asarray(_json_attr(image, "light_colors", path), np.float64)
        if intensities.shape != (n_lights,) or colors.shape != (n_lights, 3):
            raise DataError("light intensities / colours do not match the light count", path)
        if not (np.isfinite(intensities).all() and np.isfinite(colors).all()
                and (intensities >= 0).all() and (colors >= 0).all()):
            raise DataError("light intensities / colours must be finite and ≥ 0", path)
    kappa = attrs.get(PREFIX + "kappa")
    if not isinstance(kappa, (int, float)) or not kappa > 0:
        raise DataError("missing or invalid kappa", path)
    roi = _json_attr(image, "roi", path)
    names = set(image.channels)
    expected = {channel_name(i, k) for i in range(n_lights) for k in range(K)}
    missing = sorted(expected - names)
    if missing:
        raise DataError(f"missing channel(s) {', '.join(missing[:3])}"
                        f"{' …' if len(missing) > 3 else ''}", path)
    h, w = image.height, image.width
    if layout == "cube" and h != 6 * w:
        raise DataError(f"a cube atlas must be N wide and 6N high, got {w}x{h}", path)
    table = np.empty((n_lights, K, h, w), np.float32)
    for i in range(n_lights):
        for k in range(K):
            table[i, k] = image.channels[channel_name(i, k)]
    if not np.isfinite(table).all():
        raise DataError("transmittance holds NaN/Inf", path)
    if table.min() < -1e-3 or table.max() > 1 + 1e-3:
        raise DataError(f"transmittance outside [0, 1] ({table.min():.4g}..{table.max():.4g})", path)
    groups, group_names = None, []
    if PREFIX + "groups" in attrs:
        group_names = _json_attr(image, "groups", path)
        if not (isinstance(group_names, list) and group_names
                and all(isinstance(n, str) for n in group_names)):
            raise DataError(f"header attribute {PREFIX}groups must be a list of names", path)
        wanted = [channel_name(i, k, j) for j in range(len(group_names))
                  for i in range(n_lights) for k in range(K)]
        absent = [c for c in wanted if c not in names]
        if absent:
            raise DataError(f"missing group channel(s) {', '.join(absent[:3])}"
                            f"{' …' if len(absent) > 3 else ''}", path)
        groups = np.empty((len(group_names), n_lights, K, h, w), np.float32)
        for j in range(len(group_names)):
            for i in range(n_lights):
                for k in range(K):
                    groups[j, i, k] = image.channels[channel_name(i, k, j)]
        if not np.isfinite(groups).all() or groups.min() < -1e-3 or groups.max() > 1 + 1e-3:
            raise DataError("group transmittance must be finite and in [0, 1]", path)
        groups = np.clip(groups, 0, 1)
    seconds = attrs.get(PREFIX + "build_seconds", 0.0)
    return DGSM(np.clip(table, 0, 1), lights, t_max, layout, mapping, float(kappa), roi,
                float(seconds) if isinstance(seconds, (int, float)) else 0.0, {},
                groups, group_names, intensities, colors)
