"""Speed of the CPU EWA splatting renderer: 100k Gaussians at 512×512.

Prints a table of wall time against tile size and chunk size, the number of
(tile, Gaussian) pairs, and the agreement with the per-pixel twin on a small
crop of the same scene (the fast path is exact, so the error is rounding).

    .venv/bin/python benchmarks/bench_splat.py [--n 100000] [--size 512]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial.transform import Rotation

from relight_cli.formats.camera import Camera
from relight_cli.formats.gaussians_ply import Gaussians
from relight_cli.gaussians.splat import project, render, render_reference


def scene(n: int, seed: int = 0, degree: int = 1) -> Gaussians:
    """n Gaussians on a noisy unit sphere shell plus a floor, scales ~1-3 cm (a typical 3DGS object)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means = d * rng.uniform(0.9, 1.0, (n, 1))
    floor = rng.random(n) < 0.3
    means[floor] = np.column_stack([rng.uniform(-3, 3, floor.sum()), np.full(floor.sum(), -1.0),
                                    rng.uniform(-3, 3, floor.sum())])
    k = (degree + 1) ** 2
    return Gaussians(means, np.exp(rng.uniform(np.log(0.005), np.log(0.03), (n, 3))),
                     Rotation.random(n, random_state=seed).as_quat()[:, [3, 0, 1, 2]],
                     rng.uniform(0.2, 1.0, n), rng.normal(size=(n, k, 3)) * 0.3, degree)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--size", type=int, default=512)
    args = ap.parse_args()
    g = scene(args.n)
    cam = Camera.look_at([0.0, 0.8, 3.2], [0, 0, 0], width=args.size, height=args.size, fov_y_deg=50)
    t = time.perf_counter()
    pr = project(g, cam)
    t_proj = time.perf_counter() - t
    print(f"{args.n} Gaussians, {args.size}x{args.size}: projection+SH+sort {t_proj:.3f} s, "
          f"{len(pr.index)} in front of the camera")
    print(f"{'tile':>5} {'chunk':>6} {'seconds':>8}   (chunk = first chunk; it doubles up to 4096)")
    ref_img = None
    for tile, chunk in [(8, 64), (8, 256), (4, 64), (16, 64), (32, 64)]:
        t = time.perf_counter()
        out = render(g, cam, tile=tile, chunk=chunk)
        dt = time.perf_counter() - t
        if ref_img is None:
            ref_img = out.image
        diff = np.abs(out.image - ref_img).max()
        print(f"{tile:>5} {chunk:>6} {dt:8.3f}   max |Δ| vs first config {diff:.1e}")
    # Twin agreement on a 24×24 view of a 300-Gaussian subset (the twin is O(pixels × Gaussians) in Python).
    small = g.subset(np.arange(300))
    cam_s = Camera.look_at([0.0, 0.8, 3.2], [0, 0, 0], width=24, height=24, fov_y_deg=50)
    t = time.perf_counter()
    fast = render(small, cam_s)
    t_fast = time.perf_counter() - t
    t = time.perf_counter()
    slow = render_reference(small, cam_s)
    t_slow = time.perf_counter() - t
    print(f"twin check 300 Gaussians 24x24: fast {t_fast:.4f} s, per-pixel {t_slow:.2f} s, "
          f"max |Δimage| {np.abs(fast.image - slow.image).max():.1e}, "
          f"max |Δalpha| {np.abs(fast.alpha - slow.alpha).max():.1e}")


if __name__ == "__main__":
    main()
