"""Input loading shared by commands (heavy imports happen only when called)."""

from __future__ import annotations


def load_envmap(spec: str, nonfinite: str = "error"):
    """An EnvMap from a file path or a ``builtin:NAME`` (see relight_cli.builtin_envs)."""
    if spec.startswith("builtin:"):
        from relight_cli.builtin_envs import builtin_envmap
        return builtin_envmap(spec)
    from relight_cli.clitools import check_input
    from relight_cli.formats.envmap import read_envmap
    check_input(spec)
    return read_envmap(spec, nonfinite=nonfinite)
