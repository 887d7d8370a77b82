"""``relight metrics image`` (commands/metrics_image.py): help, masked scores in-process and from
the console script, batches, LPIPS with local weights, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relight_cli.formats.exr import write_exr
from relight_cli.formats.image import write_png
from relight_cli.metrics.image import image_metrics
from conftest import run_relight


def _rgb_exr(path, rgb):
    write_exr(str(path), {c: rgb[..., i] for i, c in enumerate("RGB")})


def _pair(seed=0, h=24, w=32):
    rng = np.random.default_rng(seed)
    gt = rng.uniform(0, 4, (h, w, 3))
    pred = gt + rng.normal(0, 0.3, gt.shape)
    return pred, gt


# ------------------------------------------------------------------ CLI


@pytest.fixture
def images(tmp_path):
    pred, gt = _pair(7, 24, 32)
    _rgb_exr(tmp_path / "pred.exr", pred.astype(np.float32))
    _rgb_exr(tmp_path / "gt.exr", gt.astype(np.float32))
    mask = np.zeros((24, 32), np.float32)
    mask[4:20, 6:28] = 1
    write_png(str(tmp_path / "mask.png"), mask)
    return tmp_path, pred.astype(np.float32).astype(np.float64), gt.astype(np.float32).astype(np.float64), mask > 0.5


def test_help(run_cli):
    for sub in ("image", "shadow", "compare", "lighting"):
        r = run_cli("metrics", sub, "--help")
        assert r.exit_code == 0 and "Usage" in r.output
    assert "Exit codes" in run_cli("metrics", "--help").output


def test_cli_in_process_masked(run_cli, images):
    d, pred, gt, mask = images
    out = d / "m.json"
    r = run_cli("metrics", "image", d / "pred.exr", d / "gt.exr", "--mask", d / "mask.png",
                "-o", out, "--data-range", "4")
    assert r.exit_code == 0, r.output
    rec = json.loads(out.read_text())
    assert list(rec)[:5] == ["format", "version", "kind", "metrics", "per_channel"]
    assert rec["format"] == "relight/metrics" and rec["version"] == 2 and rec["kind"] == "image"
    ref = image_metrics(pred, gt, mask, data_range=4.0)["metrics"]
    for k in ("mse", "psnr", "ssim", "mae"):
        assert rec["metrics"][k] == pytest.approx(ref[k], rel=1e-12)
    assert set(rec["inputs"]) == {"pred", "gt", "mask"}
    assert len(rec["inputs"]["gt"]["sha256"]) == 64
    assert rec["provenance"]["command"].startswith("relight metrics image")


def test_cli_subprocess_stdout_and_identical_psnr(images):
    d, *_ = images
    r = run_relight("metrics", "image", d / "gt.exr", d / "gt.exr", "-q")
    assert r.returncode == 0, r.stderr
    rec = json.loads(r.stdout)
    assert rec["metrics"]["psnr"] is None  # +∞ is stored as null
    assert rec["metrics"]["mse"] == 0.0


def test_batch_folders_jsonl_and_aggregate(run_cli, tmp_path):
    (tmp_path / "pred").mkdir()
    (tmp_path / "gt").mkdir()
    rows = []
    for i in range(4):
        pred, gt = _pair(10 + i, 16, 16)
        _rgb_exr(tmp_path / "pred" / f"f{i}.exr", pred.astype(np.float32))
        _rgb_exr(tmp_path / "gt" / f"f{i}.exr", gt.astype(np.float32))
        rows.append(image_metrics(pred.astype(np.float32), gt.astype(np.float32),
                                  data_range=1.0)["metrics"])
    _rgb_exr(tmp_path / "gt" / "extra.exr", np.zeros((16, 16, 3), np.float32))
    out, jl = tmp_path / "m.json", tmp_path / "rows.jsonl"
    r = run_cli("metrics", "image", tmp_path / "pred", tmp_path / "gt", "--data-range", "1",
                "-o", out, "--jsonl", jl, "--percentiles", "10,50,90")
    assert r.exit_code == 0, r.output
    rec = json.loads(out.read_text())
    assert rec["pairs"] == 4
    psnrs = np.array([row["psnr"] for row in rows])
    assert rec["metrics"]["psnr"] == pytest.approx(psnrs.mean(), rel=1e-12)
    agg = rec["aggregate"]["psnr"]
    assert agg["median"] == pytest.approx(np.median(psnrs), rel=1e-12)
    assert agg["p90"] == pytest.approx(np.percentile(psnrs, 90), rel=1e-12)
    lines = [json.loads(x) for x in jl.read_text().splitlines()]
    assert [x["name"] for x in lines] == ["f0", "f1", "f2", "f3"]
    # A glob on one side, a folder on the other.
    r = run_cli("metrics", "image", str(tmp_path / "pred" / "f[01].exr"), tmp_path / "gt",
                "--data-range", "1", "-o", tmp_path / "g.json")
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "g.json").read_text())["pairs"] == 2


def _fails(run_cli, code, *args):
    r = run_cli(*args)
    assert r.exit_code == code, r.output
    lines = [x for x in r.output.splitlines() if x.strip()]
    assert len(lines) == 1 and "error" in lines[0] and "Traceback" not in r.output
    return lines[0]


def test_bad_inputs(run_cli, images):
    d, pred, gt, _ = images
    out = d / "never.json"
    _rgb_exr(d / "small.exr", np.ones((10, 10, 3), np.float32))
    line = _fails(run_cli, 1, "metrics", "image", d / "small.exr", d / "gt.exr", "-o", out)
    assert "differs" in line and "small.exr" in line
    line = _fails(run_cli, 1, "metrics", "image", d / "pred.exr", d / "gt.exr",
                  "--mask", d / "nomask.png", "-o", out)
    assert "no such mask file" in line
    bad = pred.astype(np.float32).copy()
    bad[3, 4, 1] = np.nan
    _rgb_exr(d / "nan.exr", bad)
    line = _fails(run_cli, 1, "metrics", "image", d / "nan.exr", d / "gt.exr", "-o", out)
    assert "NaN" in line and "nan.exr" in line
    write_png(str(d / "empty.png"), np.zeros((24, 32), np.float32))
    assert "no pixels" in _fails(run_cli, 1, "metrics", "image", d / "pred.exr", d / "gt.exr",
                                 "--mask", d / "empty.png", "-o", out)
    assert "lpips-weights" in _fails(run_cli, 2, "metrics", "image", d / "pred.exr",
                                     d / "gt.exr", "--lpips", "-o", out)
    _fails(run_cli, 2, "metrics", "image", d / "pred.exr", d / "gt.exr", "--win-size", "4",
           "-o", out)
    (d / "p").mkdir()
    _rgb_exr(d / "p" / "lonely.exr", pred.astype(np.float32))
    line = _fails(run_cli, 1, "metrics", "image", d / "p", d / "gt_dir_missing", "-o", out)
    assert "no such ground truth file or folder" in line and "gt_dir_missing" in line
    assert "both be files" in _fails(run_cli, 2, "metrics", "image", d / "p", d / "gt.exr",
                                     "-o", out)
    (d / "g").mkdir()
    _rgb_exr(d / "g" / "other.exr", gt.astype(np.float32))
    assert "no ground truth for 1" in _fails(run_cli, 1, "metrics", "image", d / "p", d / "g",
                                             "-o", out)
    assert not out.exists()


def test_bad_input_subprocess(images):
    d, *_ = images
    r = run_relight("metrics", "image", d / "pred.exr", d / "missing.exr", "-o", d / "x.json")
    assert r.returncode == 1
    assert r.stderr.strip().count("\n") == 0 and "missing.exr" in r.stderr
    assert not (d / "x.json").exists()


def test_lpips_with_local_weights(run_cli, tmp_path):
    """LPIPS runs only from a local state dict; random weights check the plumbing
    (identical images → 0, different → > 0), not published LPIPS values."""
    torch = pytest.importorskip("torch")
    from relight_cli.metrics.lpips import _CONVS
    g = torch.Generator().manual_seed(0)
    state = {}
    for i, (name, cin, cout, k, _, _) in enumerate(_CONVS):
        state[f"{name}.weight"] = torch.randn(cout, cin, k, k, generator=g) * 0.05
        state[f"{name}.bias"] = torch.zeros(cout)
        state[f"lin{i}.model.1.weight"] = torch.rand(1, cout, 1, 1, generator=g)
    torch.save(state, tmp_path / "lpips.pth")
    rng = np.random.default_rng(0)
    gt = rng.uniform(0, 1, (48, 48, 3)).astype(np.float32)
    write_png(str(tmp_path / "gt.png"), gt)
    write_png(str(tmp_path / "pred.png"), np.clip(gt + 0.2, 0, 1))
    r = run_cli("metrics", "image", tmp_path / "gt.png", tmp_path / "gt.png", "--space", "display",
                "--lpips-weights", tmp_path / "lpips.pth", "-o", tmp_path / "same.json")
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "same.json").read_text())["metrics"]["lpips"] == 0.0
    r = run_cli("metrics", "image", tmp_path / "pred.png", tmp_path / "gt.png", "--space", "display",
                "--lpips-weights", tmp_path / "lpips.pth", "-o", tmp_path / "diff.json")
    assert json.loads((tmp_path / "diff.json").read_text())["metrics"]["lpips"] > 0
    del state["lin4.model.1.weight"]
    torch.save(state, tmp_path / "bad.pth")
    r = run_cli("metrics", "image", tmp_path / "pred.png", tmp_path / "gt.png", "--space", "display",
                "--lpips-weights", tmp_path / "bad.pth", "-o", tmp_path / "x.json")
    assert r.exit_code == 1 and "lin4.model.1.weight" in r.output
    r = run_cli("metrics", "image", tmp_path / "pred.png", tmp_path / "gt.png",
                "--lpips-weights", tmp_path / "lpips.pth", "-o", tmp_path / "x.json")
    assert r.exit_code == 2 and "--space" in r.output      # LPIPS needs display values
    assert not (tmp_path / "x.json").exists()
