"""Many pairs at once: pairing files by name, and aggregating per-pair rows.

Pairing (:func:`match_pairs`): PRED and GT are each a file, a folder or a glob
pattern.  Two files make one pair.  Otherwise both sides are expanded to file
lists (a folder: its non-hidden regular files, sorted) and matched by file name
without extension (``pred/0001.exr`` ↔ ``gt/0001.png``).  A prediction without
ground truth is an error (it would silently shrink the evaluated set); extra
ground-truth files are ignored and reported.
"""

from __future__ import annotations

import glob
import math
import os

import numpy as np

from relight_cli.errors import DataError, UsageProblem


def is_glob(spec: str) -> bool:
    return any(c in spec for c in "*?[")


def expand(spec: str, role: str) -> list[str]:
    """The files a PRED/GT/mask spec stands for (sorted)."""
    if is_glob(spec):
        files = sorted(p for p in glob.glob(spec) if os.path.isfile(p))
        if not files:
            raise DataError(f"{role} pattern matches no files", spec)
        return files
    if os.path.isdir(spec):
        files = sorted(os.path.join(spec, n) for n in os.listdir(spec)
                       if not n.startswith(".") and os.path.isfile(os.path.join(spec, n)))
        if not files:
            raise DataError(f"{role} folder holds no files", spec)
        return files
    if not os.path.exists(spec):
        raise DataError(f"no such {role} file or folder", spec)
    return [spec]


def stem(path: str) -> str:
    name = os.path.basename(path)
    return name.split(".", 1)[0] if not name.startswith(".") else name


def _by_stem(files: list[str], spec: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for f in files:
        s = stem(f)
        if s in out:
            raise DataError(f"two files share the name {s!r} ({os.path.basename(out[s])}, "
                            f"{os.path.basename(f)}); cannot match by name", spec)
        out[s] = f
    return out


def match_pairs(pred: str, gt: str) -> tuple[list[tuple[str, str, str]], list[str]]:
    """[(name, pred_path, gt_path)] and the unmatched ground-truth files.

    Raises DataError when a prediction has no ground truth, UsageProblem when a
    single file is paired with many.
    """
    for spec, role in ((pred, "prediction"), (gt, "ground truth")):
        if not is_glob(spec) and not os.path.exists(spec):
            raise DataError(f"no such {role} file or folder", spec)
    single_pred = not is_glob(pred) and not os.path.isdir(pred)
    single_gt = not is_glob(gt) and not os.path.isdir(gt)
    if single_pred and single_gt:
        return [(stem(pred), pred, gt)], []
    if single_pred != single_gt:
        raise UsageProblem("PRED and GT must both be files, or both folders/glob patterns")
    preds = _by_stem(expand(pred, "prediction"), pred)
    gts = _by_stem(expand(gt, "ground truth"), gt)
    missing = [s for s in preds if s not in gts]
    if missing:
        shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise DataError(f"no ground truth for {len(missing)} prediction(s): {shown}", gt)
    pairs = [(s, preds[s], gts[s]) for s in sorted(preds)]
    extra = [gts[s] for s in sorted(gts) if s not in preds]
    return pairs, extra


def match_masks(mask: str | None, names: list[str]) -> dict[str, str | None]:
    """name -> mask path: one file for every pair, or a folder/glob matched by name."""
    if mask is None:
        return {n: None for n in names}
    if not is_glob(mask) and not os.path.isdir(mask):
        if not os.path.exists(mask):
            raise DataError("no such mask file", mask)
        return {n: mask for n in names}
    masks = _by_stem(expand(mask, "mask"), mask)
    missing = [n for n in names if n not in masks]
    if missing:
        shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise DataError(f"no mask for {len(missing)} pair(s): {shown}", mask)
    return {n: masks[n] for n in names}


def parse_percentiles(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise UsageProblem(f"--percentiles must be comma-separated numbers, got {text!r}") from None
    if not values or any(not (0 <= v <= 100) for v in values):
        raise UsageProblem(f"--percentiles must lie in [0, 100], got {text!r}")
    return values


def aggregate(rows: list[dict], percentiles=(5.0, 95.0)) -> dict:
    """Per-metric statistics over rows of flat {metric: value} dicts.

    Returns {metric: {mean, median, min, max, p<q>...}} in the rows' key order.
    Percentiles interpolate linearly; when a metric has +∞ values (PSNR of
    identical pairs) they are empirical quantiles (a sample value, numpy's
    ``inverted_cdf``) so that no ∞ − ∞ appears, and the mean is +∞.
    """
    keys: list[str] = []
    for row in rows:
        for k in row:
            if k not in keys:
                keys.append(k)
    out = {}
    for k in keys:
        values = np.array([row[k] for row in rows if k in row], np.float64)
        method = "linear" if np.all(np.isfinite(values)) else "inverted_cdf"
        stats = {"mean": float(np.mean(values)) if np.all(np.isfinite(values)) else math.inf,
                 "median": float(np.quantile(values, 0.5, method=method)),
                 "min": float(values.min()), "max": float(values.max())}
        for q in percentiles:
            label = f"p{q:g}".replace(".", "_")
            stats[label] = float(np.percentile(values, q, method=method))
        out[k] = stats
    return out
