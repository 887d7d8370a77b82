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


def test_the_ceilings_env_lighting_is_announced_unless_quiet(tiny_models, run_cli, tmp_path):
    """Issue 53: the ceiling's env lighting (tens of seconds at the stage's size) ran with
    no line.  Scoring the env split says once per (pose, map) what it traces; -q says
    nothing."""
    from models import SWEEP_CAPTURE, SWEEP_TEACHER
    # the sweep's capture with one held-out pose under one env map
    args = [a for a in SWEEP_CAPTURE if a != "-q"]
    args[args.index("--eval-poses") + 1] = "1"
    args += ["--eval-envs", "builtin:sky", "--eval-env-res", "16x8", "-q"]
    capture = tiny_models.get("capture", args)
    teacher = tiny_models.get(SWEEP_TEACHER[0], args, *SWEEP_TEACHER[1:])
    r = run_cli("relight", capture, "--model", "teacher", "--checkpoint", teacher,
                "--splits", "env", "--eval-samples", "2", "-o", tmp_path / "a.json")
    assert r.exit_code == 0, r.output
    said = [x for x in r.output.splitlines() if "ceiling: tracing the stage's lighting" in x]
    assert said and len(said) == len(set(said)), r.output
    r = run_cli("relight", capture, "--model", "teacher", "--checkpoint", teacher,
                "--splits", "env", "--eval-samples", "2", "-q", "-o", tmp_path / "b.json")
    assert r.exit_code == 0 and "ceiling" not in r.output, r.output
