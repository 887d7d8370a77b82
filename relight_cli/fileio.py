"""The I/O base: writes that never destroy anything, stdin and stdout, the run's files.

Below the file formats (which write through it) and free of them, of the engine, of
click and of torch: the standard library and :mod:`relight_cli.errors` only.

Writes (:func:`atomic_path`) go to a temporary file beside the target, named
``.NAME.relight-tmp-PID-XXXXXXXX.EXT`` so that a run killed with SIGKILL can be
recognised and cleaned by the next run writing NAME, and are renamed into place
only when the whole command succeeds (:func:`output_transaction`).  The target
decides how: a regular file (or a new name) is replaced by rename; a symlink is
written through to its target, atomically there; a character device or FIFO is
written in place (its node is never replaced); a folder, block device or socket
is refused.  The running command's outputs and inputs are registered
(:func:`declare_output`, :func:`declare_input`), so an output that is also an
input, or two outputs on one file, are refused before any work.

A JSON output on stdout (``-o -``, :func:`write_stdout`) is held until the command
succeeds and goes out before the files are committed: every byte is checked (a
short write is finished or fails), a regular file behind stdout is synced, and a
failure (a reader that went away: BrokenPipeError; a full disk, /dev/full, a closed
stdout: a one-line OutputError naming ``stdout``) commits no file.  JSON inputs
(files, FIFOs, stdin) are read at most :data:`MAX_JSON_BYTES`.

The provenance record stored in every output (command line, input hashes) is
:mod:`relight_cli.provenance`, built on this module.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import stat
import sys
import tempfile
from pathlib import Path
from typing import Iterator


# ----------------------------------------------------------------------------- the run's files

TEMP_MARK = ".relight-tmp-"


class _Run:
    """Inputs and outputs of the running command (see output_transaction)."""

    def __init__(self):
        self.inputs: list[tuple[str, tuple]] = []
        self.outputs: list[tuple[str, tuple]] = []
        self.stdin_role: str | None = None     # the one input given as '-'
        self.stdin: bytes | None = None        # its bytes, read once
        self.streams: dict[str, bytes] = {}    # JSON inputs that are FIFOs/devices, read once
        self.digests: dict[str, str] = {}      # resolved path -> SHA-256 when first declared


# Outputs staged by the running command: all are committed together when it
# succeeds, and all removed when it fails (see output_transaction).
_PENDING: list[tuple[str, str, str]] | None = None
_RUN: _Run | None = None
# JSON documents for stdout, held with _PENDING: written first when the command succeeds.
_STDOUT: list[bytes] | None = None
# The registry of the command that ended last (its error line names its files).
_LAST_RUN: _Run | None = None
# Temporary files that exist now and are not committed: the transaction removes them
# when the command fails, even one whose writer never got to clean up (a signal in
# contextlib's code between the writer's yield and its with-block).
_LIVE_TEMPS: set[str] = set()


_INPUT_IS_OUTPUT = "an output is also an input of this command; give the output another name"


def _identity(path: str) -> tuple:
    """(resolved path, (device, inode) or None, is a character device) of ``path``."""
    real = os.path.realpath(path)
    try:
        st = os.stat(path)
    except OSError:
        return real, None, False
    return real, (st.st_dev, st.st_ino), stat.S_ISCHR(st.st_mode)


def _now(path: str, recorded: tuple) -> tuple:
    """A registered file's identity now: a long command's input (a config file another
    process rewrote atomically) may have moved to a new inode, and the old inode number
    be reused by a file this command writes later, so comparing with the identity recorded
    at the start refused a checkpoint save as "also an input" (seen: a 30-minute
    ``distill`` whose config file was rewritten while it trained)."""
    return _identity(path) if path and path != "-" else recorded


def _same(a: tuple, b: tuple) -> bool:
    if a[2] or b[2]:  # a character device (/dev/null) may take any number of streams
        return False
    return a[0] == b[0] or (a[1] is not None and a[1] == b[1])


def claim_stdin(role: str) -> None:
    """Register that input ``role`` (e.g. ``"--lights"``) reads stdin (``-``): a second
    input on stdin, or stdin left at a terminal, is a usage error before any work."""
    from .errors import UsageProblem
    if _RUN is not None:
        if _RUN.stdin_role not in (None, role):
            raise UsageProblem(f"only one input can come from stdin: {_RUN.stdin_role} and "
                               f"{role} both say '-'")
        _RUN.stdin_role = role
    if _RUN is None or _RUN.stdin is None:
        try:
            interactive = sys.stdin is None or sys.stdin.isatty()
        except (AttributeError, ValueError):
            interactive = False
        if interactive:
            raise UsageProblem(f"{role} - reads JSON from stdin, but stdin is a terminal; "
                               f"pipe the JSON in or give a file name")


def stdin_bytes() -> bytes:
    """The bytes of stdin, read once per command (the input given as ``-``); provenance
    hashes the same bytes (relight_cli.provenance.file_sha256("-"))."""
    if _RUN is not None and _RUN.stdin is not None:
        return _RUN.stdin
    stream = getattr(sys.stdin, "buffer", sys.stdin)
    data = _read_bounded(stream, "-") if stream is not None else b""
    if _RUN is not None:
        _RUN.stdin = data
    return data


#: The most bytes read from one JSON input (a file, a FIFO, a device or stdin): more is
#: refused with one line instead of reading without end (``--probe /dev/zero``).
MAX_JSON_BYTES = 256 * 1024 * 1024


def _too_large(path: str):
    from .errors import DataError
    return DataError(f"larger than {MAX_JSON_BYTES // (1024 * 1024)} MiB, the most relight "
                     f"reads from a JSON input", path)


def _read_bounded(stream, path: str) -> bytes:
    """Everything ``stream`` holds, in blocks, refusing more than MAX_JSON_BYTES."""
    chunks, total = [], 0
    while True:
        block = stream.read(min(1 << 20, MAX_JSON_BYTES + 1 - total))
        if not block:
            break
        if isinstance(block, str):
            block = block.encode("utf-8", "surrogateescape")
        chunks.append(block)
        total += len(block)
        if total > MAX_JSON_BYTES:
            raise _too_large(path)
    return b"".join(chunks)


def read_input_bytes(path: str) -> bytes:
    """The bytes of a JSON input file, at most MAX_JSON_BYTES (a larger one is a one-line
    DataError, refused before reading when its size is known).  A FIFO or device is read
    once per command and its bytes kept, so that provenance hashes what was parsed."""
    from .errors import DataError
    if _RUN is not None and path in _RUN.streams:
        return _RUN.streams[path]
    try:
        st = os.stat(path)
        if stat.S_ISREG(st.st_mode) and st.st_size > MAX_JSON_BYTES:
            raise _too_large(path)
        with open(path, "rb") as f:
            data = _read_bounded(f, path)
    except OSError as exc:
        raise DataError(f"cannot read: {_reason(exc)}", path) from None
    if _RUN is not None and not stat.S_ISREG(st.st_mode):
        _RUN.streams[path] = data
    return data


def kept_stream(path: str) -> bytes | None:
    """The bytes of a JSON input that is a FIFO or device, as this command read it
    (read_input_bytes keeps them), or None: provenance hashes what was parsed."""
    if _RUN is not None and path in _RUN.streams:
        return _RUN.streams[path]
    return None


def declare_input(path: str) -> None:
    """Register an input file of the running command; refuse one that is also an output.

    A regular file's bytes are hashed the first time it is declared (before it is read:
    commands declare their inputs when they check them), and that hash is what this
    run's provenance records for it (:func:`input_digest`): a file replaced while the
    run goes on (an env map rewritten during ``relight --frames``, which read it once)
    does not change what later outputs say they were made from."""
    from .errors import UsageProblem
    if _RUN is None or not path or path == "-" or path.startswith("builtin:"):
        return
    ident = _identity(path)
    if any(ident == other for _, other in _RUN.inputs):
        return  # already known (provenance records register every output's inputs again)
    for out, other in _RUN.outputs:
        if _same(ident, _now(out, other)):
            raise UsageProblem(_INPUT_IS_OUTPUT, path)
    _RUN.inputs.append((path, ident))
    key = os.path.realpath(path)
    if key not in _RUN.digests:
        digest = _sha256_of_file(path)
        if digest is not None:
            _RUN.digests[key] = digest


def input_digest(path: str) -> str | None:
    """The SHA-256 of input ``path`` as the running command first declared it (one hash
    per file per run, whatever name it is given by), or None: no command is running, the
    file was not declared, or it is no regular file (a FIFO's bytes: kept_stream)."""
    if _RUN is None or not path or path == "-":
        return None
    return _RUN.digests.get(os.path.realpath(path))


def _sha256_of_file(path: str, chunk: int = 1 << 20) -> str | None:
    """Hex SHA-256 of a regular file's bytes, or None (not a regular file, unreadable:
    its reader says why).  A FIFO is never opened here: an open blocks until a writer
    comes, and closing it unread drops what that writer sent, so the reader that follows
    would wait for ever (its bytes are hashed as read: kept_stream)."""
    import hashlib
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None
        with open(path, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                return None
            h = hashlib.sha256()
            while True:
                block = f.read(chunk)
                if not block:
                    break
                h.update(block)
    except OSError:
        return None
    return h.hexdigest()


def declare_output(path: str) -> None:
    """Check an output before any work and register it for the running command.

    Refuses (usage errors, exit 2) an empty name, a folder, a block device or
    socket, a missing folder, an output that is one of the command's inputs or
    another of its outputs; refuses (exit 1) a folder where no file can be
    created.  Removes this output's stale temporary files left by killed runs.
    """
    from .errors import UsageProblem
    if path == "-":
        return
    final, mode = _resolve(path)
    ident = _identity(path)
    if _RUN is not None:
        for inp, other in _RUN.inputs:
            if _same(ident, _now(inp, other)):
                raise UsageProblem(_INPUT_IS_OUTPUT, path)
        for out, other in _RUN.outputs:
            if _same(ident, other):
                also = "" if out == path else f" (also given as {out!r})"
                raise UsageProblem(f"two outputs go to one file{also}; give each its own name",
                                   path)
    if mode == "replace":
        folder, name = os.path.split(final)
        remove_stale_temps(folder or ".", name)
        _probe_folder(folder or ".", name, path)
    if _RUN is not None:
        _RUN.outputs.append((path, ident))


def _resolve(target: str) -> tuple[str, str]:
    """(path to write, "replace" | "inplace") for an output name, or a one-line error."""
    from .errors import OutputError, UsageProblem
    if target == "":
        raise UsageProblem("empty output file name", "''")
    try:
        st = os.stat(target)           # follows symlinks: the type of what is written
    except FileNotFoundError:
        st = None
    except OSError as exc:             # ELOOP, ENAMETOOLONG, EACCES on a parent ...
        raise OutputError(f"cannot write: {_reason(exc)}", target) from None
    if st is None:
        final = os.path.realpath(target) if os.path.islink(target) else target
        folder = os.path.dirname(final) or "."
        if not os.path.isdir(folder):
            raise UsageProblem("output folder does not exist", folder)
        return final, "replace"
    if stat.S_ISREG(st.st_mode):
        return os.path.realpath(target), "replace"
    if stat.S_ISDIR(st.st_mode):
        raise UsageProblem("output is a directory", target)
    if stat.S_ISCHR(st.st_mode) or stat.S_ISFIFO(st.st_mode):
        return target, "inplace"
    kind = "block device" if stat.S_ISBLK(st.st_mode) else (
        "socket" if stat.S_ISSOCK(st.st_mode) else "special file")
    raise UsageProblem(f"output is a {kind}; refusing to write to it", target)


def _reason(exc: OSError) -> str:
    return (exc.strerror or str(exc)).lower() if isinstance(exc, OSError) else str(exc)


def _temp_prefix(name: str, folder: str) -> str:
    """``.NAME.relight-tmp-PID-``, NAME cut so that mkstemp's name fits the folder's limit."""
    try:
        limit = os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    tail = f"{TEMP_MARK}{os.getpid()}-"
    room = max(1, limit - len(tail) - 1 - 8 - 16)  # '.', mkstemp's 8 random, a suffix
    while len(os.fsencode(name)) > room:
        name = name[:-1]
    return "." + name + tail


def _probe_folder(folder: str, name: str, target: str) -> None:
    """Create and remove a temporary file where the output will go: write errors
    (permissions, read-only or pseudo file systems, a name too long) surface
    before any work, naming the output."""
    from .errors import OutputError
    try:
        limit = os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    if len(os.fsencode(name)) > limit:
        raise OutputError(f"file name too long (more than {limit} bytes)", target)
    with _stop_signals_held():   # created and removed before a Ctrl-C can interrupt
        try:
            fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(name, folder), dir=folder)
        except OSError as exc:
            raise OutputError(f"cannot create a file in {folder!r}: {_reason(exc)}",
                              target) from None
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp)


# Ctrl-C, SIGTERM and SIGHUP that arrived while a temporary file was being created
# (see _stop_signals_held); the CLI's handlers ask defer_stop_signal first.
_HOLDING = 0
_HELD: list[int] = []


def defer_stop_signal(signal_number: int) -> bool:
    """True when a temporary file is being created and named: the signal is kept and
    raised again right after, where the caller's clean-up knows the file."""
    if _HOLDING:
        _HELD.append(signal_number)
        return True
    return False


@contextlib.contextmanager
def _stop_signals_held() -> Iterator[None]:
    """Hold Ctrl-C, SIGTERM and SIGHUP (as handled by the CLI) while a temporary file
    is created and its name stored: one arriving in between would leave the file with
    no one to remove it."""
    global _HOLDING
    _HOLDING += 1
    try:
        yield
    finally:
        _HOLDING -= 1
        if not _HOLDING and _HELD:
            signal_number = _HELD[0]
            _HELD.clear()
            signal.raise_signal(signal_number)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return pid > 0
    return True


def remove_stale_temps(folder: str, name: str) -> list[str]:
    """Remove ``.NAME.relight-tmp-PID-*`` files in ``folder`` whose process is gone
    (a run killed before it could clean up); returns what was removed."""
    prefix = _temp_prefix(name, folder).rsplit(TEMP_MARK, 1)[0] + TEMP_MARK
    removed = []
    try:
        entries = os.listdir(folder)
    except OSError:
        return removed
    for entry in entries:
        if not entry.startswith(prefix):
            continue
        pid_text = entry[len(prefix):].split("-", 1)[0]
        if not pid_text.isdigit() or int(pid_text) == os.getpid() or _pid_alive(int(pid_text)):
            continue
        path = os.path.join(folder, entry)
        with contextlib.suppress(OSError):
            if os.path.isfile(path) and not os.path.islink(path):
                os.unlink(path)
                removed.append(path)
    return removed


@contextlib.contextmanager
def output_transaction() -> Iterator[None]:
    """All-or-nothing outputs: atomic_path() writes inside this block are committed
    only when the whole block succeeds (a command with an EXR and a PNG output
    never leaves one without the other).  The block is also the scope of the
    input/output registry (declare_input, declare_output)."""
    global _PENDING, _RUN, _STDOUT, _LAST_RUN, _AFTER_COMMIT
    if _PENDING is not None:  # nested: the outer transaction decides
        yield
        return
    _PENDING, _RUN, _STDOUT, _AFTER_COMMIT = [], _Run(), [], []
    _LAST_RUN = _RUN
    staged = None
    try:
        yield
        staged, _PENDING = _PENDING, None
        documents, _STDOUT = _STDOUT, None
        _commit_all(staged, documents)
        said, _AFTER_COMMIT = _AFTER_COMMIT, None
        for callback in said:          # what is true only once the outputs are in place
            callback()
    except BaseException:
        _AFTER_COMMIT = None
        # Whatever was not committed (a committed file's temporary name is gone), also
        # when a signal came between taking the list and committing it.
        leftovers = {tmp for tmp, _, _ in (staged if staged is not None else _PENDING or [])}
        for tmp in leftovers | _LIVE_TEMPS:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        _LIVE_TEMPS.clear()
        _PENDING = _STDOUT = None
        raise
    finally:
        _RUN = None


#: Callbacks of the open transaction run once its outputs are committed (None: none open).
_AFTER_COMMIT: list | None = None


def after_commit(callback) -> bool:
    """Run ``callback`` once the open output transaction has committed every output, and
    never if it fails (a "wrote FILE" line is said only when FILE is in place); False,
    and nothing kept, when no transaction is open (the caller acts now)."""
    if _PENDING is None or _AFTER_COMMIT is None:
        return False
    _AFTER_COMMIT.append(callback)
    return True


@contextlib.contextmanager
def outside_transaction() -> Iterator[None]:
    """Let atomic writes in this block land at once, even inside a command's
    output transaction (a resumable job keeps each finished piece)."""
    global _PENDING, _STDOUT
    saved, _PENDING = _PENDING, None
    saved_stdout, _STDOUT = _STDOUT, None
    try:
        yield
    finally:
        _PENDING, _STDOUT = saved, saved_stdout


def _commit_all(staged: list[tuple[str, str, str]], documents: list[bytes]) -> None:
    """Commit a transaction's outputs, all or none (two phases).

    Every output is already staged: written in full to its temporary file, flushed and
    checked (atomic_path).  Phase 1 checks that every target can still take its file:
    a regular output's folder is writable and its name no folder; a device or FIFO is
    opened for writing (a FIFO with no reader fails here, before anything is
    committed).  Then stdout's documents go out.  Phase 2 renames the regular outputs
    into place, each replaced file kept as a hard-linked backup
    (``.NAME.relight-tmp-PID-*.bak``) until the transaction ends, and only then writes
    the devices and FIFOs (what they took cannot be taken back, so they come last).
    A failure anywhere in phase 2 (a rename, /dev/full, a signal) puts every committed
    output back as it was: a replaced file from its backup, a new name removed.
    """
    from .errors import OutputError
    regular = [(tmp, final) for tmp, final, mode in staged if mode == "replace"]
    special = [(tmp, final) for tmp, final, mode in staged if mode != "replace"]
    fds: dict[str, int] = {}
    done: list[tuple[str, str | None]] = []     # (committed target, its backup or None)
    try:
        for tmp, final in regular:               # phase 1: every target checked
            _check_target(final)
        for tmp, final in special:
            fds[final] = _open_in_place(final)
        for data in documents:                   # stdout: if it fails, no file is committed
            _emit_stdout(data)
        try:
            for tmp, final in regular:           # phase 2: renames, undoable
                with _stop_signals_held():       # renamed and recorded, or neither
                    backup = _backup(final)
                    try:
                        os.replace(tmp, final)
                    except OSError as exc:
                        if backup is not None:
                            with contextlib.suppress(OSError):
                                os.unlink(backup)
                        raise OutputError(f"cannot write: {_reason(exc)}", final) from None
                    _LIVE_TEMPS.discard(tmp)
                    done.append((final, backup))
            for tmp, final in special:           # then what cannot be taken back
                try:
                    _write_in_place(fds[final], tmp)
                except OSError as exc:
                    raise OutputError(f"cannot write: {_reason(exc)}", final) from None
        except BaseException:
            with _stop_signals_held():
                _restore(done)
            raise
        for _, backup in done:                   # committed: the backups go
            if backup is not None:
                with contextlib.suppress(OSError):
                    os.unlink(backup)
    finally:
        for fd in fds.values():
            with contextlib.suppress(OSError):
                os.close(fd)
        for tmp, _ in special:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            _LIVE_TEMPS.discard(tmp)


def _check_target(final: str) -> None:
    """A regular output can still be renamed into place: its name is no folder and its
    folder takes new names (another process may have changed either during the run)."""
    from .errors import OutputError
    folder = os.path.dirname(final) or "."
    if os.path.isdir(final) and not os.path.islink(final):
        raise OutputError("cannot write: is a directory", final)
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write: permission denied in {folder!r}", final)


def _backup(final: str) -> str | None:
    """A hard link (else a copy) of the file at ``final`` beside it, under a temporary
    name of this process, or None when there is no file there now."""
    import shutil
    if not os.path.lexists(final):
        return None
    folder, name = os.path.split(final)
    folder = folder or "."
    fd, backup = tempfile.mkstemp(prefix=_temp_prefix(name, folder), suffix=".bak",
                                  dir=folder)
    os.close(fd)
    try:
        os.unlink(backup)
        try:
            os.link(final, backup)
        except OSError as exc:
            if exc.errno == errno.EEXIST:
                raise
            shutil.copy2(final, backup)   # a file system without hard links
    except OSError as exc:
        from .errors import OutputError
        with contextlib.suppress(OSError):
            os.unlink(backup)
        raise OutputError(f"cannot write: cannot keep a backup: {_reason(exc)}",
                          final) from None
    return backup


def _restore(done: list[tuple[str, str | None]]) -> None:
    """Undo committed renames, last first: a replaced file back from its backup, a new
    name removed.  A backup that cannot be put back stays (nothing is lost)."""
    for final, backup in reversed(done):
        with contextlib.suppress(OSError):
            if backup is None:
                os.unlink(final)
            else:
                os.replace(backup, final)


def _commit(tmp: str, final: str, mode: str) -> None:
    """Commit one output at once (outside a transaction)."""
    from .errors import OutputError
    try:
        if mode == "replace":
            os.replace(tmp, final)
            _LIVE_TEMPS.discard(tmp)
            return
        _copy_in_place(tmp, final)
    except OSError as exc:
        raise OutputError(f"cannot write: {_reason(exc)}", final) from None
    finally:
        if mode != "replace":
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            _LIVE_TEMPS.discard(tmp)


def _open_in_place(target: str) -> int:
    """A descriptor to write a character device or FIFO (blocking once open); a FIFO
    with no reader is a one-line OutputError."""
    from .errors import OutputError
    flags = os.O_WRONLY | getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(target, flags)
    except OSError as exc:
        if exc.errno == errno.ENXIO:
            raise OutputError("FIFO has no reader", target) from None
        raise OutputError(f"cannot write: {_reason(exc)}", target) from None
    if hasattr(os, "set_blocking"):
        os.set_blocking(fd, True)
    return fd


def _copy_in_place(tmp: str, target: str) -> None:
    """Stream a finished temporary file into a character device or FIFO."""
    fd = _open_in_place(target)
    try:
        _write_in_place(fd, tmp)
    finally:
        os.close(fd)


def _write_in_place(fd: int, tmp: str) -> None:
    """Write the whole temporary file ``tmp`` to the open device or FIFO ``fd``."""
    with open(tmp, "rb") as src:
        while True:
            block = src.read(1 << 20)
            if not block:
                break
            view = memoryview(block)
            while view:
                view = view[os.write(fd, view):]


def _check_written(tmp: str, target: str, verify) -> None:
    """What the writer left must be on disk: flushed (fsync reports deferred write
    errors), not empty, and, when the file system is now full, complete: C++
    writers (OpenEXR, libpng) can drop the error of their last buffer, so their
    file is read back with ``verify`` (Python's own writers raise on a short write)."""
    from .errors import OutputError
    try:
        size = os.stat(tmp).st_size
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        vfs = os.statvfs(os.path.dirname(tmp) or ".")
    except OSError as exc:
        raise OutputError(f"cannot write: {_reason(exc)}", target) from None
    if size == 0:
        raise OutputError("nothing was written (is the disk full?)", target)
    free_blocks = vfs.f_bfree if os.geteuid() == 0 else vfs.f_bavail
    if vfs.f_blocks and free_blocks == 0 and verify is not None:
        try:
            verify(tmp)
        except Exception:
            raise OutputError("no space left on device (the output was cut short)",
                              target) from None


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike, suffix: str | None = None,
                verify=None) -> Iterator[str]:
    """Yield a temporary path for ``target``; commit it when the command succeeds.

    On any exception the temporary file is removed and the target is untouched,
    so Make never trusts a half-written output.  ``suffix`` keeps the extension
    (libraries that pick the codec by extension need it).  A symlink target is
    written through to the file it names; a character device or FIFO is written
    in place (the temporary file then lives in the system's temp folder).
    Write failures raise one-line OutputErrors naming ``target``.  ``verify(tmp)``
    reads a finished file back (raising if damaged) when the disk filled up.
    """
    from .errors import OutputError, UsageProblem
    target = os.fspath(target)
    final, mode = _resolve(target)
    if _RUN is not None:
        ident = _identity(target)
        for inp, other in _RUN.inputs:
            if _same(ident, _now(inp, other)):
                raise UsageProblem(_INPUT_IS_OUTPUT, target)
    if _PENDING:
        ident = _identity(target)
        for _, staged, _ in _PENDING:
            if _same(ident, _identity(staged)):
                raise UsageProblem("two outputs go to one file; give each its own name", target)
    if suffix is None:
        suffix = "".join(Path(final).suffixes[-1:])
    folder = (os.path.dirname(final) or ".") if mode == "replace" else tempfile.gettempdir()
    name = os.path.basename(final)
    remove_stale_temps(folder, name)
    tmp = None
    try:
        try:
            with _stop_signals_held():
                fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(name, folder), suffix=suffix,
                                           dir=folder)
                _LIVE_TEMPS.add(tmp)
                os.close(fd)
        except OSError as exc:
            raise OutputError(f"cannot create a file in {folder!r}: {_reason(exc)}",
                              target) from None
        try:
            yield tmp
        except OSError as exc:
            raise OutputError(f"cannot write: {_reason(exc)}", target) from None
        _check_written(tmp, target, verify)
        try:   # a file written over keeps its permissions; a new one gets the umask's
            mode_bits = stat.S_IMODE(os.stat(final).st_mode) if mode == "replace" else None
        except OSError:
            mode_bits = None
        if mode_bits is None:
            umask = os.umask(0)
            os.umask(umask)
            mode_bits = 0o666 & ~umask   # mkstemp makes 0600
        os.chmod(tmp, mode_bits)
        if _PENDING is not None:
            _PENDING.append((tmp, final, mode))
        else:
            _commit(tmp, final, mode)
    except BaseException:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            _LIVE_TEMPS.discard(tmp)
        raise


def write_text_atomic(target: str, text: str) -> None:
    """Write text to ``target`` atomically, or to stdout when target is ``-``
    (:func:`write_stdout`: held until the command succeeds)."""
    if target == "-":
        write_stdout(text)
        return
    with atomic_path(target) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)


# ----------------------------------------------------------------------------- stdout

#: What the error line names when stdout cannot take an output.
STDOUT_NAME = "stdout"


def check_stdout() -> None:
    """Before any work: a one-line OutputError when there is no stdout to write to
    (``-o - >&-``: the CLI points a closed descriptor 1 at /dev/null, and sys.stdout
    is None); BrokenPipeError (exit 141) when stdout is a pipe whose reader is gone."""
    from .errors import OutputError
    stream = sys.stdout
    if stream is None or getattr(stream, "closed", False):
        raise OutputError("cannot write: stdout is closed", STDOUT_NAME)
    if _reader_gone(stream):   # `... | head` that has had enough: exit 141 now, not later
        raise BrokenPipeError(errno.EPIPE, "the reader of stdout went away")


def _reader_gone(stream) -> bool:
    """True when stdout is a pipe whose reading end is closed (poll reports POLLERR)."""
    import select
    try:
        fd = stream.fileno()
        if not stat.S_ISFIFO(os.fstat(fd).st_mode) or not hasattr(select, "poll"):
            return False
        poller = select.poll()
        poller.register(fd, 0)      # POLLERR and POLLHUP are always reported
        return any(events & select.POLLERR for _, events in poller.poll(0))
    except (AttributeError, OSError, ValueError):
        return False


def write_stdout(text: str) -> None:
    """A JSON document for stdout.  Inside a command (output_transaction) it is held and
    written when the command succeeds, before its files are committed; elsewhere it is
    written now.  Either way every byte is checked (see _emit_stdout)."""
    data = text.encode("utf-8")
    if _STDOUT is not None:
        check_stdout()
        _STDOUT.append(data)
    else:
        _emit_stdout(data)


def _emit_stdout(data: bytes) -> None:
    """Write ``data`` to stdout completely or fail.

    Python's text stdout can accept a short count silently (unbuffered, as under
    PYTHONUNBUFFERED, ``write`` returns what the kernel took), which turned a full disk
    or a reader that went away mid-document into exit 0 with a cut-short output.  Here
    the bytes go to the descriptor in a loop until all are taken; a regular file behind
    stdout is synced (deferred write errors) and, on failure, cut back to its size
    before the write.  Raises BrokenPipeError when the reader went away (the CLI exits
    141), else a one-line OutputError naming ``stdout``.
    """
    from .errors import OutputError
    check_stdout()
    stream = sys.stdout
    try:
        stream.flush()                       # whatever went before goes first
    except BrokenPipeError:
        raise
    except (OSError, ValueError) as exc:
        raise OutputError(f"cannot write: {_reason(exc)}", STDOUT_NAME) from None
    try:
        fd = stream.fileno()
    except (AttributeError, OSError, ValueError):   # not a descriptor (CliRunner, StringIO)
        fd = None
    if fd is None:
        _write_stream(stream, data)
        return
    regular, restore = _stdout_file(fd)
    try:
        _write_fd(fd, data)
        if regular:
            os.fsync(fd)
    except BrokenPipeError:
        raise
    except OSError as exc:
        if restore is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, restore)
                os.lseek(fd, restore, os.SEEK_SET)
        raise OutputError(f"cannot write: {_reason(exc)}", STDOUT_NAME) from None


def _stdout_file(fd: int) -> tuple[bool, int | None]:
    """(stdout is a regular file, its size now when written at its end: a failed write
    is cut back to it, else None: a pipe, a device, a write in the middle of a file)."""
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            return False, None
        import fcntl
        at_end = (fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_APPEND
                  or os.lseek(fd, 0, os.SEEK_CUR) >= st.st_size)
        return True, (st.st_size if at_end else None)
    except (OSError, ImportError):
        return False, None


def _write_fd(fd: int, data: bytes) -> None:
    """os.write until every byte is taken; a non-blocking descriptor waits for room."""
    import select
    view = memoryview(data)
    while view:
        try:
            n = os.write(fd, view)
        except BlockingIOError:
            select.select([], [fd], [])
            continue
        if n <= 0:
            raise OSError(errno.EIO, "the output took no bytes")
        view = view[n:]


def _write_stream(stream, data: bytes) -> None:
    """The same for a stdout that is no descriptor (click's CliRunner, a StringIO)."""
    from .errors import OutputError
    try:
        buffer = getattr(stream, "buffer", None)
        if buffer is None:
            stream.write(data.decode("utf-8"))
        else:
            view = memoryview(data)
            while view:
                n = buffer.write(view)
                if n is None:          # a non-blocking raw stream that took nothing
                    continue
                if n <= 0:
                    raise OSError(errno.EIO, "the output took no bytes")
                view = view[n:]
            buffer.flush()
        stream.flush()
    except BrokenPipeError:
        raise
    except (OSError, ValueError) as exc:
        raise OutputError(f"cannot write: {_reason(exc)}", STDOUT_NAME) from None


# ----------------------------------------------------------------------------- error lines

def run_files() -> tuple[list[str], list[str]]:
    """(inputs, outputs) declared by the running command, or by the one that ended last:
    the CLI names them in error lines whose exception did not say which file it was."""
    run = _RUN if _RUN is not None else _LAST_RUN
    if run is None:
        return [], []
    return [p for p, _ in run.inputs], [p for p, _ in run.outputs]
