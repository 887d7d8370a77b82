"""``relight metrics compare`` (commands/metrics_compare.py): exit codes in-process and from the
console script."""

from __future__ import annotations

from conftest import run_relight
from relight_cli.formats.metrics_json import FORMAT, dumps, make_record


def _record(metrics, kind="image"):
    return make_record(kind, metrics, {}, {}, {"format": FORMAT, "version": 1})


def _write(path, metrics, kind="image"):
    path.write_text(dumps(_record(metrics, kind)))
    return path


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
