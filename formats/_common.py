"""Checks shared by every format reader."""

from __future__ import annotations

import json
import os

from relight_cli.errors import DataError
from relight_cli.fileio import MAX_JSON_BYTES  # noqa: F401  (the documented limit)


def check_format_version(found_format, found_version, format_name: str, max_version: int,
                         path: str) -> int:
    """Require ``found_format == format_name`` and 1 ≤ version ≤ max_version; return the version.

    Every reader calls this so that wrong files and files from a newer relight
    get the same one-line errors naming the file.
    """
    if found_format != format_name:
        raise DataError(f"not a {format_name} file (format is {found_format!r})", path)
    if not isinstance(found_version, int) or isinstance(found_version, bool) or found_version < 1:
        raise DataError("missing or invalid format version", path)
    if found_version > max_version:
        raise DataError(f"{format_name} version {found_version} is newer than this relight "
                        f"understands (≤ {max_version})", path, hint="upgrade relight")
    return found_version


# Deeper JSON than any relight format uses is refused before a recursive reader
# (or the parser itself) can overflow the stack.
MAX_JSON_DEPTH = 64

# The largest magnitude a light colour, intensity, their product (radiant intensity)
# or an SH probe coefficient may have, and the largest |coordinate| of a light or probe
# position (metres).  Outputs are float32 (max ≈ 3.4e38): radiance sums of up to
# MAX_LIGHTS lights at 1e15, SH sums of up to 441 coefficients and squared distances of
# 1e6 m all stay far inside it, so a finite input cannot make a non-finite output
# (formats/README.md, "Limits").
MAX_VALUE = 1e15
MAX_POSITION = 1e6
# The most lights a lights file, a capture.json or a DGSM header may declare.
MAX_LIGHTS = 10_000


def read_json(path: str):
    """Parse a JSON file (``-``: stdin); a missing file, a folder, non-UTF-8 bytes,
    more than MAX_JSON_BYTES or bad JSON raise one-line DataErrors naming the file."""
    return parse_json(read_text(path, "a JSON file"), path)


def read_text(path: str, what: str = "a JSON file") -> str:
    """A UTF-8 text file's content (``-``: stdin, read once per command, see
    relight_cli.fileio.stdin_bytes); one-line DataErrors naming the file.

    A JSON input may be a FIFO or a device (``<(...)``, ``/dev/stdin``), read once
    per command; any input is read at most MAX_JSON_BYTES (256 MiB), and a larger
    one is refused, so ``--probe /dev/zero`` ends with one line."""
    from relight_cli.fileio import read_input_bytes, stdin_bytes
    if path == "-":
        try:
            return stdin_bytes().decode("utf-8")
        except UnicodeDecodeError:
            raise DataError("not a text (UTF-8 JSON) stream", "-") from None
    if not os.path.exists(path):
        raise DataError("no such file", path)
    if os.path.isdir(path):
        raise DataError(f"is a directory, expected {what}", path)
    try:
        return read_input_bytes(path).decode("utf-8")
    except UnicodeDecodeError:
        raise DataError("not a text (UTF-8 JSON) file", path) from None


def _non_finite_literal(name: str):
    raise ValueError(f"{name} is not valid JSON (no NaN/Inf: JSON numbers are finite)")


def parse_json(text: str, path: str, non_finite: str = "error"):
    """Parse JSON text strictly: NaN/Infinity literals, nesting deeper than
    MAX_JSON_DEPTH and integers too long to convert are one-line DataErrors.

    ``non_finite="nan"`` reads the NaN/Infinity literals as NaN instead (a
    metrics gate must see them, and fail on them, rather than refuse the file);
    ``"allow"`` keeps Python's reading (Infinity → inf), for header fields that
    relight writes itself.
    """
    constant = {"error": _non_finite_literal, "nan": lambda name: float("nan"),
                "allow": float}[non_finite]

    def number(literal: str) -> float:  # 1e400 overflows to inf: no finite reading of it
        value = float(literal)
        if value - value != 0 and non_finite != "allow":
            return constant(literal)
        return value

    def integer(literal: str) -> int:  # 1 and 400 zeros: no float64 holds it (finite reading)
        value = int(literal)
        if value.bit_length() > 1024 and non_finite != "allow":
            raise ValueError(f"an integer of {len(literal.lstrip('-'))} digits is beyond any "
                             f"finite number")
        return value

    def unique(pairs):  # duplicate keys: which one was meant is unknowable (no "last wins")
        obj = dict(pairs)
        if len(obj) != len(pairs):
            seen = set()
            for key, _ in pairs:
                if key in seen:
                    raise ValueError(f"duplicate key {key!r}"[:120])
                seen.add(key)
        return obj

    try:
        obj = json.loads(text, parse_constant=constant, parse_float=number,
                         parse_int=integer, object_pairs_hook=unique)
    except json.JSONDecodeError as exc:
        raise DataError(f"invalid JSON: {exc.msg} at line {exc.lineno}", path) from None
    except RecursionError:
        raise DataError(f"invalid JSON: nested more than {MAX_JSON_DEPTH} levels deep",
                        path) from None
    except ValueError as exc:  # e.g. an integer of more than 4300 digits, NaN literals
        raise DataError(f"invalid JSON: {str(exc).splitlines()[0][:120]}", path) from None
    stack = [(obj, 1)]
    while stack:
        value, depth = stack.pop()
        if depth > MAX_JSON_DEPTH:
            raise DataError(f"invalid JSON: nested more than {MAX_JSON_DEPTH} levels deep", path)
        if isinstance(value, dict):
            stack.extend((v, depth + 1) for v in value.values())
        elif isinstance(value, list):
            stack.extend((v, depth + 1) for v in value)
    return obj


def is_int(value) -> bool:
    """A JSON integer (``true``/``false`` are not numbers, though Python's bool is an int)."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def number_array(value, what: str, path: str):
    """A JSON array (nested lists) of numbers as float64; booleans, strings and
    ragged lists are DataErrors naming ``what``."""
    import numpy as np
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, list):
            stack.extend(item)
        elif not is_number(item):
            raise DataError(f"{what} must hold numbers only, found {item!r}"[:160], path)
    try:
        return np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{what} must be a regular array of numbers", path) from None


def bounded(array, what: str, path: str, limit: float = MAX_VALUE):
    """``array`` (numbers, any shape) finite and within ±``limit``; else a DataError
    naming ``what`` and the file (a finite but huge value would overflow an output)."""
    import numpy as np
    a = np.asarray(array, np.float64)
    if not np.isfinite(a).all():
        raise DataError(f"{what} holds NaN/Inf", path)
    if a.size and float(np.abs(a).max()) > limit:
        raise DataError(f"{what} must lie within ±{limit:g}, got {float(np.abs(a).max()):g}",
                        path)
    return a


def save_npz(file, arrays: dict) -> None:
    """``np.savez_compressed`` with fixed zip timestamps, so identical arrays give
    identical bytes (numpy stamps every member with the current time)."""
    import zipfile

    import numpy as np
    from numpy.lib import format as npy_format
    with zipfile.ZipFile(file, mode="w", compression=zipfile.ZIP_DEFLATED,
                         allowZip64=True) as zf:
        for key, value in arrays.items():
            info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as member:
                npy_format.write_array(member, np.asanyarray(value), allow_pickle=False)
