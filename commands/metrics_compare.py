"""``relight metrics compare``: a metrics record against a baseline, the CI gate (exit
:data:`EXIT_REGRESSION` when something regressed beyond its tolerance)."""

from __future__ import annotations

import click

from relight_cli.cli.tools import check_input, check_output, no_clobber_option, quiet_option

EXIT_REGRESSION = 3  # a metric regressed beyond tolerance

def _parse_keyed(values, what, convert):
    """['psnr=0.01', '0.001', '*.ssim=1e-4'] -> {'psnr': 0.01, None: 0.001, '*.ssim': 1e-4}."""
    from relight_cli.errors import UsageProblem
    out = {}
    for text in values:
        key, sep, value = text.rpartition("=")
        try:
            out[key if sep else None] = convert(value)
        except ValueError:
            raise UsageProblem(f"{what} must look like [METRIC=]VALUE, got {text!r}") from None
    return out


def _tolerance(text):
    value = float(text)
    if not value >= 0 or value == float("inf"):
        raise ValueError(text)
    return value


def _direction(text):
    from relight_cli.metrics.compare import DIRECTIONS
    if text not in DIRECTIONS:
        raise ValueError(text)
    return text


@click.command("compare", short_help="Compare a metrics JSON with a baseline; exit 3 on regression.")
@click.argument("new", metavar="NEW.json")
@click.argument("baseline", metavar="BASELINE.json")
@click.option("--rtol", multiple=True, metavar="[METRIC=]VALUE",
              help="Relative tolerance (default 1e-3), for all metrics or one; repeatable. METRIC "
                   "is a dotted key, a pattern like '*.psnr', or a name like 'psnr'.")
@click.option("--atol", multiple=True, metavar="[METRIC=]VALUE",
              help="Absolute tolerance (default 1e-9); repeatable like --rtol.")
@click.option("--better", multiple=True, metavar="METRIC=higher|lower|either",
              help="Which direction is better (defaults: psnr/ssim/iou/F higher; errors lower; "
                   "unknown metrics: either, so any move beyond tolerance fails).")
@click.option("--only-changed", is_flag=True, help="List only metrics that moved beyond tolerance.")
@click.option("-o", "--output", default=None, metavar="FILE.json|-",
              help="Also write the comparison as JSON (relight/metrics-comparison, "
                   "formats/metrics_json.md), written even when something regressed; with '-' "
                   "it goes to stdout and the table to stderr.")
@click.option("--json", "as_json", is_flag=True,
              help="Write the comparison JSON to stdout (the same as -o -).")
@no_clobber_option
@quiet_option
@click.pass_context
def command(ctx, new, baseline, rtol, atol, better, only_changed, output, as_json,
                    no_clobber, quiet):
    """Compare metrics record NEW.json with BASELINE.json and print what moved.

    Each metric regresses when it moved in its bad direction by more than
    atol + rtol·|baseline|; improvements never fail.  A metric missing from
    NEW.json is a regression.  Either file may be '-' (stdin), not both.

    \b
    Exit codes: 0 nothing regressed, 3 something regressed, 1 unreadable or
    mismatched files, 2 usage error.

    \b
    Examples:
      relight metrics compare new.json baseline.json --rtol 0.01 --rtol psnr=0.002 \\
          --better my_score=higher
      relight metrics image a.exr b.exr -o - | relight metrics compare - base.json -o cmp.json
    """
    from relight_cli.errors import UsageProblem
    from relight_cli.formats.metrics_json import read_metrics
    from relight_cli.jobs.metrics import compare

    if as_json:
        if output not in (None, "-"):
            raise UsageProblem("--json writes the comparison to stdout; it cannot go with -o FILE")
        output = "-"
    check_output(output, no_clobber, kind="json")
    rtols = _parse_keyed(rtol, "--rtol", _tolerance)
    atols = _parse_keyed(atol, "--atol", _tolerance)
    directions = _parse_keyed(better, "--better", _direction)
    if None in directions:
        raise UsageProblem("--better needs METRIC=higher|lower|either")
    check_input(new, stdin="NEW.json")
    check_input(baseline, stdin="BASELINE.json")
    result = compare(read_metrics(new), read_metrics(baseline), rtols, atols, directions,
                     new_name=new, baseline_name=baseline)
    if output is not None:
        _write_comparison(output, result.kind, result.rows, result.regressed, new, baseline,
                          {"rtol": list(rtol), "atol": list(atol), "better": list(better)})
    if not quiet or result.regressed:
        click.echo(result.table(only_changed=only_changed), nl=False, err=output == "-")
    if result.regressed:
        click.echo(f"relight metrics compare: regression against {baseline} "
                   f"(exit {EXIT_REGRESSION})", err=True)
        ctx.exit(EXIT_REGRESSION)


def _write_comparison(output, kind, rows, regressed, new, baseline, given):
    """The relight/metrics-comparison record, landing at once: a regression (exit 3)
    must not discard it as a failed command's outputs are."""
    from relight_cli.cli.tools import dumps_json
    from relight_cli.formats.metrics_json import (COMPARISON_FORMAT, COMPARISON_VERSION,
                                                  make_comparison)
    from relight_cli.metrics.compare import DEFAULT_ATOL, DEFAULT_RTOL
    from relight_cli.fileio import outside_transaction, write_text_atomic
    from relight_cli.provenance import provenance
    settings = dict(given, default_rtol=DEFAULT_RTOL, default_atol=DEFAULT_ATOL)
    record = provenance(COMPARISON_FORMAT, COMPARISON_VERSION,
                        {"new": new, "baseline": baseline}, settings)
    comparison = make_comparison(kind, [r.to_json() for r in rows],
                                 EXIT_REGRESSION if regressed else 0, record["inputs"], settings,
                                 record)
    with outside_transaction():
        write_text_atomic(output, dumps_json(comparison))
