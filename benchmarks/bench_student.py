"""The student's per-frame cost (RelightableHands App. C on this machine) and its quality.

1. Machine limits, measured in the same run and on the same torch threads as the
   decoder: float32 GEMM GFLOP/s (torch.mm, 1024² and 2048²), the dense 3×3 conv GFLOP/s
   of torch's own conv kernels — their best, measured again at the end of the run, is
   the peak the decoder is checked against — and raw embree occlusion rays/s.
2. Per-frame stages for one hand and two hands, tiny and paper widths: joint features,
   visibility tracing, feature transport (cull + transport + shade, thread-seconds),
   UV sampling (texel maps), decoder, rendering (G-buffer lookup) — beside the paper's
   V100 numbers (0.3 / 2.7 / 1.5 / 15.8 ms; 21 ms one hand, 32 ms two hands).
3. The decoder's GFLOP per frame (counted by hooks on the very convolutions timed:
   2·C_in·C_out·k²·H·W per conv per hand, forward only) and its achieved GFLOP/s against
   the peak, for plain eager, channels_last and torch.compile (where it works), all in
   inference mode; a rate above the peak is printed as ``inconsistent measurement``.
4. Features for a new pose at the paper's defaults (coarse proxy, 16×32, Phong
   16/32/64): wall time, rays traced against the N·M a naive tracer casts, and the
   bake's throughput as a fraction of raw embree on the same rays.
5. Quality (``--quality``): student, w/o specular, w/o visibility, DRAM, distilled from one
   tiny teacher; masked MSE ×10⁻³ / PSNR / SSIM on held-out poses × evaluation env maps
   against the teacher, and against the capture's ground-truth env renders.

Writes student.{md,json,png} under --out (default benchmarks/out); the plot: per-frame
stage times beside the paper's (left) and, with ``--quality``, distillation seconds
against the MSE vs the teacher and vs the ground truth, every model (right).
``--quick``: tiny widths (one and two hands) and the paper widths on one hand, no
torch.compile.  Run:
    .venv/bin/python benchmarks/bench_student.py [--quick] [--quality] [--iters N] [--threads N] [--out DIR]
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

PAPER_MS = {"joint features": 0.3, "visibility": 2.7, "uv sampling": 1.5, "decoder": 15.8}
STAGES = ("joint features", "visibility", "feature transport", "uv sampling", "decoder",
          "rendering")


def best_of(fn, repeat=5):
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def frame_stages(hand, preset: str, compile_decoder: bool = True) -> dict:
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.envmap import discretize_env
    from relight_cli.hand.scene import posed_meshes, preview_camera
    from relight_cli.neural import distill as D
    from relight_cli.neural.config import STUDENT_PRESETS, StudentConfig, resolve_config
    from relight_cli.neural.student import build_student
    from relight_cli.neural.teacher import composite
    from relight_cli.render.gbuffer import render_gbuffer

    cfg = resolve_config(preset, None, {}, presets=STUDENT_PRESETS, config_class=StudentConfig)
    env = discretize_env(builtin_envmap("builtin:sky"), 16, 32)
    meshes = posed_meshes(hand, 0, "fine")
    cam = preview_camera(meshes, 256, 256)
    pose_dim = (hand.n_joints - 1) * 3
    net = build_student(cfg, 12, pose_dim).eval()
    out = {}
    features = D.StudentFeatures(cfg)
    t0 = time.perf_counter()
    pf = features.pose(hand, 0)
    maps = features.maps(pf, env, cam.center)
    wall = time.perf_counter() - t0
    st = pf.stats
    out["visibility"] = st.get("trace", 0.0)
    out["feature transport"] = sum(st.get(k, 0.0) for k in ("cull", "transport", "shade", "scene"))
    out["uv sampling"] = st.get("texels", 0.0)
    out["features wall"] = wall
    n_hands = len(meshes)
    pose = D.pose_vector(D.hand_poses(hand, 0))
    x = torch.from_numpy(maps)
    with torch.inference_mode():
        out["joint features"] = best_of(lambda: net.pose(pose, cfg.tex_res))
        joint = net.pose(pose, cfg.tex_res)
        inp = torch.cat([x, joint], 1)

        def decode(module, h):
            for conv in module.convs:
                h = torch.nn.functional.leaky_relu(conv(h), 0.2)
            return module.head(h)

        with B.ConvFlops(net) as counted:          # the very convs timed below
            decode(net, inp)
        flops = counted.forward
        out["decoder"] = best_of(lambda: decode(net, inp))
        variants = {"eager": out["decoder"]}
        cl = build_student(cfg, 12, pose_dim).eval().to(memory_format=torch.channels_last)
        inp_cl = inp.contiguous(memory_format=torch.channels_last)
        variants["channels_last"] = best_of(lambda: decode(cl, inp_cl))
        # bfloat16 autocast: timed, and its error against the float32 decoder in dB (PSNR
        # with the float32 output's peak as the range: untrained weights give a nearly flat
        # texture, whose own min-max range would exaggerate any error), so speed is never
        # bought without saying the cost
        reference = decode(net, inp).float()

        def bf16(h):
            with torch.autocast("cpu", dtype=torch.bfloat16):
                return decode(net, h)
        try:
            variants["bfloat16"] = best_of(lambda: bf16(inp))
            err = float(((bf16(inp).float() - reference) ** 2).mean())
            span = float(reference.abs().max()) or 1.0
            out["bfloat16_psnr_db"] = (10 * np.log10(span ** 2 / err) if err > 0
                                       else float("inf"))
        except RuntimeError as exc:     # a CPU without bf16 kernels: report, do not fail
            variants["bfloat16"] = f"unavailable ({type(exc).__name__})"
        if not compile_decoder:
            variants["compile"] = "skipped (--quick)"
        else:
            try:
                compiled = torch.compile(lambda h: decode(net, h))
                variants["compile"] = best_of(lambda: compiled(inp))
            except Exception as exc:  # no compiler toolchain: report, do not fail
                variants["compile"] = f"unavailable ({type(exc).__name__})"
    gb = render_gbuffer(meshes, cam, 1)
    tex = [torch.rand(3, cfg.tex_res, cfg.tex_res) for _ in range(n_hands)]
    out["rendering"] = best_of(lambda: composite(tex, gb))
    numeric = [v for k, v in variants.items() if isinstance(v, float) and k != "bfloat16"]
    best = min(numeric)
    out.update({"hands": n_hands, "preset": preset, "decoder_gflop": flops / 1e9,
                "decoder_best_seconds": best, "decoder_gflops_achieved": flops / 1e9 / best,
                "threads": torch.get_num_threads(), "decoder_variants": variants,
                "total": out["joint features"] + out["features wall"] + best + out["rendering"]})
    return out


def new_pose_features(hand) -> dict:
    """Paper defaults; rays traced vs naive, and vs raw embree on the same rays."""
    from relight_cli import features as F
    from relight_cli.envmap import discretize_env
    from relight_cli.bake import PoseFeatures
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.raytrace import RayScene

    settings = F.FeatureSettings(shininess=(16.0, 32.0, 64.0), specular="phong", visibility=True)
    env = discretize_env(builtin_envmap("builtin:sky"), 16, 32)
    eye = np.array([0.0, 0.1, 1.0])
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        pf = PoseFeatures(hand, 0, settings, (16, 32), (128, 128))
        results, _ = pf.bake([env], eye)
        times.append(time.perf_counter() - t0)
    baker = pf.baker
    traced = baker.stats.rays_traced
    possible = len(baker.receivers) * len(baker.directions)
    # raw embree on as many rays of the same kind (receiver → grid direction)
    rng = np.random.default_rng(0)
    idx = rng.integers(0, len(baker.receivers), traced)
    dirs = baker.directions[rng.integers(0, len(baker.directions), traced)]
    scene = RayScene([(m.vertices, m.faces) for m in pf.posed])
    origins = baker.receivers.points[idx] + 1e-4 * baker.receivers.normals[idx]
    scene.occluded(origins[:10], dirs[:10])
    t0 = time.perf_counter()
    scene.occluded(origins, dirs)
    raw = time.perf_counter() - t0
    return {"seconds": min(times), "rays_traced": int(traced), "rays_naive": int(possible),
            "raw_embree_seconds": raw, "trace_fraction_of_raw": raw / max(
                pf.stats.get("trace", 1e-9), 1e-9)}


def quality(iters: int, work: Path) -> tuple:
    """Student, w/o specular, w/o visibility and DRAM distilled from one teacher, through
    the jobs of ``relight train-teacher`` and ``relight distill``
    (:mod:`relight_cli.jobs.train_teacher`, :mod:`relight_cli.jobs.distill`) with the
    commands' defaults: ({row: {"metrics", "seconds"}}, {"train": envs, "eval": envs})."""
    from relight_cli.formats.checkpoint import write_checkpoint
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.formats.metrics_json import make_record
    from relight_cli.cli.inputs import load_envmap
    from relight_cli.jobs import distill as JD
    from relight_cli.jobs.synth_capture import make_capture
    from relight_cli.jobs import train_teacher as JT
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.train import resolve_device
    from relight_cli.provenance import file_sha256

    def capture_data(config):
        return CaptureData(str(cap), config.tex_res, config.aa, config.visibility,
                           config.falloff, config.holdout, config.cache_poses)

    def scores(result) -> dict:
        # as the commands' --metrics-out records them (relight/metrics, kind validation)
        return make_record("validation", {k: v for k, v in result.metrics.items()
                                          if k != "step"}, {}, {}, {})["metrics"]

    cap = work / "cap"
    make_capture(str(cap), cameras=4, lights=32, group=4, frames=16, res=64, tex_res=128,
                 aa=1, eval_poses=2, eval_cameras=2, eval_envs=("builtin:sky", "builtin:studio"))
    device = resolve_device("auto")
    config = JT.configure(None, "tiny", None, {"iters": 2 * iters})
    trained = JT.run(capture_data(config), JT.Options(config, "tiny", device, progress=False))
    teacher = scores(trained.result)
    write_checkpoint(str(work / "teacher.pt"), trained.result.checkpoint)
    tck = JD.load_teacher(read_checkpoint(str(work / "teacher.pt"), kind="teacher"), device,
                          file_sha256(str(work / "teacher.pt")))
    train = ["builtin:sky", "builtin:studio", "builtin:uniform"]
    shared = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "envmaps" / "polyhaven"
    hdris = sorted(shared.glob("*.hdr")) if shared.is_dir() else []
    # a fixed split: the last two real HDRIs are never trained on (else sky + studio)
    held = [str(p) for p in hdris[-2:]] if len(hdris) >= 3 else []
    train += [str(p) for p in (hdris[:-2] if held else hdris)]
    envs = {(s.split(":", 1)[1] if s.startswith("builtin:") else
             Path(s).name.split(".", 1)[0] or Path(s).name): load_envmap(s) for s in train + held}
    rows = {}
    for name, extra in (("student", {}), ("w/o specular", {"specular": False}),
                        ("w/o visibility", {"visibility": False}), ("DRAM", {"student": "dram"})):
        t0 = time.perf_counter()
        config = JD.configure("tiny", None, {"iters": iters, **extra})
        distilled = JD.run(tck, capture_data(tck.config), envs,
                           JD.Options(config, "tiny", device, n_eval=len(held), progress=False))
        rows[name] = {"metrics": scores(distilled.result), "seconds": time.perf_counter() - t0}
    rows["(teacher, vs ground truth)"] = {"metrics": {"vs_ground_truth": teacher.get("env", {})},
                                          "seconds": 0.0}
    return rows, {"train": [Path(e).name if os.path.isabs(e) else e for e in train],
                  "eval": [Path(e).name if os.path.isabs(e) else e for e in held]}


def markdown(report: dict, quick: bool) -> list[str]:
    from relight_cli.visibility import trace_threads
    m = report["machine"]
    peak, threads = m["peak_gflops"], m["torch_threads"]
    lines = ["# Student: per-frame cost and quality", "",
             B.run_description(report["command"], quick, report["wall_seconds"]), "",
             B.machine_line(m), "",
             f"**FLOP ceiling**: {peak:.1f} GFLOP/s on {threads} torch thread(s) — the best of "
             f"fp32 GEMM (torch.mm 1024²: {m['gemm_gflops']:.1f}, 2048²: "
             f"{m['gemm_gflops_2048']:.1f}) and dense 3×3 convolutions (torch's conv kernels, "
             f"{', '.join(f'{a}→{b} at {n}²' for a, b, n in B.CONV_SHAPES)}: "
             f"{m['conv_gflops']:.1f}), measured {m.get('peak_measurements', 1)} times in this "
             f"run (start and end), on the same threads as the decoder.  The decoder's FLOP "
             f"floor is its GFLOP at that peak; a rate above the peak (below 1× the floor) "
             f"would mean a wrong FLOP count or timing and is printed as *inconsistent "
             f"measurement*.", "",
             "## Per-frame stages (ms; 256² view, features at the preset's size)", "",
             "| preset | hands | joint features | visibility | feature transport | uv sampling | "
             "decoder | rendering | total |", "|---|---|---|---|---|---|---|---|---|"]
    for s in report["stages"]:
        lines.append(f"| {s['preset']} | {s['hands']} | " + " | ".join(
            f"{1e3 * s[k]:.1f}" for k in ("joint features", "visibility", "feature transport",
                                          "uv sampling", "decoder", "rendering", "total")) + " |")
    lines.append("| paper's numbers (V100) | 1 | 0.3 | 2.7 | — | 1.5 | 15.8 | — | "
                 "21 (two hands: 32) |")
    lines += ["", f"Visibility and feature transport are thread-seconds of the bake "
              f"({trace_threads()} tracing threads); decoder: eager; total: joint features + the "
              f"bake's wall time + the fastest decoder variant + rendering.", "",
              "## Decoder", "",
              "GFLOP/frame: forward convs of the timed decoder (2 per multiply-add, every hand; "
              "the joint features are timed and counted apart).  Best of 5 runs each.", "",
              "bfloat16: autocast; its error is the PSNR of its output against the float32 "
              "decoder's (the float32 output's peak as the range; untrained weights, so a "
              "trained decoder's error may differ): the fastest variant counts as 'best' only "
              "among the float32 ones.", "",
              "| preset | hands | GFLOP/frame | eager ms | channels_last ms | compile ms | "
              "bfloat16 ms (PSNR vs fp32) | best fp32 GFLOP/s | × FLOP floor |",
              "|---|---|---|---|---|---|---|---|---|"]
    for s in report["stages"]:
        v = s["decoder_variants"]
        fmt = lambda x: f"{1e3 * x:.1f}" if isinstance(x, float) else str(x)  # noqa: E731
        floor = s["decoder_gflop"] / peak                  # seconds at the peak
        ratio = s["decoder_best_seconds"] / floor
        ok = B.consistent(s["decoder_gflops_achieved"], peak) and s["threads"] == threads
        lines.append(f"| {s['preset']} | {s['hands']} | {s['decoder_gflop']:.3f} | "
                     f"{fmt(v['eager'])} | {fmt(v['channels_last'])} | {fmt(v['compile'])} | "
                     f"{fmt(v.get('bfloat16', '—'))}"
                     + (f" ({s['bfloat16_psnr_db']:.1f} dB)" if "bfloat16_psnr_db" in s else "")
                     + " | "
                     f"{B.rate_cell(s['decoder_gflops_achieved'], peak, s['threads'], threads)} | "
                     f"{ratio:.2f}{'' if ok else ' (inconsistent)'} |")
    f = report["new_pose_features"]
    lines += ["", "## Features for a new pose (coarse proxy, 16×32, Phong 16/32/64, 128²)", "",
              f"{1e3 * f['seconds']:.0f} ms wall (best of 3); {f['rays_traced']:,} rays traced "
              f"of {f['rays_naive']:,} naive ({100 * f['rays_traced'] / f['rays_naive']:.0f} %); "
              f"raw embree on as many rays of the same kind, one call: "
              f"{1e3 * f['raw_embree_seconds']:.0f} ms — the bake's trace stage runs at "
              f"{100 * f['trace_fraction_of_raw']:.0f} % of raw embree's rays per "
              f"thread-second."]
    if "quality" in report:
        lines += ["", f"## Quality ({report['iters']} iterations, tiny preset)", "",
                  "Held-out poses × evaluation env maps "
                  f"({', '.join(report['quality_envs']['eval']) or 'split by distill'}); "
                  f"training env maps: {', '.join(report['quality_envs']['train'])}.", "",
                  "| model | vs teacher MSE ×1e-3 | PSNR | SSIM | vs ground truth MSE ×1e-3 | PSNR | "
                  "SSIM | s |", "|---|---|---|---|---|---|---|---|"]
        nan = float("nan")
        for name, r in report["quality"].items():
            t = r["metrics"].get("vs_teacher", {})
            g = r["metrics"].get("vs_ground_truth", {})
            lines.append(f"| {name} | {t.get('mse', nan) * 1e3:.3f} | "
                         f"{t.get('psnr', nan):.2f} | {t.get('ssim', nan):.3f} | "
                         f"{g.get('mse', nan) * 1e3:.3f} | {g.get('psnr', nan):.2f} "
                         f"| {g.get('ssim', nan):.3f} | {r['seconds']:.0f} |")
        for key, label in (("vs_teacher", "against the teacher"),
                           ("vs_ground_truth", "against the ground truth")):
            rows = sorted((r["metrics"][key]["mse"], name) for name, r in report["quality"].items()
                          if np.isfinite(r["metrics"].get(key, {}).get("mse", nan)))
            if rows:
                lines += ["", f"MSE {label}, lowest first, as measured in this table: "
                          + " < ".join(f"{name} ({mse * 1e3:.3f})" for mse, name in rows) + "."]
    lines += ["", "Plot: student.png."]
    return lines


def main():
    ap = B.parser(__doc__, "tiny widths (one and two hands) and the paper widths on one hand, "
                           "no torch.compile")
    ap.add_argument("--quality", action="store_true", help="also distill and score 4 models")
    ap.add_argument("--iters", type=B.integer(0), default=150)
    ap.add_argument("--threads", type=B.integer(1), default=None,
                    help="torch threads for the whole run, peak included [default: torch's, "
                         "which follows OMP_NUM_THREADS]")
    args = ap.parse_args()
    out = B.start(args, "bench_student.py")
    wall0 = time.perf_counter()
    B.set_threads(args.threads)
    from relight_cli.hand.model import builtin_hand
    from relight_cli.hand.scene import two_hands

    report = {"command": B.run_command("bench_student.py", sys.argv[1:]), "quick": args.quick,
              "iters": args.iters, "machine": B.machine_limits(embree=True, conv=True)}
    report["machine"]["gemm_gflops_2048"] = B.gemm_gflops(2048)
    one = builtin_hand("right", "fist")
    two = two_hands(builtin_hand("right", "fist"))
    runs = ([("tiny", one), ("tiny", two), ("paper", one)] if args.quick else
            [(p, h) for p in ("tiny", "paper") for h in (one, two)])
    report["stages"] = [frame_stages(h, p, not args.quick) for p, h in runs]
    report["new_pose_features"] = new_pose_features(one)
    if args.quality:
        work = Path(tempfile.mkdtemp(prefix="bench_student_"))
        try:
            report["quality"], report["quality_envs"] = quality(args.iters, work)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    B.flop_peak(report["machine"])                   # again at the end: the best of all
    report["wall_seconds"] = time.perf_counter() - wall0
    peak = report["machine"]["peak_gflops"]
    report["inconsistent"] = [s["decoder_gflops_achieved"] for s in report["stages"]
                              if not B.consistent(s["decoder_gflops_achieved"], peak)]
    lines = markdown(report, args.quick)
    (out / "student.md").write_text("\n".join(lines) + "\n")
    (out / "student.json").write_text(json.dumps(report, indent=1, default=str) + "\n")
    write_plot(out / "student.png", report)
    print("\n".join(lines))
    if report["inconsistent"]:
        print(f"bench_student.py: warning: {len(report['inconsistent'])} decoder rate(s) above "
              f"the measured peak {peak:.1f} GFLOP/s: inconsistent measurement", file=sys.stderr)


def write_plot(path: Path, report: dict) -> None:
    """Stage times per frame beside the paper's; with --quality, seconds against MSE."""
    quality = report.get("quality")
    fig, axes = B.figure(2 if quality else 1)
    ax = axes[0]
    bars = [(f"{s['preset']}, {s['hands']} hand(s)", {k: 1e3 * s[k] for k in STAGES})
            for s in report["stages"]] + [("paper (V100), 1 hand", PAPER_MS)]
    left = np.zeros(len(bars))
    for stage in STAGES:
        widths = [b[1].get(stage, 0.0) for b in bars]
        ax.barh([b[0] for b in bars], widths, left=left, label=stage)
        left += widths
    ax.set_xlabel("ms per frame (256x256 view)")
    ax.set_title("student: per-frame stages", fontsize=10)
    ax.grid(True, axis="x", alpha=0.5)
    ax.legend(fontsize=7)
    if quality:
        curves = {"vs teacher": [], "vs ground truth": []}
        for name, r in quality.items():
            for key, label in (("vs_teacher", "vs teacher"), ("vs_ground_truth", "vs ground truth")):
                m = r["metrics"].get(key, {})
                if "mse" in m:
                    curves[label].append((max(r["seconds"], 1e-3), m["mse"] * 1e3, name))
        B.plot(axes[1], curves, "distillation seconds", "MSE x 1e-3 (held-out poses x envs)",
               "quality against cost", logx=False)
    B.save(fig, path, report["machine"])


if __name__ == "__main__":
    B.run_main("bench_student.py", main)
