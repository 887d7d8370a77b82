"""Speed against error of environment-map resampling and conversion.

For each path (exact lat-long → lat-long, rotation, cube → lat-long splatting,
lat-long → cube, the 1e6-sun case) prints wall time, the relative power error
|∫L'dω − ∫L dω| / ∫L dω, and, where a reference exists, the mean absolute
per-texel error against it:

* OpenEXR's own orientation pair (OrientationCube.exr → our lat-long vs their
  OrientationLatLong.exr), when ../shared/data is present;
* a smooth analytic environment L(ω) = 1.5 + 0.5·ω + 0.3·(ω_y, ω_z, ω_x)² whose
  exact cell means are approximated by 64× supersampled quadrature.

Writes envmap.{md,json,png} under --out (default benchmarks/out/): the table, and
seconds against texel error (left) and power error (right), one curve per path.
Machine limits in the same run: memory copy bandwidth (resampling streams texels)
and fp32 GEMM.

Usage:  .venv/bin/python benchmarks/bench_envmap.py [--quick] [--out DIR]
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402

from relight_cli import envmap as E  # noqa: E402
from relight_cli.formats.envmap import EnvMap, read_envmap  # noqa: E402

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def smooth(d):
    return 1.5 + 0.5 * d + 0.3 * d[..., [1, 2, 0]] ** 2


def cell_means(layout, h, w, n=8):
    """Reference: mean of `smooth` over each texel cell by n×n exact sub-cells."""
    acc = np.zeros((h * w, 3))
    area = np.zeros(h * w)
    for d, omega, idx in E._subcells(layout, h, w, n):
        for c in range(3):
            acc[:, c] += np.bincount(idx, weights=smooth(d)[:, c] * omega, minlength=h * w)
        area += np.bincount(idx, weights=omega, minlength=h * w)
    return (acc / area[:, None]).reshape(h, w, 3)


def timed(fn, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return out, best


def main():
    args = B.parser(__doc__, "skip the largest conversions").parse_args()
    out_dir = B.start(args, "bench_envmap.py")
    machine = B.machine_limits()
    rows = []
    src = EnvMap(cell_means("latlong", 256, 512).astype(np.float32))
    src_cube = EnvMap(cell_means("cube", 6 * 128, 128).astype(np.float32), "cube")
    p0 = E.power(src)
    cases = [
        ("latlong 512x256 → latlong 32x16 (exact)", lambda: E.resample(src, "latlong", 16, 32), ("latlong", 16, 32)),
        ("latlong 512x256 → latlong 128x64 (exact)", lambda: E.resample(src, "latlong", 64, 128), ("latlong", 64, 128)),
        ("latlong 512x256 → latlong 1024x512 (exact, up)", lambda: E.resample(src, "latlong", 512, 1024), ("latlong", 512, 1024)),
        ("latlong 512x256 → cube 64 (splat)", lambda: E.resample(src, "cube", 6 * 64, 64), ("cube", 6 * 64, 64)),
        ("latlong 512x256 → cube 256 (splat)", lambda: E.resample(src, "cube", 6 * 256, 256), ("cube", 6 * 256, 256)),
        ("cube 128 → latlong 32x16 (splat)", lambda: E.resample(src_cube, "latlong", 16, 32), ("latlong", 16, 32)),
        ("cube 128 → latlong 256x128 (splat)", lambda: E.resample(src_cube, "latlong", 128, 256), ("latlong", 128, 256)),
        ("cube 128 → latlong 2048x1024 (gather)", lambda: E.resample(src_cube, "latlong", 1024, 2048), ("latlong", 1024, 2048)),
    ]
    if args.quick:   # the small conversions only (the large ones take most of the time)
        cases = [c for c in cases if not any(k in c[0] for k in ("1024", "2048", "cube 256",
                                                                 "256x128"))]
    for name, fn, (layout, h, w) in cases:
        out, sec = timed(fn, repeat=1 if "2048" in name or "1024" in name else 3)
        ref = cell_means(layout, h, w, n=4)
        base = p0 if name.startswith("latlong") else E.power(src_cube)
        rows.append((name, sec, float(np.abs(E.power(out) / base - 1).max()),
                     float(np.abs(out.radiance - ref).mean() / ref.mean())))
    sun = np.full((256, 512, 3), 0.5, np.float32)
    sun[70, 300] = 1e6
    sun_env = EnvMap(sun)
    for layout, h, w in [("latlong", 16, 32), ("cube", 96, 16)] + ([] if args.quick else
                                                                    [("cube", 384, 64)]):
        out, sec = timed(lambda: E.resample(sun_env, layout, h, w))
        rows.append((f"1e6 sun 512x256 → {layout} {w}x{h}", sec,
                     float(np.abs(E.power(out) / E.power(sun_env) - 1).max()), float("nan")))
    cube_file = SHARED / "envmaps" / "OrientationCube.exr"
    if cube_file.exists() and not args.quick:
        cube = read_envmap(str(cube_file))
        lat = read_envmap(str(SHARED / "envmaps" / "OrientationLatLong.exr"))
        out, sec = timed(lambda: E.resample(cube, "latlong", lat.height, lat.width), repeat=1)
        rows.append(("OpenEXR OrientationCube → latlong 1024x512 vs theirs", sec,
                     float(np.abs(E.power(out) / E.power(cube) - 1).max()),
                     float(np.abs(out.radiance - lat.radiance).mean() / lat.radiance.mean())))
        near = E.lookup(cube, E.latlong_directions(lat.height, lat.width).reshape(-1, 3))
        rows.append(("  (nearest-texel lookup, for comparison)", float("nan"), float("nan"),
                     float(np.abs(near.reshape(lat.radiance.shape) - lat.radiance).mean()
                           / lat.radiance.mean())))
    lines = ["# Environment maps: resampling time against error", "", B.machine_line(machine),
             "", "| path | seconds | power rel. error | mean abs error / mean |",
             "|---|---|---|---|"]
    lines += [f"| {n} | {s:.3f} | {p:.2e} | {e:.2e} |" for n, s, p, e in rows]
    lines += ["", "Plot: envmap.png (seconds against the per-texel error and the power error)."]
    text = "\n".join(lines)
    print(text)
    (out_dir / "envmap.md").write_text(text + "\n")
    (out_dir / "envmap.json").write_text(json.dumps(
        {"machine": machine, "rows": [dict(zip(("path", "seconds", "power_error", "texel_error"), r))
                                      for r in rows]}, indent=1, default=float) + "\n")
    write_plot(out_dir / "envmap.png", rows, machine)


def _family(name: str) -> str:
    if "OpenEXR" in name or name.startswith(" "):
        return ""
    if name.startswith("1e6 sun"):
        return "1e6 sun → " + name.split("→ ")[1].split()[0]
    src, rest = name.split(" → ")
    return f"{src.split()[0]} → {rest.split()[0]}" + (" (exact)" if "exact" in rest else "")


def write_plot(path: Path, rows: list, machine: dict) -> None:
    """Seconds against texel error (left) and power error (right), one curve per path."""
    texel, power = {}, {}
    for name, sec, p, e in rows:
        family = _family(name) or "OpenEXR orientation cube → lat-long"
        size = name.split("→ ")[-1].split(" (")[0].split(" vs")[0] if "→" in name else ""
        texel.setdefault(family, []).append((sec, e, size))
        power.setdefault(family, []).append((sec, p, size))
    fig, (left, right) = B.figure(2)
    B.plot(left, {k: v for k, v in texel.items() if not k.startswith("1e6")}, "seconds",
           "mean |error| / mean (texels, vs exact cell means)", "per-texel error")
    B.plot(right, power, "seconds", "|power' / power - 1|", "power ∫L dω preserved")
    B.save(fig, path, machine)


if __name__ == "__main__":
    B.run_main("bench_envmap.py", main)
