"""Deep Gaussian Shadow Maps in OpenEXR (spec: ``formats/dgsm_exr.md``).

One EXR per build: for light i and bin k the channel ``light{i}.t{k:03d}`` holds
T at the bin centre t_k = t_min_i + (k + ½)·(t_max_i − t_min_i) / K over the H×W
direction atlas (t_min_i = 0, the paper's shells from the light, unless the map's bins
were fitted to its receivers: version 3, ``relight.dgsm.t_min``).
The table is a :class:`DGSM` (arrays and their metadata); building it and the
geometry (atlas mapping, lookup) live in ``relight_cli.gaussians.dgsm``, the
opacity mappings in ``relight_cli.gaussians.transmittance``; this module holds,
reads, validates and writes it.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field

import numpy as np

from relight_cli.errors import DataError

FORMAT = "relight/dgsm"
VERSION = 3            # 3: optional t_min (bins over the receivers); 2 is still written
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
        t_min: [L] where each light's bins start (metres), or None: 0, the paper's
            shells from the light.
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
    t_min: np.ndarray | None = None

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
                    colors=self.colors, t_min=self.t_min)

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
    t_min = getattr(dgsm, "t_min", None)
    if t_min is not None and (np.asarray(t_min) > 0).any():
        # bins that do not start at the light: a reader of version 2 would misplace them
        attributes[PREFIX + "t_min"] = json.dumps([float(t) for t in t_min])
        if provenance is not None:
            provenance = dict(provenance, version=3)
    elif provenance is not None and provenance.get("version") == 3:
        provenance = dict(provenance, version=2)      # nothing of version 3 in it
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


def _number_attr(image, key, shape, path, limit):
    """A JSON header attribute holding numbers of ``shape``, finite and within ±limit
    (anything else, e.g. a string, is a one-line DataError naming the attribute)."""
    from ._common import number_array
    what = f"header attribute {PREFIX + key}"
    try:
        array = number_array(_json_attr(image, key, path), what, path)
    except DataError as exc:
        if "numbers only" in exc.message:
            raise
        array = None                    # ragged: reported with the shape below
    if array is None or array.shape != shape:
        raise DataError(f"header attribute {PREFIX + key} must be {len(shape)}-D of shape "
                        f"{shape} (the light count)", path)
    if not np.isfinite(array).all() or (array.size and np.abs(array).max() > limit):
        raise DataError(f"header attribute {PREFIX + key} must be finite and within "
                        f"±{limit:g}", path)
    return array


def _count(attrs, key, path):
    from ._common import is_int
    value = attrs.get(PREFIX + key)
    if not is_int(value) or value < 1:
        raise DataError(f"missing or invalid {PREFIX + key} in the header (an integer ≥ 1, "
                        f"got {value!r})"[:200], path)
    return value


def _missing(wanted, names, what, path):
    """Raise naming the first channels of ``wanted`` ((light, bin, group) triples, made
    lazily) absent from ``names``: at most len(names) + 4 names are ever made, so a header
    declaring 10⁹ channels costs what the file holds, not what it claims."""
    from itertools import islice
    absent = list(islice((c for c in (channel_name(i, k, j) for i, k, j in wanted)
                          if c not in names), 4))
    if absent:
        raise DataError(f"missing {what}channel(s) {', '.join(absent[:3])}"
                        f"{' …' if len(absent) > 3 else ''}", path)


#: The most bins a DGSM may declare (dgsm-build --bins is at most 999).
MAX_BINS = 999

_TABLE_CHANNEL = re.compile(r"(?:group(\d+)\.)?light(\d+)\.t(\d+)")


def _uncovered(names, n_lights, bins, n_groups, path):
    """Refuse table channels (``light{i}.t{k}``, ``group{j}.light{i}.t{k}``) that the
    header's counts do not cover: a ``bins`` or ``lights`` one too small would otherwise
    drop a bin or a light silently.  Other channel names are left alone (additive
    versions may add them)."""
    extra = []
    for name in names:
        m = _TABLE_CHANNEL.fullmatch(name)
        if m is None:
            continue
        group, light, k = m.group(1), int(m.group(2)), int(m.group(3))
        group = None if group is None else int(group)
        if name != channel_name(light, k, group):
            continue                    # not a name this format makes (light00.t1 ...)
        if light >= n_lights or k >= bins or (group is not None and group >= n_groups):
            extra.append(name)
    if extra:
        extra.sort()
        raise DataError(f"channel(s) {', '.join(extra[:3])}{' …' if len(extra) > 3 else ''} "
                        f"beyond the header ({PREFIX}lights = {n_lights}, {PREFIX}bins = "
                        f"{bins}, {n_groups} group(s)): the header and the channels disagree",
                        path)


def _roi_number(value, what, path, lo=-math.inf, infinite=False):
    """A finite number ≥ lo (or ±inf, also written "inf"/"-inf", when ``infinite``)."""
    if infinite and value in ("inf", "-inf"):
        value = float(value)
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    try:
        number = number and not math.isnan(float(value))
    except OverflowError:               # an integer of 400 digits
        number = False
    if (not number or (not infinite and not math.isfinite(value))
            or not (lo <= value or (infinite and math.isinf(value)))):
        raise DataError(f"header attribute {PREFIX}roi: {what} must be "
                        f"{'a number or ±inf' if infinite else 'a finite number'}"
                        f"{f' ≥ {lo:g}' if lo > -math.inf else ''}, got {value!r}"[:200], path)
    return value


def _roi_box(value, sizes, what, path):
    """An inclusive index box [lo..., hi...] within ``sizes``, or the empty box
    ([0, 0, -1, -1] / [0, -1]); returns whether it is empty."""
    n = len(sizes)
    empty = [0] * n + [-1] * n
    from ._common import is_int
    if not (isinstance(value, list) and len(value) == 2 * n and all(is_int(v) for v in value)):
        raise DataError(f"header attribute {PREFIX}roi: {what} must be {2 * n} integers, "
                        f"got {value!r}"[:200], path)
    if value == empty:
        return True
    if not all(0 <= value[a] <= value[a + n] < size for a, size in enumerate(sizes)):
        raise DataError(f"header attribute {PREFIX}roi: {what} {value!r} is not a box inside "
                        f"the table (min ≤ max, within {' × '.join(map(str, sizes))}; "
                        f"{empty} when empty)"[:200], path)
    return False


def _check_roi(roi, n_lights, bins, h, w, n_groups, path):
    """The per-light ROI records (formats/dgsm_exr.md): one per light (or none recorded);
    each field present has its type, boxes lie inside the table with min ≤ max (or are the
    empty box), pixels, bins and texels are empty together, and numbers are finite."""
    if roi and len(roi) != n_lights:
        raise DataError(f"header attribute {PREFIX}roi holds {len(roi)} record(s) for "
                        f"{n_lights} light(s)", path)
    for i, rec in enumerate(roi):
        _check_roi_record(rec, f"roi[{i}]", bins, h, w, n_groups, path)


def _check_roi_record(rec, at, bins, h, w, n_groups, path):
    from ._common import is_int
    if not isinstance(rec, dict):
        raise DataError(f"header attribute {PREFIX}roi: {at} must be an object", path)
    empty = []
    if "pixels" in rec:
        empty.append(_roi_box(rec["pixels"], (w, h), f"{at}.pixels", path))
    if "bins" in rec:
        empty.append(_roi_box(rec["bins"], (bins,), f"{at}.bins", path))
    for key in ("texels", "receivers"):
        if key in rec and not (is_int(rec[key]) and rec[key] >= 0):
            raise DataError(f"header attribute {PREFIX}roi: {at}.{key} must be an integer "
                            f"≥ 0, got {rec[key]!r}"[:200], path)
    if "texels" in rec:
        if rec["texels"] > h * w * max(1, n_groups or 0):
            raise DataError(f"header attribute {PREFIX}roi: {at}.texels = {rec['texels']} "
                            f"exceeds the {w}x{h} atlas", path)
        empty.append(rec["texels"] == 0)
    if len(set(empty)) > 1:
        raise DataError(f"header attribute {PREFIX}roi: {at}'s pixels, bins and texels "
                        f"disagree (one is empty, another not)", path)
    if "centroid" in rec:
        c = rec["centroid"]
        if not (isinstance(c, list) and len(c) == 3):
            raise DataError(f"header attribute {PREFIX}roi: {at}.centroid must be 3 "
                            f"numbers, got {c!r}"[:200], path)
        for v in c:
            _roi_number(v, f"{at}.centroid", path)
    if rec.get("radius") is not None:
        _roi_number(rec["radius"], f"{at}.radius", path, 0)
    if "bounding_radius" in rec:
        _roi_number(rec["bounding_radius"], f"{at}.bounding_radius", path, 0)
    if "height" in rec:
        hgt = rec["height"]
        if not (isinstance(hgt, list) and len(hgt) == 2):
            raise DataError(f"header attribute {PREFIX}roi: {at}.height must be [lo, hi], "
                            f"got {hgt!r}"[:200], path)
        lo, hi = (_roi_number(v, f"{at}.height", path, infinite=True) for v in hgt)
        if lo > hi and rec.get("receivers", 0) != 0:
            raise DataError(f"header attribute {PREFIX}roi: {at}.height {hgt!r} has lo > "
                            f"hi but receivers in it"[:200], path)
    if "groups" in rec:
        sub = rec["groups"]
        if n_groups is None or not isinstance(sub, list) or len(sub) != n_groups:
            raise DataError(f"header attribute {PREFIX}roi: {at}.groups must list one "
                            f"record per occluder group ({n_groups or 0})", path)
        for j, g in enumerate(sub):
            _check_roi_record(g, f"{at}.groups[{j}]", bins, h, w, None, path)


def read_dgsm(path: str):
    """Read and validate a DGSM EXR → :class:`DGSM`.

    The header is not trusted: the light and bin counts are bounded by MAX_LIGHTS,
    MAX_BINS and by the channels the file holds before any channel name is made,
    and every attribute is type-checked (formats/dgsm_exr.md)."""
    from relight_cli.formats.exr import check_format, read_exr

    from ._common import MAX_LIGHTS, MAX_POSITION, MAX_VALUE

    image = read_exr(path)
    version = check_format(image, FORMAT, VERSION)
    attrs = image.attributes
    layout = attrs.get(PREFIX + "layout")
    if not isinstance(layout, str) or layout not in LAYOUTS:
        raise DataError(f"unknown atlas layout {layout!r}"[:200], path)
    n_lights, K = _count(attrs, "lights", path), _count(attrs, "bins", path)
    if n_lights > MAX_LIGHTS or K > MAX_BINS:
        raise DataError(f"{n_lights} light(s) × {K} bin(s) in the header; a DGSM holds at most "
                        f"{MAX_LIGHTS:,} lights and {MAX_BINS} bins", path)
    names = set(image.channels)
    if n_lights * K > len(names):   # say which are missing, naming at most len(names) + 4
        _missing(((i, k, None) for i in range(n_lights) for k in range(K)), names, "", path)
    lights = _number_attr(image, "light_positions", (n_lights, 3), path, MAX_POSITION)
    t_max = _number_attr(image, "t_max", (n_lights,), path, MAX_POSITION)
    if not (t_max > 0).all():
        raise DataError("light positions / t_max must be finite (t_max > 0)", path)
    t_min = None
    if version >= 3 and PREFIX + "t_min" in attrs:
        t_min = _number_attr(image, "t_min", (n_lights,), path, MAX_POSITION)
        if not ((t_min >= 0).all() and (t_min < t_max).all()):
            raise DataError(f"header attribute {PREFIX}t_min must hold 0 ≤ t_min < t_max per "
                            f"light", path)
    mapping = attrs.get(PREFIX + "mapping")
    if not isinstance(mapping, str):
        raise DataError(f"unknown opacity mapping {mapping!r}"[:200], path)
    if version == 1:
        if mapping not in V1_MAPPINGS:
            raise DataError(f"unknown opacity mapping {mapping!r}", path)
        mapping = V1_MAPPINGS[mapping]
        intensities = colors = None      # version 1 did not store them
    else:
        if mapping not in MAPPINGS:
            raise DataError(f"unknown opacity mapping {mapping!r}", path)
        intensities = _number_attr(image, "light_intensities", (n_lights,), path, MAX_VALUE)
        colors = _number_attr(image, "light_colors", (n_lights, 3), path, MAX_VALUE)
        if not ((intensities >= 0).all() and (colors >= 0).all()):
            raise DataError("light intensities / colours must be finite and ≥ 0", path)
        if (colors * intensities[:, None]).max(initial=0.0) > MAX_VALUE:
            raise DataError(f"header attributes {PREFIX}light_colors × light_intensities "
                            f"(radiant intensity) must lie within {MAX_VALUE:g}", path)
    kappa = attrs.get(PREFIX + "kappa")
    if (not isinstance(kappa, (int, float)) or isinstance(kappa, bool)
            or not 0 < kappa <= MAX_VALUE):
        raise DataError(f"missing or invalid {PREFIX}kappa (a number > 0, got {kappa!r})"[:200],
                        path)
    roi = _json_attr(image, "roi", path)
    if not isinstance(roi, list) or not all(isinstance(r, dict) for r in roi):
        raise DataError(f"header attribute {PREFIX}roi must be a list of objects", path)
    _missing(((i, k, None) for i in range(n_lights) for k in range(K)), names, "", path)
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
        _missing(((i, k, j) for j in range(len(group_names))
                  for i in range(n_lights) for k in range(K)), names, "group ", path)
        groups = np.empty((len(group_names), n_lights, K, h, w), np.float32)
        for j in range(len(group_names)):
            for i in range(n_lights):
                for k in range(K):
                    groups[j, i, k] = image.channels[channel_name(i, k, j)]
        if not np.isfinite(groups).all() or groups.min() < -1e-3 or groups.max() > 1 + 1e-3:
            raise DataError("group transmittance must be finite and in [0, 1]", path)
        groups = np.clip(groups, 0, 1)
    _uncovered(names, n_lights, K, len(group_names), path)
    _check_roi(roi, n_lights, K, h, w, len(group_names) if groups is not None else None, path)
    seconds = attrs.get(PREFIX + "build_seconds", 0.0)
    return DGSM(np.clip(table, 0, 1), lights, t_max, layout, mapping, float(kappa), roi,
                float(seconds) if isinstance(seconds, (int, float)) else 0.0, {},
                groups, group_names, intensities, colors, t_min)
