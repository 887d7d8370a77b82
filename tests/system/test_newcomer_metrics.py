"""`relight metrics image` scores inside the ground truth's mask by default (issue 24).

A synthetic pair whose background is perfect and whose inside differs: the default score
is the masked one (checked against numpy), `--whole-image` gives the whole-image one, and
the record says which region was scored (`details.region`, `mask_source`, `pixels`).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from conftest import run_relight
from relight_cli.formats.exr import write_exr
from relight_cli.formats.image import write_png

H, W = 24, 32


def _exr(path, rgb, alpha=None, extra=None):
    channels = {c: rgb[..., i].astype(np.float32) for i, c in enumerate("RGB")}
    if alpha is not None:
        channels["A"] = alpha.astype(np.float32)
    channels.update(extra or {})
    write_exr(str(path), channels)


def _psnr(pred, gt, region):
    """numpy reference: MSE over the region's pixels and channels, R = max − min of the
    ground truth over the region (the linear space's default)."""
    diff = (pred - gt)[region]
    r = gt[region].max() - gt[region].min()
    return 10 * math.log10(r ** 2 / np.mean(diff ** 2))


@pytest.fixture
def pair(tmp_path):
    """GT with alpha = a rectangle (the hand); pred equals GT outside it, noisy inside."""
    rng = np.random.default_rng(3)
    gt = rng.uniform(0.1, 2.0, (H, W, 3))
    mask = np.zeros((H, W), bool)
    mask[5:19, 8:26] = True
    pred = gt.copy()
    pred[mask] += rng.normal(0, 0.2, (mask.sum(), 3))
    gt, pred = gt.astype(np.float32).astype(np.float64), pred.astype(np.float32).astype(np.float64)
    alpha = np.where(mask, 1.0, 0.0)
    alpha[4, 8:26] = 0.4                                # a soft edge below 0.5: background
    _exr(tmp_path / "gt.exr", gt, alpha)
    _exr(tmp_path / "pred.exr", pred, np.ones((H, W)))  # the prediction's alpha is ignored
    return tmp_path, pred, gt, mask


def test_masked_by_default_whole_image_on_request(run_cli, pair):
    d, pred, gt, mask = pair
    r = run_cli("metrics", "image", d / "pred.exr", d / "gt.exr", "-o", d / "m.json")
    assert r.exit_code == 0, r.output
    rec = json.loads((d / "m.json").read_text())
    assert rec["metrics"]["psnr"] == pytest.approx(_psnr(pred, gt, mask), rel=1e-9)
    assert rec["metrics"]["mse"] == pytest.approx(np.mean((pred - gt)[mask] ** 2), rel=1e-9)
    assert rec["details"]["region"] == "mask" and rec["details"]["mask_source"] == "alpha"
    assert rec["details"]["pixels"] == mask.sum() and rec["details"]["image_pixels"] == H * W
    assert list(rec["details"])[:4] == ["region", "mask_source", "pixels", "image_pixels"]
    assert rec["settings"]["whole_image"] is False and rec["settings"]["mask"] is False
    assert "inside the ground truth's alpha" in r.stderr

    r = run_cli("metrics", "image", d / "pred.exr", d / "gt.exr", "--whole-image",
                "-o", d / "w.json")
    assert r.exit_code == 0, r.output
    whole = json.loads((d / "w.json").read_text())
    everything = np.ones((H, W), bool)
    assert whole["metrics"]["psnr"] == pytest.approx(_psnr(pred, gt, everything), rel=1e-9)
    assert whole["details"]["region"] == "image" and "mask_source" not in whole["details"]
    assert whole["details"]["pixels"] == H * W and whole["settings"]["whole_image"] is True
    # a perfect background only dilutes the error: the whole-image score flatters
    assert whole["metrics"]["mse"] < rec["metrics"]["mse"]


def test_mask_file_wins_and_cannot_go_with_whole_image(run_cli, pair):
    d, pred, gt, mask = pair
    fg = np.zeros((H, W), np.float32)
    fg[8:16, 10:20] = 1
    write_png(str(d / "fg.png"), fg)
    r = run_cli("metrics", "image", d / "pred.exr", d / "gt.exr", "--mask", d / "fg.png")
    assert r.exit_code == 0, r.output
    rec = json.loads(r.stdout)
    assert rec["details"]["mask_source"] == "file" and rec["details"]["pixels"] == 80
    assert rec["metrics"]["psnr"] == pytest.approx(_psnr(pred, gt, fg > 0.5), rel=1e-9)
    r = run_cli("metrics", "image", d / "pred.exr", d / "gt.exr", "--mask", d / "fg.png",
                "--whole-image", "-o", d / "x.json")
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert r.exit_code == 2 and len(lines) == 1 and "--whole-image" in lines[0], r.output
    assert not (d / "x.json").exists()


def test_no_alpha_scores_every_pixel(run_cli, tmp_path):
    rng = np.random.default_rng(0)
    gt = rng.uniform(0, 1, (H, W, 3))
    _exr(tmp_path / "gt.exr", gt)
    _exr(tmp_path / "pred.exr", gt + 0.01)
    rec = json.loads(run_cli("metrics", "image", tmp_path / "pred.exr", tmp_path / "gt.exr").stdout)
    assert rec["details"]["region"] == "image" and rec["details"]["pixels"] == H * W


def test_alpha_is_A_not_a_hands_coverage(run_cli, tmp_path):
    """A two-hand capture image has A (both hands) and hand0.A, hand1.A: A is the mask."""
    gt = np.full((H, W, 3), 0.5)
    alpha = np.zeros((H, W))
    alpha[4:20, 4:28] = 1
    left = np.zeros((H, W), np.float32)
    left[4:20, 4:12] = 1
    _exr(tmp_path / "gt.exr", gt, alpha, {"hand0.A": left, "hand1.A": alpha - left})
    _exr(tmp_path / "pred.exr", gt + 0.1)
    rec = json.loads(run_cli("metrics", "image", tmp_path / "pred.exr", tmp_path / "gt.exr").stdout)
    assert rec["details"]["pixels"] == 16 * 24 and list(rec["per_channel"]) == ["R", "G", "B"]


def test_empty_alpha_is_one_line_naming_whole_image(run_cli, pair):
    d, pred, gt, _ = pair
    _exr(d / "blank.exr", gt, np.zeros((H, W)))
    r = run_cli("metrics", "image", d / "pred.exr", d / "blank.exr", "-o", d / "x.json")
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert r.exit_code == 1 and len(lines) == 1, r.output
    assert "--whole-image" in lines[0] and lines[0].endswith(f"({d / 'blank.exr'})")
    assert not (d / "x.json").exists()
    r = run_cli("metrics", "image", d / "pred.exr", d / "blank.exr", "--whole-image")
    assert r.exit_code == 0 and json.loads(r.stdout)["details"]["region"] == "image"


def test_batch_says_which_pairs_were_masked(run_cli, pair):
    d, pred, gt, mask = pair
    for folder in ("p", "g"):
        (d / folder).mkdir()
    _exr(d / "p" / "a.exr", pred)
    _exr(d / "g" / "a.exr", gt, np.where(mask, 1.0, 0.0))
    _exr(d / "p" / "b.exr", pred)
    _exr(d / "g" / "b.exr", gt)                        # no alpha: every pixel
    r = run_cli("metrics", "image", d / "p", d / "g", "--jsonl", d / "rows.jsonl",
                "-o", d / "m.json")
    assert r.exit_code == 0, r.output
    rec = json.loads((d / "m.json").read_text())
    assert rec["details"] == {"region": "mixed", "masked_pairs": 1}
    rows = [json.loads(x) for x in (d / "rows.jsonl").read_text().splitlines()]
    assert [(x["name"], x["region"], x["pixels"]) for x in rows] == [
        ("a", "mask", int(mask.sum())), ("b", "image", H * W)]
    r = run_cli("metrics", "image", d / "p", d / "g", "--whole-image")
    assert json.loads(r.stdout)["details"] == {"region": "image", "masked_pairs": 0}


def test_console_script_default_is_masked(pair):
    d, pred, gt, mask = pair
    r = run_relight("metrics", "image", d / "pred.exr", d / "gt.exr")
    assert r.returncode == 0, r.stderr
    rec = json.loads(r.stdout)
    assert rec["details"]["region"] == "mask"
    assert rec["metrics"]["psnr"] == pytest.approx(_psnr(pred, gt, mask), rel=1e-9)
    assert r.stderr.count("\n") == 1 and f"{int(mask.sum())} of {H * W} pixels" in r.stderr


def test_help_says_the_default_region(run_cli):
    text = run_cli("metrics", "image", "--help").output
    assert "--whole-image" in text and "alpha" in text and "details.region" in text


def test_preview_shows_prediction_ground_truth_and_error(run_cli, pair):
    """--preview: one labelled PNG, prediction and ground truth on the ground truth's exposure
    (equal where the pair is equal), the error tile black where they agree and bright inside."""
    from PIL import Image
    d, pred, gt, mask = pair
    r = run_cli("metrics", "image", d / "pred.exr", d / "gt.exr", "-o", d / "m.json",
                "--preview", d / "p.png")
    assert r.exit_code == 0, r.output
    sheet_px = np.asarray(Image.open(d / "p.png").convert("RGB"), np.float64) / 255
    assert sheet_px.shape[0] > 3 * H and sheet_px.shape[1] > 3 * W * 3
    # the tiles: prediction and ground truth on one exposure, so equal where the pair is
    # (outside the rectangle); the error tile black there and lit inside
    from relight_cli.jobs.metrics import comparison_tiles
    shown_pred, shown_gt, err = comparison_tiles(pred, gt, mask)
    np.testing.assert_array_equal(shown_pred.image[~mask], shown_gt.image[~mask])
    assert np.abs(shown_pred.image[mask] - shown_gt.image[mask]).max() > 0.05
    assert err.image[~mask].max() == 0 and np.median(err.image[mask]) > 0.1
    assert shown_pred.note.split(",")[0] == shown_gt.note == "white = " + shown_gt.note[8:]
    # one pair only; nothing written on a refusal
    (d / "a").mkdir()
    (d / "b").mkdir()
    for k in range(2):
        _exr(d / "a" / f"{k}.exr", pred)
        _exr(d / "b" / f"{k}.exr", gt)
    r = run_cli("metrics", "image", d / "a", d / "b", "-o", d / "m2.json", "--preview",
                d / "p2.png")
    assert r.exit_code == 2 and "--preview shows one pair" in r.output
    assert not (d / "p2.png").exists() and not (d / "m2.json").exists()
    # --preview onto -o or onto an input: a usage error, nothing written, the input untouched
    before = (d / "gt.exr").read_bytes()
    for target, message in ((d / "m3.json", "two outputs go to one file"),
                            (d / "gt.exr", "name it .png")):
        r = run_cli("metrics", "image", d / "pred.exr", d / "gt.exr", "-o", d / "m3.json",
                    "--preview", target)
        assert r.exit_code == 2 and message in r.output, r.output
        assert not (d / "m3.json").exists()
    assert (d / "gt.exr").read_bytes() == before
