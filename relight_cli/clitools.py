"""Options and helpers shared by every subcommand (click and stdlib only).

Command modules import this at top level; it must stay light so that
``relight --help`` never imports torch, embree or OpenImageIO.
"""

from __future__ import annotations

import json
import os
import sys

import click


def quiet_option(func):
    return click.option("--quiet", "-q", is_flag=True,
                        help="Silence progress bars and log messages on stderr.")(func)


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


def seed_option(func):
    return click.option("--seed", type=click.IntRange(0, SEED_MAX), default=0, show_default=True,
                        help="Random seed; identical inputs and seed give identical outputs.")(func)


def output_option(text: bool = False, required: bool = True, help: str | None = None):
    """``-o/--output``; for text formats ``-`` means stdout."""
    default_help = "Output file" + (" ('-' for stdout)." if text else ".")
    return click.option("-o", "--output", type=str, required=required, help=help or default_help)


def no_clobber_option(func):
    return click.option("--no-clobber", is_flag=True,
                        help="Refuse to overwrite an existing output (exit 2).")(func)


def check_output(path: str | None, no_clobber: bool = False, text: bool = False) -> None:
    """Validate an output path before any work is done, and register it.

    Usage errors (exit 2): an empty name, a folder, a missing folder, a block
    device or socket, an output that is one of the command's inputs or outputs
    (see relight_cli.provenance.declare_output); a folder where no file can be
    created exits 1.
    """
    from .errors import UsageProblem
    from .provenance import declare_output
    if path is None:
        return
    if path == "-":
        if not text:
            raise UsageProblem("this output is binary and cannot go to stdout; give a file name")
        return
    if no_clobber and os.path.lexists(path):
        raise UsageProblem("output exists and --no-clobber was given", path)
    declare_output(path)


def preview_option(help: str):
    """``--preview PNG``: a picture of the result (relight_cli.preview), never data."""
    return click.option("--preview", default=None, metavar="PNG", help=help)


def check_preview_name(path: str | None) -> None:
    """``--preview`` must name a .png: anything else is a usage error (exit 2)."""
    from .errors import UsageProblem
    if path is not None and not path.lower().endswith(".png"):
        raise UsageProblem("--preview writes a PNG picture: name it .png", path)


def check_preview(path: str | None, no_clobber: bool = False) -> None:
    """:func:`check_preview_name`, then :func:`check_output`."""
    check_preview_name(path)
    check_output(path, no_clobber)


def check_input(path: str) -> str:
    """Fail early and clearly for a missing input or a directory given as a file."""
    from .errors import DataError
    if path.startswith("builtin:"):
        return path
    if not os.path.exists(path):
        raise DataError("no such file", path)
    if os.path.isdir(path):
        raise DataError("is a directory, expected a file", path)
    if not os.access(path, os.R_OK):
        raise DataError("file is not readable (permissions)", path)
    from .provenance import declare_input
    declare_input(path)
    return path


def log(message: str, quiet: bool = False) -> None:
    """A log line on stderr (never stdout, which may carry data)."""
    if not quiet:
        click.echo(message, err=True)


def progress(iterable=None, total=None, desc: str = "", quiet: bool = False):
    """A tqdm progress bar on stderr, silent under --quiet."""
    from tqdm import tqdm
    return tqdm(iterable, total=total, desc=desc, disable=quiet, file=sys.stderr,
                leave=False, dynamic_ncols=True)


def dumps_json(obj) -> str:
    """JSON with stable key order and round-trippable floats."""
    return json.dumps(obj, indent=2, sort_keys=False, allow_nan=False) + "\n"


def parse_size(text: str, what: str = "--size") -> tuple[int, int]:
    """Parse 'WxH' (or a single N meaning N) into (width, height)."""
    from .errors import UsageProblem
    try:
        if "x" in text.lower():
            w, h = text.lower().split("x")
            w, h = int(w), int(h)
        else:
            w = h = int(text)
    except ValueError:
        raise UsageProblem(f"{what} must look like WxH or N, got {text!r}") from None
    if w <= 0 or h <= 0 or w > 65536 or h > 65536:
        raise UsageProblem(f"{what} must be positive and at most 65536, got {text!r}")
    return w, h


def parse_vector(text: str, n: int, what: str, minimum: float | None = None) -> tuple[float, ...]:
    """``"x,y,z"`` → n finite floats (each ≥ ``minimum`` when given); else a usage error."""
    from .errors import UsageProblem
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
