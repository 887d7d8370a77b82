"""The ``relight`` click group: one registry, lazy subcommands, one error path.

``relight --help`` imports every command module for its short help, so command
modules import only click and the standard library at module level; torch,
embree and OpenImageIO are imported inside the callbacks.
"""

from __future__ import annotations

import importlib
import signal
import sys
import traceback
import warnings

import click

from .. import __version__
from ..errors import RelightError

# name -> "module:attribute"; the only place a subcommand is registered.
COMMANDS: dict[str, str] = {
    "bake-features": "relight_cli.commands.bake_features:command",
    "camera": "relight_cli.commands.camera:command",
    "dgsm-build": "relight_cli.commands.dgsm_build:command",
    "distill": "relight_cli.commands.distill:command",
    "envmap": "relight_cli.commands.envmap:command",
    "fit-geometry": "relight_cli.commands.fit_geometry:command",
    "metrics": "relight_cli.commands.metrics:command",
    "personalize": "relight_cli.commands.personalize:command",
    "relight": "relight_cli.commands.relight:command",
    "sh-probe": "relight_cli.commands.sh_probe:command",
    "synth-capture": "relight_cli.commands.synth_capture:command",
    "train-teacher": "relight_cli.commands.train_teacher:command",
}


class RelightGroup(click.Group):
    """A click group that loads subcommands on demand and owns the error path."""

    def list_commands(self, ctx):
        return sorted(COMMANDS)

    def get_command(self, ctx, name):
        target = COMMANDS.get(name)
        if target is None:
            return None
        module_name, attr = target.split(":")
        return getattr(importlib.import_module(module_name), attr)

    def invoke(self, ctx):
        from ..fileio import output_transaction
        from .tools import held_log_lines
        try:
            # Library warnings (numpy, torch, pygltflib...) would come before the one error
            # line or mix with progress: the subcommand's --debug option (tools.quiet_option,
            # which also sees `relight --debug CMD`) silences them inside this block unless
            # --debug was given.  Log lines are held until the work shows progress or the
            # outputs are committed (tools.held_log_lines; outside the transaction, so that
            # a failed commit drops them too): a failing run says only its error line.
            with held_log_lines(), output_transaction(), warnings.catch_warnings():
                return super().invoke(ctx)
        except BrokenPipeError:
            _broken_pipe()
        except RelightError as exc:
            _report(ctx, exc, exc.exit_code)
        except click.exceptions.Exit:
            raise
        except click.ClickException:
            raise
        except click.Abort:
            raise
        except (KeyboardInterrupt, Terminated) as exc:
            _stopped(ctx, exc)
        except MemoryError as exc:
            where = _input_in_traceback(exc)
            if where is not None:   # e.g. an .npy whose header declares a huge shape
                _report(ctx, RelightError("out of memory reading this input (damaged, or "
                                          "larger than this machine can hold)", where), 1)
            _report(ctx, RelightError("out of memory; try a smaller resolution or fewer inputs"), 1)
        except OSError as exc:   # a reader's open() or read(): permissions, a folder, EIO...
            stop = _stop_in_chain(exc)
            if stop is not None:
                _stopped(ctx, stop)
            _report(ctx, _os_error(exc), 1)
        except Exception as exc:  # a bug, not a user error: still one line unless --debug
            stop = _stop_in_chain(exc)
            if stop is not None:   # a library's clean-up failed after the signal (zipfile)
                _stopped(ctx, stop)
            library = _library_message(exc)
            if library is not None:
                _report(ctx, library, 1)
            _report(ctx, RelightError(f"internal error: {type(exc).__name__}: {exc}",
                                      hint="rerun with --debug for a traceback and report it"), 1)

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        args = list(sys.argv[1:] if args is None else args)
        from ..provenance import set_command_line
        set_command_line(args)
        try:
            return self._main(args, prog_name, complete_var, standalone_mode, **extra)
        finally:
            # the command is over: engine code called from Python afterwards (in the same
            # process, e.g. after CliRunner) records no command line of its own
            set_command_line(None)

    def _main(self, args, prog_name, complete_var, standalone_mode, **extra):
        if not standalone_mode:
            return super().main(args, prog_name or "relight", complete_var, False, **extra)
        try:
            rv = super().main(args, prog_name or "relight", complete_var, False, **extra)
        except BrokenPipeError:   # e.g. `relight --help | head -1`
            _broken_pipe()
        except click.UsageError as exc:
            where = exc.ctx.command_path if exc.ctx is not None else "relight"
            hint = f" (see '{where} --help')" if exc.ctx is not None else ""
            click.echo(f"{where}: error: {exc.format_message()}{hint}", err=True)
            sys.exit(2)
        except click.ClickException as exc:
            click.echo(f"relight: error: {exc.format_message()}", err=True)
            sys.exit(exc.exit_code)
        except click.Abort:
            click.echo("relight: aborted", err=True)
            sys.exit(1)
        sys.exit(rv if isinstance(rv, int) else 0)


#: Exit status when stdout (or stderr) is a pipe whose reader went away (`relight ... -o - |
#: head -c 10`): 128 + SIGPIPE, what the shell reports for a program killed by SIGPIPE (as git
#: exits); no message, no traceback, no output committed.
EXIT_BROKEN_PIPE = 141


def _broken_pipe():
    """The reader of stdout went away: exit quietly (Python's documented recipe: point
    stdout at /dev/null so that the interpreter's final flush cannot fail again)."""
    import os
    devnull = os.open(os.devnull, os.O_WRONLY)
    for stream in (sys.stdout, sys.stderr):
        try:
            os.dup2(devnull, stream.fileno())
        except (AttributeError, OSError, ValueError):   # not a real file (CliRunner)
            pass
    sys.exit(EXIT_BROKEN_PIPE)


class Terminated(BaseException):
    """SIGTERM/SIGHUP arrived: unwinds like Ctrl-C, so temporary files are removed."""

    def __init__(self, signal_number: int):
        super().__init__(signal_number)
        self.signal_number = signal_number
        self.signal_name = signal.Signals(signal_number).name


_STOP_SIGNALS = ("SIGTERM", "SIGHUP")


def _terminate(signal_number, frame):
    from ..fileio import defer_stop_signal
    if defer_stop_signal(signal_number):   # raised again once the temporary file is known
        return
    # `timeout` signals the process and then its whole group: the second copy must
    # not interrupt the clean-up (or the interpreter's shutdown) the first one started.
    for name in _STOP_SIGNALS:
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_IGN)
    raise Terminated(signal_number)


def _interrupt(signal_number, frame):
    """Ctrl-C: KeyboardInterrupt, as Python's own handler, but held like SIGTERM."""
    from ..fileio import defer_stop_signal
    if not defer_stop_signal(signal_number):
        raise KeyboardInterrupt


def _stop_in_chain(exc: BaseException):
    """The KeyboardInterrupt or Terminated an exception was raised while handling, if any."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, (KeyboardInterrupt, Terminated)):
            return exc
        exc = exc.__context__
    return None


def _stopped(ctx, exc: BaseException):
    # Objects a signal left half-done (a zipfile member being written) complain when
    # collected at exit; the one line below says what happened.
    sys.unraisablehook = lambda unraisable: None
    if isinstance(exc, Terminated):
        click.echo(f"relight {_subcommand(ctx)}: terminated by signal {exc.signal_name}",
                   err=True)
        sys.exit(128 + exc.signal_number)
    click.echo(f"relight {_subcommand(ctx)}: interrupted", err=True)
    sys.exit(130)


def _subcommand(ctx) -> str:
    return ctx.invoked_subcommand or ctx.info_name or "relight"


def _report(ctx, exc: RelightError, code: int):
    debug = ctx.params.get("debug") or ctx.meta.get("relight.debug")
    if debug:
        traceback.print_exc()
    if exc.path is not None and _is_placeholder(exc.path):
        # "(<in memory>)" says nothing: name the inputs the bad data came from
        inputs, _ = _run_files()
        if inputs:
            exc.path = ", ".join(inputs)
    click.echo(f"relight {_subcommand(ctx)}: error: {_one_line(str(exc))}", err=True)
    sys.exit(code)


# ----------------------------------------------------------------------------- error lines
# Exceptions that reach the top level without naming their file (a library's or a
# reader's own), turned into the one line `relight CMD: error: WHAT (FILE)`.


def _one_line(text: str) -> str:
    """One printable line: a library's message may hold newlines, control bytes, or raw
    bytes decoded with replacement."""
    import re
    lines = [line.strip() for line in re.split(r"[\r\n]+", str(text).replace("\t", " "))
             if line.strip()]
    text = " ".join(lines)
    return "".join(c if c.isprintable() else "\ufffd" for c in text)


def _is_placeholder(path: str) -> bool:
    return path.startswith("<") and path.endswith(">")


def _run_files() -> tuple[list[str], list[str]]:
    from ..fileio import run_files
    return run_files()


def _same_file(a, b) -> bool:
    import os
    try:
        return os.path.realpath(os.fspath(a)) == os.path.realpath(os.fspath(b))
    except (TypeError, ValueError):
        return False


def _is_reader(frame) -> bool:
    """A frame of a file reader: a format module, or a function named read*/load*."""
    module = str(frame.f_globals.get("__name__", ""))
    name = frame.f_code.co_name.lstrip("_")
    return module.startswith("relight_cli.formats.") or name.startswith(("read", "load"))


def _input_in_traceback(exc: BaseException) -> str | None:
    """The input file (one the command declared: relight_cli.fileio.declare_input)
    that the innermost reader frame of ``exc``'s traceback was given: the file a reader
    was reading when it failed without saying which (a MemoryError from an .npy header,
    an OSError without a file name).  None when no reader frame holds one."""
    import os
    inputs, _ = _run_files()
    if not inputs:
        return None
    frames = []
    tb = exc.__traceback__
    while tb is not None:
        frames.append(tb.tb_frame)
        tb = tb.tb_next
    for frame in reversed(frames):
        if not _is_reader(frame):
            continue
        for value in list(frame.f_locals.values()):
            if not isinstance(value, (str, os.PathLike)):
                continue
            value = os.fspath(value)
            if not isinstance(value, str) or not 0 < len(value) < 4096:   # not a JSON text
                continue
            for path in inputs:
                if value == path or _same_file(value, path):
                    return path
    return None


def _input_in_text(text: str) -> str | None:
    """A declared input named in a library's message (OpenImageIO writes the file name)."""
    inputs, _ = _run_files()
    for path in sorted(inputs, key=len, reverse=True):
        if path and path in text:
            return path
    return None


def _os_error(exc: OSError) -> RelightError:
    """``cannot read: permission denied (FILE)`` for an OSError a reader let through
    (PermissionError, IsADirectoryError, EIO...); ``cannot write`` for an output."""
    import errno
    import os
    reason = (exc.strerror or str(exc) or type(exc).__name__).lower()
    if exc.errno == errno.ENOSPC:
        reason = "no space left on device"
    name = exc.filename
    if name is None:
        where = _input_in_traceback(exc)
        if where is not None:
            return RelightError(f"cannot read: {reason}", where)
        return RelightError(f"input/output error: {reason}")
    name = os.fsdecode(name) if isinstance(name, bytes) else str(name)
    from ..fileio import TEMP_MARK
    _, outputs = _run_files()
    writing = TEMP_MARK in os.path.basename(name) or any(_same_file(name, o) for o in outputs)
    return RelightError(f"cannot {'write' if writing else 'read'}: {reason}", name)


def _library_message(exc: Exception) -> RelightError | None:
    """A library's error text that Python could not decode (OpenImageIO's geterror() on a
    damaged EXR holds raw header bytes: UnicodeDecodeError), decoded with replacement:
    one line naming the input it is about, or None when no input can be named."""
    if not isinstance(exc, UnicodeDecodeError) or not isinstance(exc.object, (bytes, bytearray)):
        return None
    import re
    text = bytes(exc.object).decode("utf-8", "replace")
    first = next((line for line in re.split(r"[\r\n]+", text) if line.strip()), "")
    where = _input_in_text(first) or _input_in_traceback(exc)
    if where is None:
        return None
    first = first.replace(f"({where})", "").replace(f'"{where}"', "").replace(where, "")
    first = re.sub(r"\s+:", ":", " ".join(first.split())).strip(" :")
    return RelightError(f"unreadable file: {first[:200] or 'undecodable library message'}",
                        where)


@click.group(cls=RelightGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="relight")
@click.option("--debug", is_flag=True,
              help="Show a traceback for errors and library warnings (for bug reports); "
                   "also accepted after the subcommand.")
@click.option("--quiet", "-q", is_flag=True,
              help="Silence progress and log messages on stderr; also accepted after the "
                   "subcommand.")
@click.pass_context
def cli(ctx, debug, quiet):
    """Relight articulated hands and 3D Gaussian avatars.

    Each subcommand reads and writes documented file formats (see formats/ and
    the man pages), so pipelines chain them in shell scripts and Make.

    \b
    Conventions of every subcommand:
      sizes are WxH (width first, as OpenImageIO writes them), or N for NxN;
      '-' reads a JSON input from stdin (one per command line), and -o -
      writes a JSON output to stdout; binary outputs need a file name whose
      extension says what it is (.exr .png .json .npz .ply .pt);
      progress is a bar on a terminal, else a plain line every few seconds;
      a closed stdout pipe (... | head) exits quietly with status 141, a
      full one (disk, /dev/full) with 1, and no file is committed;
      -q and --debug go before or after the subcommand; an old spelling of a
      renamed option (synth-capture --lights/--res, relight --t-max,
      bake-features --frames) is refused, naming the new one.
    """
    ctx.meta["relight.debug"] = debug
    ctx.meta["relight.quiet"] = quiet


def _fill_closed_standard_descriptors():
    """Point a closed stdin/stdout/stderr (``relight ... >&-``) at /dev/null.

    Python then has no sys.stdout (``-o -`` fails with one line before any work), and
    the next file opened can never become descriptor 1: a library printing on stdout, or
    a write meant for stdout, would otherwise land in that file."""
    import os
    for fd, flags in ((0, os.O_RDONLY), (1, os.O_WRONLY), (2, os.O_WRONLY)):
        try:
            os.fstat(fd)
            continue
        except OSError:
            pass
        try:
            new = os.open(os.devnull, flags)
        except OSError:
            continue
        if new != fd:
            os.dup2(new, fd)
            os.close(new)


def main():  # console-script entry point
    _fill_closed_standard_descriptors()
    # `timeout`, CI runners and process managers stop jobs with SIGTERM (or SIGHUP):
    # clean up exactly as for Ctrl-C instead of dying with temporary files left.
    for name in _STOP_SIGNALS:
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), _terminate)
    signal.signal(signal.SIGINT, _interrupt)
    try:
        cli.main()
    except Terminated as exc:  # before or after a subcommand ran
        sys.exit(128 + exc.signal_number)
