"""Full-reference image metrics: MSE, PSNR, SSIM, MAE — per channel and overall, masked.

Images are [H, W, C] float arrays.  ``space`` chooses what is compared:

* ``linear``: the stored values (linear HDR radiance).  PSNR/SSIM need a data
  range R; by default R = max − min of the ground truth over the evaluated region.
* ``srgb``: both images tone-mapped with the *same* exposure (from the ground
  truth's log-average luminance, or given) by Reinhard + sRGB
  (:func:`relight_cli.tonemap.tonemap`), R = 1.
* ``display``: values already display-referred in [0, 1] (8-bit PNGs), R = 1.

With a mask (foreground-only, as both hand papers evaluate), MSE, MAE and PSNR
average over mask pixels only, and SSIM uses *masked local statistics*: each
window's means, variances and covariance are taken over the foreground pixels in
it, so background pixels have no influence at all; the SSIM map is averaged over
foreground pixels at least (win_size−1)/2 from the image border (as
scikit-image crops its border).  With an all-foreground mask this is exactly
``skimage.metrics.structural_similarity`` (tested); without a mask scikit-image
is called directly.
"""

from __future__ import annotations

import math

import numpy as np

SPACES = ("linear", "srgb", "display")
METRIC_NAMES = ("mse", "psnr", "ssim", "mae")
K1, K2 = 0.01, 0.03  # Wang et al. 2004 constants (scikit-image defaults)


def exposure_from(gt: np.ndarray, region: np.ndarray | None = None, key: float = 0.18) -> float:
    """Exposure that maps the ground truth's log-average luminance to ``key`` (Reinhard)."""
    rgb = np.clip(np.asarray(gt, np.float64), 0, None)
    if rgb.shape[-1] >= 3:
        lum = rgb[..., :3] @ np.array([0.2126, 0.7152, 0.0722])
    else:
        lum = rgb[..., 0]
    if region is not None:
        lum = lum[region]
    positive = lum[lum > 0]
    log_avg = float(np.exp(np.mean(np.log(positive + 1e-9)))) if positive.size else 1.0
    return key / max(log_avg, 1e-12)


def to_space(pred: np.ndarray, gt: np.ndarray, space: str, region: np.ndarray | None = None,
             exposure: float | None = None):
    """Map both images into the compared space.

    Returns:
        (pred [H, W, C] float64, gt [H, W, C] float64, natural data range or None,
        exposure used or None).
    """
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    if space == "linear":
        return pred, gt, None, None
    if space == "display":
        return pred, gt, 1.0, None
    if space != "srgb":
        raise ValueError(f"space must be one of {SPACES}, got {space!r}")
    from relight_cli.tonemap import tonemap
    if exposure is None:
        exposure = exposure_from(gt, region)

    def mapped(image):
        if image.shape[-1] == 3:
            return tonemap(image, exposure)
        # Grey or odd channel counts: tone-map each channel as a grey image.
        return np.stack([tonemap(np.repeat(image[..., c:c + 1], 3, axis=-1), exposure)[..., 0]
                         for c in range(image.shape[-1])], axis=-1)

    return mapped(pred), mapped(gt), 1.0, float(exposure)


def psnr_from_mse(mse: float, data_range: float) -> float:
    """10·log10(R²/MSE) in dB; +∞ for identical images."""
    if mse == 0:
        return math.inf
    return 10.0 * math.log10(data_range ** 2 / mse)


def masked_ssim_map(x: np.ndarray, y: np.ndarray, mask: np.ndarray, data_range: float,
                    win_size: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """SSIM map of one channel with local statistics over foreground pixels only.

    Args:
        x, y: [H, W] float64 images.
        mask: [H, W] bool foreground.
        data_range: R in C1 = (K1 R)², C2 = (K2 R)².

    Returns:
        (S [H, W] float64, valid [H, W] bool): S is meaningful where ``valid``
        (foreground, ≥ 2 foreground pixels in the window, inside the uncropped area).
    """
    from scipy.ndimage import uniform_filter

    m = mask.astype(np.float64)
    n_window = win_size * win_size

    def local(a):
        return uniform_filter(a, size=win_size)  # mode 'reflect', as scikit-image

    w = local(m)                          # fraction of the window in the foreground
    count = w * n_window
    safe = np.where(w > 0, w, 1.0)
    ux = local(m * x) / safe
    uy = local(m * y) / safe
    uxx = local(m * x * x) / safe
    uyy = local(m * y * y) / safe
    uxy = local(m * x * y) / safe
    # Sample covariance over the foreground pixels of the window (N/(N−1)), which
    # for a full window is scikit-image's cov_norm = NP/(NP−1).
    norm = np.where(count > 1.5, count / np.maximum(count - 1, 1e-12), 0.0)
    vx = norm * (uxx - ux * ux)
    vy = norm * (uyy - uy * uy)
    vxy = norm * (uxy - ux * uy)
    c1 = (K1 * data_range) ** 2
    c2 = (K2 * data_range) ** 2
    a1 = 2 * ux * uy + c1
    a2 = 2 * vxy + c2
    b1 = ux ** 2 + uy ** 2 + c1
    b2 = vx + vy + c2
    s = (a1 * a2) / (b1 * b2)
    pad = (win_size - 1) // 2
    interior = np.zeros_like(mask, dtype=bool)
    interior[pad:mask.shape[0] - pad, pad:mask.shape[1] - pad] = True
    valid = mask & interior & (count > 1.5)
    return s, valid


def image_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None,
                  data_range: float | None = None, win_size: int = 7,
                  channel_names: list[str] | None = None) -> dict:
    """MSE, PSNR, SSIM, MAE of ``pred`` against ``gt``.

    Args:
        pred, gt: [H, W, C] float arrays in the compared space (see :func:`to_space`).
        mask: [H, W] bool foreground, or None for every pixel.
        data_range: R for PSNR and SSIM; None = max − min of ``gt`` over the region
            (1 if that is 0).
        win_size: SSIM window (odd, ≥ 3, ≤ the smaller image side).
        channel_names: names for ``per_channel`` (default R, G, B, A or c0, c1, ...).

    Returns:
        {"metrics": {mse, psnr, ssim, mae}, "per_channel": {name: {...}},
        "data_range": R, "pixels": foreground pixel count}.  Overall MSE/MAE
        average over pixels and channels; overall PSNR comes from overall MSE;
        overall SSIM is the mean of the channel SSIMs (scikit-image's convention).
    """
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    if pred.ndim == 2:
        pred = pred[..., None]
    if gt.ndim == 2:
        gt = gt[..., None]
    if pred.shape != gt.shape:
        raise ValueError(f"shape mismatch: {pred.shape} vs {gt.shape}")
    h, w, c = gt.shape
    if win_size < 3 or win_size % 2 == 0:
        raise ValueError("SSIM window size must be odd and ≥ 3")
    if min(h, w) < win_size:
        raise ValueError(f"image {w}x{h} is smaller than the SSIM window ({win_size})")
    region = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    n = int(region.sum())
    if n == 0:
        raise ValueError("mask selects no pixels")
    if data_range is None:
        values = gt[region]
        data_range = float(values.max() - values.min()) or 1.0
    names = channel_names or (["R", "G", "B", "A"][:c] if c <= 4 else [f"c{i}" for i in range(c)])
    diff = pred[region] - gt[region]            # [n, C]
    mse_c = np.mean(diff ** 2, axis=0)
    mae_c = np.mean(np.abs(diff), axis=0)
    ssim_c = np.empty(c)
    for i in range(c):
        ssim_c[i] = channel_ssim(pred[..., i], gt[..., i], None if mask is None else region,
                                 data_range, win_size)
    per_channel = {}
    for i, name in enumerate(names):
        per_channel[name] = {"mse": float(mse_c[i]), "psnr": psnr_from_mse(float(mse_c[i]), data_range),
                             "ssim": float(ssim_c[i]), "mae": float(mae_c[i])}
    mse = float(np.mean(diff ** 2))
    overall = {"mse": mse, "psnr": psnr_from_mse(mse, data_range), "ssim": float(np.mean(ssim_c)),
               "mae": float(np.mean(np.abs(diff)))}
    return {"metrics": overall, "per_channel": per_channel, "data_range": float(data_range),
            "pixels": n}


def channel_ssim(x: np.ndarray, y: np.ndarray, mask: np.ndarray | None, data_range: float,
                 win_size: int = 7) -> float:
    """Mean SSIM of one [H, W] channel (scikit-image without a mask; masked statistics with one)."""
    if mask is None:
        from skimage.metrics import structural_similarity
        return float(structural_similarity(np.asarray(x, np.float64), np.asarray(y, np.float64),
                                           win_size=win_size, data_range=data_range))
    s, valid = masked_ssim_map(np.asarray(x, np.float64), np.asarray(y, np.float64), mask,
                               data_range, win_size)
    if not valid.any():
        raise ValueError("mask has no pixel with a full enough SSIM window; "
                         "the foreground is too thin or touches only the border")
    return float(s[valid].mean())
