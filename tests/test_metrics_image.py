"""`relight metrics image`: MSE/PSNR/SSIM/MAE against scikit-image and hand-computed cases,
masked metrics, batches, the CLI surface and bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from skimage.metrics import mean_squared_error, peak_signal_noise_ratio, structural_similarity

from relight_cli.formats.exr import write_exr
from relight_cli.formats.image import write_png
from relight_cli.metrics.image import image_metrics, masked_ssim_map, to_space

from conftest import run_relight


def _rgb_exr(path, rgb):
    write_exr(str(path), {c: rgb[..., i] for i, c in enumerate("RGB")})


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
