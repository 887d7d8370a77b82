"""Comparing metric records (relight_cli/metrics/compare.py): directions, tolerances, lookup
precedence, missing/new metrics, +∞."""

from __future__ import annotations

import math

import pytest

from relight_cli.metrics.compare import compare_metrics, lookup


def test_directions_and_slack():
    base = [("psnr", 30.0), ("mse", 0.01), ("custom", 5.0)]
    rows = compare_metrics([("psnr", 29.99), ("mse", 0.0100001), ("custom", 5.0)], base)
    assert [r.status for r in rows] == ["ok", "ok", "ok"]   # within rtol 1e-3
    rows = compare_metrics([("psnr", 29.0), ("mse", 0.005), ("custom", 5.1)], base)
    assert [r.status for r in rows] == ["REGRESSED", "improved", "REGRESSED"]  # custom: either
    rows = compare_metrics([("psnr", 29.0), ("mse", 0.02), ("custom", 5.1)], base,
                           rtol={"psnr": 0.05}, atol={"*.x": 1, "mse": 0.02},
                           better={"custom": "higher"})
    assert [r.status for r in rows] == ["ok", "ok", "improved"]
    assert rows[0].slack == pytest.approx(1e-9 + 0.05 * 30)


def test_lookup_precedence():
    opts = {None: 1, "psnr": 2, "*.psnr": 3, "stage.psnr": 4}
    assert lookup(opts, "stage.psnr", 0) == 4
    assert lookup(opts, "other.psnr", 0) == 3
    assert lookup(opts, "psnr", 0) == 2
    assert lookup(opts, "mse", 0) == 1
    assert lookup({}, "mse", 7) == 7


def test_missing_new_and_infinity():
    rows = compare_metrics([("a.psnr", math.inf), ("b", 1.0)],
                           [("a.psnr", math.inf), ("a.mse", 0.0)])
    status = {r.key: r.status for r in rows}
    assert status == {"a.psnr": "ok", "a.mse": "missing", "b": "new"}
    rows = compare_metrics([("psnr", 80.0)], [("psnr", math.inf)])
    assert rows[0].status == "REGRESSED"      # identical images no longer identical
    rows = compare_metrics([("psnr", math.inf)], [("psnr", 80.0)])
    assert rows[0].status == "improved"
