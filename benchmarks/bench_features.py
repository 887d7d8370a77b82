"""Shading features: time against error, embree throughput, cost of an extra env map.

1. Time vs error: bake-features' engine at env resolutions 8×16 … 64×128 on the
   coarse proxy and on the fine mesh, against a brute-force reference (256×512 env,
   fine-mesh visibility, evaluated at texel centres on the fine surface) at a random
   subset of covered texels.  Error = relative RMS over those texels, per feature.
2. Throughput: rays traced per second of the whole per-pose bake (cull + trace +
   transport + shade) as a fraction of raw embree occlusion throughput on the very
   same rays, measured in the same run.
3. Amortized time per extra env map with the pose's visibility and transport cached.

Writes ``features_time_vs_error.{md,csv,svg}`` under ``--out`` (default
benchmarks/out/) and prints the tables.

    .venv/bin/python benchmarks/bench_features.py [--pose relaxed] [--texels 256] [--quick]
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import numpy as np

from relight_cli import features as F
from relight_cli.hand.model import builtin_hand
from relight_cli.hand.scene import posed_meshes, preview_camera
from relight_cli.raytrace import RayScene
from relight_cli.uvraster import rasterize_uv

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
NAMES = ["diffuse", "phong16", "phong32", "phong64", "visibility"]


def load_env(name: str):
    if name.startswith("builtin:"):
        from relight_cli.builtin_envs import builtin_envmap
        return builtin_envmap(name)
    from relight_cli.formats.envmap import read_envmap
    return read_envmap(name)


def texel_samples(mesh, res: int, count: int, seed: int):
    """Random covered texels: (rows, cols), surface points and normals on ``mesh``."""
    raster = rasterize_uv(mesh.uv, mesh.faces_uv, res)
    rows, cols = np.nonzero(raster.inside)
    pick = np.random.default_rng(seed).choice(len(rows), size=min(count, len(rows)), replace=False)
    rows, cols = rows[pick], cols[pick]
    face = raster.face[rows, cols]
    bary = raster.barycentric[rows, cols]
    corners = mesh.faces[face]
    points = np.einsum("kj,kjc->kc", bary, mesh.vertices[corners])
    normals = np.einsum("kj,kjc->kc", bary, mesh.normals[corners])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return rows, cols, points, normals


def reference(fine, points, normals, env, eye, settings, env_res):
    """Brute-force reference at arbitrary receivers: every needed pair traced, fine env."""
    d = F.discretize_env(env, *env_res)
    scene = RayScene([(m.vertices, m.faces) for m in fine])
    receivers = F.Receivers(points, normals, np.ones(len(points), bool))
    offset = 1e-4 * F.scene_diagonal([(fine[0].vertices, fine[0].faces)])
    cache = F.VisibilityCache(scene, receivers, d.directions, offset)
    view = F.view_directions(points, eye)
    out = {name: [] for name in NAMES}
    t0 = time.perf_counter()
    step = 64  # receivers per chunk: bounds the [n, M] masks at M = 131072
    for s in range(0, len(points), step):
        sl = slice(s, s + step)
        sub = F.Receivers(points[sl], normals[sl], receivers.defined[sl])
        c = F.VisibilityCache(scene, sub, d.directions, offset)
        need = F.needed_pairs(sub, F.reflect(view[sl], sub.normals), d.directions, d.lit, settings)
        c.require(need)
        feats = F.shade(sub, view[sl], [d], c.visible, settings)[0]
        for name in NAMES:
            out[name].append(feats[name])
        cache.rays_traced += c.rays_traced
    seconds = time.perf_counter() - t0
    return {k: np.concatenate(v) for k, v in out.items()}, seconds, cache.rays_traced


def bake_texels(meshes, env, eye, settings, env_res, res):
    """Engine bake of the whole pose, then texel maps; returns maps per name, seconds, stats."""
    t0 = time.perf_counter()
    baker = F.FeatureBaker([F.PoseMesh(m.vertices, m.faces, m.normals, m.name) for m in meshes],
                           settings, env_res=env_res)
    feats = baker.bake([env], eye)[0][0]
    bake_seconds = time.perf_counter() - t0
    raster = rasterize_uv(meshes[0].uv, meshes[0].faces_uv, res)
    maps = F.texel_maps(feats, meshes[0].faces, raster)
    return maps, bake_seconds, baker


def rel_rms(x, ref):
    return float(np.sqrt(np.mean((x - ref) ** 2)) / max(np.sqrt(np.mean(ref ** 2)), 1e-30))


def write_svg(path: Path, rows: list[dict]):
    """A log-log plot of seconds vs diffuse error, one polyline per mesh (no matplotlib)."""
    w, h, pad = 560, 380, 60
    pts = [(r["seconds"], r["err_diffuse"], r["mesh"], r["env_res"]) for r in rows]
    xs = [math.log10(p[0]) for p in pts]
    ys = [math.log10(max(p[1], 1e-6)) for p in pts]
    x0, x1 = min(xs) - 0.1, max(xs) + 0.1
    y0, y1 = min(ys) - 0.1, max(ys) + 0.1

    def X(v):
        return pad + (v - x0) / (x1 - x0) * (w - 2 * pad)

    def Y(v):
        return h - pad - (v - y0) / (y1 - y0) * (h - 2 * pad)
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" '
             f'font-family="sans-serif" font-size="11">',
             f'<rect width="{w}" height="{h}" fill="white"/>',
             f'<line x1="{pad}" y1="{h - pad}" x2="{w - pad}" y2="{h - pad}" stroke="black"/>',
             f'<line x1="{pad}" y1="{pad}" x2="{pad}" y2="{h - pad}" stroke="black"/>',
             f'<text x="{w / 2}" y="{h - 15}" text-anchor="middle">seconds per pose (log)</text>',
             f'<text x="15" y="{h / 2}" transform="rotate(-90 15 {h / 2})" text-anchor="middle">'
             f'relative RMS error of diffuse (log)</text>']
    for e in range(math.floor(x0), math.ceil(x1) + 1):
        if x0 <= e <= x1:
            parts.append(f'<text x="{X(e)}" y="{h - pad + 15}" text-anchor="middle">1e{e}</text>')
    for e in range(math.floor(y0), math.ceil(y1) + 1):
        if y0 <= e <= y1:
            parts.append(f'<text x="{pad - 5}" y="{Y(e)}" text-anchor="end">1e{e}</text>')
    colours = {"coarse": "#1f77b4", "fine": "#d62728"}
    for mesh, colour in colours.items():
        sel = [(X(math.log10(p[0])), Y(math.log10(max(p[1], 1e-6))), p[3]) for p in pts
               if p[2] == mesh]
        if not sel:
            continue
        parts.append('<polyline fill="none" stroke="%s" points="%s"/>'
                     % (colour, " ".join(f"{a:.1f},{b:.1f}" for a, b, _ in sel)))
        for a, b, label in sel:
            parts.append(f'<circle cx="{a:.1f}" cy="{b:.1f}" r="3" fill="{colour}"/>')
            parts.append(f'<text x="{a + 5:.1f}" y="{b - 5:.1f}" fill="{colour}">{label}</text>')
        parts.append(f'<text x="{w - pad - 60}" y="{pad + (20 if mesh == "fine" else 5)}" '
                     f'fill="{colour}">{mesh} mesh</text>')
    parts.append("</svg>")
    path.write_text("\n".join(parts) + "\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default=str(DATA / "envmaps" / "StageEnvLatLong.exr"),
                    help="env map (default: the shared StageEnvLatLong.exr, else builtin:sky)")
    ap.add_argument("--pose", default="relaxed")
    ap.add_argument("--texels", type=int, default=256, help="reference texels (random subset)")
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--ref-env-res", default="256x512")
    ap.add_argument("--quick", action="store_true", help="fewer configurations (smoke run)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "out"))
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    env_spec = args.env if Path(args.env).exists() or args.env.startswith("builtin:") \
        else "builtin:sky"
    env = load_env(env_spec)
    hand = builtin_hand("right", args.pose)
    coarse = posed_meshes(hand, 0, "coarse")
    fine = posed_meshes(hand, 0, "fine")
    eye = preview_camera(coarse).center
    settings = F.FeatureSettings(shininess=(16, 32, 64), specular="phong")
    ref_res = tuple(int(v) for v in args.ref_env_res.split("x"))
    print(f"env {env_spec}; hand {args.pose}: coarse {len(coarse[0].vertices)} vertices, "
          f"fine {len(fine[0].vertices)}; eye {np.round(eye, 3).tolist()}")

    # -- reference at random covered texels of the fine mesh's surface
    rows, cols, points, normals = texel_samples(fine[0], args.res, args.texels, seed=0)
    ref, ref_seconds, ref_rays = reference(fine, points, normals, env, eye, settings, ref_res)
    print(f"reference: {len(points)} texels, env {ref_res[0]}x{ref_res[1]}, fine-mesh "
          f"visibility: {ref_rays} rays, {ref_seconds:.1f} s")

    # -- time vs error
    env_list = [(8, 16), (16, 32), (32, 64)] if args.quick else [(8, 16), (16, 32), (32, 64),
                                                                 (64, 128)]
    results = []
    for mesh_name, meshes in (("coarse", coarse), ("fine", fine)):
        for env_res in env_list:
            if mesh_name == "fine" and env_res == (64, 128) and args.quick:
                continue
            best = None
            for _ in range(1 if mesh_name == "fine" or env_res[0] >= 32 else 3):
                maps, seconds, baker = bake_texels(meshes, env, eye, settings, env_res, args.res)
                best = seconds if best is None else min(best, seconds)
            row = {"mesh": mesh_name, "env_res": f"{env_res[0]}x{env_res[1]}",
                   "seconds": best, "rays": baker.stats.rays_traced,
                   "rays_possible": len(baker.receivers) * len(baker.directions)}
            for name in NAMES:
                got = maps[name][rows, cols]
                row["err_" + name] = rel_rms(got, ref[name])
            results.append(row)
            print(f"  {mesh_name:6s} {row['env_res']:>7s}: {best:7.3f} s, "
                  f"{row['rays']:>9d} rays ({row['rays'] / row['rays_possible']:.0%} of N·M), "
                  + ", ".join(f"{n} {row['err_' + n]:.3f}" for n in NAMES))

    # -- throughput vs raw embree on the same rays (default settings, coarse)
    env16 = F.discretize_env(env, 16, 32)
    meshes = [F.PoseMesh(m.vertices, m.faces, m.normals, m.name) for m in coarse]
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        baker = F.FeatureBaker(meshes, settings, env_res=(16, 32))
        baker.bake([env16], eye)
        times.append(time.perf_counter() - t0)
        if times[-1] == min(times):
            stages = dict(baker.stats.seconds)
    pose_seconds = min(times)
    todo = np.flatnonzero(baker.cache.traced)
    m = len(baker.directions)
    origins = baker.cache._origins[todo // m]
    dirs = baker.cache._dirs32[todo % m]
    scene = RayScene([(mm.vertices, mm.faces) for mm in meshes])
    scene.occluded(origins[:1], dirs[:1])  # BVH build (its cost is the bake's "scene" stage)
    raw = []
    for _ in range(3):
        t0 = time.perf_counter()
        scene.occluded(origins, dirs)
        raw.append(time.perf_counter() - t0)
    raw_seconds = min(raw)
    rays = len(todo)
    fraction = raw_seconds / pose_seconds
    trace_fraction = raw_seconds / stages["trace"]
    # -- amortized extra env maps (same pose and eye; visibility and transport cached)
    extra_envs = [env16] + [F.DiscreteEnv(env16.directions, env16.solid_angle,
                                          env16.radiance * (1 + 0.1 * k) + k, 16, 32, f"v{k}")
                            for k in range(1, 8)]
    t0 = time.perf_counter()
    for e in extra_envs:
        baker.bake([e], eye)
    per_env = (time.perf_counter() - t0) / len(extra_envs)
    # including discretizing a full-resolution env map each time
    t0 = time.perf_counter()
    for _ in range(4):
        baker.bake([env], eye)
    per_env_full = (time.perf_counter() - t0) / 4
    n_pairs = len(baker.receivers) * m
    print(f"\nnew pose at defaults (coarse, 16x32, phong 16/32/64): {pose_seconds:.3f} s "
          f"(best of 3); stages {', '.join(f'{k} {v:.3f}' for k, v in stages.items())}")
    print(f"rays traced {rays} of {n_pairs} pairs ({rays / n_pairs:.0%}); raw embree on the same "
          f"rays {raw_seconds:.3f} s = {rays / raw_seconds / 1e6:.2f} Mrays/s; whole bake "
          f"{rays / pose_seconds / 1e6:.2f} Mrays/s = {fraction:.0%} of raw; trace stage alone "
          f"(ray building + embree) {trace_fraction:.0%} of raw")
    print(f"extra env map (cached pose): {per_env * 1000:.1f} ms each (pre-discretized), "
          f"{per_env_full * 1000:.1f} ms including discretizing the "
          f"{env.height}x{env.width} source")

    # -- files
    keys = ["mesh", "env_res", "seconds", "rays", "rays_possible"] + ["err_" + n for n in NAMES]
    with open(out / "features_time_vs_error.csv", "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=keys)
        wr.writeheader()
        for r in results:
            wr.writerow(r)
    lines = [f"# bake-features: time vs error ({env_spec}, hand {args.pose})", "",
             f"Reference: {len(points)} random covered texels at {args.res}², fine-mesh surface "
             f"and visibility, env {ref_res[0]}x{ref_res[1]} ({ref_seconds:.1f} s). "
             "Error: relative RMS over those texels.", "",
             "| mesh | env | s / pose | rays | " + " | ".join(NAMES) + " |",
             "|---|---|---|---|" + "---|" * len(NAMES)]
    for r in results:
        lines.append(f"| {r['mesh']} | {r['env_res']} | {r['seconds']:.3f} | {r['rays']} | "
                     + " | ".join(f"{r['err_' + n]:.4f}" for n in NAMES) + " |")
    lines += ["", f"New pose at defaults: {pose_seconds:.3f} s; {rays} rays "
                  f"({rays / n_pairs:.0%} of N·M); raw embree {raw_seconds:.3f} s on the same rays; "
                  f"whole-bake throughput {fraction:.0%} of raw (trace stage alone {trace_fraction:.0%}).",
              f"Extra env map with cached visibility: {per_env * 1000:.1f} ms "
              f"({per_env_full * 1000:.1f} ms including discretizing the full-size map)."]
    (out / "features_time_vs_error.md").write_text("\n".join(lines) + "\n")
    write_svg(out / "features_time_vs_error.svg", results)
    print(f"\nwrote {out / 'features_time_vs_error.md'}, .csv, .svg")


if __name__ == "__main__":
    main()
