"""Point lights in JSON (spec: ``formats/lights_json.md``)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import numpy as np

from relight_cli.errors import DataError

from ._common import MAX_LIGHTS, MAX_POSITION, MAX_VALUE, check_format_version

FORMAT = "relight/lights"
VERSION = 1


@dataclass
class Lights:
    """L point lights: the one light record (files, the renderers, the light stage, the
    scene light estimator).

    Attributes:
        positions: [L, 3] float64, metres, world (+Y up).
        colors: [L, 3] float64 linear RGB (non-negative; relative spectrum).
        intensities: [L] float64 non-negative scale (radiant intensity up to a
            global scale; radiance at distance r is colour·intensity / r²).
        names: [L] optional labels ("" when absent).
        extra: other top-level fields (e.g. an estimator's settings), kept on read.
        provenance: the provenance record.
    """

    positions: np.ndarray
    colors: np.ndarray | None = None
    intensities: np.ndarray | None = None
    names: list = field(default_factory=list)
    extra: dict = field(default_factory=dict)
    provenance: dict | None = None

    def __post_init__(self):
        self.positions = np.asarray(self.positions, np.float64).reshape(-1, 3)
        n = len(self.positions)
        self.colors = (np.ones((n, 3)) if self.colors is None
                       else np.asarray(self.colors, np.float64).reshape(n, 3))
        self.intensities = (np.ones(n) if self.intensities is None
                            else np.asarray(self.intensities, np.float64).reshape(n))
        if not self.names:
            self.names = [""] * n

    def __len__(self) -> int:
        return len(self.positions)

    @classmethod
    def from_radiant_intensity(cls, positions, intensity, names=None) -> "Lights":
        """Lights of RGB radiant intensity ``intensity``: [L, 3] (colors = intensity,
        intensities = 1), or a scalar or [L] (white: colors = 1, intensities = it).
        Either way :meth:`radiant_intensity` gives it back exactly (x·1.0 = x)."""
        positions = np.asarray(positions, np.float64).reshape(-1, 3)
        n = len(positions)
        inten = np.asarray(intensity, np.float64)
        if inten.ndim <= 1 and inten.size in (1, n):
            return cls(positions, None, np.broadcast_to(inten.reshape(-1), (n,)).copy(),
                       list(names or []))
        return cls(positions, inten.reshape(n, 3).copy(), None, list(names or []))

    def radiant_intensity(self) -> np.ndarray:
        """[L, 3] float64 linear RGB radiant intensity, colors × intensities: irradiance
        I/r² at distance r, facing the light (what the renderers shade with)."""
        return self.colors * self.intensities[:, None]

    def subset(self, indices) -> "Lights":
        """The lights ``indices`` (a grouped-light frame turns on a subset); ``extra`` is
        kept, the provenance (of the whole record) is not."""
        idx = np.asarray(indices, np.int64).reshape(-1)
        return Lights(self.positions[idx], self.colors[idx], self.intensities[idx],
                      [self.names[i] for i in idx], dict(self.extra))


def lights_to_json(lights: Lights) -> dict:
    items = []
    for i in range(len(lights)):
        item = {"position": [float(v) for v in lights.positions[i]],
                "color": [float(v) for v in lights.colors[i]],
                "intensity": float(lights.intensities[i])}
        if lights.names[i]:
            item["name"] = str(lights.names[i])
        items.append(item)
    out = {"format": FORMAT, "version": VERSION, "lights": items}
    out.update(lights.extra)
    if lights.provenance is not None:
        out["provenance"] = lights.provenance
    return out


def write_lights(path: str, lights: Lights, provenance: dict | None = None) -> None:
    """Write atomically ('-' for stdout); floats round-trip exactly."""
    from relight_cli.fileio import write_text_atomic
    if provenance is not None:
        lights.provenance = provenance
    validate(lights, path)
    write_text_atomic(path, json.dumps(lights_to_json(lights), indent=2, allow_nan=False) + "\n")


def _vector(value, n, what, path, nonneg=False, limit=MAX_VALUE):
    if (not isinstance(value, list) or len(value) != n
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise DataError(f"{what} must be a list of {n} numbers, got {value!r}"[:200], path)
    if not all(math.isfinite(v) for v in value):
        raise DataError(f"{what} holds NaN/Inf", path)
    if nonneg and any(v < 0 for v in value):
        raise DataError(f"{what} must be non-negative, got {value!r}"[:200], path)
    if any(abs(v) > limit for v in value):   # finite but huge: would overflow the outputs
        raise DataError(f"{what} must lie within ±{limit:g}, got {value!r}"[:200], path)
    return [float(v) for v in value]


def _scalar(value, what, path, limit=MAX_VALUE):
    """One non-negative number (not a list: a light's colour goes in 'color', and a
    one-element list is not a number the format allows)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        raise DataError(f"{what} must be a number ≥ 0 (per-channel values go in 'color'), "
                        f"got {value!r}"[:200], path)
    return _vector([value], 1, what, path, True, limit)[0]


def lights_from_json(obj, path: str = "") -> Lights:
    if not isinstance(obj, dict):
        raise DataError("expected a JSON object", path)
    check_format_version(obj.get("format"), obj.get("version"), FORMAT, VERSION, path)
    items = obj.get("lights")
    if not isinstance(items, list) or not items:
        raise DataError("'lights' must be a non-empty list", path)
    if len(items) > MAX_LIGHTS:
        raise DataError(f"{len(items):,} lights; a lights file holds at most {MAX_LIGHTS:,}",
                        path)
    pos, col, inten, names = [], [], [], []
    for i, item in enumerate(items):
        if not isinstance(item, dict):
            raise DataError(f"lights[{i}] must be an object", path)
        if "position" not in item:
            raise DataError(f"lights[{i}] has no 'position'", path)
        pos.append(_vector(item["position"], 3, f"lights[{i}].position", path,
                           limit=MAX_POSITION))
        col.append(_vector(item.get("color", [1.0, 1.0, 1.0]), 3, f"lights[{i}].color", path, True))
        inten.append(_scalar(item.get("intensity", 1.0), f"lights[{i}].intensity", path))
        name = item.get("name", "")
        if not isinstance(name, str):
            raise DataError(f"lights[{i}].name must be a string", path)
        names.append(name)
        if max(col[-1]) * inten[-1] > MAX_VALUE:
            raise DataError(f"lights[{i}] radiant intensity (color × intensity) must lie within "
                            f"{MAX_VALUE:g}, got {max(col[-1]) * inten[-1]:g}", path)
    extra = {k: v for k, v in obj.items() if k not in ("format", "version", "lights", "provenance")}
    return Lights(np.array(pos), np.array(col), np.array(inten), names, extra, obj.get("provenance"))


def read_lights(path: str) -> Lights:
    """Read and validate a lights JSON file.  Raises DataError naming the file."""
    from ._common import read_json
    obj = read_json(path)
    return lights_from_json(obj, path)


def validate(lights: Lights, path: str = "") -> None:
    if len(lights) == 0:
        raise DataError("no lights", path)
    for name, arr in (("positions", lights.positions), ("colors", lights.colors),
                      ("intensities", lights.intensities)):
        if not np.isfinite(arr).all():
            raise DataError(f"light {name} hold NaN/Inf", path)
    if (lights.colors < 0).any() or (lights.intensities < 0).any():
        raise DataError("light colours and intensities must be non-negative", path)
    if len(lights) > MAX_LIGHTS:
        raise DataError(f"{len(lights):,} lights; a lights file holds at most {MAX_LIGHTS:,}",
                        path)
    for name, arr, limit in (("positions", lights.positions, MAX_POSITION),
                             ("colors", lights.colors, MAX_VALUE),
                             ("intensities", lights.intensities, MAX_VALUE),
                             ("radiant intensities (color × intensity)",
                              lights.radiant_intensity(), MAX_VALUE)):
        if np.abs(arr).max() > limit:
            raise DataError(f"light {name} must lie within ±{limit:g}", path)
