"""The relight/metrics JSON format (formats/metrics_json.py): round trip, +∞, validation."""

from __future__ import annotations

import json
import math

import pytest

from relight_cli.formats.metrics_json import (FORMAT, VERSION, dumps, flatten, loads,
                                              make_record)


def _record(metrics, kind="image"):
    return make_record(kind, metrics, {}, {}, {"format": FORMAT, "version": 1})


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
