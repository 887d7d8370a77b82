"""``relight relight CAPTURE/``: score learned models against a capture's images.

The capture mode of ``relight relight`` (commands/relight.py dispatches on IN): a
relight/capture folder's frames and eval/ env renders, each hand by its own learned model
(``--checkpoint`` per hand), scored inside the hand masks (MSE, PSNR, SSIM, MAE, beside
the perfect-texture ceiling; per hand too): a relight/metrics JSON (kind validation) with
one object per ``--splits`` split.  The work is :mod:`relight_cli.jobs.score_capture`.
"""

from __future__ import annotations

from dataclasses import dataclass

import click

from relight_cli.cli.tools import check_input, check_output, log, no_clobber_option, quiet_option

#: What the dispatcher says IN is in this mode.
DESCRIPTION = "a capture (IN = CAPTURE/)"
#: Said of options of the other modes given here.
REFUSAL = ("{} do not apply to a capture (IN = CAPTURE/ renders the capture's own cameras, "
           "lights and env maps)")
_HAND_FILES = (".npz", ".ply", ".obj", ".glb", ".gltf", ".stl", ".off")


def accepts(spec: str, given: set) -> bool:
    """Whether IN ``spec`` is a capture: a folder, or a capture.json."""
    import os
    if spec.lower().endswith(_HAND_FILES):
        return False      # a file name (a folder by that name is then refused as a hand/avatar)
    return os.path.isdir(spec) or os.path.basename(spec) == "capture.json"


@dataclass(frozen=True)
class Run:
    """This mode's options as given (the click parameters, one field each)."""

    input: str
    output: str
    model: str | None
    checkpoint: tuple
    device: str | None
    env_res: str | None
    aa: int | None
    splits: str | None
    eval_samples: int | None
    subject: str | None
    no_clobber: bool
    quiet: bool


def _scored_help() -> str:
    from relight_cli.neural.registry import names
    return ("The learned model scored: " + " or ".join(names(scores_captures=True)) + ".")


@click.command("relight", short_help="Score learned hand models against a capture's images.")
@click.argument("input", metavar="CAPTURE")
@click.option("-o", "--output", required=True, help="The scores: a relight/metrics JSON.")
@click.option("--model", default=None, metavar="NAME", help=_scored_help())
@click.option("--checkpoint", multiple=True, metavar="CKPT.pt",
              help="The model's checkpoint (relight/checkpoint); repeat it to give each hand "
                   "its own (each hand takes the one trained on its handedness).")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default=None,
              help="Where the model runs [default: auto].")
@click.option("--env-res", "env_res", default=None, metavar="WxH",
              help="Lat-long grid WxH the env renders are integrated over [default: 32x16].")
@click.option("--aa", type=int, default=None,
              help="Sub-pixel samples per axis [default: the capture's own sampling].")
@click.option("--splits", default=None, metavar="LIST",
              help="Comma-separated splits scored: train, heldout, grouped (every "
                   "grouped-light frame), fully_lit, env [default: heldout (grouped for a "
                   "capture no checkpoint trained on), fully_lit, env].")
@click.option("--eval-samples", type=int, default=None, metavar="N",
              help="At most N evenly spaced samples per split [default: all].")
@click.option("--subject", default=None, metavar="SUBJECT.npz",
              help="--model linear: condition on this hand file's mean texture T̄ (relight "
                   "personalize writes one) instead of the capture's own, so a subject "
                   "personalised from photos is scored against the capture's ground truth "
                   "(scores say \"subject\": \"own\").")
@no_clobber_option
@quiet_option
def command(**options):
    """Render the capture CAPTURE/ (a relight/capture folder)'s frames and its
    eval/ env renders with --model teacher|linear, each hand by its own
    --checkpoint, and score them against the capture's images inside the hand
    masks (MSE, PSNR, SSIM, MAE; per hand too for two hands): -o is a
    relight/metrics JSON (kind validation) with one object per --splits split.

    \b
    Examples:
      relight relight capture/ --model teacher --checkpoint teacher.pt -o scores.json
      relight relight both/ --model teacher --checkpoint right.pt --checkpoint left.pt \\
          -o both_scores.json
      relight relight unseen/ --model linear --checkpoint universal.pt --subject me.npz \\
          --splits env -o me_scores.json
    """
    _capture(Run(**options))


def _capture(a) -> None:
    """Capture mode: a capture's frames and env renders, each hand by its own learned
    model, scored against the capture's images (relight/metrics JSON;
    relight_cli.jobs.score_capture)."""
    import os
    import time

    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.capture import index_path
    from relight_cli.cli.inputs import env_grid
    from relight_cli.envmap import DEFAULT_GRID
    from relight_cli.neural import registry
    from relight_cli.neural.evaluate import SPLITS

    scored = registry.names(scores_captures=True)
    if a.model not in scored:
        raise UsageProblem(f"a capture is scored with --model {' or '.join(scored)} (and one "
                           f"--checkpoint per hand)")
    if not a.checkpoint:
        raise UsageProblem(f"--model {a.model} needs --checkpoint CKPT.pt (one per hand)")
    names = None
    if a.splits is not None:
        names = [n.strip() for n in a.splits.split(",") if n.strip()]
        bad = [n for n in names if n not in SPLITS]
        if not names or bad:
            raise UsageProblem(f"--splits takes {', '.join(SPLITS)}"
                               + (f"; unknown: {', '.join(bad)}" if bad else ""))
    if a.eval_samples is not None and a.eval_samples < 1:
        raise UsageProblem(f"--eval-samples must be ≥ 1, got {a.eval_samples}")
    if a.aa is not None and not 1 <= a.aa <= 8:
        raise UsageProblem(f"--aa must be in [1, 8], got {a.aa}")
    grid = env_grid(a.env_res) if a.env_res is not None else DEFAULT_GRID
    index = index_path(a.input)   # names a folder without capture.json and a capture.json that is a folder
    if a.subject is not None and a.model != "linear":
        raise UsageProblem("--subject gives a linear model its subject's mean texture; use "
                           "it with --model linear")
    for path in (index, *a.checkpoint, *([a.subject] if a.subject else [])):
        check_input(path)
    # after the inputs (never one of them): the scores are a relight/metrics JSON
    check_output(a.output, a.no_clobber, kind="json")

    start = time.perf_counter()
    from relight_cli.formats.metrics_json import make_record, write_metrics
    from relight_cli.jobs.score_capture import CaptureOptions, score_capture
    from relight_cli.neural.train import resolve_device
    from relight_cli.provenance import numbered_roles, provenance

    device = resolve_device(a.device or "auto")
    models = _load_hand_models(a.checkpoint, registry.get(a.model).kind, device)
    texture = None
    if a.subject is not None:
        from relight_cli.formats.hand_npz import read_hand
        texture = read_hand(a.subject).mean_texture
        if texture is None:
            raise DataError("the hand file carries no mean texture (relight personalize "
                            "writes one)", a.subject)
    options = CaptureOptions(names, a.eval_samples, a.aa, grid, a.model, texture)
    try:
        result = score_capture(os.path.dirname(index) or ".", models, options, device,
                               log=lambda m: log(m, a.quiet), quiet=a.quiet)
    except ValueError as exc:
        raise UsageProblem(str(exc)) from None
    if not result.scores:
        raise DataError(f"the capture has no samples in {', '.join(result.settings['splits'])}",
                        index)
    inputs = {"capture": index, **numbered_roles("checkpoint", a.checkpoint),
              **({"subject": a.subject} if a.subject else {})}
    record = provenance("relight/metrics", 2, inputs, result.settings)
    write_metrics(a.output, make_record("validation", result.scores,
                                        {r: {"path": p} for r, p in inputs.items()},
                                        result.settings, record))
    log(f"wrote {a.output} ({time.perf_counter() - start:.1f} s): {summary(result.scores)}",
        a.quiet)


def summary(scores: dict) -> str:
    """The scores line: per split its MSE, PSNR (and the gap to the perfect texture's
    ceiling where scored), SSIM and sample count."""
    def split(name, m):
        gap = (f" ({m['gap_to_ceiling']:.2f} dB below its ceiling)"
               if m.get("gap_to_ceiling") is not None else "")
        return (f"{name}: MSE {m['mse'] * 1e3:.3f}e-3 PSNR {m['psnr']:.2f} dB{gap} "
                f"SSIM {m['ssim']:.3f} ({m['samples']})")
    return "; ".join(split(n, m) for n, m in scores.items())


def _load_hand_models(paths, kind: str, device) -> list:
    """One HandModel per checkpoint path (of ``kind``: teacher or linear); DataError
    naming the file for one that does not load or build."""
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.neural.evaluate import load_hand_model
    models = []
    for path in paths:
        ckpt = read_checkpoint(path, kind=kind)
        try:
            models.append(load_hand_model(ckpt, device, name=path))
        except (ValueError, UsageProblem) as exc:
            raise DataError(getattr(exc, "message", str(exc)), path) from None
    return models
