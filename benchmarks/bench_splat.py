"""Speed of the CPU EWA splatting renderer: 100k Gaussians at 512×512.

Prints a table of wall time against tile size and chunk size, the number of
(tile, Gaussian) pairs, and the agreement with the per-pixel twin on a small
crop of the same scene (the fast path is exact, so the error is rounding).

Writes splat.{md,json,png} under --out (default benchmarks/out/): the plot shows the
render seconds against the tile size (one curve per first chunk size; the fast path is
exact, so configurations differ in time only) and the twin check, seconds against the
error vs the per-pixel reference.  Machine limits in the same run.

    .venv/bin/python benchmarks/bench_splat.py [--quick] [--n 100000] [--size 512] [--out DIR]
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402

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
    ap = B.parser(__doc__, "20k Gaussians at 256x256")
    ap.add_argument("--n", type=B.integer(1), default=None,
                    help="Gaussians [default: 100000; quick 20000]")
    ap.add_argument("--size", type=B.integer(1), default=None,
                    help="image size [default: 512; quick 256]")
    args = ap.parse_args()
    out_dir = B.start(args, "bench_splat.py")
    machine = B.machine_limits()
    n = args.n or (20_000 if args.quick else 100_000)
    size = args.size or (256 if args.quick else 512)
    log = B.Tee()
    log("# CPU EWA splatting: time by configuration", "", B.machine_line(machine), "")
    g = scene(n)
    cam = Camera.look_at([0.0, 0.8, 3.2], [0, 0, 0], width=size, height=size, fov_y_deg=50)
    t = time.perf_counter()
    pr = project(g, cam)
    t_proj = time.perf_counter() - t
    log(f"{n} Gaussians, {size}x{size}: projection+SH+sort {t_proj:.3f} s, "
        f"{len(pr.index)} in front of the camera", "")
    log("| tile | first chunk | seconds | max |Δ| vs first config |", "|---|---|---|---|")
    ref_img = None
    rows = []
    for tile, chunk in [(8, 64), (8, 256), (4, 64), (16, 64)] + ([] if args.quick else [(32, 64)]):
        t = time.perf_counter()
        out = render(g, cam, tile=tile, chunk=chunk)
        dt = time.perf_counter() - t
        if ref_img is None:
            ref_img = out.image
        diff = float(np.abs(out.image - ref_img).max())
        rows.append({"tile": tile, "chunk": chunk, "seconds": dt, "max_diff": diff})
        log(f"| {tile} | {chunk} | {dt:.3f} | {diff:.1e} |")
    # Twin agreement on a 24×24 view of a 300-Gaussian subset (the twin is O(pixels × Gaussians) in Python).
    small = g.subset(np.arange(300))
    cam_s = Camera.look_at([0.0, 0.8, 3.2], [0, 0, 0], width=24, height=24, fov_y_deg=50)
    t = time.perf_counter()
    fast = render(small, cam_s)
    t_fast = time.perf_counter() - t
    t = time.perf_counter()
    slow = render_reference(small, cam_s)
    t_slow = time.perf_counter() - t
    twin = {"fast_seconds": t_fast, "reference_seconds": t_slow,
            "max_image_diff": float(np.abs(fast.image - slow.image).max()),
            "max_alpha_diff": float(np.abs(fast.alpha - slow.alpha).max())}
    log("", f"Twin check, 300 Gaussians at 24x24: fast {t_fast:.4f} s, per-pixel {t_slow:.2f} s, "
        f"max |Δimage| {twin['max_image_diff']:.1e}, max |Δalpha| {twin['max_alpha_diff']:.1e}.",
        "", "(chunk = the first chunk of a tile's Gaussian list; it doubles up to 4096.) "
        "Plot: splat.png.")
    (out_dir / "splat.md").write_text(log.text())
    (out_dir / "splat.json").write_text(json.dumps({"machine": machine, "gaussians": n,
                                                    "size": size, "rows": rows, "twin": twin},
                                                   indent=1) + "\n")
    fig, (left, right) = B.figure(2)
    B.plot(left, {f"first chunk {c}": [(r["tile"], r["seconds"], f"{r['tile']}px")
                                       for r in rows if r["chunk"] == c]
                  for c in sorted({r["chunk"] for r in rows})},
           "tile size (pixels)", "render seconds", f"{n} Gaussians, {size}x{size}", logy=False)
    B.plot(right, {"tile renderer": [(t_fast, twin["max_image_diff"], "fast")],
                   "per-pixel twin (reference)": [(t_slow, 0.0, "reference")]},
           "seconds (300 Gaussians, 24x24)", "max |Δ image| vs per-pixel twin",
           "the fast path against its twin")
    B.save(fig, out_dir / "splat.png", machine)


if __name__ == "__main__":
    B.run_main("bench_splat.py", main)
