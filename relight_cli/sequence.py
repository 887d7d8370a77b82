"""The one frame grammar: which frames a command works on, and where each frame's files go.

Every command that works on a motion takes the same two options (as oiiotool's ``--frames``
works in any command), and parses them here, once:

    --frame K               one frame of the recording (outputs are plain file names)
    --frames all|A:B[:S]    a sequence in one process: every frame, or the frames A, A+S, …
                            before B (a Python slice, B exclusive and clipped to the
                            recording; A or B may be empty: ``:10``, ``5:``)

A sequence's outputs are patterns holding ``{frame}`` (Python format syntax, e.g.
``out/frame_{frame:04d}.exr``); a command over several env maps also names ``{env}``.
:class:`OutputPattern` validates a pattern once (only those fields; an integer format spec
for ``{frame}``, a width for ``{env}``: a pattern cannot index, convert or write a control
byte), :func:`plan_outputs` expands every target and refuses two frames on one file before
any work, and :func:`write_sequence` is the writer loop with its progress bar.

A count of frames (how many to make) is not a selection: it is ``--n-frames N`` wherever a
command makes frames.  The grammar's errors are :class:`~relight_cli.errors.UsageProblem`
(exit 2); nothing here imports click.
"""

from __future__ import annotations

import re
import string
from dataclasses import dataclass

from relight_cli.errors import UsageProblem

#: The help text of ``--frames`` (commands add what their patterns hold).
FRAMES_HELP = ("Work on a sequence in one process: every frame (all) or the frames A, A+S, … "
               "before B (A:B[:S], a Python slice; B is clipped to the recording).")
#: The help text of ``--frame``.
FRAME_HELP = "One frame of the recording [default: 0]."

# A format spec a {frame} field may carry: fill 0 and/or a width, then d (e.g. 04d, 5, d).
_FRAME_SPEC = re.compile(r"^0?[0-9]{0,2}d?$")
# An {env} field's spec: an optional width (a name is text).
_ENV_SPEC = re.compile(r"^[0-9]{0,2}s?$")


@dataclass(frozen=True)
class Frames:
    """A parsed ``--frames`` value: ``all`` or a slice (``start``/``stop`` may be None)."""

    text: str
    start: int | None = None
    stop: int | None = None
    step: int | None = None
    every: bool = False

    def resolve(self, n_frames: int, what: str = "--frames") -> list[int]:
        """The frame indices this selects in a recording of ``n_frames`` frames; a
        UsageProblem when it selects none."""
        frames = list(range(n_frames))
        if not self.every:
            frames = frames[slice(self.start, self.stop, self.step)]
        if not frames:
            raise UsageProblem(f"{what} {self.text} selects no frame of a recording of "
                               f"{n_frames}")
        return frames

    def as_slice(self) -> slice:
        """The selection as a slice over frame numbers (``all``: every one)."""
        return slice(None) if self.every else slice(self.start, self.stop, self.step)


def parse_frames(text: str | None, what: str = "--frames",
                 count_option: str | None = None) -> Frames:
    """``all``, ``A:B`` or ``A:B:S`` → :class:`Frames`; a UsageProblem for anything else.
    ``count_option`` names the option that now holds a count, for a bare number given
    where a count used to be (``--frames 10`` → ``--n-frames 10``)."""
    spec = (text or "").strip()
    if spec == "all":
        return Frames(spec, every=True)
    parts = spec.split(":")
    if len(parts) == 1 and count_option is not None and spec.isdigit():
        raise UsageProblem(f"{what} selects frames (all, A:B or A:B:S); a number of frames "
                           f"is {count_option} {spec}")
    if len(parts) not in (2, 3):
        raise UsageProblem(f"{what} takes all, A:B or A:B:S, got {text!r}")
    try:
        values = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise UsageProblem(f"{what} takes integers (all, A:B or A:B:S), got {text!r}") from None
    if any(v is not None and v < 0 for v in values):
        raise UsageProblem(f"{what} takes frame indices ≥ 0, got {text!r}")
    if len(values) == 3 and (values[2] is None or values[2] < 1):
        raise UsageProblem(f"{what} step must be ≥ 1, got {text!r}")
    return Frames(spec, *values)


def select(frame: int | None, frames: str | None, n_frames: int, source: str,
           frame_option: str = "--frame", frames_option: str = "--frames") -> list[int]:
    """The frames a command works on: ``--frames`` (a sequence), else the one ``--frame``
    (default 0), checked against a recording of ``n_frames`` frames named ``source``."""
    if frames is not None:
        return parse_frames(frames, frames_option).resolve(n_frames, frames_option)
    frame = check_frame(frame, frames, frame_option, frames_option)
    if frame >= n_frames:
        raise UsageProblem(f"{frame_option} {frame} is out of range: {source} has {n_frames} "
                           f"frame(s)")
    return [frame]


def check_frame(frame: int | None, frames: str | None, frame_option: str = "--frame",
                frames_option: str = "--frames") -> int:
    """The usage checks of ``--frame``/``--frames`` that need no input (not both, a frame
    ≥ 0, a well-formed selection); returns the single frame (0 when neither is given)."""
    if frame is not None and frames is not None:
        raise UsageProblem(f"{frame_option} works on one frame, {frames_option} on a sequence: "
                           f"give one of them")
    if frames is not None:
        parse_frames(frames, frames_option)
    frame = 0 if frame is None else frame
    if frame < 0:
        raise UsageProblem(f"{frame_option} must be ≥ 0, got {frame}")
    return frame


class OutputPattern:
    """An output name that may hold ``{frame}`` and ``{env}`` fields (``fields`` says which
    this command fills), validated once: no other field, no attribute or index access, no
    conversion, an integer format spec for ``{frame}`` and a width for ``{env}``."""

    def __init__(self, pattern: str, what: str = "-o", fields: tuple = ("frame", "env")):
        self.pattern, self.what, self.fields = pattern, what, tuple(fields)
        self.names = set()
        bad = None
        try:
            for _, field, spec, conversion in string.Formatter().parse(pattern):
                if field is None:
                    continue
                allowed = {"frame": _FRAME_SPEC, "env": _ENV_SPEC}.get(field)
                if field not in self.fields or allowed is None or conversion is not None \
                        or not allowed.match(spec or ""):
                    bad = "{" + field + ("!" + conversion if conversion else "") \
                        + (":" + spec if spec else "") + "}"
                    break
                self.names.add(field)
            else:
                self.format(frame=0, env="x")
        except (KeyError, IndexError, ValueError) as exc:
            bad = f"({type(exc).__name__}: {exc})"
        if bad is not None:
            allowed_text = " and ".join("{" + f + "}" for f in self.fields)
            raise UsageProblem(f"output name {pattern!r} may only use {allowed_text} "
                               f"fields, found {bad}")

    def holds(self, field: str) -> bool:
        return field in self.names

    def format(self, frame: int | None = None, env: str | None = None) -> str:
        """This pattern's file name for one frame (and env map)."""
        values = {}
        if "frame" in self.fields:
            values["frame"] = 0 if frame is None else frame
        if "env" in self.fields:
            values["env"] = "" if env is None else env
        return self.pattern.format(**values)


def sequence_pattern(pattern: str | None, what: str, fields: tuple = ("frame",)):
    """A sequence's ``-o``/``--preview`` pattern (None passes): a file pattern (not
    stdout) that holds ``{frame}`` and names each frame differently."""
    if pattern is None:
        return None
    if pattern == "-":
        raise UsageProblem(f"{what} of a sequence is a file pattern, not stdout")
    if "{frame" not in pattern:
        raise UsageProblem(f"with --frames, {what} must hold {{frame}} (e.g. "
                           f"'out/frame_{{frame:04d}}.exr'): one file per frame", pattern)
    parsed = OutputPattern(pattern, what, fields)
    if parsed.format(frame=0) == parsed.format(frame=1):
        raise UsageProblem(f"{what} pattern {pattern!r} gives every frame the same file")
    return parsed


def plan_outputs(patterns: dict, frames: list, envs: tuple = (None,)) -> dict:
    """Every target of a run, before any work: ``patterns`` maps an option (``-o``,
    ``--preview``…) to its :class:`OutputPattern` or None; returns ``{(frame, env):
    {option: path or None}}`` in frame-major order.  A UsageProblem when two targets of
    one option share a file."""
    plan = {(frame, env): {} for frame in frames for env in envs}
    for what, pattern in patterns.items():
        seen = {}
        for key, targets in plan.items():
            path = None if pattern is None else pattern.format(*key)
            if path is not None and path in seen:
                two = "frames" if seen[path][0] != key[0] else "env maps"
                raise UsageProblem(f"{what} pattern {pattern.pattern!r} gives two {two} the "
                                   f"same file")
            if path is not None:
                seen[path] = key
            targets[what] = path
    return plan


def write_sequence(items, write, total: int, desc: str, quiet: bool = False,
                   unit: str = "frame", bar: bool = True) -> list:
    """The writer loop: ``write(item)`` for each item of ``items`` (a generator of frames,
    rendered as they are asked for), with a progress bar of ``total`` ``unit``s on stderr
    when ``bar``; returns what ``write`` returned, in order."""
    import contextlib

    from relight_cli.progress import progress
    done = []
    meter = progress(total=total, desc=desc, unit=unit, quiet=quiet) if bar \
        else contextlib.nullcontext()
    with meter as frames_bar:
        for item in items:
            done.append(write(item))
            if frames_bar is not None:
                frames_bar.update(1)
    return done


class Outputs:
    """A command's per-frame outputs: ``targets`` maps an option (``-o``, ``--preview``…)
    to (the name given or None, its kind, e.g. ``exr``).  For one frame (``frames`` None)
    the names are plain file names; for a sequence they are ``{frame}`` patterns, each
    validated here (:func:`sequence_pattern`) before any input is read."""

    def __init__(self, frames: str | None, targets: dict):
        self.sequence = frames is not None
        self.kinds = {what: kind for what, (_, kind) in targets.items()}
        self.names = {what: name for what, (name, _) in targets.items()}
        self.patterns = ({what: sequence_pattern(name, what) for what, name in
                          self.names.items()} if self.sequence else None)

    def check(self, frames: list, check) -> None:
        """Every target of ``frames`` checked by ``check(path, kind, what)`` (the CLI's
        output check: clobbering, a folder, an input…) before any work; two frames on
        one file are a usage error."""
        if not self.sequence:
            for what, name in self.names.items():
                check(name, self.kinds[what], what)
            return
        for targets in plan_outputs(self.patterns, frames).values():
            for what, path in targets.items():
                check(path, self.kinds[what], what)

    def paths(self, frame: int) -> dict:
        """{option: file name or None} of one frame."""
        if not self.sequence:
            return dict(self.names)
        return {what: None if p is None else p.format(frame)
                for what, p in self.patterns.items()}
