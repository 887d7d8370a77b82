"""Image metrics (relight_cli/metrics/image.py): MSE/PSNR/SSIM/MAE against scikit-image and
hand-computed cases, masks, the masked SSIM's slow twin, the sRGB space."""

from __future__ import annotations

import math

import numpy as np
import pytest
from skimage.metrics import mean_squared_error, peak_signal_noise_ratio, structural_similarity

from relight_cli.metrics.image import image_metrics, masked_ssim_map, to_space


def _pair(seed=0, h=24, w=32):
    rng = np.random.default_rng(seed)
    gt = rng.uniform(0, 4, (h, w, 3))
    pred = gt + rng.normal(0, 0.3, gt.shape)
    return pred, gt


# ------------------------------------------------------------------ engine


def test_matches_scikit_image_unmasked():
    pred, gt = _pair()
    r = 4.0
    out = image_metrics(pred, gt, data_range=r)
    # Same formulas, same float64 data: agreement to rounding.
    assert out["metrics"]["mse"] == pytest.approx(mean_squared_error(gt, pred), rel=1e-12)
    assert out["metrics"]["psnr"] == pytest.approx(peak_signal_noise_ratio(gt, pred, data_range=r),
                                                   rel=1e-12)
    assert out["metrics"]["ssim"] == pytest.approx(
        structural_similarity(gt, pred, data_range=r, channel_axis=-1), rel=1e-12)
    for i, c in enumerate("RGB"):
        ch = out["per_channel"][c]
        assert ch["ssim"] == pytest.approx(structural_similarity(gt[..., i], pred[..., i],
                                                                 data_range=r), rel=1e-12)
        assert ch["psnr"] == pytest.approx(peak_signal_noise_ratio(gt[..., i], pred[..., i],
                                                                   data_range=r), rel=1e-12)
        assert ch["mae"] == pytest.approx(np.abs(gt[..., i] - pred[..., i]).mean(), rel=1e-12)


def test_identical_images():
    _, gt = _pair()
    m = image_metrics(gt, gt)["metrics"]
    assert m["mse"] == 0 and m["mae"] == 0 and m["psnr"] == math.inf
    assert m["ssim"] == pytest.approx(1.0, abs=1e-12)


def test_constant_offset_hand_computed():
    _, gt = _pair()
    d = 0.25
    out = image_metrics(gt + d, gt, data_range=2.0)["metrics"]
    assert out["mse"] == pytest.approx(d * d, rel=1e-12)
    assert out["mae"] == pytest.approx(d, rel=1e-12)
    assert out["psnr"] == pytest.approx(10 * math.log10(4.0 / d ** 2), rel=1e-12)
    # A constant offset leaves variances/covariance unchanged; only the luminance term drops.
    assert 0.9 < out["ssim"] < 1.0


def test_known_noise_level():
    rng = np.random.default_rng(3)
    gt = rng.uniform(0, 1, (64, 64, 3))
    sigma = 0.05
    pred = gt + rng.normal(0, sigma, gt.shape)
    m = image_metrics(pred, gt, data_range=1.0)["metrics"]
    # 12288 samples: the mean of squares has relative std √(2/n) ≈ 1.3 %; allow 5 %.
    assert m["mse"] == pytest.approx(sigma ** 2, rel=0.05)
    assert m["mae"] == pytest.approx(sigma * math.sqrt(2 / math.pi), rel=0.05)
    assert m["psnr"] == pytest.approx(-20 * math.log10(sigma), abs=0.25)


def test_mask_ignores_background_exactly():
    pred, gt = _pair(1, 32, 40)
    mask = np.zeros(gt.shape[:2], bool)
    mask[6:26, 8:30] = True
    a = image_metrics(pred, gt, mask, data_range=4.0)
    pred2, gt2 = pred.copy(), gt.copy()
    rng = np.random.default_rng(9)
    pred2[~mask] = rng.uniform(-100, 100, (int((~mask).sum()), 3))
    gt2[~mask] = rng.uniform(-100, 100, (int((~mask).sum()), 3))
    b = image_metrics(pred2, gt2, mask, data_range=4.0)
    assert a == b  # bit-identical: background never enters any statistic
    diff = (pred - gt)[mask]
    assert a["metrics"]["mse"] == pytest.approx(np.mean(diff ** 2), rel=1e-12)
    assert a["pixels"] == int(mask.sum())


def test_full_mask_equals_scikit_image():
    pred, gt = _pair(2)
    full = np.ones(gt.shape[:2], bool)
    for i in range(3):
        s, valid = masked_ssim_map(pred[..., i], gt[..., i], full, 4.0)
        ref = structural_similarity(pred[..., i], gt[..., i], data_range=4.0)
        assert s[valid].mean() == pytest.approx(ref, rel=1e-10)  # float64 filter rounding only


def test_masked_ssim_slow_twin():
    """Masked SSIM at one pixel equals SSIM of the foreground samples in its window."""
    pred, gt = _pair(4, 20, 20)
    mask = np.zeros((20, 20), bool)
    mask[3:15, 5:18] = True
    x, y = pred[..., 0], gt[..., 0]
    s, valid = masked_ssim_map(x, y, mask, 4.0)
    c1, c2 = (0.01 * 4) ** 2, (0.03 * 4) ** 2
    for (i, j) in [(5, 7), (3, 5), (14, 16), (9, 12)]:
        assert valid[i, j]
        win = mask[i - 3:i + 4, j - 3:j + 4]
        a, b = x[i - 3:i + 4, j - 3:j + 4][win], y[i - 3:i + 4, j - 3:j + 4][win]
        ux, uy = a.mean(), b.mean()
        vx, vy = a.var(ddof=1), b.var(ddof=1)
        vxy = np.cov(a, b, ddof=1)[0, 1]
        ref = (2 * ux * uy + c1) * (2 * vxy + c2) / ((ux ** 2 + uy ** 2 + c1) * (vx + vy + c2))
        assert s[i, j] == pytest.approx(ref, rel=1e-9)


def test_srgb_space_uses_one_exposure():
    pred, gt = _pair(5)
    p, g, r, exposure = to_space(pred, gt, "srgb")
    assert r == 1.0 and exposure > 0
    from relight_cli.tonemap import tonemap
    np.testing.assert_allclose(p, tonemap(pred, exposure), rtol=0, atol=0)
    np.testing.assert_allclose(g, tonemap(gt, exposure), rtol=0, atol=0)
    # Scaling both images by k and the exposure by 1/k gives the same display images.
    p2, g2, _, e2 = to_space(pred * 3, gt * 3, "srgb")
    assert e2 == pytest.approx(exposure / 3, rel=1e-9)
    np.testing.assert_allclose(p2, p, atol=1e-12)
