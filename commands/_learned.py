"""Options and checks shared by the training commands (train-teacher, distill)."""

from __future__ import annotations

import click


def training_options(validation: str):
    """--vgg-weights, --resume, --device, --metrics-out (``validation`` says what it
    scores) and --seed, in that order."""
    options = [
        click.option("--vgg-weights", default=None, metavar="VGG16.pth",
                     help="Local torchvision vgg16 state dict enabling the VGG loss (Eq. 5); "
                          "nothing is downloaded: copy e.g. vgg16-397923af.pth from a machine "
                          "that has it. Without it λ_VGG is 0."),
        click.option("--resume", default=None, metavar="CKPT.pt",
                     help="Continue a run from its checkpoint, exactly (weights, Adam, step, "
                          "RNG)."),
        click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto",
                     show_default=True,
                     help="Where to train. Under torchrun: DDP over the processes."),
        click.option("--metrics-out", default=None, metavar="VAL.json",
                     help=f"Validation metrics (relight/metrics, kind validation): {validation}."),
        click.option("--seed", type=int, default=None,
                     help="Seed (initialization, sampling) [default: 0]."),
    ]

    def decorate(func):
        for option in reversed(options):
            func = option(func)
        return func
    return decorate


def check_outputs(output: str, metrics_out: str | None, no_clobber: bool) -> None:
    """-o is a .pt checkpoint, --metrics-out a .json (or -); registered before any work."""
    from relight_cli.clitools import check_output
    check_output(output, no_clobber, kind="pt")
    check_output(metrics_out, no_clobber, kind="json", what="--metrics-out")


def write_validation(metrics_out: str | None, result, inputs: dict, config, record,
                     sampling: dict | None = None) -> None:
    """The run's validation record (relight/metrics, kind validation), if asked for;
    ``record`` is the checkpoint's provenance, restated as this file's format."""
    if metrics_out is None:
        return
    from relight_cli.formats.metrics_json import FORMAT, VERSION, make_record, write_metrics
    write_metrics(metrics_out, make_record(
        "validation", {k: v for k, v in result.metrics.items() if k != "step"},
        {role: {"path": path} for role, path in inputs.items()}, config.to_dict(),
        dict(record, format=FORMAT, version=VERSION),
        details={"history": result.history, **({"sampling": sampling} if sampling else {})}))
