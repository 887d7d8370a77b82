"""Provenance of outputs and atomic writes.

Every output records the format name and version, the command line that made it
and the SHA-256 of its input files, so a pipeline can be audited and a stale
file detected.  No timestamps: identical inputs give identical outputs.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shlex
import sys
import tempfile
from pathlib import Path
from typing import Iterator

from . import __version__

# The argv of the running command, set by the CLI group (``cli.RelightGroup``);
# engine code used from Python leaves it empty.
_COMMAND_LINE: list[str] = []


def set_command_line(argv: list[str]) -> None:
    _COMMAND_LINE[:] = ["relight", *argv]


def command_line() -> str:
    """The command line of this run, shell-quoted ('' when used as a library)."""
    return shlex.join(_COMMAND_LINE) if _COMMAND_LINE else ""


def file_sha256(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes (builtin inputs like ``builtin:sky`` hash their name)."""
    p = str(path)
    if p.startswith("builtin:"):
        return "builtin:" + hashlib.sha256(p.encode()).hexdigest()[:16]
    h = hashlib.sha256()
    with open(p, "rb") as f:
        while True:
            block = f.read(chunk)
            if not block:
                break
            h.update(block)
    return h.hexdigest()


def provenance(format_name: str, version: int, inputs: dict[str, str] | None = None,
               settings: dict | None = None) -> dict:
    """The provenance record stored in every output.

    Args:
        format_name: e.g. ``"relight/envmap"``.
        version: format major version.
        inputs: role -> path of each input file (hashed here).
        settings: the options that shaped the output (JSON-serializable).
    """
    record = {
        "format": format_name,
        "version": int(version),
        "tool": f"relight {__version__}",
        "command": command_line(),
        "inputs": {role: {"path": str(p), "sha256": file_sha256(p)}
                   for role, p in (inputs or {}).items()},
    }
    if settings:
        record["settings"] = settings
    return record


# Outputs staged by the running command: all are renamed into place together
# when it succeeds, and all removed when it fails (see output_transaction).
_PENDING: list[tuple[str, Path]] | None = None


@contextlib.contextmanager
def output_transaction() -> Iterator[None]:
    """All-or-nothing outputs: atomic_path() writes inside this block are renamed
    into place only when the whole block succeeds (a command with an EXR and a
    PNG output never leaves one without the other)."""
    global _PENDING
    if _PENDING is not None:  # nested: the outer transaction decides
        yield
        return
    _PENDING = []
    try:
        yield
        staged, _PENDING = _PENDING, None
        for tmp, target in staged:
            os.replace(tmp, target)
    except BaseException:
        staged, _PENDING = _PENDING or [], None
        for tmp, _ in staged:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        raise


@contextlib.contextmanager
def outside_transaction() -> Iterator[None]:
    """Let atomic writes in this block land at once, even inside a command's
    output transaction (a resumable job keeps each finished piece)."""
    global _PENDING
    saved, _PENDING = _PENDING, None
    try:
        yield
    finally:
        _PENDING = saved


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike, suffix: str | None = None) -> Iterator[str]:
    """Yield a temporary path in the target's folder; rename it onto the target on success.

    On any exception the temporary file is removed and the target is untouched,
    so Make never trusts a half-written output.  ``suffix`` keeps the extension
    (libraries that pick the codec by extension need it).
    """
    target = Path(target)
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        from .errors import UsageProblem
        raise UsageProblem("output folder does not exist", str(folder))
    if suffix is None:
        suffix = "".join(target.suffixes[-1:])
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp" + suffix, dir=folder)
    os.close(fd)
    try:
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; outputs get normal permissions
        if _PENDING is not None:
            _PENDING.append((tmp, target))
        else:
            os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_text_atomic(target: str, text: str) -> None:
    """Write text to ``target`` atomically, or to stdout when target is ``-``."""
    if target == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    with atomic_path(target) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
