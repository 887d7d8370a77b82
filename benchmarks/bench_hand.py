"""Speed and accuracy of the hand model: LBS and keypoint fitting.

Prints two tables (markdown) and optionally writes them to a file:

1. LBS time per frame of the coarse and fine meshes (numpy fast path, torch
   CPU batched, the per-vertex loop reference per 100 vertices); target: fine
   mesh ≤ 5 ms.
2. Fitting N frames of synthetic keypoints (random poses incl. fist and
   at-limit poses, known bone scales ±5%, 2 mm Gaussian noise, 10% outliers):
   wall time, MPJPE vs the true joints, median vertex error, bone-scale error;
   target: 100 frames ≤ 60 s on a 2-core machine.

Writes hand.{md,json,png} under --out (default benchmarks/out/); the plot: LBS time
against its error vs the loop reference (left), fitting time against MPJPE and median
vertex error over the frame counts (right).  Machine limits in the same run.

Usage:  .venv/bin/python benchmarks/bench_hand.py [--quick] [--frames 25,100,200] [--out DIR]
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402

from relight_cli.hand import poses as P  # noqa: E402
from relight_cli.hand.fitting import FitOptions, fit, personalize_mesh, synthetic_truth  # noqa: E402
from relight_cli.hand.model import PARENTS, builtin_hand  # noqa: E402
from relight_cli.hand.skinning import lbs, lbs_reference, lbs_torch, posed_joints  # noqa: E402


def _best(fn, repeat=30):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def bench_lbs(repeat: int = 30):
    import torch

    torch.set_num_threads(1)
    hand = builtin_hand(pose=None)
    pose = P.named_pose("fist")
    pose[0] = [0.3, -1.2, 0.5]                 # a global rotation too: every vertex moves
    rows = []
    for which in ("coarse", "fine"):
        m = hand.mesh(which)
        numpy_ms = _best(lambda: lbs(m.vertices, m.weights, hand.rest_joints, PARENTS, pose),
                         repeat) * 1e3
        batch = np.concatenate([pose[None], P.random_poses(15, seed=1)])
        tv, tw, tj = (torch.tensor(a) for a in (m.vertices, m.weights, hand.rest_joints))
        tb = torch.tensor(batch)
        torch_ms = _best(lambda: lbs_torch(tv, tw, tj, PARENTS, tb), max(3, repeat // 3)) \
            * 1e3 / 16
        sel = np.linspace(0, len(m.vertices) - 1, 100).astype(int)   # spread over all parts
        ref_ms = _best(lambda: lbs_reference(m.vertices[sel], m.weights[sel], hand.rest_joints,
                                             PARENTS, pose), 3) * 1e3
        ref = lbs_reference(m.vertices[sel], m.weights[sel], hand.rest_joints, PARENTS, pose)
        err = np.abs(lbs(m.vertices[sel], m.weights[sel], hand.rest_joints, PARENTS, pose)
                     - ref).max()
        torch_err = np.abs(lbs_torch(tv, tw, tj, PARENTS, tb)[0][0].numpy()[sel] - ref).max()
        rows.append({"mesh": which, "vertices": len(m.vertices), "numpy_ms": numpy_ms,
                     "torch_ms": torch_ms, "reference_ms_per_100": ref_ms, "numpy_error_m": err,
                     "torch_error_m": torch_err})
    lines = ["| mesh | vertices | numpy ms/frame | torch ms/frame (batch 16) | loop reference ms/100 v "
             "| max |numpy − reference| m | max |torch − reference| m |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['mesh']} | {r['vertices']} | {r['numpy_ms']:.2f} | {r['torch_ms']:.2f} | "
              f"{r['reference_ms_per_100']:.1f} | {r['numpy_error_m']:.1e} | "
              f"{r['torch_error_m']:.1e} |" for r in rows]
    return "\n".join(lines), rows


def _synthetic(template, n, seed):
    """Known poses (hard cases first) plus keypoints with 2 mm noise and 10% outliers."""
    poses, trans, scales, rest, joints = synthetic_truth(template, n, seed)
    rng = np.random.default_rng(seed + 1)
    kp = joints + rng.normal(0, 0.002, joints.shape)
    out = rng.random(joints.shape[:2]) < 0.10
    kp[out] += rng.normal(0, 0.05, (out.sum(), 3))
    return poses, trans, scales, rest, joints, kp


def bench_fit(frame_counts):
    template = builtin_hand(pose=None)
    m = template.coarse
    lines = ["| frames | wall s | MPJPE mm | worst frame mm | median vertex mm | bone scale err "
             "median % | max % |", "|---|---|---|---|---|---|---|"]
    rows = []
    for n in frame_counts:
        poses, trans, scales, rest, joints, kp = _synthetic(template, n, seed=n)
        t = time.perf_counter()
        result = fit(template, kp, None, options=FitOptions(iterations=300))
        wall = time.perf_counter() - t
        fitted = posed_joints(result.poses, result.translations, result.rest_joints, PARENTS)
        err = np.linalg.norm(fitted - joints, axis=-1) * 1000
        tv = lbs(personalize_mesh(m.vertices, m.weights, template.rest_joints, PARENTS, scales),
                 m.weights, rest, PARENTS, poses, trans)
        fv = lbs(personalize_mesh(m.vertices, m.weights, template.rest_joints, PARENTS,
                                  result.bone_scales), m.weights, result.rest_joints, PARENTS,
                 result.poses, result.translations)
        verr = np.median(np.linalg.norm(fv - tv, axis=-1)) * 1000
        serr = np.abs(result.bone_scales[1:] / scales[1:] - 1) * 100
        lines.append(f"| {n} | {wall:.1f} | {err.mean():.2f} | {err.mean(1).max():.2f} | "
                     f"{verr:.2f} | {np.median(serr):.2f} | {serr.max():.2f} |")
        rows.append({"frames": n, "seconds": wall, "mpjpe_mm": float(err.mean()),
                     "median_vertex_mm": float(verr), "bone_scale_error_pct": float(np.median(serr))})
        print(lines[-1], flush=True)
    return "\n".join(lines), rows


def main():
    ap = B.parser(__doc__, "5 and 10 frames, fewer LBS repeats")
    ap.add_argument("--frames", type=B.integers(1), default=None,
                    help="fitting frame counts [default: 25,100,200; quick: 5,10]")
    args = ap.parse_args()
    out = B.start(args, "bench_hand.py")
    machine = B.machine_limits()
    frame_counts = [int(x) for x in (args.frames or ("5,10" if args.quick else "25,100,200"))
                    .split(",")]
    lbs_text, lbs_rows = bench_lbs(10 if args.quick else 30)
    text = ["# Hand model: LBS and keypoint fitting", "", B.machine_line(machine), "", "## LBS",
            lbs_text, "", "## Keypoint fitting (2 mm noise, 10% outliers)"]
    print("\n".join(text), flush=True)
    fit_text, fit_rows = bench_fit(frame_counts)
    text += [fit_text, "", "LBS timed on 1 torch thread. Plot: hand.png."]
    (out / "hand.md").write_text("\n".join(text) + "\n")
    (out / "hand.json").write_text(json.dumps({"machine": machine, "lbs": lbs_rows,
                                               "fit": fit_rows}, indent=1, default=float) + "\n")
    fig, (left, right) = B.figure(2)
    B.plot(left, {k: [(r[f"{k}_ms"], r[f"{k}_error_m"], r["mesh"]) for r in lbs_rows]
                  for k in ("numpy", "torch")},
           "ms per frame", "max |LBS − loop reference| (m)", "LBS: fast paths vs the loop twin")
    B.plot(right, {"MPJPE": [(r["seconds"], r["mpjpe_mm"], f"{r['frames']} fr") for r in fit_rows],
                   "median vertex error": [(r["seconds"], r["median_vertex_mm"], f"{r['frames']} fr")
                                           for r in fit_rows]},
           "wall seconds (fit of N frames)", "error (mm)", "keypoint fitting", logx=False,
           logy=False)
    B.save(fig, out / "hand.png", machine)


if __name__ == "__main__":
    B.run_main("bench_hand.py", main)
