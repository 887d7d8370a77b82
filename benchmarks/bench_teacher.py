"""The OLAT teacher: training throughput, render cost per frame, and quality against baselines.

1. Machine limits, measured in the same run: float32 GEMM GFLOP/s of torch on this
   machine's threads (the ceiling every conv runs against).
2. Training throughput (iterations/s) and peak memory: ``tiny`` (as trained), and the
   ``paper`` widths on 128² and 256² textures (a few iterations each), extrapolated to the
   paper's 1024² by the FLOP count (∝ texels), with the FLOPs per iteration.
3. Env-map render per frame at 16×32 directions, split into visibility, inputs, network and
   compositing, for the tiny model and the paper widths (timing only: untrained weights).
4. Quality on held-out poses (masked MSE ×10⁻³, PSNR, SSIM) — and on fully lit frames and
   the env-map ground truth — for: the teacher, the teacher without visibility
   (RelightableHands Table 1), the GGX baseline (App. B / Table 3), and the physical
   renderer with the stage's true materials (the upper bound only a synthetic stage has),
   on a single hand and on two interacting hands; with held-out MSE against training time
   as a plot.

Writes teacher.{md,json,png} under --out (default benchmarks/out); the plot: held-out
MSE against training seconds, one curve per scene and model.  ``--quick``: one scene
(single hand), small capture, 8 iterations, tiny widths, teacher with and without visibility.  Run:
    .venv/bin/python benchmarks/bench_teacher.py [--quick] [--iters N] [--out DIR]
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402


def conv_flops(config, pose_dim: int) -> float:
    """Forward FLOPs of one U-Net pass (one light) of ``config`` (2 per MAC)."""
    from relight_cli.neural.models import build_model
    model = build_model(config, pose_dim)
    n = config.tex_res
    total = 0.0
    hooks = []

    def hook(module, inputs, output):
        nonlocal total
        k = module.kernel_size[0] * module.kernel_size[1]
        total += 2.0 * output.numel() * module.in_channels * k

    for m in model.modules():
        if isinstance(m, torch.nn.Conv2d):
            hooks.append(m.register_forward_hook(hook))
    with torch.no_grad():
        model(torch.zeros(1, 7, n, n), torch.zeros(1, pose_dim), torch.zeros(1, dtype=torch.long))
    for h in hooks:
        h.remove()
    return total


def make_capture(folder: Path, two_hands: bool, frames: int, quick: bool) -> Path:
    from click.testing import CliRunner

    from relight_cli.cli import cli
    args = ["synth-capture", "-o", str(folder), "--cameras", "4" if quick else "6",
            "--leds", "32", "--group", "4", "--size", "48" if quick else "64",
            "--tex-res", "128", "--aa", "1", "--eval-poses", "2", "--eval-cameras", "2",
            "--eval-envs", "builtin:sky,builtin:studio", "-q"]
    if two_hands:
        from relight_cli.formats.hand_npz import write_hand
        from relight_cli.hand.model import builtin_hand
        from relight_cli.hand.scene import two_hands as pair
        from relight_cli.render.capture import hand_motion
        motion = folder.parent / f"{folder.name}_motion.npz"
        write_hand(str(motion), pair(hand_motion(builtin_hand("right"), frames, seed=5)))
        args = ["synth-capture", str(motion), "--motion", "file", *args[1:]]
    else:
        args += ["--frames", str(frames)]
    r = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert r.exit_code == 0, r.output
    return folder


def physical_upper_bound(folder: Path) -> dict:
    """Held-out frames re-rendered with the stage's own renderer and true materials."""
    from relight_cli.formats import capture as C
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.train import _metrics
    from relight_cli.render.appearance import hand_materials
    from relight_cli.render.capture import FrameRenderer, Plan, StageSettings
    from relight_cli.render.shading import PointLights

    data = CaptureData(str(folder), 32, holdout=0.25)
    s = data.capture.settings
    settings = StageSettings(**{k: v for k, v in s.items() if k in StageSettings.__dataclass_fields__})
    materials = hand_materials(data.hand, "fine", max(settings.tex_res, 256), settings.seed)
    plan = Plan(data.hand, data.capture.cameras,
                PointLights(data.capture.light_positions, data.capture.light_intensity),
                data.capture.light_names, data.capture.frames, np.zeros(3), data.capture.key)
    renderer = FrameRenderer(plan, materials, settings)
    rows = []
    for frame in data.heldout_frames:
        for cam, result in renderer.frame(frame, [data.capture.camera(n) for n in frame.images]):
            gt, mask = C.read_image(os.path.join(str(folder), C.image_path(frame.index, cam.name)))
            m = _metrics(result.image, gt, mask)
            if m:
                rows.append(m)
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def validation(iters: int) -> dict:
    """Validation every sixth of the run on 6 samples; a quick run (< 60 iterations) gets a
    few points on 2 samples, so that validation does not cost more than training."""
    if iters >= 60:
        return {"val_every": max(1, iters // 6), "val_samples": 6}
    return {"val_every": max(2, iters // 3), "val_samples": 2}


def train_variant(folder: Path, variant: str, iters: int) -> dict:
    from relight_cli.neural.config import resolve_config
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.train import train

    overrides = {"iters": iters, **validation(iters),
                 "lambda_vgg": 0.0, "neg_start": iters // 4}
    if variant == "no-visibility":
        overrides["visibility"] = False
    if variant == "ggx":
        overrides["model"] = "ggx"
    cfg = resolve_config("tiny", None, overrides)
    data = CaptureData(str(folder), cfg.tex_res, cfg.aa, cfg.visibility, cfg.falloff, cfg.holdout)
    t0 = time.perf_counter()
    result = train(data, cfg, torch.device("cpu"), show_progress=False)
    total = time.perf_counter() - t0
    # validation steps are spread evenly: map them to training seconds
    per_step = result.seconds / max(1, result.steps_run)
    curve = [(h["step"] * per_step, h.get("heldout", {}).get("mse")) for h in result.history]
    return {"metrics": result.metrics, "seconds": total, "train_seconds": result.seconds,
            "its": result.steps_run / result.seconds, "peak_rss_mb": result.peak_memory_mb,
            "curve": curve}


def throughput(folder: Path, widths: str, tex: int, iters: int) -> dict:
    from relight_cli.neural.config import resolve_config
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.train import train
    cfg = resolve_config(widths, None, {"tex_res": tex, "iters": iters, "val_samples": 1,
                                        "lambda_vgg": 0.0, "val_every": 0, "save_every": 0})
    data = CaptureData(str(folder), cfg.tex_res, cfg.aa, cfg.visibility, cfg.falloff, cfg.holdout)
    data.sample(*data.splits()["train"][0])              # warm the geometry cache
    t0 = time.perf_counter()
    result = train(data, cfg, torch.device("cpu"), show_progress=False)
    del t0
    flops = conv_flops(cfg, data.pose_dim) * 3 * cfg.batch * 4     # fwd+bwd ≈ 3×, 4 LEDs/frame
    return {"preset": widths, "tex_res": tex, "its": result.steps_run / result.seconds,
            "sec_per_it": result.seconds / result.steps_run, "gflop_per_it": flops / 1e9,
            "peak_rss_mb": result.peak_memory_mb}


def env_render_cost(folder: Path, widths: str, tex: int) -> dict:
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.features import discretize_env
    from relight_cli.neural import teacher as T
    from relight_cli.neural.config import resolve_config
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.models import build_model
    from relight_cli.render.gbuffer import render_gbuffer

    cfg = resolve_config(widths, None, {"tex_res": tex})
    data = CaptureData(str(folder), tex, 2)
    model = build_model(cfg, data.pose_dim).eval()
    denv = discretize_env(builtin_envmap("builtin:sky"), 16, 32)
    timing = T.Timing()
    t0 = time.perf_counter()
    texels = data.texels(0)
    cam = data.capture.cameras[0]
    gb = render_gbuffer(texels.meshes, cam, 2, scene=texels.renderer.scene)
    timing.add("geometry", time.perf_counter() - t0)
    lights, weights = T.env_light_inputs(texels, denv, True, timing)
    T.render_lights(model, texels, gb, data.poses(0), lights, weights, True, cfg.falloff,
                    timing=timing)
    return {"preset": widths, "tex_res": tex, "directions": int(len(weights)),
            **{k: v for k, v in timing.seconds.items()},
            "total": float(sum(timing.seconds.values()))}


def write_plot(path: Path, curves: dict, machine: dict, what: str = "teacher"):
    """Held-out MSE (×1e-3) against training seconds, every curve."""
    fig, (ax,) = B.figure(1, 7.2, 4.6)
    B.plot(ax, {name: [(t, m * 1e3) for t, m in curve if m] for name, curve in curves.items()},
           "training seconds", "held-out MSE x 1e-3 (log)", f"{what}: validation during training",
           logx=False, labels=False)
    B.save(fig, path, machine)


def main():
    ap = B.parser(__doc__, "one small capture (single hand), 8 iterations, tiny widths only")
    ap.add_argument("--iters", type=int, default=None, help="training iterations per variant")
    args = ap.parse_args()
    out = B.start(args, "bench_teacher.py")
    iters = args.iters or (8 if args.quick else 400)
    frames = 8 if args.quick else 24
    work = Path(tempfile.mkdtemp(prefix="bench_teacher_"))
    report = {"machine": B.machine_limits(), "iters": iters}
    try:
        t0 = time.perf_counter()
        captures = {"single": make_capture(work / "single", False, frames, args.quick)}
        if not args.quick:
            captures["two"] = make_capture(work / "two", True, frames, args.quick)
        report["capture_seconds"] = time.perf_counter() - t0
        report["throughput"] = [throughput(captures["single"], "tiny", 32, 5 if args.quick else 20)]
        if not args.quick:
            report["throughput"] += [throughput(captures["single"], "paper", 128, 2),
                                     throughput(captures["single"], "paper", 256, 1)]
        report["env_render"] = [env_render_cost(captures["single"], "tiny", 32)]
        if not args.quick:
            report["env_render"].append(env_render_cost(captures["single"], "paper", 128))
        quality = {}
        curves = {}
        for cname, folder in captures.items():
            for variant in ("teacher", "no-visibility") if args.quick else ("teacher", "no-visibility", "ggx"):
                r = train_variant(folder, variant, iters)
                quality[f"{cname}/{variant}"] = r
                curves[f"{cname} {variant}"] = r["curve"]
            quality[f"{cname}/physical (true materials)"] = {
                "metrics": {"heldout": physical_upper_bound(folder)}}
        report["quality"] = quality
    finally:
        shutil.rmtree(work, ignore_errors=True)

    lines = ["# OLAT teacher: speed and quality", "", B.machine_line(report["machine"]),
             f"Captures: {frames} frames, 32 LEDs (groups of 4), 64² or 48² images; "
             f"made in {report['capture_seconds']:.1f} s.", "",
             "## Training throughput", "",
             "| widths | texture | it/s | s/it | GFLOP/it | GFLOP/s achieved | peak RSS MB |",
             "|---|---|---|---|---|---|---|"]
    for t in report["throughput"]:
        lines.append(f"| {t['preset']} | {t['tex_res']}² | {t['its']:.2f} | {t['sec_per_it']:.2f} | "
                     f"{t['gflop_per_it']:.1f} | {t['gflop_per_it'] / t['sec_per_it']:.1f} | "
                     f"{t['peak_rss_mb']:.0f} |")
    big = ([t for t in report["throughput"] if t["preset"] == "paper"] or [None])[-1]
    if big is not None:
        scale = (1024 / big["tex_res"]) ** 2
        lines += ["", f"Paper preset at 1024² (extrapolated ×{scale:.0f} from {big['tex_res']}² "
                  f"by FLOPs): {big['sec_per_it'] * scale:.0f} s/iteration here, i.e. 100k "
                  f"iterations ≈ {big['sec_per_it'] * scale * 1e5 / 86400:.0f} days on this CPU "
                  f"— a GPU job."]
    lines += ["", "## Env-map render per frame (16×32 directions, seconds)", "",
              "| widths | texture | lit dirs | geometry | visibility | inputs | network | composite | total |",
              "|---|---|---|---|---|---|---|---|---|"]
    for e in report["env_render"]:
        lines.append(f"| {e['preset']} | {e['tex_res']}² | {e['directions']} | "
                     + " | ".join(f"{e.get(k, 0):.3f}" for k in ("geometry", "visibility", "inputs",
                                                                   "network", "composite"))
                     + f" | {e['total']:.3f} |")
    lines += ["", f"## Quality ({iters} iterations, tiny preset, no VGG)", "",
              "| scene / model | held-out MSE ×1e-3 | PSNR | SSIM | fully lit PSNR | env PSNR | train s |",
              "|---|---|---|---|---|---|---|"]
    for name, r in report["quality"].items():
        m = r["metrics"]
        h = m.get("heldout", {})
        lines.append(f"| {name} | {h.get('mse', float('nan')) * 1e3:.3f} | {h.get('psnr', float('nan')):.2f} "
                     f"| {h.get('ssim', float('nan')):.3f} | "
                     f"{m.get('fully_lit', {}).get('psnr', float('nan')):.2f} | "
                     f"{m.get('env', {}).get('psnr', float('nan')):.2f} | "
                     f"{r.get('train_seconds', 0):.0f} |")
    lines += ["", "RelightableHands Table 1/3 (real light stage, their units): teacher with visibility "
              "beats without, and beats the GGX baseline by a large margin. Plot: teacher.png "
              "(held-out MSE against training seconds)."]
    (out / "teacher.md").write_text("\n".join(lines) + "\n")
    (out / "teacher.json").write_text(json.dumps(report, indent=1, default=float) + "\n")
    write_plot(out / "teacher.png", curves, report["machine"])
    print("\n".join(lines))


if __name__ == "__main__":
    main()
