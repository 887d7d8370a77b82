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

from . import __version__
from .errors import RelightError

# name -> "module:attribute"; the only place a subcommand is registered.
COMMANDS: dict[str, str] = {
    "bake-features": "relight_cli.commands.bake_features:command",
    "camera": "relight_cli.commands.camera:command",
    "dgsm-build": "relight_cli.commands.dgsm_build:command",
    "distill": "relight_cli.commands.distill:command",
    "envmap": "relight_cli.commands.envmap:command",
    "fit-geometry": "relight_cli.commands.fit_geometry:command",
    "metrics": "relight_cli.commands.metrics:command",
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
        from .provenance import output_transaction
        try:
            # Library warnings (numpy, torch, pygltflib...) would come before the one error
            # line or mix with progress: the subcommand's --debug option (clitools.quiet_option,
            # which also sees `relight --debug CMD`) silences them inside this block unless
            # --debug was given.
            with output_transaction(), warnings.catch_warnings():
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
        except MemoryError:
            _report(ctx, RelightError("out of memory; try a smaller resolution or fewer inputs"), 1)
        except Exception as exc:  # a bug, not a user error: still one line unless --debug
            stop = _stop_in_chain(exc)
            if stop is not None:   # a library's clean-up failed after the signal (zipfile)
                _stopped(ctx, stop)
            _report(ctx, RelightError(f"internal error: {type(exc).__name__}: {exc}",
                                      hint="rerun with --debug for a traceback and report it"), 1)

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        args = list(sys.argv[1:] if args is None else args)
        from .provenance import set_command_line
        set_command_line(args)
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
    from .provenance import defer_stop_signal
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
    from .provenance import defer_stop_signal
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
    click.echo(f"relight {_subcommand(ctx)}: error: {exc}", err=True)
    sys.exit(code)


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
      a closed stdout pipe (... | head) exits quietly with status 141;
      -q and --debug go before or after the subcommand; an old spelling of a
      renamed option (synth-capture --lights/--res, relight --t-max,
      bake-features --frames) is refused, naming the new one.
    """
    ctx.meta["relight.debug"] = debug
    ctx.meta["relight.quiet"] = quiet


def main():  # console-script entry point
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
