"""URHand's linear model: training throughput, render cost per frame, quality of each ablation.

1. Training throughput (iterations/s, peak memory): ``tiny`` (as trained) and the
   ``paper`` widths on a 128² texture (a few iterations), with the teacher's tiny
   throughput on the same capture for reference.
2. Render per frame, seconds split into geometry, visibility and network (features + one
   forward pass): the group of a capture frame (point lights) and an env map at 16×32
   directions, for the linear model at tiny and paper widths, against the teacher's
   per-direction sum (:func:`_common.env_render_cost`).  URHand reports 25.7 ms
   (grouped lights) and 31.9 ms (env map) on an A100 at 1024².
3. Quality (masked MSE, PSNR, SSIM) on held-out poses under grouped lights, on fully lit
   frames (novel illumination) and on the capture's env-map ground truth, for the full
   model, its paper form (no residual start), each ablation of URHand Tables 2–3 we built
   (non-linear light path, + linearity loss Eq. 17, the holistic MLP model, Phong
   features, w/o specular, w/o visibility, w/o refiner, + the adversarial loss with and
   without its lighting prompt), the OLAT teacher, and the physical renderer with the
   stage's true materials (the upper bound only a synthetic stage has).

Writes linear.{md,json,png} under --out (default benchmarks/out); the plot: held-out
MSE against training seconds, one curve per model.  ``--quick``: a small capture, 8
iterations, tiny widths, two of the variants (no teacher).  Run:
    .venv/bin/python benchmarks/bench_linear.py [--quick] [--iters N] [--out DIR]
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as B  # noqa: E402
from _common import (env_render_cost, make_capture,  # noqa: E402
                     physical_upper_bound, train_variant, validation, write_plot)

QUICK_VARIANTS = ("linear (ours: residual start)", "non-linear light path")

VARIANTS = {
    "linear (ours: residual start)": {},
    "linear (paper form)": {"residual": False},
    "non-linear light path": {"light_path": "nonlinear"},
    "non-linear + linearity loss": {"light_path": "nonlinear", "linearity_loss": 0.1},
    "MLP-based linear [64] (holistic)": {"light_path": "mlp"},
    "Phong features": {"features": "phong"},
    "w/o specular": {"specular": False},
    "w/o visibility": {"visibility": False},
    "w/o refiner": {"refiner": False},
    "+ lighting-aware GAN (λ 0.01)": {"lambda_gan": 0.01},
    "+ GAN w/o lighting prompt": {"lambda_gan": 0.01, "gan_conditioned": False},
}


def _linear_data(folder: Path, cfg):
    from relight_cli.neural.data import CaptureData
    return CaptureData(str(folder), cfg.tex_res, cfg.aa, cfg.visibility, cfg.falloff,
                       cfg.holdout)


def train_linear(folder: Path, overrides: dict, iters: int) -> dict:
    from relight_cli.neural.linear import resolve_config
    from relight_cli.neural.linear_train import train
    cfg = resolve_config("tiny", None, {"iters": iters, "lambda_vgg": 0.0, **validation(iters),
                                        "lr_drop": (2 * iters) // 3, **overrides})
    data = _linear_data(folder, cfg)
    t0 = time.perf_counter()
    result = train(data, cfg, torch.device("cpu"), show_progress=False)
    per_step = result.seconds / max(1, result.steps_run)   # validation spread evenly
    curve = [(h["step"] * per_step, h.get("heldout", {}).get("mse")) for h in result.history]
    return {"metrics": result.metrics, "seconds": time.perf_counter() - t0,
            "train_seconds": result.seconds, "its": result.steps_run / result.seconds,
            "peak_rss_mb": result.peak_memory_mb, "curve": curve}


def throughput(folder: Path, preset: str, tex: int, iters: int) -> dict:
    from relight_cli.neural.linear import resolve_config
    from relight_cli.neural.linear_train import train
    levels = {"tiny": 3, "paper": 5 if tex >= 128 else 3}[preset]
    cfg = resolve_config(preset, None, {"tex_res": tex, "iters": iters, "val_samples": 1,
                                        "lambda_vgg": 0.0, "val_every": 0, "save_every": 0,
                                        "light_levels": levels,
                                        **({"encoder": [64] * 5, "decoder": [64] * 5}
                                           if preset == "paper" else {})})
    data = _linear_data(folder, cfg)
    data.sample(*data.splits()["train"][0])              # warm the geometry cache
    result = train(data, cfg, torch.device("cpu"), show_progress=False)
    return {"preset": preset, "tex_res": tex, "its": result.steps_run / result.seconds,
            "sec_per_it": result.seconds / result.steps_run, "peak_rss_mb": result.peak_memory_mb}


def render_cost(folder: Path, preset: str, tex: int) -> list:
    """Per-frame render seconds of an untrained model (timing only) for one capture
    frame's LED group and for builtin:sky at 16×32."""
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.envmap import discretize_env
    from relight_cli.neural import teacher as T
    from relight_cli.neural.linear import URHandModel, resolve_config
    from relight_cli.neural.linear_train import render_lights
    from relight_cli.render.gbuffer import render_gbuffer

    extra = {"light_levels": 5, "encoder": [64] * 5, "decoder": [64] * 5} \
        if preset == "paper" else {}
    cfg = resolve_config(preset, None, {"tex_res": tex, **extra})
    data = _linear_data(folder, cfg)
    model = URHandModel(cfg, data.pose_dim).eval()
    mean = torch.full((1, 3, tex, tex), 0.15)
    rows = []
    frame = data.train_frames[0]
    for what in ("grouped lights", "env map"):
        timing = T.Timing()
        t0 = time.perf_counter()
        data._texels.clear()
        texels = data.texels(frame.pose)
        gb = render_gbuffer(texels.meshes, data.capture.cameras[0], 2,
                            scene=texels.renderer.scene)
        timing.add("geometry", time.perf_counter() - t0)
        if what == "env map":
            denv = discretize_env(builtin_envmap("builtin:sky"), 16, 32)
            lights, weights = T.env_light_inputs(texels, denv, True, timing)
        else:
            pos = data.capture.light_positions[np.asarray(frame.lights_on)]
            lights = T.point_light_inputs(texels, pos, True, timing)
            weights = data.capture.light_intensity[np.asarray(frame.lights_on)]
        render_lights(model, texels, gb, data.poses(frame.pose), lights, weights, mean, timing)
        rows.append({"model": f"linear {preset}", "tex_res": tex, "lighting": what,
                     "lights": int(len(weights)), **timing.seconds,
                     "total": float(sum(timing.seconds.values()))})
    return rows


def main():
    ap = B.parser(__doc__, "small capture, 8 iterations, tiny widths, 2 variants")
    ap.add_argument("--iters", type=B.integer(1), default=None,
                    help="training iterations per variant")
    ap.add_argument("--variants", default=None, metavar="A,B",
                    help="only the quality variants whose names contain one of these words")
    args = ap.parse_args()
    out = B.start(args, "bench_linear.py")
    iters = args.iters or (8 if args.quick else 150)
    frames = 8 if args.quick else 24
    work = Path(tempfile.mkdtemp(prefix="bench_linear_"))
    report = {"machine": B.machine_limits(), "iters": iters}
    sizes = [("tiny", 32)] + ([] if args.quick else [("paper", 128)])
    try:
        t0 = time.perf_counter()
        folder = make_capture(work / "single", False, frames, args.quick)
        report["capture_seconds"] = time.perf_counter() - t0
        report["throughput"] = [throughput(folder, p, t, 10 if p == "tiny" and not args.quick
                                           else 2) for p, t in sizes]
        report["render"] = [r for p, t in sizes for r in render_cost(folder, p, t)]
        report["teacher_env"] = [] if args.quick else [env_render_cost(folder, p, t)
                                                       for p, t in sizes]
        print(json.dumps({k: report[k] for k in ("throughput", "render", "teacher_env")},
                         default=float), flush=True)
        quality = {}
        words = args.variants.split(",") if args.variants else None
        for name, overrides in VARIANTS.items():
            if words and not any(w in name for w in words):
                continue
            if args.quick and not words and name not in QUICK_VARIANTS:
                continue
            quality[name] = train_linear(folder, overrides, iters)
            print(name, {k: round(v.get("psnr", 0), 2) for k, v in
                         quality[name]["metrics"].items() if isinstance(v, dict)}, flush=True)
        if not args.quick:         # (bench_teacher.py --quick covers the teacher)
            quality["OLAT teacher (tiny)"] = train_variant(folder, "teacher", iters)
        quality["physical (true materials)"] = {"metrics": {"heldout": physical_upper_bound(folder)}}
        report["quality"] = quality
    finally:
        shutil.rmtree(work, ignore_errors=True)

    lines = ["# URHand linear model: speed and quality", "", B.machine_line(report["machine"]),
             f"Capture: {frames} frames, 32 LEDs (groups of 4); made in "
             f"{report['capture_seconds']:.1f} s.", "",
             "## Training throughput (CPU)", "",
             "| widths | texture | it/s | s/it | peak RSS MB |", "|---|---|---|---|---|"]
    for t in report["throughput"]:
        lines.append(f"| {t['preset']} | {t['tex_res']}² | {t['its']:.2f} | "
                     f"{t['sec_per_it']:.2f} | {t['peak_rss_mb']:.0f} |")
    lines += ["", "Paper widths at 128² use 5 F_G levels and 5 light-path levels (the paper's "
              "6 need 1024²).", "",
              "## Render per frame (seconds; untrained weights, timing only)", "",
              "| model | texture | lighting | lights | geometry | visibility | network | total |",
              "|---|---|---|---|---|---|---|---|"]
    for r in report["render"]:
        lines.append(f"| {r['model']} | {r['tex_res']}² | {r['lighting']} | {r['lights']} | "
                     + " | ".join(f"{r.get(k, 0):.3f}" for k in ("geometry", "visibility",
                                                                   "network"))
                     + f" | {r['total']:.3f} |")
    for e in report["teacher_env"]:
        lines.append(f"| teacher {e['preset']} (Σ directions) | {e['tex_res']}² | env map | "
                     f"{e['directions']} | {e.get('geometry', 0):.3f} | "
                     f"{e.get('visibility', 0):.3f} | "
                     f"{e.get('inputs', 0) + e.get('network', 0) + e.get('composite', 0):.3f} | "
                     f"{e['total']:.3f} |")
    lines += ["", f"## Quality ({iters} iterations, tiny preset, no perceptual loss)", "",
              "| model | held-out MSE ×1e-3 | PSNR | SSIM | fully lit PSNR | SSIM | env PSNR | "
              "SSIM | train s |", "|---|---|---|---|---|---|---|---|---|"]
    nan = float("nan")
    for name, r in report["quality"].items():
        q = r["metrics"]
        h, f, e = q.get("heldout", {}), q.get("fully_lit", {}), q.get("env", {})
        lines.append(f"| {name} | {h.get('mse', nan) * 1e3:.3f} | {h.get('psnr', nan):.2f} | "
                     f"{h.get('ssim', nan):.3f} | {f.get('psnr', nan):.2f} | "
                     f"{f.get('ssim', nan):.3f} | {e.get('psnr', nan):.2f} | "
                     f"{e.get('ssim', nan):.3f} | {r.get('train_seconds', 0):.0f} |")
    lines += ["", "No LPIPS: no local weights. URHand Table 2–3 (real stage, ten identities): "
              "the linear model beats the non-linear one most on novel illumination; Phong, "
              "w/o specular, w/o visibility and w/o refiner each lose."]
    lines += ["", "Plot: linear.png (held-out MSE against training seconds)."]
    (out / "linear.md").write_text("\n".join(lines) + "\n")
    (out / "linear.json").write_text(json.dumps(report, indent=1, default=float) + "\n")
    write_plot(out / "linear.png", {name: r["curve"] for name, r in report["quality"].items()
                                    if "curve" in r}, report["machine"], "URHand linear model")
    print("\n".join(lines))


if __name__ == "__main__":
    B.run_main("bench_linear.py", main)
