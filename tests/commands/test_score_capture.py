"""`relight relight CAPTURE/` (commands/score_capture.py): its scores line."""

from __future__ import annotations


def test_the_scores_line_gives_psnr_beside_mse_and_ssim(tiny_models, run_cli, tmp_path):
    """``relight relight CAPTURE/``'s closing line (issue 53): per split the MSE, the PSNR
    with its gap to the ceiling, the SSIM and the sample count, each the number the
    written relight/metrics JSON holds."""
    import json
    import re

    from models import SWEEP_CAPTURE, SWEEP_TEACHER
    capture = tiny_models.get("capture", SWEEP_CAPTURE)
    teacher = tiny_models.get(SWEEP_TEACHER[0], SWEEP_CAPTURE, *SWEEP_TEACHER[1:])
    out = tmp_path / "scores.json"
    r = run_cli("relight", capture, "--model", "teacher", "--checkpoint", teacher,
                "--eval-samples", "1", "-o", out)
    assert r.exit_code == 0, r.output
    line = next(x for x in r.output.splitlines() if x.startswith(f"wrote {out} ("))
    metrics = json.loads(out.read_text())["metrics"]
    assert metrics
    for name, m in metrics.items():
        said = re.search(rf"{name}: MSE ([\d.]+)e-3 PSNR (-?[\d.]+) dB \((-?[\d.]+) dB below its "
                         rf"ceiling\) SSIM ([\d.]+) \((\d+)\)", line)
        assert said, (name, line)
        assert float(said.group(1)) == round(m["mse"] * 1e3, 3)
        assert float(said.group(2)) == round(m["psnr"], 2)
        assert abs(float(said.group(3)) - (m["ceiling"]["psnr"] - m["psnr"])) <= 0.005 + 1e-9
        assert float(said.group(4)) == round(m["ssim"], 3)
        assert int(said.group(5)) == m["samples"]
    # a split scored without a ceiling: no gap
    from relight_cli.commands.score_capture import summary
    one = {"mse": 1e-3, "psnr": 30.0, "ssim": 0.9, "samples": 2}
    assert summary({"env": one}) == "env: MSE 1.000e-3 PSNR 30.00 dB SSIM 0.900 (2)"
