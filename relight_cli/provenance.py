"""Provenance of outputs: what made them, from what.

Every output records the format name and version, the command line that made it
and the SHA-256 of its input files, so a pipeline can be audited and a stale
file detected.  No timestamps or timings, and no presentation flags (``-q``,
``--debug``) in the stored command line: identical inputs give identical bytes.

The writes themselves, stdin/stdout and the running command's input/output
registry are the I/O base, :mod:`relight_cli.fileio`.
"""

from __future__ import annotations

import hashlib
import os
import shlex

from . import __version__, fileio


# The argv of the running command, set by the CLI group (``cli.RelightGroup``);
# engine code used from Python leaves it empty.
_COMMAND_LINE: list[str] = []


# Flags that change what is shown, not what is written: left out of the stored
# command line so that they never change an output's bytes.
PRESENTATION_FLAGS = frozenset({"-q", "--quiet", "--debug", "--no-clobber"})


def set_command_line(argv: list[str] | None) -> None:
    """The running command's argv (``relight`` prepended), or None when it is over."""
    _COMMAND_LINE[:] = [] if argv is None else \
        ["relight", *(a for a in argv if a not in PRESENTATION_FLAGS)]


def command_line() -> str:
    """The command line of this run, shell-quoted ('' when used as a library)."""
    return shlex.join(_COMMAND_LINE) if _COMMAND_LINE else ""


def file_sha256(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes (builtin inputs like ``builtin:sky`` hash their name).

    Inside a command, an input it declared has the hash of the bytes it had when first
    declared (:func:`relight_cli.fileio.input_digest`), for the whole run: what the
    command read, even if the file is replaced while it runs."""
    p = str(path)
    if p.startswith("builtin:"):
        return "builtin:" + hashlib.sha256(p.encode()).hexdigest()[:16]
    if p == "-":
        return hashlib.sha256(fileio.stdin_bytes()).hexdigest()
    kept = fileio.kept_stream(p)
    if kept is not None:   # a FIFO already read: the same bytes
        return hashlib.sha256(kept).hexdigest()
    first = fileio.input_digest(p)
    if first is not None:  # hashed when the run declared it: what it read
        return first
    if os.path.exists(p) and not os.path.isfile(p):   # a device or FIFO: bounded, once
        return hashlib.sha256(fileio.read_input_bytes(p)).hexdigest()
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
    for p in (inputs or {}).values():
        fileio.declare_input(str(p))
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


def numbered_roles(role: str, paths) -> dict:
    """Provenance roles of repeated inputs: ``role`` for one path, else ``role.0``,
    ``role.1`` … (e.g. one ``--checkpoint`` per hand)."""
    paths = list(paths)
    if len(paths) == 1:
        return {role: paths[0]}
    return {f"{role}.{i}": p for i, p in enumerate(paths)}
