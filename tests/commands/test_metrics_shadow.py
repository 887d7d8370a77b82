"""``relight metrics shadow`` (commands/metrics_shadow.py): in-process, visibility, console script,
bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import run_relight
from relight_cli.formats.exr import write_exr


def square(h, w, y0, x0, s, value=1.0):
    m = np.zeros((h, w))
    m[y0:y0 + s, x0:x0 + s] = value
    return m


def _grey_exr(path, values):
    write_exr(str(path), {"Y": np.asarray(values, np.float32)})


def test_cli_in_process_and_visibility(run_cli, tmp_path):
    gt = square(40, 40, 10, 10, 20, 0.8)
    pred = square(40, 40, 10, 15, 20, 0.6)
    _grey_exr(tmp_path / "p.exr", pred)
    _grey_exr(tmp_path / "g.exr", gt)
    _grey_exr(tmp_path / "pv.exr", 1 - pred)
    _grey_exr(tmp_path / "gv.exr", 1 - gt)
    r = run_cli("metrics", "shadow", tmp_path / "p.exr", tmp_path / "g.exr", "-o", tmp_path / "s.json")
    assert r.exit_code == 0, r.output
    rec = json.loads((tmp_path / "s.json").read_text())
    assert rec["kind"] == "shadow" and rec["metrics"]["sm_iou"] == pytest.approx(0.6)
    assert rec["details"]["sae_region"] == "gt"
    r = run_cli("metrics", "shadow", tmp_path / "pv.exr", tmp_path / "gv.exr", "--matte",
                "visibility", "-o", tmp_path / "v.json")
    assert r.exit_code == 0, r.output
    v = json.loads((tmp_path / "v.json").read_text())
    for k, value in rec["metrics"].items():
        assert v["metrics"][k] == pytest.approx(value, abs=1e-6)  # float32 1 − x rounding


def test_cli_subprocess_and_bad_input(tmp_path):
    _grey_exr(tmp_path / "p.exr", square(16, 16, 2, 2, 5))
    _grey_exr(tmp_path / "g.exr", square(16, 16, 2, 2, 5))
    r = run_relight("metrics", "shadow", tmp_path / "p.exr", tmp_path / "g.exr", "--roi", "0,0,8,8")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["metrics"]["sm_iou"] == 1.0
    _grey_exr(tmp_path / "big.exr", np.zeros((20, 16)))
    out = tmp_path / "x.json"
    r = run_relight("metrics", "shadow", tmp_path / "big.exr", tmp_path / "g.exr", "-o", out)
    assert r.returncode == 1 and "differs" in r.stderr and "big.exr" in r.stderr
    _grey_exr(tmp_path / "hdr.exr", square(16, 16, 2, 2, 5, 3.0))
    r = run_relight("metrics", "shadow", tmp_path / "hdr.exr", tmp_path / "g.exr", "-o", out)
    assert r.returncode == 1 and "[0, 1]" in r.stderr
    nan = square(16, 16, 2, 2, 5)
    nan[0, 0] = np.nan
    _grey_exr(tmp_path / "nan.exr", nan)
    r = run_relight("metrics", "shadow", tmp_path / "nan.exr", tmp_path / "g.exr", "-o", out)
    assert r.returncode == 1 and "NaN" in r.stderr
    r = run_relight("metrics", "shadow", tmp_path / "p.exr", tmp_path / "g.exr", "--roi", "10,10,10,10",
                    "-o", out)
    assert r.returncode == 2 and "ROI" in r.stderr
    r = run_relight("metrics", "shadow", tmp_path / "p.exr", tmp_path / "g.exr", "--roi", "1,2",
                    "-o", out)
    assert r.returncode == 2
    for err in (r.stderr,):
        assert err.strip().count("\n") == 0 and "Traceback" not in err
    assert not out.exists()
