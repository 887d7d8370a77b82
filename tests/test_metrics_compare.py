"""`relight metrics compare`: directions, tolerances, missing/new metrics, +∞, exit codes."""

from __future__ import annotations

import json
import math

import pytest

from conftest import run_relight
from relight_cli.formats.metrics_json import (FORMAT, VERSION, dumps, flatten, loads,
                                              make_record)
from relight_cli.metrics.compare import compare_metrics, lookup


def _record(metrics, kind="image"):
    return make_record(kind, metrics, {}, {}, {"format": FORMAT, "version": 1})


def _write(path, metrics, kind="image"):
    path.write_text(dumps(_record(metrics, kind)))
    return path


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


def test_format_round_trip_and_validation():
    rec = _record({"stage": {"psnr": math.inf, "ssim": 0.5}})
    text = dumps(rec)
    back = loads(text)
    assert back["metrics"] == {"stage": {"psnr": None, "ssim": 0.5}}
    assert flatten(back["metrics"]) == [("stage.psnr", None), ("stage.ssim", 0.5)]
    assert list(back)[:4] == ["format", "version", "kind", "metrics"]
    from relight_cli.errors import DataError
    newer = dict(back, version=VERSION + 1)
    with pytest.raises(DataError, match="newer"):
        loads(json.dumps(newer), "x.json")
    with pytest.raises(DataError, match="not a relight/metrics"):
        loads(json.dumps({"format": "other", "version": 1, "metrics": {}}), "x.json")
    with pytest.raises(DataError, match="not a number"):
        loads(json.dumps(dict(back, metrics={"a": "high"})), "x.json")


def test_cli_exit_codes(run_cli, tmp_path):
    base = _write(tmp_path / "base.json", {"psnr": 30.0, "ssim": 0.9})
    same = _write(tmp_path / "same.json", {"psnr": 30.0, "ssim": 0.9})
    worse = _write(tmp_path / "worse.json", {"psnr": 28.0, "ssim": 0.9})
    r = run_cli("metrics", "compare", same, base)
    assert r.exit_code == 0 and "0 regressed" in r.output
    r = run_cli("metrics", "compare", worse, base)
    assert r.exit_code == 3
    assert "REGRESSED" in r.output and "psnr" in r.output
    r = run_cli("metrics", "compare", worse, base, "--rtol", "psnr=0.1")
    assert r.exit_code == 0, r.output
    r = run_cli("metrics", "compare", worse, base, "--better", "psnr=lower")
    assert r.exit_code == 0 and "improved" in r.output
    r = run_cli("metrics", "compare", worse, base, "--rtol", "psnr=abc")
    assert r.exit_code == 2
    r = run_cli("metrics", "compare", worse, base, "--better", "psnr=sideways")
    assert r.exit_code == 2
    shadow = _write(tmp_path / "shadow.json", {"psnr": 30.0}, kind="shadow")
    r = run_cli("metrics", "compare", shadow, base)
    assert r.exit_code == 1 and "kind" in r.output
    (tmp_path / "broken.json").write_text("{not json")
    r = run_cli("metrics", "compare", tmp_path / "broken.json", base)
    assert r.exit_code == 1 and "broken.json" in r.output


def test_cli_subprocess_regression_code(tmp_path):
    base = _write(tmp_path / "base.json", {"stage": {"mse": 0.01}})
    worse = _write(tmp_path / "new.json", {"stage": {"mse": 0.02}})
    r = run_relight("metrics", "compare", worse, base)
    assert r.returncode == 3
    assert "stage.mse" in r.stdout and "regression" in r.stderr
    r = run_relight("metrics", "compare", tmp_path / "nope.json", base)
    assert r.returncode == 1 and "nope.json" in r.stderr
