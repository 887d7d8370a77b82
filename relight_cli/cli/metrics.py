"""The ``relight metrics`` subcommands' shared readers and writers (CLI layer).

Images read as colour (+ alpha), as one channel, as masks, with their NaN/Inf refused
naming the file; the ``-o``/``--jsonl`` options and the record writer.  Each subcommand
is its own module (commands/metrics_*.py); what they share is here, not in one of them.
"""

from __future__ import annotations

import click

from relight_cli.cli.tools import check_input, check_output

output_option = click.option("-o", "--output", default="-", show_default=True,
                       help="Metrics JSON file ('-' for stdout).")
jsonl_option = click.option("--jsonl", "jsonl", default=None,
                      help="Also write one JSON row per pair to this file ('-' for stdout).")
percentiles_option = click.option("--percentiles", default="5,95", show_default=True,
                            help="Percentiles reported in the batch aggregate.")


def finite_or_fail(pixels, path):
    import numpy as np

    from relight_cli.errors import DataError
    bad = ~np.isfinite(pixels)
    if bad.any():
        n = int(bad.reshape(bad.shape[0], bad.shape[1], -1).any(axis=-1).sum())
        raise DataError(f"{n} pixel(s) hold NaN or Inf values", path)
    return pixels


def read_rgb(path: str):
    """[H, W, C] float32 colour channels (R, G, B when named so; alpha dropped) and their names."""
    pixels, names, _ = read_rgb_alpha(path)
    return pixels, names


def read_rgb_alpha(path: str):
    """(colour channels and their names as :func:`read_rgb`, the [H, W] float32 alpha
    channel or None): alpha is the channel named ``A`` beside colour channels, as
    OpenImageIO names the alpha of EXR, PNG and TIFF files.  Per-hand coverage
    (``hand0.A``) and a one-channel image are not alpha."""
    from relight_cli.formats.image import read_image
    check_input(path)
    pixels, names = read_image(path)
    alpha = pixels[..., names.index("A")] if "A" in names and len(names) > 1 else None
    if all(c in names for c in "RGB"):
        idx = [names.index(c) for c in "RGB"]
        pixels, names = pixels[..., idx], ["R", "G", "B"]
    elif pixels.shape[-1] == 4:
        pixels, names = pixels[..., :3], names[:3]
    elif pixels.shape[-1] == 2:  # grey + alpha
        pixels, names = pixels[..., :1], names[:1]
    return (finite_or_fail(pixels, path),
            [n.split(".")[-1] or f"c{i}" for i, n in enumerate(names)], alpha)


def alpha_mask(alpha, path: str):
    """[H, W] bool foreground (alpha > 0.5) of a ground truth's alpha channel."""
    import numpy as np

    from relight_cli.errors import DataError
    if not np.isfinite(alpha).all():
        raise DataError("the alpha channel holds NaN or Inf values (score every pixel with "
                        "--whole-image)", path)
    mask = alpha > 0.5
    if not mask.any():
        raise DataError("the alpha channel selects no pixels (foreground is alpha > 0.5); "
                        "score every pixel with --whole-image", path)
    return mask


def read_single(path: str):
    """[H, W] float64 from a one-channel image, its Y/A channel, or Rec. 709 luminance of RGB."""
    import numpy as np

    from relight_cli.formats.image import read_image
    check_input(path)
    pixels, names = read_image(path)
    finite_or_fail(pixels, path)
    if pixels.shape[-1] == 1:
        return pixels[..., 0].astype(np.float64)
    for name in ("Y", "A"):
        if name in names and not all(c in names for c in "RGB"):
            return pixels[..., names.index(name)].astype(np.float64)
    if all(c in names for c in "RGB"):
        rgb = np.stack([pixels[..., names.index(c)] for c in "RGB"], axis=-1)
    else:
        rgb = pixels[..., :3] if pixels.shape[-1] >= 3 else pixels[..., :1].repeat(3, -1)
    return rgb.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])


def read_mask(path: str, shape):
    from relight_cli.errors import DataError
    from relight_cli.jobs.metrics import same_size
    values = read_single(path)
    same_size(values.shape, shape, path)
    mask = values > 0.5
    if not mask.any():
        raise DataError("mask selects no pixels (foreground is where the mask is > 0.5)", path)
    return mask


def check_outputs(output, jsonl, no_clobber):
    from relight_cli.errors import UsageProblem
    check_output(output, no_clobber, kind="json")
    if jsonl is not None:
        check_output(jsonl, no_clobber, kind="jsonl", what="--jsonl")
        if jsonl == "-" and output == "-":
            raise UsageProblem("--jsonl - and -o - would both write to stdout; give one a file name")


def write_scores(output, jsonl, scores):
    """The record of a :class:`relight_cli.jobs.metrics.Scores` (with its provenance) and,
    with --jsonl, one JSON row per pair."""
    from relight_cli.formats.metrics_json import FORMAT, VERSION, write_metrics
    from relight_cli.fileio import write_text_atomic
    from relight_cli.provenance import provenance
    record, rows = scores.record(provenance(FORMAT, VERSION, scores.inputs(), scores.settings))
    if jsonl is not None:
        import json
        write_text_atomic(jsonl, "".join(json.dumps(r, allow_nan=False, ensure_ascii=False) + "\n"
                                         for r in rows))
    write_metrics(output, record)


def is_multi(spec) -> bool:
    """A folder or a glob: a batch of files matched by name."""
    import os

    from relight_cli.metrics.batch import is_glob
    return is_glob(spec) or os.path.isdir(spec)


def progress_over(items, desc, quiet):
    from relight_cli.cli.tools import progress
    return progress(items, total=len(items), desc=desc, quiet=quiet)
