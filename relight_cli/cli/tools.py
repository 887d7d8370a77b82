"""Options and helpers shared by every subcommand (click and stdlib only).

Command modules import this at top level; it must stay light so that
``relight --help`` never imports torch, embree or OpenImageIO.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys

import click


def _quiet(ctx, param, value):
    """-q after the subcommand, or before it (``relight -q CMD``): either silences."""
    from ..progress import set_command
    names = []
    while ctx.parent is not None:
        names.append(ctx.info_name)
        ctx = ctx.parent
    set_command(" ".join(["relight", *reversed(names)]))
    return bool(value or ctx.meta.get("relight.quiet"))


def _debug(ctx, param, value):
    """--debug after the subcommand, or before it (``relight --debug CMD``): either shows
    tracebacks and library warnings; without it library warnings are silenced (they would
    come before the one error line or mix with progress)."""
    import warnings
    if value:
        ctx.meta["relight.debug"] = True
    if not ctx.meta.get("relight.debug"):
        warnings.simplefilter("ignore")


def quiet_option(func):
    """``-q/--quiet`` and ``--debug``, accepted after the subcommand as before it."""
    func = click.option("--debug", is_flag=True, expose_value=False, callback=_debug,
                        help="Show a traceback for errors and library warnings (also "
                             "accepted before the subcommand: relight --debug CMD).")(func)
    return click.option("--quiet", "-q", is_flag=True, callback=_quiet,
                        help="Silence progress and log messages on stderr (also accepted "
                             "before the subcommand: relight -q CMD).")(func)


def renamed_option(old: str, new: str, takes_value: bool = True, why: str = ""):
    """A hidden ``old`` option that refuses itself naming ``new`` (a one-line usage
    error, exit 2): a renamed option keeps no silent alias, so a name means one thing."""
    def refuse(ctx, param, value):
        if value is None or value is False:
            return None
        raise click.UsageError(f"{old} was renamed {new}" + (f"; {why}" if why else ""), ctx)
    return click.option(old, "renamed_" + old.lstrip("-").replace("-", "_"), hidden=True,
                        is_flag=not takes_value, expose_value=False, callback=refuse,
                        is_eager=True)


SEED_MAX = 2**32 - 1  # numpy's SeedSequence and torch accept 0..2^32-1 everywhere


class FiniteFloat(click.FloatRange):
    """A float option that is finite (never NaN or ±Inf) and within its range.

    Every float option of every command uses this type, so that ``nan``,
    ``inf`` and out-of-range values are usage errors (exit 2) naming the option,
    before any work.  ``min_open``/``max_open`` exclude the bounds.
    """

    name = "float"

    def convert(self, value, param, ctx):
        number = click.FLOAT.convert(value, param, ctx)
        if not _finite(number):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return super().convert(number, param, ctx)

    def _describe_range(self) -> str:
        """``0<x<=10`` as click writes it, numbers in short form; ``finite`` if unbounded."""
        lo = None if self.min is None else f"{self.min:g}"
        hi = None if self.max is None else f"{self.max:g}"
        if lo is None and hi is None:
            return "finite"
        if lo is None:
            return f"x{'<' if self.max_open else '<='}{hi}"
        if hi is None:
            return f"x{'>' if self.min_open else '>='}{lo}"
        return f"{lo}{'<' if self.min_open else '<='}x{'<' if self.max_open else '<='}{hi}"


class ShadowStrength(click.ParamType):
    """``auto`` or a finite number in [0, 1] (``relight --shadow-strength``)."""

    name = "auto|s"

    def convert(self, value, param, ctx):
        if isinstance(value, str) and value.strip().lower() == "auto":
            return "auto"
        return FiniteFloat(0, 1).convert(value, param, ctx)


class SquareSize(click.ParamType):
    """A square size option: ``N`` or ``NxN`` → N; a non-square ``WxH`` is a usage error
    (the thing it sizes is square), so every size option takes the same syntax."""

    name = "N"

    def __init__(self, minimum: int | None = None, maximum: int | None = None):
        self.minimum, self.maximum = minimum, maximum

    def convert(self, value, param, ctx):
        from ..errors import UsageProblem
        what = param.opts[0] if param is not None and param.opts else "size"
        if isinstance(value, int):
            w = h = value
        else:
            try:
                w, h = parse_size(str(value), what, minimum=-(2**31), maximum=2**31)
            except UsageProblem as exc:
                self.fail(exc.message, param, ctx)
        if w != h:
            self.fail(f"{value!r} is not square: this size is N or NxN", param, ctx)
        if ((self.minimum is not None and w < self.minimum)
                or (self.maximum is not None and w > self.maximum)):
            self.fail(f"{value!r} is not in the range {self.minimum}..{self.maximum}", param, ctx)
        return w


def seed_option(func):
    return click.option("--seed", type=click.IntRange(0, SEED_MAX), default=0, show_default=True,
                        help="Random seed; identical inputs and seed give identical outputs.")(func)


def colour_space_option(func):
    """``--colour-space auto|srgb|linear``: the space of the input Gaussian PLYs' colours
    (formats/gaussians_ply.md); they are decoded to linear once, on read."""
    return click.option("--colour-space", "colour_space",
                        type=click.Choice(["auto", "srgb", "linear"]), default="auto",
                        show_default=True,
                        help="Colour space of the input PLYs' colours, decoded to linear on "
                             "read: srgb (display-referred, as 3DGS training fits them to "
                             "photographs), linear (as stored), or auto: linear for PLYs "
                             "relight wrote (they say so in their header), srgb for others. "
                             "Meshes, hands and builtin: objects are linear.")(func)


def output_option(text: bool = False, required: bool = True, help: str | None = None):
    """``-o/--output``; for text formats ``-`` means stdout."""
    default_help = "Output file" + (" ('-' for stdout)." if text else ".")
    return click.option("-o", "--output", type=str, required=required, help=help or default_help)


def no_clobber_option(func):
    return click.option("--no-clobber", is_flag=True,
                        help="Refuse to overwrite an existing output (exit 2).")(func)


#: What an output holds -> (the extensions its name may end with, what to call it).
OUTPUT_KINDS = {
    "exr": ((".exr",), "an OpenEXR image"),
    "png": ((".png",), "a PNG preview"),
    "json": ((".json",), "a JSON file"),
    "jsonl": ((".jsonl",), "a JSON Lines file"),
    "npz": ((".npz",), "an npz archive"),
    "ply": ((".ply",), "a Gaussians PLY"),
    "pt": ((".pt", ".pth"), "a checkpoint"),
    "video": ((".webp", ".png"), "an animated WebP or PNG"),
}
TEXT_KINDS = ("json", "jsonl")


def check_output(path: str | None, no_clobber: bool = False, text: bool = False,
                 kind: str | None = None, what: str = "-o") -> None:
    """Validate an output path before any work is done, and register it.

    Usage errors (exit 2): an empty name, a folder, a missing folder, a block
    device or socket, an output that is one of the command's inputs or outputs
    (see relight_cli.fileio.declare_output), a name whose extension is not
    ``kind``'s (see OUTPUT_KINDS; character devices and FIFOs, which have no
    extension, are exempt), ``-`` for anything but JSON; a folder where no file
    can be created exits 1.
    """
    from ..errors import UsageProblem
    from ..fileio import declare_output
    if path is None:
        return
    text = text or kind in TEXT_KINDS
    if path == "-":
        if not text:
            raise UsageProblem(f"{what} is binary and cannot go to stdout ('-' is for JSON "
                               f"outputs); give a file name")
        from ..fileio import check_stdout
        check_stdout()   # `-o - >&-`: one line (stdout), exit 1, before any work
        return
    if no_clobber and os.path.lexists(path):
        raise UsageProblem("output exists and --no-clobber was given", path)
    declare_output(path)
    if kind is not None:
        check_extension(path, kind, what)


def preview_exposure_option(func):
    """``--preview-exposure S``: one fixed tone-mapping scale for every preview of a run
    (relight's hand and Gaussian modes; formats/preview.md)."""
    return click.option(
        "--preview-exposure", type=FiniteFloat(0, 1e12, min_open=True), default=None,
        metavar="S",
        help="A fixed scale for --preview's tone mapping (Reinhard after × S), the same for "
             "every picture: renders compared side by side, or a sequence's frames, show "
             "their change [default: each picture its own, key 0.18 over its "
             "log-average].")(func)


def preview_option(help: str):
    """``--preview PNG``: a picture of the result (relight_cli.preview), never data;
    commands check it with ``check_output(path, no_clobber, kind="png", what="--preview")``."""
    return click.option("--preview", default=None, metavar="PNG", help=help)


def check_extension(path: str, kind: str, what: str = "-o") -> None:
    """A usage error unless ``path`` ends with one of ``kind``'s extensions (any case);
    an existing character device or FIFO (``/dev/null``, a named pipe) passes."""
    import stat

    from ..errors import UsageProblem
    extensions, noun = OUTPUT_KINDS[kind]
    if path.lower().endswith(extensions):
        return
    try:
        mode = os.stat(path).st_mode
    except OSError:
        mode = 0
    if stat.S_ISCHR(mode) or stat.S_ISFIFO(mode):
        return
    raise UsageProblem(f"{what} is {noun} (name it {' or '.join(extensions)})", path)


#: Names of inputs that may be FIFOs or devices (read once, bounded: formats._common.read_text).
STREAM_INPUT_EXTENSIONS = (".json", ".jsonl")


def check_input(path: str, stdin: str | None = None) -> str:
    """Fail early and clearly for a missing input or a directory given as a file.

    ``-`` reads stdin, for JSON inputs only: ``stdin`` names the input (e.g.
    ``"--lights"``) so that two inputs both given as ``-`` are a usage error.

    A FIFO, device or socket is refused (exit 1) unless the input is JSON (``stdin``
    given, or a name ending .json/.jsonl): binary readers (EXR, PLY, npz, checkpoints)
    would block on a FIFO with no writer or read /dev/zero without end."""
    from ..errors import DataError, UsageProblem
    if path.startswith("builtin:"):
        return path
    if path == "-":
        if stdin is None:
            raise UsageProblem("this input cannot come from stdin ('-' reads JSON inputs "
                               "only); give a file name")
        from ..fileio import claim_stdin
        claim_stdin(stdin)
        return path
    if not os.path.exists(path):
        raise DataError("no such file", path)
    if os.path.isdir(path):
        raise DataError("is a directory, expected a file", path)
    special = _special_kind(path)
    if special and stdin is None and not path.lower().endswith(STREAM_INPUT_EXTENSIONS):
        raise DataError(f"is a {special}, not a regular file (this input is read as a file)",
                        path)
    if not os.access(path, os.R_OK):
        raise DataError("file is not readable (permissions)", path)
    from ..fileio import declare_input
    declare_input(path)
    return path


def _special_kind(path: str) -> str | None:
    """What a non-regular file is ("FIFO", "character device", ...), None for a regular one."""
    import stat
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    for test, name in ((stat.S_ISFIFO, "FIFO (named pipe)"), (stat.S_ISCHR, "character device"),
                       (stat.S_ISBLK, "block device"), (stat.S_ISSOCK, "socket")):
        if test(mode):
            return name
    return None if stat.S_ISREG(mode) else "special file"


def log(message: str, quiet: bool = False) -> None:
    """A log line on stderr (never stdout, which may carry data).  A ``wrote …`` line is
    said once the command's outputs are committed (relight_cli.fileio.after_commit), so
    a run that fails after staging an output says only its one error line.  Any other line
    (``read …``, notes) is held while a command runs, until its work shows progress or it
    succeeds (:func:`held_log_lines`), so a run refused after reading some of its inputs
    also says only its error line; the lines keep their order."""
    if quiet:
        return
    if message.startswith("wrote "):
        from relight_cli.fileio import after_commit
        if after_commit(lambda: _say(message)):
            return
        _say(message)
    elif _HELD is not None:
        _HELD.append(message)
    else:
        click.echo(message, err=True)


# The running command's log lines not said yet (None: none held, lines go out at once).
_HELD: list[str] | None = None


@contextlib.contextmanager
def held_log_lines():
    """Hold the log lines of the command run in this block (the relight group's invoke):
    said in order before the first progress is shown (the inputs are read and checked,
    the work has begun; from then on lines go out as they come), before the first line
    said at once (``wrote …``), or when the block ends without an error; never said when
    it fails, whose stderr is then its one error line (DESIGN.md, "How every command
    behaves").  A deliberate exit (``ctx.exit``) says them too."""
    global _HELD
    if _HELD is not None:   # nested: the outer block decides
        yield
        return
    from ..progress import before_shown
    _HELD = []
    before_shown(release_log_lines)
    try:
        yield
    except click.exceptions.Exit:
        release_log_lines()
        raise
    else:
        release_log_lines()
    finally:
        _HELD = None
        before_shown(None)


def release_log_lines() -> None:
    """Say the held log lines now, and hold no more (the block of :func:`held_log_lines`)."""
    global _HELD
    held, _HELD = _HELD, None
    for message in held or ():
        click.echo(message, err=True)


def _say(message: str) -> None:
    release_log_lines()
    click.echo(message, err=True)


def progress(iterable=None, total=None, desc: str = "", quiet: bool = False, **kwargs):
    """Progress on stderr: a tqdm bar on a terminal, else a plain line every few
    seconds and a final one (relight_cli.progress); silent under --quiet."""
    from ..progress import progress as make
    return make(iterable, total=total, desc=desc, quiet=quiet, **kwargs)


def dumps_json(obj) -> str:
    """JSON with stable key order and round-trippable floats."""
    return json.dumps(obj, indent=2, sort_keys=False, allow_nan=False) + "\n"


def parse_size(text: str, what: str = "--size", single: bool = True, minimum: int = 1,
               maximum: int = 65536) -> tuple[int, int]:
    """Parse ``WxH`` (width first, as OpenImageIO writes sizes), or a single ``N``
    meaning N×N where ``single``, into (width, height); else a usage error naming
    ``what``.  Every size option of every command goes through here."""
    from ..errors import UsageProblem
    form = "WxH or N" if single else "WxH"
    parts = text.strip().lower().split("x")
    try:
        if len(parts) == 2:
            w, h = int(parts[0]), int(parts[1])
        elif len(parts) == 1 and single:
            w = h = int(parts[0])
        else:
            raise ValueError(text)
    except ValueError:
        raise UsageProblem(f"{what} must look like {form} (width x height, e.g. 32x16), "
                           f"got {text!r}") from None
    if not (minimum <= w <= maximum and minimum <= h <= maximum):
        raise UsageProblem(f"{what} must be {minimum} to {maximum} on each side, got {text!r}")
    return w, h


def parse_env_res(text: str, what: str = "--env-res") -> tuple[int, int]:
    """``WxH`` of a lat-long integration grid → (width, height), at least 2x2 and at
    least as wide as tall: an old ``HxW`` spelling (``16x32``, from before sizes were
    written width first everywhere) is a usage error that says the right one."""
    from ..errors import UsageProblem
    w, h = parse_size(text, what, single=False, minimum=2, maximum=8192)
    if w < h:
        raise UsageProblem(f"{what} is WxH, width first (e.g. 32x16): a lat-long grid is at "
                           f"least as wide as tall, got {text!r}; did you mean {h}x{w}?")
    if h > 4096:
        raise UsageProblem(f"{what} height must be at most 4096, got {text!r}")
    return w, h


def parse_vector(text: str, n: int, what: str, minimum: float | None = None) -> tuple[float, ...]:
    """``"x,y,z"`` → n finite floats (each ≥ ``minimum`` when given); else a usage error."""
    from ..errors import UsageProblem
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise UsageProblem(f"{what} must be {n} comma-separated numbers, got {text!r}") from None
    if len(values) != n or not all(map(_finite, values)):
        raise UsageProblem(f"{what} must be {n} finite comma-separated numbers, got {text!r}")
    if minimum is not None and min(values) < minimum:
        raise UsageProblem(f"{what} values must be ≥ {minimum:g}, got {text!r}")
    return values


def _finite(x: float) -> bool:
    return x == x and abs(x) != float("inf")


def given_options(ctx) -> dict:
    """The options given on the command line (not defaulted): parameter name → its flag."""
    from click.core import ParameterSource
    return {p.name: p.opts[0] for p in ctx.command.params
            if isinstance(p, click.Option) and ctx.params.get(p.name) is not None
            and ctx.get_parameter_source(p.name) == ParameterSource.COMMANDLINE}


def refuse_given(ctx, names, message: str) -> None:
    """A usage error (exit 2) naming the given options among ``names`` (parameter names):
    ``message`` with ``{}`` standing for them, e.g. "{} only apply to --model physical"."""
    from relight_cli.errors import UsageProblem
    given = given_options(ctx)
    named = [flag for name, flag in given.items() if name in set(names)]
    if named:
        raise UsageProblem(message.format(", ".join(named)))
