"""Score learned hand models on a capture: ``relight relight CAPTURE/`` as an engine job.

:func:`score_capture` renders a capture's frames and its eval/ env renders, each hand
by its own model (:class:`~relight_cli.neural.evaluate.HandModel`), and scores them
against the capture's images inside the hand masks (MSE, PSNR, SSIM, MAE; per hand for
two hands), through :class:`~relight_cli.neural.evaluate.CaptureEvaluator`.  The capture
is given as its folder (or a ``CaptureData``): the evaluator reads each model's texel
data at that model's texture resolution, which only it knows.
"""

from __future__ import annotations

from dataclasses import dataclass

from relight_cli.envmap import DEFAULT_GRID


def _quiet(message: str) -> None:
    pass


@dataclass
class CaptureOptions:
    """splits: among :data:`relight_cli.neural.evaluate.SPLITS` (None: the evaluator's
    default).  eval_samples: at most this many evenly spaced samples per split (None:
    all).  aa: samples per pixel axis (None: the capture's own).  env_res: (H, W) grid
    the models integrate env maps over.  model: the kind recorded (teacher, linear).
    subject_texture: a subject's own T̄ [3, M, M] (a personalised hand.npz's
    ``mean_texture``) every linear model is conditioned on instead of the capture's
    (:func:`~relight_cli.neural.evaluate.with_own_subject`), or None."""

    splits: list | None = None
    eval_samples: int | None = None
    aa: int | None = None
    env_res: tuple = DEFAULT_GRID
    model: str = "teacher"
    subject_texture: object = None


@dataclass
class CaptureScores:
    """{split: {mse, psnr, ssim, mae, samples[, hand: {...}]}} and the settings the
    relight/metrics record keeps."""

    scores: dict
    settings: dict


def score_capture(capture, models: list, options: CaptureOptions, device="cpu", log=_quiet,
                  quiet: bool = True) -> CaptureScores:
    """Score ``models`` (one per hand, or one for all) on ``capture``; a progress bar over
    the samples on stderr unless ``quiet``.  ValueError for models that do not fit the
    capture's hands; the scores may be empty (no samples in the splits)."""
    from relight_cli.neural.evaluate import CaptureEvaluator
    from relight_cli.progress import progress

    o = options
    evaluator = CaptureEvaluator(capture, models, device, o.aa, o.env_res)
    if getattr(evaluator, "ceiling", None) is not None:
        evaluator.ceiling.quiet = quiet   # the ceiling's stage shading can take minutes
        evaluator.ceiling.log = log
    if o.subject_texture is not None:
        from relight_cli.neural.evaluate import with_own_subject
        evaluator.models = with_own_subject(evaluator.models, o.subject_texture)
    if not evaluator.sampling["matched"]:
        log(f"note: pixels sampled {evaluator.aa}×{evaluator.aa}, but the capture's images were "
            f"made with {evaluator.sampling['capture_aa']}×{evaluator.sampling['capture_aa']} "
            f"(recorded as settings.sampling.matched = false)")
    chosen = o.splits or evaluator.default_splits()
    available = evaluator.data.splits()
    total = sum(len(available.get(n) or []) if o.eval_samples is None
                else min(o.eval_samples, len(available.get(n) or [])) for n in chosen)
    with progress(total=total, desc="relight (capture samples)", quiet=quiet) as bar:
        scores = evaluator.evaluate(chosen, o.eval_samples, progress=bar.update)
    settings = {"model": o.model, "splits": chosen, "eval_samples": o.eval_samples,
                "env_res": list(o.env_res), "aa": evaluator.aa, "sampling": evaluator.sampling,
                "hands": [{"hand": k, "name": evaluator.names[k], "checkpoint": m.name,
                           "model": m.model_name, "sides": m.sides, "step": m.step,
                           **({"subject": m.subject} if m.subject else {})}
                          for k, m in enumerate(evaluator.models)]}
    return CaptureScores(scores, settings)
