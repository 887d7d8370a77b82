"""A Gaussian sequence index: per-frame 3DGS PLYs as one avatar (spec:
``formats/gaussian_sequence.md``).

Avatar methods export one PLY per frame (Animatable Gaussians ``posed_gaussians/%08d.ply``,
PlayCanvas' flipbook ``frame_0000.ply``); this small JSON says what a bare file pattern
cannot: which frames there are, at what rate, in which units and up axis, and whether
every frame holds the same Gaussians (same topology).
"""

from __future__ import annotations

import math
import os
import re
import string
from dataclasses import dataclass

from relight_cli.errors import DataError

from ._common import check_format_version, is_int, is_number, read_json

FORMAT = "relight/gaussian-sequence"
VERSION = 1
#: Units a sequence's coordinates may be in, and their size in metres.
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
#: Up axes a sequence may have; each is turned to +Y (the toolkit's up) on read.
UP_AXES = ("+y", "-y", "+z", "-z")
COLOUR_SPACES = ("srgb", "linear")
#: The most frames an index may declare (a 10-minute clip at 120 fps).
MAX_FRAMES = 72_000


@dataclass
class GaussianSequenceIndex:
    """A read index: ``pattern`` (absolute, holding ``{frame}``), the frame numbers
    ``first`` … ``first + count − 1``, ``fps`` (or None), ``units`` (a key of
    :data:`UNITS`), ``up`` (one of :data:`UP_AXES`), ``colour_space`` (or None: the
    PLYs' own), ``same_topology``."""

    pattern: str
    first: int
    count: int
    fps: float | None = None
    units: str = "m"
    up: str = "+y"
    colour_space: str | None = None
    same_topology: bool = False

    @property
    def frames(self) -> list:
        return list(range(self.first, self.first + self.count))


# A format spec a {frame} field may carry: fill 0 and/or a width, then d (as the output
# patterns of relight_cli.sequence).
_FRAME_SPEC = re.compile(r"^0?[0-9]{0,2}d?$")


def pattern_problem(pattern: str) -> str | None:
    """What is wrong with a frame pattern (None: nothing): only ``{frame}`` fields, each
    with an integer format at most (no index, attribute, conversion or other field)."""
    try:
        fields = list(string.Formatter().parse(pattern))
    except ValueError as exc:
        return f"is not a valid pattern ({exc})"
    for _, field, spec, conversion in fields:
        if field is None:
            continue
        if field != "frame" or conversion is not None or not _FRAME_SPEC.match(spec or ""):
            text = "{" + field + ("!" + conversion if conversion else "") \
                + (":" + spec if spec else "") + "}"
            return f"may only use {{frame}} fields (e.g. {{frame:04d}}), found {text}"
    return None


def is_index(path: str) -> bool:
    """Whether ``path`` names a sequence index (by its extension: ``.json``)."""
    return path.lower().endswith(".json")


def read_sequence_index(path: str) -> GaussianSequenceIndex:
    """Read and check an index; one-line DataErrors naming it."""
    obj = read_json(path)
    if not isinstance(obj, dict):
        raise DataError("expected a JSON object", path)
    check_format_version(obj.get("format"), obj.get("version"), FORMAT, VERSION, path)
    pattern = obj.get("frames")
    if not isinstance(pattern, str) or "{frame" not in pattern:
        raise DataError("'frames' must be a file pattern holding {frame} (e.g. "
                        "'frame_{frame:04d}.ply')", path)
    bad = pattern_problem(pattern)
    if bad is not None:
        raise DataError(f"'frames' {bad}", path)
    if not pattern.lower().endswith(".ply"):
        raise DataError(f"'frames' names PLY files, got {pattern!r}"[:200], path)
    first, count = obj.get("first", 0), obj.get("count")
    if not is_int(first) or not 0 <= first <= 10**9:
        raise DataError(f"'first' must be an integer in [0, 1e9], got {first!r}"[:200], path)
    if not is_int(count) or not 1 <= count <= MAX_FRAMES:
        raise DataError(f"'count' must be an integer in [1, {MAX_FRAMES}], got {count!r}"[:200],
                        path)
    fps = obj.get("fps")
    if fps is not None and not (is_number(fps) and math.isfinite(fps) and 0 < fps <= 10_000):
        raise DataError(f"'fps' must be a number in (0, 10000], got {fps!r}"[:200], path)
    choices = (("units", tuple(UNITS), "m"), ("up", UP_AXES, "+y"),
               ("colour_space", COLOUR_SPACES, None))
    values = {}
    for key, allowed, default in choices:
        value = obj.get(key, default)
        if value is not None and value not in allowed:
            raise DataError(f"'{key}' must be one of {', '.join(allowed)}, got {value!r}"[:200],
                            path)
        values[key] = value
    same = obj.get("same_topology", False)
    if not isinstance(same, bool):
        raise DataError(f"'same_topology' must be true or false, got {same!r}"[:200], path)
    folder = os.path.dirname(os.path.abspath(path))
    return GaussianSequenceIndex(os.path.join(folder, pattern), first, count,
                                 None if fps is None else float(fps), values["units"],
                                 values["up"], values["colour_space"], same)
