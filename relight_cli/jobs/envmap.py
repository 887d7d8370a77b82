"""Convert an environment map: ``relight envmap`` as a job.

:func:`convert` resamples a loaded :class:`~relight_cli.envmap.EnvMap` to the layout,
size and rotation of :class:`EnvmapOptions` (area-weighted over exact texel solid
angles, :func:`relight_cli.envmap.resample`; untouched when nothing changes) and
returns it with its statistics and the settings its provenance records.

    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.jobs.envmap import EnvmapOptions, convert
    done = convert(builtin_envmap("sky"), EnvmapOptions(layout="cube", size=(16, 96)))
    done.stats["power"]
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class EnvmapOptions:
    """``relight envmap``'s options, parsed: ``layout`` (``latlong``, ``cube``, None: the
    input's), ``size`` (width, height: a cube map's is (N, 6N); None: from the input),
    ``rotate_y`` (degrees about +Y), ``negative`` (what to do with negative radiance:
    ``error`` refuses it, ``clamp`` sets it to 0)."""

    layout: str | None = None
    size: tuple | None = None
    rotate_y: float = 0.0
    negative: str = "error"


@dataclass
class Converted:
    """What :func:`convert` made: the ``env`` map, its ``stats``
    (:func:`relight_cli.envmap.info`) and the ``settings`` its provenance records."""

    env: object
    stats: dict
    settings: dict


def convert(env, options: EnvmapOptions, log=None) -> Converted:
    """``env`` in ``options``' layout, size and rotation; UsageProblem for a size given
    as WxH to a cube map kept a cube (no --to); ``log`` (callable(str)) says what was
    resampled."""
    import math

    from relight_cli import envmap as E
    from relight_cli.errors import UsageProblem

    clamped = _negative(env, options.negative, log)
    if clamped is not None:
        env = clamped
    target = options.layout or env.layout
    if options.size is not None and options.layout is None and target == "cube":
        # The input is a cube and stays one: --size is its face size, never WxH.
        raise UsageProblem("--size for a cube map is one face size N, e.g. --size 64")
    if options.size is not None:
        w, h = options.size
    elif target == env.layout:
        w, h = env.width, env.height
    elif target == "latlong":
        w, h = 4 * env.width, 2 * env.width
    else:
        w = max(1, env.height // 2)
        h = 6 * w
    rotate_y = options.rotate_y
    result = env
    if (target != env.layout or (w, h) != (env.width, env.height)
            or math.fmod(rotate_y, 360.0) != 0.0):
        result = E.resample(env, target, h, w, rotation=E.rotation_y(rotate_y))
        if log is not None:
            log(f"resampled to {target} {w}x{h}"
                + (f", rotated {rotate_y}° about +Y" if rotate_y else ""))
    settings = {"layout": target, "width": w, "height": h, "rotate_y": rotate_y}
    if options.negative != "error":     # recorded when it can change pixels
        settings["negative"] = options.negative
    return Converted(result, E.info(result), settings)


def _negative(env, policy: str, log):
    """``env`` with its negative radiance set to 0 (``clamp``, logged: how many pixels,
    how deep), None when it has none; ``error`` refuses it as the reader does."""
    import numpy as np

    from relight_cli.errors import UsageProblem
    from relight_cli.formats.envmap import EnvMap, check_negative

    if policy not in ("error", "clamp"):
        raise UsageProblem(f"--negative must be error or clamp, got {policy!r}")
    low = env.radiance < 0
    if not low.any():
        return None
    if policy == "error":
        check_negative(env.radiance, env.name)
    if log is not None:
        log(f"clamped {int(low.any(axis=-1).sum())} pixel(s) of negative radiance (down to "
            f"{float(env.radiance.min()):.4g}) to 0")
    return EnvMap(np.maximum(env.radiance, np.float32(0.0)), env.layout, env.name)
