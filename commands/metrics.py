"""``relight metrics``: image, shadow and lighting-consistency metrics, and the CI gate.

A group of one module per subcommand (loaded when called, as ``relight``'s own
subcommands are): ``image`` (commands/metrics_image.py), ``shadow``, ``lighting`` write a
``relight/metrics`` JSON record (spec: formats/metrics_json.md); ``compare`` checks one
against a baseline and exits with ``EXIT_REGRESSION`` (3) when something regressed.  The
scoring is :mod:`relight_cli.jobs.metrics`; the shared readers and writers are
:mod:`relight_cli.cli.metrics`.
"""

from __future__ import annotations

import importlib

import click

#: subcommand -> module under relight_cli.commands (its ``command``)
SUBCOMMANDS = {"compare": "metrics_compare", "image": "metrics_image",
               "lighting": "metrics_lighting", "shadow": "metrics_shadow"}


class MetricsGroup(click.Group):
    """Loads a subcommand's module when it is asked for."""

    def list_commands(self, ctx):
        return list(SUBCOMMANDS)

    def get_command(self, ctx, name):
        if name not in SUBCOMMANDS:
            return None
        return importlib.import_module(f"relight_cli.commands.{SUBCOMMANDS[name]}").command


@click.group("metrics", cls=MetricsGroup,
             short_help="Image, shadow and lighting metrics; compare with a baseline.")
def command():
    """Compute quality metrics as relight/metrics JSON, and gate on them.

    \b
    Exit codes: 0 success, 1 bad data, 2 usage error,
    3 (compare only) a metric regressed beyond its tolerance.
    """
