"""Shadow metrics (relight_cli/metrics/shadow.py): SAE, SM-IoU, boundary F-measure on synthetic
mattes with known answers, defined empty cases, the slow twin, ROI."""

from __future__ import annotations

import math

import numpy as np
import pytest

from relight_cli.metrics.shadow import (boundary, boundary_scores, boundary_scores_reference,
                                        shadow_metrics)


def disc(h, w, cy, cx, r, value=1.0):
    y, x = np.mgrid[0:h, 0:w]
    return np.where((y - cy) ** 2 + (x - cx) ** 2 <= r * r, value, 0.0)


def square(h, w, y0, x0, s, value=1.0):
    m = np.zeros((h, w))
    m[y0:y0 + s, x0:x0 + s] = value
    return m


def test_shifted_squares_exact_iou_and_sae():
    gt = square(64, 64, 10, 10, 20, 0.8)
    pred = square(64, 64, 10, 15, 20, 0.6)   # shifted 5 px right, weaker shadow
    m = shadow_metrics(pred, gt)["metrics"]
    # |P∩G| = 20·15 = 300, |P∪G| = 800 − 300 = 500.
    assert m["sm_iou"] == pytest.approx(0.6, abs=1e-15)
    # Over G: 300 px with |0.6 − 0.8| = 0.2, 100 px with |0 − 0.8| = 0.8 → (60 + 80)/400.
    assert m["sae"] == pytest.approx(140 / 400, rel=1e-12)


def test_shifted_discs_iou_matches_lens_area():
    r, d = 20.0, 10.0
    gt = disc(80, 100, 40, 40, r)
    pred = disc(80, 100, 40, 40 + d, r)
    m = shadow_metrics(pred, gt)["metrics"]
    lens = 2 * r * r * math.acos(d / (2 * r)) - d / 2 * math.sqrt(4 * r * r - d * d)
    iou = lens / (2 * math.pi * r * r - lens)
    # Pixelized discs of radius 20: area error ~ perimeter·O(1 px)/area ≈ a few %.
    assert m["sm_iou"] == pytest.approx(iou, abs=0.02)


def test_boundary_tolerance():
    gt = disc(64, 64, 32, 32, 15)
    near = disc(64, 64, 32, 33, 15)     # 1 px shift: every boundary pixel within 2 px
    far = disc(64, 64, 32, 38, 15)      # 6 px shift: only the top/bottom arcs match
    assert shadow_metrics(near, gt, tolerance=2)["metrics"]["boundary_f"] == 1.0
    f_far = shadow_metrics(far, gt, tolerance=2)["metrics"]["boundary_f"]
    assert 0.1 < f_far < 0.7
    assert shadow_metrics(far, gt, tolerance=6)["metrics"]["boundary_f"] == 1.0


def test_ring_boundary_has_two_circles():
    ring = disc(64, 64, 32, 32, 20) - disc(64, 64, 32, 32, 10)
    filled = disc(64, 64, 32, 32, 20)
    b = boundary(ring > 0.5)
    assert b.sum() > boundary(filled > 0.5).sum()  # inner circle adds boundary pixels
    p, r, f = boundary_scores(filled > 0.5, ring > 0.5, 1.0)
    assert p == 1.0 and r < 1.0  # the inner circle of the ring is missed by the disc


def test_fast_boundary_matches_slow_twin():
    rng = np.random.default_rng(0)
    for _ in range(5):
        a = rng.uniform(size=(24, 30)) > 0.6
        b = rng.uniform(size=(24, 30)) > 0.6
        for tol in (0.0, 1.0, 1.5, 3.0):
            assert boundary_scores(a, b, tol) == pytest.approx(boundary_scores_reference(a, b, tol),
                                                               abs=1e-15)


def test_empty_and_full_cases():
    empty = np.zeros((16, 16))
    full = np.ones((16, 16))
    some = square(16, 16, 4, 4, 6, 0.5)
    m = shadow_metrics(empty, empty)
    assert m["metrics"] == {"sae": 0.0, "sm_iou": 1.0, "boundary_f": 1.0,
                            "boundary_precision": 1.0, "boundary_recall": 1.0}
    assert m["sae_region"] == "none"
    m = shadow_metrics(full, full)["metrics"]
    assert m["sm_iou"] == 1.0 and m["boundary_f"] == 1.0 and m["sae"] == 0.0
    m = shadow_metrics(full, empty)["metrics"]   # phantom shadow everywhere
    assert m["sm_iou"] == 0.0 and m["boundary_f"] == 0.0 and m["sae"] == 1.0
    m = shadow_metrics(some, empty)            # GT empty: SAE over the predicted region
    assert m["sae_region"] == "pred" and m["metrics"]["sae"] == pytest.approx(0.5)
    assert m["metrics"]["sm_iou"] == 0.0 and m["metrics"]["boundary_f"] == 0.0
    m = shadow_metrics(empty, some)["metrics"]
    assert m["sae"] == pytest.approx(0.5) and m["sm_iou"] == 0.0 and m["boundary_f"] == 0.0


def test_roi_crops_both():
    gt = square(32, 32, 2, 2, 6) + square(32, 32, 20, 20, 6)
    pred = square(32, 32, 2, 2, 6)
    assert shadow_metrics(pred, gt)["metrics"]["sm_iou"] == pytest.approx(0.5)
    assert shadow_metrics(pred, gt, roi=(0, 0, 12, 12))["metrics"]["sm_iou"] == 1.0
    with pytest.raises(ValueError):
        shadow_metrics(pred, gt, roi=(20, 20, 20, 20))
