"""Speed and accuracy of the hand model: LBS and keypoint fitting.

Prints two tables (markdown) and optionally writes them to a file:

1. LBS time per frame of the coarse and fine meshes (numpy fast path, torch
   CPU batched, the per-vertex loop reference per 100 vertices); target: fine
   mesh ≤ 5 ms.
2. Fitting N frames of synthetic keypoints (random poses incl. fist and
   at-limit poses, known bone scales ±5%, 2 mm Gaussian noise, 10% outliers):
   wall time, MPJPE vs the true joints, median vertex error, bone-scale error;
   target: 100 frames ≤ 60 s on a 2-core machine.

Usage:  .venv/bin/python benchmarks/bench_hand.py [--frames 25,100,200] [--out bench_hand.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

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


def bench_lbs():
    import torch

    torch.set_num_threads(1)
    hand = builtin_hand(pose=None)
    pose = P.named_pose("fist")
    pose[0] = [0.3, -1.2, 0.5]                 # a global rotation too: every vertex moves
    rows = []
    for which in ("coarse", "fine"):
        m = hand.mesh(which)
        numpy_ms = _best(lambda: lbs(m.vertices, m.weights, hand.rest_joints, PARENTS, pose)) * 1e3
        batch = torch.tensor(P.random_poses(16, seed=1))
        tv, tw, tj = (torch.tensor(a) for a in (m.vertices, m.weights, hand.rest_joints))
        torch_ms = _best(lambda: lbs_torch(tv, tw, tj, PARENTS, batch), 10) * 1e3 / 16
        sel = np.linspace(0, len(m.vertices) - 1, 100).astype(int)   # spread over all parts
        ref_ms = _best(lambda: lbs_reference(m.vertices[sel], m.weights[sel], hand.rest_joints,
                                             PARENTS, pose), 3) * 1e3
        err = np.abs(lbs(m.vertices[sel], m.weights[sel], hand.rest_joints, PARENTS, pose)
                     - lbs_reference(m.vertices[sel], m.weights[sel], hand.rest_joints, PARENTS,
                                     pose)).max()
        rows.append((which, len(m.vertices), numpy_ms, torch_ms, ref_ms, err))
    lines = ["| mesh | vertices | numpy ms/frame | torch ms/frame (batch 16) | loop reference ms/100 v "
             "| max |numpy − reference| m |", "|---|---|---|---|---|---|"]
    lines += [f"| {w} | {v} | {a:.2f} | {b:.2f} | {c:.1f} | {e:.1e} |" for w, v, a, b, c, e in rows]
    return "\n".join(lines)


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
        print(lines[-1], flush=True)
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="25,100,200")
    ap.add_argument("--out", default=None, help="also write the tables (markdown) here")
    args = ap.parse_args()
    frame_counts = [int(x) for x in args.frames.split(",")]
    text = ["## LBS", bench_lbs(), "", "## Keypoint fitting (2 mm noise, 10% outliers)"]
    print("\n".join(text), flush=True)
    text.append(bench_fit(frame_counts))
    text.append(f"\nmachine: {os.cpu_count()} CPUs, torch 1 thread")
    print(text[-1])
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            f.write("\n".join(text) + "\n")


if __name__ == "__main__":
    main()
