"""A clip's per-frame translation path (spec: ``formats/path_json.md``): the placement key
``path=FILE.json`` moves an object by translations[k] at frame k, so a static avatar or
prop walks through a scene in ``relight relight --frames`` and ``dgsm-build --frames``."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from relight_cli.errors import DataError

from ._common import MAX_POSITION, check_format_version, is_number, number_array, read_json

FORMAT = "relight/path"
VERSION = 1
#: The most frames a path may hold (as a relight/gaussian-sequence index).
MAX_FRAMES = 72_000


@dataclass
class Path:
    """``translations`` [N, 3] metres (frame k's offset, added after the placement) and
    the clip's ``fps`` (or None)."""

    translations: np.ndarray
    fps: float | None = None

    def __len__(self) -> int:
        return len(self.translations)


def read_path(path: str) -> Path:
    """Read and check a path; one-line DataErrors naming it."""
    obj = read_json(path)
    if not isinstance(obj, dict):
        raise DataError("expected a JSON object", path)
    check_format_version(obj.get("format"), obj.get("version"), FORMAT, VERSION, path)
    items = obj.get("translations")
    if not isinstance(items, list) or not items:
        raise DataError("'translations' must be a non-empty list of [x, y, z]", path)
    if len(items) > MAX_FRAMES:
        raise DataError(f"{len(items):,} translations; a path holds at most {MAX_FRAMES:,}",
                        path)
    values = number_array(items, "translations", path)
    if values.ndim != 2 or values.shape[1] != 3:
        raise DataError("'translations' must be a list of [x, y, z] (3 numbers each)", path)
    if not np.isfinite(values).all() or np.abs(values).max() > MAX_POSITION:
        raise DataError(f"'translations' must be finite metres within ±{MAX_POSITION:g}", path)
    fps = obj.get("fps")
    if fps is not None and not (is_number(fps) and math.isfinite(fps) and 0 < fps <= 10_000):
        raise DataError(f"'fps' must be a number in (0, 10000], got {fps!r}"[:200], path)
    return Path(values.astype(np.float64), None if fps is None else float(fps))
