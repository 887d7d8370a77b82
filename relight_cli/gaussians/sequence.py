"""Gaussian sequences: an IN or ``--object`` of ``relight relight`` / an OCCLUDER of
``dgsm-build`` as Gaussians frame by frame (DGSM paper Sec. 1: animated avatars moving
through a scene).

A spec ``SOURCE[:PLACEMENT]`` (relight_cli.gaussians.placement) is one of

=========================  ===========================================================
``avatar.ply``, a mesh,    static: the same Gaussians every frame
``builtin:NAME``
``hand.npz``               a hand motion: frame K is its pose K as Gaussians
                           (``frame=K`` in the placement pins one pose: static)
``avatar/{frame:06d}.ply`` a per-frame PLY pattern (frames found on disk: every
                           number from the lowest to the highest file, none missing)
``avatar.json``            a ``relight/gaussian-sequence`` index (formats/
                           gaussian_sequence.md): pattern, frames, fps, units, up axis
=========================  ===========================================================

A placement applies to the whole sequence: its similarity (``fit``, ``centre`` and
``on-floor`` read the object's robust box) is resolved once, on the recording's first
frame, so the motion is kept, and a frame rendered alone (``--frames K:K+1``) is placed
exactly as in the whole clip.
"""

from __future__ import annotations

import os
import re
import string

import numpy as np

from relight_cli.errors import DataError, UsageProblem

#: The most frames a file pattern may span (first to last number found).
MAX_PATTERN_FRAMES = 72_000


def is_pattern(source: str) -> bool:
    """Whether a source names per-frame files (holds a ``{frame}`` field)."""
    return "{frame" in source


def _pattern_regex(pattern: str):
    """A regex matching the file names of ``pattern`` (its base name), the frame number in
    group 1; the fields checked by relight_cli.sequence.OutputPattern first."""
    out = []
    for literal, field, spec, _ in string.Formatter().parse(pattern):
        out.append(re.escape(literal))
        if field is None:
            continue
        width = re.match(r"^0?([0-9]{0,2})d?$", spec or "").group(1)
        if (spec or "").startswith("0") and width:
            out.append(r"(\d{%d,})" % int(width))
        elif width:
            out.append(r" *(\d+)")
        else:
            out.append(r"(\d+)")
    return re.compile("^" + "".join(out) + "$")


def pattern_frames(pattern: str, spec: str) -> list:
    """The frame numbers of the files a ``{frame}`` pattern names: every number from the
    lowest to the highest found, each file present (a gap is a DataError naming the
    missing file).  The folder part of the pattern may not hold a field."""
    from relight_cli.sequence import OutputPattern
    OutputPattern(pattern, "a Gaussian sequence pattern", ("frame",))   # UsageProblem
    folder, name = os.path.split(pattern)
    if is_pattern(folder):
        raise UsageProblem("a sequence pattern's {frame} field goes in the file name, not the "
                           "folder", spec)
    folder = folder or "."
    if not os.path.isdir(folder):
        raise DataError("no such folder for the sequence's frames", folder)
    regex = _pattern_regex(name)
    numbers = set()
    for entry in os.listdir(folder):
        m = regex.match(entry)
        if m and pattern.format(frame=int(m.group(1))) == os.path.join(
                os.path.split(pattern)[0], entry):
            numbers.add(int(m.group(1)))
    if not numbers:
        raise DataError(f"no file matches the sequence pattern {name!r}", folder)
    first, last = min(numbers), max(numbers)
    if last - first + 1 > MAX_PATTERN_FRAMES:
        raise DataError(f"the pattern's files span frames {first}–{last}, more than "
                        f"{MAX_PATTERN_FRAMES:,} frames", pattern)
    missing = next((k for k in range(first, last + 1) if k not in numbers), None)
    if missing is not None:
        raise DataError(f"frame {missing} of the sequence {first}–{last} is missing",
                        pattern.format(frame=missing))
    return list(range(first, last + 1))


class GaussianSource:
    """One spec as Gaussians per frame.  ``frames``: the frame numbers of a sequence
    (None: static, any frame); :meth:`frame` the placed Gaussians of one frame;
    :meth:`files` the input files of that frame (provenance)."""

    def __init__(self, spec: str, what: str = "IN", colour_space: str = "auto",
                 same_topology: bool = False, offset=None):
        from relight_cli.gaussians.placement import USAGE, parse_spec
        self.spec, self.what = spec, what
        self.offset = None if offset is None else np.asarray(offset, np.float64)
        try:
            self.source, self.placement = parse_spec(spec)
        except ValueError as exc:
            raise UsageProblem(f"bad {what} placement: {exc}; expected {USAGE}", spec) from None
        self.colour_space = colour_space
        self.same_topology = same_topology
        self.fps = None
        self.base = None            # the index's units/up similarity (before the placement)
        self._hand = None
        self._colors = None
        self._static = None
        self._similarity = None
        self._count = None
        lower = self.source.lower()
        if is_pattern(self.source):
            self.kind, self.pattern = "pattern", self.source
            self.frames = pattern_frames(self.pattern, spec)
        elif lower.endswith(".json"):
            from relight_cli.formats.gaussian_sequence import read_sequence_index
            from relight_cli.fileio import declare_input
            declare_input(self.source)
            index = read_sequence_index(self.source)
            self.kind, self.pattern = "index", index.pattern
            self.frames = index.frames
            self.fps, self.same_topology = index.fps, index.same_topology
            if index.colour_space is not None and colour_space == "auto":
                self.colour_space = index.colour_space     # an explicit option wins
            self.base = _base_similarity(index.units, index.up)
        elif lower.endswith(".npz") and self.placement.frame is None:
            from relight_cli.formats.hand_npz import read_hand
            self.kind, self.pattern = "hand", None
            self._hand = read_hand(self.source)
            self.frames = list(range(self._hand.n_frames)) if self._hand.n_frames > 1 else None
        else:
            self.kind, self.pattern, self.frames = "static", None, None
        self.path = None
        if self.placement.path is not None:
            self._read_path()

    def _read_path(self) -> None:
        """``path=FILE.json``: per-frame translations; a static source moves over the
        path's frames, a moving one keeps its own (each must have a translation)."""
        from relight_cli.fileio import declare_input
        from relight_cli.formats.path_json import read_path
        declare_input(self.placement.path)
        self.path = read_path(self.placement.path)
        n = len(self.path)
        if self.frames is None:
            self.frames = list(range(n))
        elif self.frames[-1] >= n:
            raise DataError(f"the path has {n} translation(s), but {self.source} has frames up "
                            f"to {self.frames[-1]}", self.placement.path)
        self.fps = self.fps or self.path.fps

    @property
    def moves(self) -> bool:
        return self.frames is not None

    def files(self, frame: int) -> list:
        """The input files of ``frame`` (the pattern's file, or the source)."""
        if self.pattern is not None:
            return [self.pattern.format(frame=frame)]
        return [self.source]

    def frame(self, frame: int):
        """The placed Gaussians of ``frame`` (a static source: the same every frame; with a
        path, moved by the frame's translation)."""
        if self.frames is None and self._static is not None:
            return self._static
        if self.frames is not None and frame not in self._frame_set():
            raise UsageProblem(f"frame {frame} is not in {self.spec} (frames "
                               f"{self.frames[0]}–{self.frames[-1]})")
        if self.kind == "static":           # read and placed once (a path moves it)
            if self._static is None:
                self._static = self._place(self._raw(0), 0)
            placed = self._static
        else:
            placed = self._place(self._raw(frame), frame)
        if self.path is not None:           # path=FILE.json: the frame's translation, last
            from dataclasses import replace
            placed = replace(placed, means=placed.means + self.path.translations[frame])
        _check_reach(placed, self.spec)
        return placed

    def _place(self, g, frame: int):
        """``g`` (frame ``frame``) placed by the clip's one similarity (resolved on the
        recording's first frame) and dgsm-build's --translate."""
        from relight_cli.gaussians.placement import prune, transform_gaussians
        if self._similarity is None:
            first = g if self.kind == "static" or frame == self.frames[0] \
                else self._raw(self.frames[0])
            self._similarity = _resolve_placement(self.placement, first, self.spec) or False
        try:
            g = prune(g, self.placement)     # crop/min-opacity/max-scale: every frame
            placed = g if self._similarity is False else transform_gaussians(g, self._similarity)
        except ValueError as exc:
            raise DataError(f"cannot place it: {exc}", self.spec) from None
        if self.offset is not None:      # dgsm-build --translate: after the placement
            placed.means = placed.means + self.offset
        return placed

    def _frame_set(self):
        if not hasattr(self, "_set"):
            self._set = set(self.frames)
        return self._set

    def _raw(self, frame: int):
        """Frame ``frame``'s Gaussians in the world's units and up axis (before the
        placement), checked (a frame of another size under same_topology)."""
        from relight_cli.gaussians.from_mesh import hand_gaussians
        from relight_cli.gaussians.placement import transform_gaussians
        if self.kind == "hand":
            if self._colors is None:          # the same every frame: computed once
                from relight_cli.gaussians.from_mesh import hand_colors
                self._colors = hand_colors(self._hand)
            try:
                g = hand_gaussians(self._hand, frame if self.frames is not None else 0,
                                   colors=self._colors)
            except ValueError as exc:
                raise DataError(str(exc), self.source) from None
        elif self.kind in ("pattern", "index"):
            path = self.pattern.format(frame=frame)
            from relight_cli.fileio import declare_input
            declare_input(path)
            g = _load(path, self.colour_space)
            if self.base is not None:
                g = transform_gaussians(g, self.base)
        else:
            g = _load(self.source, self.colour_space, self.placement.frame)
        if len(g) == 0:
            raise DataError("no Gaussians", self.files(frame)[0])
        if self.same_topology:
            if self._count is None:
                self._count = len(g)
            elif len(g) != self._count:
                raise DataError(f"frame {frame} holds {len(g):,} Gaussians, but the sequence "
                                f"declares the same topology and its first frame read holds "
                                f"{self._count:,}", self.files(frame)[0])
        return g


def _load(path: str, colour_space: str, frame=None):
    """Gaussians of one file (colour space where the loader takes one)."""
    import inspect

    from relight_cli.gaussians.from_mesh import load_gaussians
    if "colour_space" in inspect.signature(load_gaussians).parameters:
        return load_gaussians(path, frame=frame, colour_space=colour_space)
    return load_gaussians(path, frame=frame)


def _resolve_placement(placement, g, spec):
    """The placement's similarity for these Gaussians (None: the identity)."""
    from relight_cli.gaussians.placement import resolve
    if placement.is_identity():
        return None
    try:
        return resolve(placement, g)
    except ValueError as exc:
        raise DataError(f"cannot place it: {exc}", spec) from None


def _check_reach(g, spec) -> None:
    """Beyond ~1000 km the float32 PLY/EXR outputs lose the millimetres (or overflow)."""
    reach = max(float(np.abs(g.means).max()), float(np.abs(g.scales).max()))
    if not reach <= 1e6:
        raise DataError(f"placed Gaussians reach {reach:.3g} m from the origin (more than "
                        f"1e6 m); check the placement's scale and translate", spec)


def _base_similarity(units: str, up: str):
    """The similarity taking an index's units and up axis to metres and +Y up (None: the
    identity)."""
    from relight_cli.formats.gaussian_sequence import UNITS
    from relight_cli.gaussians.placement import Similarity, axis_rotation
    rotation = {"+y": np.eye(3), "-y": axis_rotation("x", 180.0),
                "+z": axis_rotation("x", -90.0), "-z": axis_rotation("x", 90.0)}[up]
    scale = UNITS[units]
    if scale == 1.0 and up == "+y":
        return None
    return Similarity(scale, rotation, np.zeros(3))


def recording_start(sources: list) -> int:
    """The first frame of the recording (of the first moving source; 0 when none moves):
    what is resolved once for a clip (placements, estimated lights) is resolved there, so
    that a frame made alone equals the same frame of the whole clip."""
    moving = [s for s in sources if s.moves]
    return moving[0].frames[0] if moving else 0


def clip_frames(sources: list, frames_text: str | None, frame: int | None) -> list:
    """The frames a clip renders: ``--frames`` over the recording of the first moving
    source (every other moving source must hold each of them), or the one ``--frame``
    (default: the recording's first frame).  A UsageProblem when nothing moves and
    ``--frames`` is given, or a frame is not in a source."""
    from relight_cli.sequence import check_frame, parse_frames
    moving = [s for s in sources if s.moves]
    if frames_text is not None and not moving:
        raise UsageProblem("--frames renders a sequence, but no IN or --object moves (give a "
                           "hand.npz with frames, a '{frame}' PLY pattern or a sequence index)")
    if not moving:
        check_frame(frame, frames_text)
        return [0]
    recording = moving[0].frames
    if frames_text is not None:
        selection = parse_frames(frames_text)
        if selection.every:
            chosen = list(recording)
        else:
            chosen = [k for k in range(recording[-1] + 1)[selection.as_slice()]
                      if k >= recording[0]]
            if not chosen:
                raise UsageProblem(f"--frames {frames_text} selects no frame of "
                                   f"{moving[0].spec} (frames {recording[0]}–{recording[-1]})")
    else:
        chosen = [recording[0] if frame is None else check_frame(frame, None)]
    for source in moving:
        have = set(source.frames)
        absent = next((k for k in chosen if k not in have), None)
        if absent is not None:
            raise UsageProblem(f"frame {absent} is not in {source.spec} (frames "
                               f"{source.frames[0]}–{source.frames[-1]})")
    return chosen
