"""Shadow-matte scores of the DGSM paper: SAE, SM-IoU and boundary F-measure.

A shadow matte is an [H, W] array in [0, 1], 1 = fully shadowed (a visibility
map is ``1 − matte``).  With threshold t:

* shadow regions: P = {pred > t}, G = {gt > t} (the pseudo-GT shadow region).
* **SAE** (shadow absolute error): mean |pred − gt| over G.  Defined cases:
  G empty and P non-empty → mean over P (phantom shadows are still errors);
  both empty → 0.  ``sae_region`` says which region was used.
* **SM-IoU**: |P ∩ G| / |P ∪ G|; both empty → 1 (the mattes agree: no shadow).
* **Boundary F-measure** with pixel tolerance τ: boundary pixels are region pixels
  with a 4-neighbour outside the region (the image border does not make a
  boundary).  Precision = fraction of predicted boundary pixels within Euclidean
  distance τ of a GT boundary pixel; recall the other way round; F = 2PR/(P+R).
  Both boundaries empty (each region is empty or the whole image) → P = R = F = 1
  when the regions are equal, else 0; exactly one boundary empty → P = R = F = 0
  (the non-empty side has nothing to match).

An optional ROI (x, y, w, h in pixels) crops both mattes before scoring.
"""

from __future__ import annotations

import numpy as np

METRIC_NAMES = ("sae", "sm_iou", "boundary_f", "boundary_precision", "boundary_recall")


def boundary(region: np.ndarray) -> np.ndarray:
    """[H, W] bool: pixels of ``region`` with a 4-neighbour outside it (image border excluded)."""
    r = np.asarray(region, bool)
    padded = np.pad(r, 1, mode="edge")  # edge padding: the frame is not a boundary
    inner = (padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:])
    return r & ~inner


def _within(source: np.ndarray, target: np.ndarray, tolerance: float) -> np.ndarray:
    """For each True pixel of ``source``: is a True pixel of ``target`` within ``tolerance``?"""
    from scipy.ndimage import distance_transform_edt
    distance = distance_transform_edt(~target)  # distance to the nearest target pixel
    return distance[source] <= tolerance + 1e-9


def boundary_scores(pred_region: np.ndarray, gt_region: np.ndarray, tolerance: float = 2.0):
    """(precision, recall, F) of region boundaries with a pixel tolerance (see module doc)."""
    bp = boundary(pred_region)
    bg = boundary(gt_region)
    n_p, n_g = int(bp.sum()), int(bg.sum())
    if n_p == 0 and n_g == 0:
        same = float(np.array_equal(np.asarray(pred_region, bool), np.asarray(gt_region, bool)))
        return same, same, same
    if n_p == 0 or n_g == 0:
        return 0.0, 0.0, 0.0
    precision = float(_within(bp, bg, tolerance).mean())
    recall = float(_within(bg, bp, tolerance).mean())
    f = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return precision, recall, f


def boundary_scores_reference(pred_region, gt_region, tolerance: float = 2.0):
    """Slow twin of :func:`boundary_scores`: explicit pairwise distances (tests only)."""
    bp = np.argwhere(boundary(pred_region)).astype(np.float64)
    bg = np.argwhere(boundary(gt_region)).astype(np.float64)
    if len(bp) == 0 and len(bg) == 0:
        same = float(np.array_equal(np.asarray(pred_region, bool), np.asarray(gt_region, bool)))
        return same, same, same
    if len(bp) == 0 or len(bg) == 0:
        return 0.0, 0.0, 0.0
    d = np.sqrt(((bp[:, None, :] - bg[None, :, :]) ** 2).sum(-1))
    precision = float((d.min(axis=1) <= tolerance + 1e-9).mean())
    recall = float((d.min(axis=0) <= tolerance + 1e-9).mean())
    f = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return precision, recall, f


def crop_roi(matte: np.ndarray, roi: tuple[int, int, int, int] | None) -> np.ndarray:
    """Crop [H, W] to (x, y, w, h); raises ValueError when the ROI leaves the image."""
    if roi is None:
        return matte
    x, y, w, h = (int(v) for v in roi)
    height, width = matte.shape[:2]
    if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > width or y + h > height:
        raise ValueError(f"ROI {x},{y},{w},{h} does not fit in the {width}x{height} matte")
    return matte[y:y + h, x:x + w]


def shadow_metrics(pred: np.ndarray, gt: np.ndarray, threshold: float = 0.1,
                   tolerance: float = 2.0, roi=None) -> dict:
    """SAE, SM-IoU and boundary F-measure of two [H, W] shadow mattes (1 = shadow).

    Returns:
        {"metrics": {sae, sm_iou, boundary_f, boundary_precision, boundary_recall},
        "sae_region": "gt" | "pred" | "none", "shadow_pixels": {"pred": n, "gt": n}}.
    """
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"shape mismatch: {pred.shape} vs {gt.shape}")
    pred = crop_roi(pred, roi)
    gt = crop_roi(gt, roi)
    p_region = pred > threshold
    g_region = gt > threshold
    error = np.abs(pred - gt)
    if g_region.any():
        sae, sae_region = float(error[g_region].mean()), "gt"
    elif p_region.any():
        sae, sae_region = float(error[p_region].mean()), "pred"
    else:
        sae, sae_region = 0.0, "none"
    union = int((p_region | g_region).sum())
    iou = 1.0 if union == 0 else float((p_region & g_region).sum()) / union
    precision, recall, f = boundary_scores(p_region, g_region, tolerance)
    return {"metrics": {"sae": sae, "sm_iou": iou, "boundary_f": f,
                        "boundary_precision": precision, "boundary_recall": recall},
            "sae_region": sae_region,
            "shadow_pixels": {"pred": int(p_region.sum()), "gt": int(g_region.sum())}}
