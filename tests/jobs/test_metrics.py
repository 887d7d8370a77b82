"""relight_cli.jobs.metrics called without click: closed forms on tiny images and Gaussians, and
results equal to what ``relight metrics`` writes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from relight_cli.errors import DataError, UsageProblem
from relight_cli.formats.gaussians_ply import Gaussians, rgb_to_sh_dc


def _gaussians(means, scale, alpha=0.9):
    means = np.asarray(means, np.float64).reshape(-1, 3)
    n = len(means)
    return Gaussians(means, np.full((n, 3), scale), np.tile([1.0, 0, 0, 0], (n, 1)),
                     np.full(n, alpha), rgb_to_sh_dc(np.full((n, 3), 0.6))[:, None, :], 0)


def _cli(*args):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


# ------------------------------------------------------------------ metrics image


def test_image_job_psnr_of_a_known_mse():
    """pred = gt + c on every channel: MSE = c², PSNR = 10·log10(R²/c²), MAE = c, inside
    the region only (the offset outside it is not scored)."""
    from relight_cli.jobs.metrics import ImageOptions, ImagePair, image

    rng = np.random.default_rng(0)
    gt = rng.uniform(0.0, 1.0, (12, 16, 3)).astype(np.float32)
    pred = gt + np.float32(0.25)
    region = np.zeros((12, 16), bool)
    region[2:10, 3:13] = True
    pred[~region] += 5.0
    scores = image([ImagePair("x", pred, gt, ["R", "G", "B"], region, "file")],
                   ImageOptions(data_range=2.0))
    r = scores.results[0][4]
    assert r["metrics"]["mse"] == pytest.approx(0.0625, rel=1e-5)
    assert r["metrics"]["mae"] == pytest.approx(0.25, rel=1e-5)
    assert r["metrics"]["psnr"] == pytest.approx(10 * math.log10(4.0 / 0.0625), rel=1e-5)
    assert r["region"] == "mask" and r["pixels"] == 80 and r["image_pixels"] == 192
    assert scores.note == "inside --mask (80 of 192 pixels)" and scores.preview is None


def test_image_job_equals_what_the_cli_writes(tmp_path):
    """A batch of two pairs scored inside the ground truths' alpha: the job's record and
    rows equal the command's JSON and JSONL (but for provenance); a one-pair preview."""
    from relight_cli.formats.exr import write_exr
    from relight_cli.formats.image import read_image
    from relight_cli.jobs.metrics import ImageOptions, ImagePair, image

    rng = np.random.default_rng(1)
    (tmp_path / "p").mkdir()
    (tmp_path / "g").mkdir()
    pairs = []
    for name in ("a", "b"):
        gt = rng.uniform(0.1, 2.0, (10, 14, 3)).astype(np.float32)
        pred = (gt * rng.uniform(0.8, 1.2, gt.shape)).astype(np.float32)
        alpha = (rng.uniform(size=(10, 14)) > 0.3).astype(np.float32)
        gp, pp = str(tmp_path / "g" / f"{name}.exr"), str(tmp_path / "p" / f"{name}.exr")
        write_exr(gp, {**{c: gt[..., i] for i, c in enumerate("RGB")}, "A": alpha})
        write_exr(pp, {c: pred[..., i] for i, c in enumerate("RGB")})
        g, _ = read_image(gp)
        p, _ = read_image(pp)
        pairs.append(ImagePair(name, p[..., [0, 1, 2]], g[..., [0, 1, 2]], ["R", "G", "B"],
                               g[..., 3] > 0.5, "alpha", pp, gp))
    out, rows = tmp_path / "m.json", tmp_path / "m.jsonl"
    r = _cli("metrics", "image", tmp_path / "p", tmp_path / "g", "--space", "srgb",
             "--percentiles", "10,90", "--jsonl", rows, "-o", out, "-q")
    assert r.exit_code == 0, r.output
    scores = image(pairs, ImageOptions(space="srgb", percentiles=[10.0, 90.0]), multi=True)
    record, job_rows = scores.record({"inputs": {}})
    written = json.loads(out.read_text())
    for key in ("kind", "metrics", "aggregate", "pairs", "details", "settings"):
        assert record[key] == written[key], key
    assert [json.loads(line) for line in rows.read_text().splitlines()] == job_rows
    assert set(scores.inputs()) == {"a:pred", "a:gt", "b:pred", "b:gt"}
    one = image(pairs[:1], ImageOptions(preview=True))
    assert one.preview.shape[-1] == 3 and 0 <= one.preview.min() < one.preview.max() <= 1
    assert set(one.inputs()) == {"pred", "gt"}


# ------------------------------------------------------------------ metrics shadow, lighting


def test_shadow_job_closed_forms_and_cli(tmp_path):
    """Identical mattes: SAE 0, IoU 1; a visibility matte is 1 − shadow; a shifted square
    has IoU = overlap / union; the job equals the command's record."""
    from PIL import Image

    from relight_cli.jobs.metrics import ShadowOptions, ShadowPair, shadow

    gt = np.zeros((20, 20))
    gt[4:12, 4:12] = 1.0
    pred = np.zeros((20, 20))
    pred[6:14, 4:12] = 1.0
    same = shadow([ShadowPair("s", gt, gt)], ShadowOptions()).results[0][4]["metrics"]
    assert same["sae"] == 0 and same["sm_iou"] == 1 and same["boundary_f"] == 1
    vis = shadow([ShadowPair("v", 1 - pred, 1 - gt)], ShadowOptions(matte="visibility"))
    m = vis.results[0][4]["metrics"]
    assert m["sm_iou"] == pytest.approx(48 / 80) and m["sae"] == pytest.approx(16 / 64)
    Image.fromarray((pred * 255).astype(np.uint8)).save(tmp_path / "p.png")
    Image.fromarray((gt * 255).astype(np.uint8)).save(tmp_path / "g.png")
    r = _cli("metrics", "shadow", tmp_path / "p.png", tmp_path / "g.png", "--roi", "2,2,16,16",
             "-o", tmp_path / "s.json", "-q")
    assert r.exit_code == 0, r.output
    scores = shadow([ShadowPair("p", pred, gt, str(tmp_path / "p.png"), str(tmp_path / "g.png"))],
                    ShadowOptions(roi=(2, 2, 16, 16)))
    record, _ = scores.record({"inputs": {}})
    written = json.loads((tmp_path / "s.json").read_text())
    for key in ("metrics", "details", "settings"):
        assert record[key] == written[key], key
    with pytest.raises(UsageProblem):
        shadow([ShadowPair("p", pred, gt)], ShadowOptions(roi=(30, 30, 4, 4)))


def test_lighting_job_equals_what_the_cli_writes(tmp_path):
    """An avatar shell inside a lit scene shell: the job's metrics and settings are the
    command's; a relit avatar adds relit and delta."""
    from relight_cli.formats.gaussians_ply import read_gaussians, write_gaussians
    from relight_cli.jobs.metrics import LightingOptions, lighting

    rng = np.random.default_rng(2)
    d = rng.normal(size=(160, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    key = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])
    scene = _gaussians(d * 1.2, 0.05)
    scene.sh[:, 0] = rgb_to_sh_dc(0.15 + 0.8 * np.clip(d @ key, 0, None)[:, None] ** 2
                                  * np.array([1.0, 0.9, 0.7]))
    avatar = _gaussians(d[:120] * 0.3, 0.01)
    avatar.sh[:, 0] = rgb_to_sh_dc(0.2 + 0.6 * np.clip(d[:120] @ key, 0, None)[:, None]
                                   * np.ones(3))
    for name, g in (("scene", scene), ("avatar", avatar)):
        write_gaussians(str(tmp_path / f"{name}.ply"), g)
    r = _cli("metrics", "lighting", "--scene", tmp_path / "scene.ply", "--avatar",
             tmp_path / "avatar.ply", "--relit", tmp_path / "avatar.ply", "--max-points", "64",
             "--neighbours", "8", "-o", tmp_path / "l.json", "-q")
    assert r.exit_code == 0, r.output
    s, a = read_gaussians(str(tmp_path / "scene.ply")), read_gaussians(str(tmp_path / "avatar.ply"))
    scores = lighting(s, [a], [a], LightingOptions(neighbours=8, max_points=64))
    record = scores.record({"inputs": {}})
    written = json.loads((tmp_path / "l.json").read_text())
    for key in ("metrics", "settings", "frames"):
        assert record[key] == written[key], key
    assert record["metrics"]["delta"]["paa_y"] == 0   # relit = orig


# ------------------------------------------------------------------ metrics compare


def _record(kind, **metrics):
    from relight_cli.formats.metrics_json import make_record
    return make_record(kind, metrics, {}, {}, {})


def test_compare_job_gates_on_the_bad_direction_only():
    """PSNR down beyond atol + rtol·|base| regresses, up never does; an unknown option
    name and a kind mismatch are refused."""
    from relight_cli.jobs.metrics import compare

    base = _record("image", psnr=30.0, mse=0.01)
    worse = compare(_record("image", psnr=29.0, mse=0.01), base)
    better = compare(_record("image", psnr=31.0, mse=0.005), base)
    within = compare(_record("image", psnr=29.0, mse=0.01), base, rtols={"psnr": 0.05})
    assert worse.regressed and not better.regressed and not within.regressed
    assert "REGRESSED" in worse.table() and worse.kind == "image"
    with pytest.raises(DataError, match="differs from the baseline"):
        compare(_record("shadow", sae=0.1), base)
    with pytest.raises(UsageProblem, match="--rtol names no metric"):
        compare(base, base, rtols={"nope": 0.1})
