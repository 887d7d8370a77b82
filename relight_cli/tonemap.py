"""Tone mapping of linear radiance for PNG previews (never for data)."""

from __future__ import annotations

import numpy as np


def srgb_oetf(linear: np.ndarray) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1) of values in [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def tonemap(rgb: np.ndarray, exposure: float | None = None, key: float = 0.18) -> np.ndarray:
    """Reinhard's global operator, then sRGB: linear [H, W, 3] → display [H, W, 3] in [0, 1].

    ``exposure`` None picks it from the log-average luminance (scene key);
    non-finite inputs are shown black rather than poisoning the average.
    """
    rgb = np.nan_to_num(np.asarray(rgb, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    rgb = np.clip(rgb, 0, None)
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    if exposure is None:
        positive = lum[lum > 0]
        log_avg = float(np.exp(np.mean(np.log(positive + 1e-9)))) if positive.size else 1.0
        exposure = key / max(log_avg, 1e-12)
    scaled = rgb * exposure
    scaled_lum = lum * exposure
    mapped = scaled_lum / (1.0 + scaled_lum)
    ratio = np.where(scaled_lum > 0, mapped / np.where(scaled_lum > 0, scaled_lum, 1), 0.0)
    return srgb_oetf(scaled * ratio[..., None])
