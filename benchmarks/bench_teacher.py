"""The OLAT teacher: training throughput, render cost per frame, and quality against baselines.

1. Machine limits, measured in the same run and on the same torch threads as every
   network below: float32 GEMM GFLOP/s (torch.mm) and the dense 3×3 conv GFLOP/s of
   torch's own conv kernels; their best, measured again at the end of the run, is the
   peak every achieved GFLOP/s is checked against (a rate above it is printed as
   ``inconsistent measurement``, never as a result).
2. Training throughput (iterations/s) and peak memory: ``tiny`` (as trained), and the
   ``paper`` widths on 128² (also in ``--quick``) and 256² textures (a few iterations
   each), extrapolated to the paper's 1024² (conv FLOPs ∝ texels).  FLOPs are counted by
   hooks on the very convolutions each timed iteration runs (:class:`_common.ConvFlops`:
   2·C_in·C_out·k²·H·W per conv per sample forward; backward = weight gradient + input
   gradient, one forward each, the input gradient only where the input needs one), and
   the rate is over the iterations after the first (warm-up), whole iterations timed
   (data, loss and Adam included: a lower bound of the convs' own rate).
3. Env-map render per frame at 16×32 directions, split into visibility, inputs, network and
   compositing, for the tiny model and the paper widths (timing only: untrained weights),
   with the network's forward GFLOP and GFLOP/s.
4. Quality on held-out poses (masked MSE ×10⁻³, PSNR, SSIM) — and on fully lit frames and
   the env-map ground truth — for: the teacher, the teacher without visibility
   (RelightableHands Table 1), the GGX baseline (App. B / Table 3), and the physical
   renderer with the stage's true materials (the upper bound only a synthetic stage has),
   on a single hand and on two interacting hands; with held-out MSE against training time
   as a plot.  The only ordering written is the one measured here.

Writes teacher.{md,json,png} under --out (default benchmarks/out); the plot: held-out
MSE against training seconds, one curve per scene and model.  ``--quick``: one scene
(single hand), small capture, 8 iterations, tiny widths, teacher with and without
visibility, and the paper widths' training throughput at 128² only.  Run:
    .venv/bin/python benchmarks/bench_teacher.py [--quick] [--iters N] [--threads N] [--out DIR]
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


def throughput(folder: Path, widths: str, tex: int, iters: int, threads: int,
               channels_last: bool | None = None) -> dict:
    """Training throughput of preset ``widths`` at ``tex``² (``channels_last``: the
    preset's memory format unless given)."""
    from relight_cli.neural.config import resolve_config
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.train import fit
    values = {"tex_res": tex, "iters": iters, "val_samples": 1, "lambda_vgg": 0.0,
              "val_every": 0, "save_every": 0}
    if channels_last is not None:
        values["channels_last"] = channels_last
    cfg = resolve_config(widths, None, values)
    from relight_cli.neural.train import batch_indices
    data = CaptureData(str(folder), cfg.tex_res, cfg.aa, cfg.visibility, cfg.falloff, cfg.holdout)
    items = data.splits()["train"]
    for step in range(iters):      # warm the geometry caches of every sample the steps draw
        for i in batch_indices(cfg.seed, step, len(items), cfg.batch):
            data.sample(*items[int(i)], with_image=False)
    task = B.timed_teacher_task(data, cfg, evaluate=False)
    result = fit(task, cfg, torch.device("cpu"), show_progress=False)
    task.flops.close()
    assert torch.get_num_threads() == threads
    timed = task.steps[1:] if len(task.steps) > 1 else task.steps   # the first one warms up
    seconds = sum(t for t, _, _ in timed)
    flops = sum(f for _, f, _ in timed)
    forward = sum(f for _, _, f in timed)
    alone = network_alone(data, cfg, items, max(len(timed), 3))
    return {"preset": widths, "tex_res": tex, "channels_last": cfg.channels_last,
            "network_alone": alone,
            "iterations": len(task.steps),
            "iterations_timed": len(timed), "first_iteration_s": task.steps[0][0],
            "sec_per_it": seconds / len(timed), "its": len(timed) / seconds,
            "gflop_per_it": flops / len(timed) / 1e9,
            "forward_gflop_per_it": forward / len(timed) / 1e9,
            "gflops": flops / seconds / 1e9, "threads": torch.get_num_threads(),
            "peak_rss_mb": result.peak_memory_mb}


def network_alone(data, cfg, items, iters: int) -> dict:
    """The network's own rate in a training iteration: the same model (fresh weights,
    the config's memory layout) run forward and backward on the assembled inputs of
    ``cfg.batch`` real training samples, one U-Net pass per sample as training runs it,
    with a mean-square loss on its output instead of the render, no optimizer step.
    {"sec_per_it", "gflop_per_it", "gflops"} over ``iters`` iterations after one warm-up:
    what the convolutions, resizes and activations of an iteration cost, without input
    assembly, compositing, the image loss or Adam."""
    from relight_cli.neural.models import build_model, pose_vector
    model = build_model(cfg, data.pose_dim)
    if cfg.channels_last:
        model = model.to(memory_format=torch.channels_last)
    model.train()
    batch = []
    for item in items[:cfg.batch]:
        sample = data.sample(*item, with_image=False)
        batch.append((torch.from_numpy(sample.inputs), pose_vector(sample.poses),
                      torch.from_numpy(sample.hand_of)))

    def step():
        for inputs, pose, hand_of in batch:
            out = model(inputs, pose, hand_of)
            (out.square().mean() / len(batch)).backward()
    step()
    with B.ConvFlops(model) as flops:
        t0 = time.perf_counter()
        for _ in range(iters):
            step()
        seconds = time.perf_counter() - t0
    return {"sec_per_it": seconds / iters, "gflop_per_it": flops.total / iters / 1e9,
            "gflops": flops.total / seconds / 1e9, "iterations": iters}


def _f(v, spec):
    return "—" if v is None or not np.isfinite(v) else format(v, spec)


def markdown(report: dict, quick: bool) -> list[str]:
    m = report["machine"]
    peak, threads = m["peak_gflops"], m["torch_threads"]
    lines = ["# OLAT teacher: speed and quality", "",
             B.run_description(report["command"], quick, report["wall_seconds"]),
             "", B.machine_line(m), "",
             f"**FLOP ceiling**: {peak:.1f} GFLOP/s on {threads} torch thread(s) — the best of "
             f"fp32 GEMM (torch.mm 1024²) and dense 3×3 convolutions (torch's conv kernels, "
             f"{', '.join(f'{a}→{b} at {n}²' for a, b, n in B.CONV_SHAPES)}), measured "
             f"{m.get('peak_measurements', 1)} times in this run (start and end), on the same "
             f"threads as every network below.  An achieved rate above it would mean a wrong "
             f"FLOP count or timing and is printed as *inconsistent measurement*.", "",
             "**FLOPs**: convolutions only, 2 per multiply-add, counted by hooks on the passes "
             "that were timed: forward 2·C_in·C_out·k²·H·W per conv per sample (one U-Net pass "
             "per light and hand); backward = weight gradient (1× forward) + input gradient "
             "(1× forward, none where the conv's input needs no gradient), so an iteration is "
             "≈ 3× its forward.  Bias adds, activations, resizes, the loss and Adam are not "
             "counted but are timed: the GFLOP/s are lower bounds of the convs' own rate.", "",
             f"Captures: {report['frames']} frames, 32 LEDs (groups of 4), "
             f"{report['image_size']}² images; made in {report['capture_seconds']:.1f} s.", "",
             "## Training throughput", "",
             "Seconds per iteration over the iterations after the first (which warms up); "
             "batch 2 (frame, camera) samples of 4 lights each, their texel geometry and "
             "visibility cached beforehand: an iteration times input assembly, image reads, "
             "forward, loss, backward and Adam.", "",
             "Network alone: the same model's forward and backward passes on the inputs of "
             "real training samples (one U-Net pass per sample, a mean-square loss on its "
             "output, no render, no image loss, no Adam; :func:`network_alone`), timed in the "
             "same run: the share of an iteration the network itself takes, and its rate "
             "against the run's GEMM.", "",
             "| widths | texture | iterations (timed) | s/it | it/s | forward GFLOP/it | "
             "fwd+bwd GFLOP/it | GFLOP/s achieved | % of peak | network alone: s/it | "
             "GFLOP/s | % of GEMM | peak RSS MB |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    gemm = m["gemm_gflops"]
    for t in report["throughput"]:
        ok = B.consistent(t["gflops"], peak) and t["threads"] == threads
        label = t["preset"] + (" (channels_last)" if t.get("channels_last") else "")
        net = t.get("network_alone")
        alone = "| — | — | — "
        if net:
            alone = (f"| {net['sec_per_it']:.3f} | "
                     f"{B.rate_cell(net['gflops'], peak, t['threads'], threads)} | "
                     f"{100 * net['gflops'] / gemm:.0f} % ")
        lines.append(f"| {label} | {t['tex_res']}² | {t['iterations']} "
                     f"({t['iterations_timed']}) | {t['sec_per_it']:.3f} | {t['its']:.2f} | "
                     f"{t['forward_gflop_per_it']:.2f} | {t['gflop_per_it']:.2f} | "
                     f"{B.rate_cell(t['gflops'], peak, t['threads'], threads)} | "
                     f"{100 * t['gflops'] / peak:.0f} %{'' if ok else ' (inconsistent)'} "
                     f"{alone}| {t['peak_rss_mb']:.0f} |")
    big = ([t for t in report["throughput"] if t["preset"] == "paper"] or [None])[-1]
    if big is not None:
        scale = (1024 / big["tex_res"]) ** 2
        lines += ["", f"Paper widths at 1024², extrapolated ×{scale:.0f} from {big['tex_res']}² "
                  f"(conv FLOPs ∝ texels): {big['sec_per_it'] * scale:.0f} s/iteration here, "
                  f"so the paper's 100k iterations ≈ "
                  f"{big['sec_per_it'] * scale * 1e5 / 86400:.0f} days on this machine."]
    lines += ["", "## Env-map render per frame (16×32 directions, seconds)", "",
              "Untrained weights (timing only); network GFLOP: forward convs of every lit "
              "direction's pass.", "",
              "| widths | texture | lit dirs | geometry | visibility | inputs | network | "
              "composite | total | network GFLOP | network GFLOP/s |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for e in report["env_render"]:
        label = e["preset"] + (" (channels_last)" if e.get("channels_last") else "")
        lines.append(f"| {label} | {e['tex_res']}² | {e['directions']} | "
                     + " | ".join(f"{e.get(k, 0):.3f}" for k in ("geometry", "visibility", "inputs",
                                                                   "network", "composite"))
                     + f" | {e['total']:.3f} | {e['network_gflop']:.1f} | "
                     f"{B.rate_cell(e['network_gflops'], peak, e['threads'], threads)} |")
    lines += ["", f"## Quality ({report['iters']} iterations, tiny preset, no VGG)", "",
              "| scene / model | held-out MSE ×1e-3 | PSNR | SSIM | fully lit PSNR | env PSNR | "
              "train s |", "|---|---|---|---|---|---|---|"]
    for name, r in report["quality"].items():
        mm = r["metrics"]
        h = mm.get("heldout", {})
        lines.append(f"| {name} | {_f(h.get('mse', np.nan) * 1e3, '.3f')} | "
                     f"{_f(h.get('psnr'), '.2f')} | {_f(h.get('ssim'), '.3f')} | "
                     f"{_f(mm.get('fully_lit', {}).get('psnr'), '.2f')} | "
                     f"{_f(mm.get('env', {}).get('psnr'), '.2f')} | "
                     f"{_f(r.get('train_seconds'), '.1f')} |")
    lines += ["", "Train s: training steps only (validation excluded).  Held-out MSE, lowest "
              "first, as measured in this table (learned models only):"]
    scenes = {}
    for name, r in report["quality"].items():
        scene, model = name.split("/", 1)
        mse = r["metrics"].get("heldout", {}).get("mse")
        if "train_seconds" in r and mse is not None and np.isfinite(mse):
            scenes.setdefault(scene, []).append((mse, model))
    for scene, rows in scenes.items():
        lines.append(f"- {scene}: " + " < ".join(f"{model} ({mse * 1e3:.3f})"
                                                  for mse, model in sorted(rows)))
    lines += ["", "Plot: teacher.png (held-out MSE against training seconds)."]
    return lines


def main():
    ap = B.parser(__doc__, "one small capture (single hand), 8 iterations, tiny widths, "
                           "paper widths' throughput at 128² only")
    ap.add_argument("--iters", type=B.integer(1), default=None,
                    help="training iterations per variant")
    ap.add_argument("--threads", type=B.integer(1), default=None,
                    help="torch threads for the whole run, peak included [default: torch's, "
                         "which follows OMP_NUM_THREADS]")
    args = ap.parse_args()
    out = B.start(args, "bench_teacher.py")
    wall0 = time.perf_counter()
    threads = B.set_threads(args.threads)
    iters = args.iters or (8 if args.quick else 400)
    frames = 8 if args.quick else 24
    report = {"command": B.run_command("bench_teacher.py", sys.argv[1:]), "quick": args.quick,
              "machine": B.machine_limits(conv=True), "iters": iters, "frames": frames,
              "image_size": 48 if args.quick else 64, "stage_seconds": {}}
    stage_t = [wall0]

    def stage(name):
        now = time.perf_counter()
        report["stage_seconds"][name] = now - stage_t[0]
        stage_t[0] = now
        print(f"bench_teacher.py: {name} done ({now - wall0:.0f} s)", file=sys.stderr, flush=True)

    stage("machine limits")
    work = Path(tempfile.mkdtemp(prefix="bench_teacher_"))
    try:
        captures = {"single": B.make_capture(work / "single", False, frames, args.quick)}
        if not args.quick:
            captures["two"] = B.make_capture(work / "two", True, frames, args.quick)
        report["capture_seconds"] = time.perf_counter() - stage_t[0]
        stage("captures")
        report["throughput"] = [throughput(captures["single"], "tiny", 32,
                                           5 if args.quick else 20, threads),
                                throughput(captures["single"], "paper", 128, 2 if args.quick
                                           else 3, threads)]
        # the cpu preset (64², untied biases) in both memory formats: what channels_last
        # buys in the same run
        # (12 iterations in --quick too: the cpu preset's rates are the ones quoted)
        for nhwc in (False, True):
            report["throughput"].append(throughput(captures["single"], "cpu", 64,
                                                   12 if args.quick else 20, threads, nhwc))
        if not args.quick:
            report["throughput"].append(throughput(captures["single"], "paper", 256, 2, threads))
        stage("throughput")
        report["env_render"] = [B.env_render_cost(captures["single"], "tiny", 32)]
        # the cpu preset in both layouts: what loading its checkpoints in channels_last
        # buys at inference (the resampling above all)
        report["env_render"] += [B.env_render_cost(captures["single"], "cpu", 64, nhwc)
                                 for nhwc in (False, True)]
        if not args.quick:
            report["env_render"].append(B.env_render_cost(captures["single"], "paper", 128))
        stage("env render")
        quality = {}
        curves = {}
        variants = ("teacher", "no-visibility") if args.quick else ("teacher", "no-visibility",
                                                                    "ggx")
        for cname, folder in captures.items():
            for variant in variants:
                r = B.train_variant(folder, variant, iters)
                quality[f"{cname}/{variant}"] = r
                curves[f"{cname} {variant}"] = r["curve"]
                stage(f"quality {cname}/{variant}")
            quality[f"{cname}/physical (true materials)"] = {
                "metrics": {"heldout": B.physical_upper_bound(folder)}}
            stage(f"quality {cname}/physical")
        report["quality"] = quality
    finally:
        shutil.rmtree(work, ignore_errors=True)
    B.flop_peak(report["machine"])                   # again at the end: the best of both
    stage("peak again")
    report["wall_seconds"] = time.perf_counter() - wall0
    peak = report["machine"]["peak_gflops"]
    rates = [t["gflops"] for t in report["throughput"]] + [e["network_gflops"]
                                                            for e in report["env_render"]]
    rates += [t["network_alone"]["gflops"] for t in report["throughput"]
              if t.get("network_alone")]
    report["inconsistent"] = [r for r in rates if not B.consistent(r, peak)]
    lines = markdown(report, args.quick)
    (out / "teacher.md").write_text("\n".join(lines) + "\n")
    (out / "teacher.json").write_text(json.dumps(report, indent=1, default=float) + "\n")
    B.write_plot(out / "teacher.png", curves, report["machine"])
    print("\n".join(lines))
    if report["inconsistent"]:
        print(f"bench_teacher.py: warning: {len(report['inconsistent'])} rate(s) above the "
              f"measured peak {peak:.1f} GFLOP/s: inconsistent measurement", file=sys.stderr)


if __name__ == "__main__":
    B.run_main("bench_teacher.py", main)
