"""Checks shared by every format reader."""

from __future__ import annotations

import json
import os

from relight_cli.errors import DataError


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


def read_json(path: str):
    """Parse a JSON file; a missing file, a folder, non-UTF-8 bytes or bad JSON
    raise one-line DataErrors naming the file."""
    if not os.path.exists(path):
        raise DataError("no such file", path)
    if os.path.isdir(path):
        raise DataError("is a directory, expected a JSON file", path)
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except UnicodeDecodeError:
        raise DataError("not a text (UTF-8 JSON) file", path) from None
    except json.JSONDecodeError as exc:
        raise DataError(f"invalid JSON: {exc.msg} at line {exc.lineno}", path) from None
