"""Scores of learned models' renders: masked image metrics per sample, their means over
samples, and the ceiling beside them.

The one home of how a render is scored against ground truth (MSE, PSNR, SSIM, MAE inside
the hand mask, per hand too), used by every validation loop (teachers, the linear model,
students), :func:`relight_cli.neural.evaluate.evaluate_capture` and the studies.  It
imports nothing else of :mod:`relight_cli.neural`, so the training loops and the
evaluator both depend on it without depending on each other.
"""

from __future__ import annotations

import numpy as np


def spread(n_items: int, count: int | None) -> np.ndarray:
    """Indices of at most ``count`` evenly spaced items of ``n_items`` (None: all)."""
    count = n_items if count is None else min(n_items, count)
    return np.unique(np.linspace(0, n_items - 1, count).round().astype(int))


def _win(image) -> int:
    return min(7, (min(image.shape[:2]) // 2) * 2 - 1)


def score(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, hand_masks=None,
          names=None) -> dict:
    """{mse, psnr, ssim, mae} inside ``mask`` > 0.5 and, per hand, {name: {...}} inside
    ``hand_masks[k]`` > 0.5 (the image's data range, so per-hand PSNR/SSIM compare with
    the whole); {} when the mask is empty."""
    from relight_cli.metrics.image import image_metrics
    region = mask > 0.5
    if not region.any():
        return {}
    values = gt[region]
    data_range = float(values.max() - values.min()) or 1.0
    out = dict(image_metrics(pred, gt, region, data_range, _win(gt))["metrics"])
    for k, name in enumerate(names or []):
        own = hand_masks[k] > 0.5
        if own.any():
            out[name] = image_metrics(pred, gt, own, data_range, _win(gt))["metrics"]
    return out


def hand_names(sides: list) -> list:
    """Names of a scene's hands in scores: their handedness, or hand0, hand1 … when two
    hands share one."""
    return list(sides) if len(set(sides)) == len(sides) else [f"hand{k}" for k in
                                                            range(len(sides))]


def mean_scores(rows: list) -> dict:
    """Means of per-sample score dicts (nested per-hand dicts averaged over the samples
    where that hand is visible), with their sample counts."""
    out = {}
    flat = [r for r in rows if r]
    if not flat:
        return out
    keys = [k for k in flat[0] if not isinstance(flat[0][k], dict)]
    for key in keys:
        out[key] = float(np.mean([r[key] for r in flat]))
    out["samples"] = len(flat)
    nested = dict.fromkeys(k for r in flat for k, v in r.items() if isinstance(v, dict))
    for name in nested:
        out[name] = mean_scores([r[name] for r in flat if name in r])
    return out


def attach_ceiling(scores: dict, ceiling_rows: list) -> dict:
    """Add ``ceiling`` (the mean perfect-texture scores of the same samples) and
    ``gap_to_ceiling`` (ceiling PSNR − model PSNR, dB) to one split's ``scores``."""
    ceiling = mean_scores([r for r in ceiling_rows if r])
    if scores and ceiling and "psnr" in scores:
        scores["ceiling"] = ceiling
        scores["gap_to_ceiling"] = float(ceiling["psnr"] - scores["psnr"])
    return scores
