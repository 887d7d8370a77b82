"""Inputs the commands share: an env map, a hand, a roughness map, placed Gaussians,
an env-map grid.

Each loader takes what a user types (a path, ``builtin:NAME``, ``SOURCE[:PLACEMENT]``)
and returns the engine's object, with the toolkit's one-line errors (a bad spec is a
UsageProblem, exit 2; a bad file a DataError naming it).  Heavy modules are imported
when a loader is called (the commands import this module inside their callbacks).
"""

from __future__ import annotations


def env_grid(text: str, what: str = "--env-res"):
    """A ``WxH`` lat-long grid option → :class:`relight_cli.envmap.EnvGrid` ((height,
    width) to the engine); usage errors as :func:`relight_cli.clitools.parse_env_res`."""
    from relight_cli.clitools import parse_env_res
    from relight_cli.envmap import EnvGrid
    return EnvGrid.from_wh(*parse_env_res(text, what))


def load_envmap(spec: str, nonfinite: str = "error"):
    """An EnvMap from a file path or a ``builtin:NAME`` (see relight_cli.builtin_envs)."""
    if spec.startswith("builtin:"):
        from relight_cli.builtin_envs import builtin_envmap
        return builtin_envmap(spec)
    from relight_cli.clitools import check_input
    from relight_cli.formats.envmap import read_envmap
    check_input(spec)
    return read_envmap(spec, nonfinite=nonfinite)


def load_hand(spec: str):
    """HandData from a hand.npz or builtin:right|left|two[:POSE]."""
    from relight_cli.errors import UsageProblem
    if spec.startswith("builtin:"):
        from relight_cli.hand.model import builtin_hand
        from relight_cli.hand.poses import POSE_NAMES
        parts = spec.split(":")[1:]
        which = parts[0] if parts else "right"
        pose = parts[1] if len(parts) > 1 else "relaxed"
        if which not in ("right", "left", "two") or len(parts) > 2 or pose not in POSE_NAMES:
            raise UsageProblem(f"unknown built-in hand {spec!r}; use builtin:right|left|two"
                               f"[:POSE] with POSE one of {', '.join(POSE_NAMES)}")
        if which == "two":
            from relight_cli.hand.scene import two_hands
            return two_hands(builtin_hand("right", pose))
        return builtin_hand(which, pose)
    from relight_cli.clitools import check_input
    from relight_cli.formats.hand_npz import read_hand
    check_input(spec)
    return read_hand(spec)


def read_roughness_map(path: str):
    """[H, W] float64 roughness in (0, 1] from an EXR's Y or R channel (UV space)."""
    import numpy as np

    from relight_cli.errors import DataError
    from relight_cli.formats.exr import read_exr
    image = read_exr(path)
    name = next((c for c in ("Y", "R", "roughness.Y") if c in image.channels), None)
    if name is None:
        raise DataError("roughness map needs a Y or R channel", path)
    values = image.channels[name].astype(np.float64)
    if not np.isfinite(values).all() or values.min() <= 0 or values.max() > 1:
        raise DataError("roughness map values must be finite and in (0, 1]", path)
    return values


def parse_occluder(spec: str, what: str):
    """``SOURCE[:PLACEMENT]`` → (source, Placement); a bad spec is a usage error (exit 2)."""
    from relight_cli.errors import UsageProblem
    from relight_cli.gaussians.placement import USAGE, parse_spec
    try:
        return parse_spec(spec)
    except ValueError as exc:
        raise UsageProblem(f"bad {what} placement: {exc}; expected {USAGE}", spec) from None


def load_placed(source: str, placement, spec: str, offset=None):
    """Load Gaussians (PLY, mesh or builtin:) and apply the placement, then ``offset`` [3]."""
    import numpy as np

    from relight_cli.errors import DataError
    from relight_cli.gaussians.from_mesh import load_gaussians
    from relight_cli.gaussians.placement import place

    g = load_gaussians(source, frame=getattr(placement, "frame", None))
    if len(g) == 0:
        raise DataError("no Gaussians", source)
    try:
        g = place(g, placement)
    except ValueError as exc:
        raise DataError(f"cannot place it: {exc}", spec) from None
    if offset is not None:
        g.means = g.means + np.asarray(offset, np.float64)
    # Beyond ~1000 km the float32 PLY/EXR outputs lose the millimetres (or overflow).
    reach = max(float(np.abs(g.means).max()), float(np.abs(g.scales).max()))
    if not reach <= 1e6:
        raise DataError(f"placed Gaussians reach {reach:.3g} m from the origin (more than "
                        f"1e6 m); check the placement's scale and translate", spec)
    return g
