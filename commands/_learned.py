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


def check_inputs(config_file: str | None, vgg_weights: str | None, resume: str | None) -> None:
    """--config (or - for stdin), --vgg-weights and --resume are readable files."""
    from relight_cli.cli.tools import check_input
    for path, role in ((config_file, "--config"), (vgg_weights, None), (resume, None)):
        if path is not None:
            check_input(path, stdin=role)


def check_capture(capture: str, index_ok: bool = True) -> str:
    """CAPTURE as a capture folder (with ``index_ok``, its capture.json stands for it):
    DataError if it is neither, its capture.json checked when present."""
    import os

    from relight_cli.cli.tools import check_input
    from relight_cli.errors import DataError
    if not os.path.isdir(capture):
        if index_ok and os.path.exists(capture) and os.path.basename(capture) == "capture.json":
            capture = os.path.dirname(capture) or "."
        else:
            raise DataError("CAPTURE must be a capture folder (with capture.json)", capture)
    if os.path.isfile(os.path.join(capture, "capture.json")):
        check_input(os.path.join(capture, "capture.json"))
    return capture


def file_inputs(vgg_weights: str | None, resume: str | None, config_file: str | None) -> dict:
    """The provenance roles of the optional input files given (in this order)."""
    return {role: path for role, path in (("vgg_weights", vgg_weights), ("resume", resume),
                                          ("config", config_file)) if path is not None}


def read_captures(folders, config, cache_poses: int | None = None) -> list:
    """One CaptureData per capture folder, at ``config``'s geometry settings."""
    from relight_cli.cli.inputs import load_capture
    return [load_capture(folder, config, cache_poses) for folder in folders]


def read_vgg(path: str | None, device):
    """The VGG loss of --vgg-weights on ``device``, or None."""
    if path is None:
        return None
    from relight_cli.neural.losses import load_vgg
    return load_vgg(path).to(device)


def saver(output: str):
    """save(checkpoint): a periodic checkpoint lands at once (an interrupted run keeps
    its progress), outside the command's output transaction."""
    def save(checkpoint):
        from relight_cli.formats.checkpoint import write_checkpoint
        from relight_cli.fileio import outside_transaction
        with outside_transaction():
            write_checkpoint(output, checkpoint)
    return save


def check_outputs(output: str, metrics_out: str | None, no_clobber: bool) -> None:
    """-o is a .pt checkpoint, --metrics-out a .json (or -); registered before any work."""
    from relight_cli.cli.tools import check_output
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
