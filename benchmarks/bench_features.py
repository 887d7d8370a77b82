"""Shading features: time against error, embree throughput, cost of an extra env map.

1. Time vs error: bake-features' engine at env resolutions 8×16 … 64×128 on the
   coarse proxy and on the fine mesh, against a brute-force reference (256×512 env,
   fine-mesh visibility, evaluated at texel centres on the fine surface) at a random
   subset of covered texels.  Error = relative RMS over those texels, per feature.
2. Speed at default settings (:func:`speed_study`): new-pose time, throughput of the
   whole per-pose bake (scene + cull + trace + transport + shade) as a fraction of raw
   embree occlusion throughput on the very same rays at the same thread count, and
   the amortized time per extra env map with the pose's visibility and transport
   cached; medians of interleaved rounds, with the load average printed.

Writes ``features_time_vs_error.{md,csv,png}`` under ``--out`` (default
benchmarks/out/) and prints the tables; the plot: seconds per pose against the
relative RMS error of every feature, one curve per mesh and feature.  Machine limits
in the same run (fp32 GEMM, memory bandwidth, raw embree rays/s on a sphere, beside
the raw embree throughput on the bake's own rays).

    .venv/bin/python benchmarks/bench_features.py [--pose relaxed] [--texels 256] [--quick]
    .venv/bin/python benchmarks/bench_features.py --speed-only [--rounds 15]
"""

from __future__ import annotations

import csv
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402

from relight_cli import features as F
from relight_cli.envmap import DiscreteEnv, discretize_env
from relight_cli.geometry import Receivers, reflect, scene_diagonal, view_directions
from relight_cli.hand.model import builtin_hand
from relight_cli.hand.poses import POSE_NAMES
from relight_cli.hand.scene import posed_meshes, preview_camera
from relight_cli.raytrace import RayScene
from relight_cli.visibility import VisibilityCache, trace_threads
from relight_cli.uvraster import rasterize_uv

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
DEFAULT_ENV = str(DATA / "envmaps" / "StageEnvLatLong.exr")
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
    d = discretize_env(env, *env_res)
    scene = RayScene([(m.vertices, m.faces) for m in fine])
    receivers = Receivers(points, normals, np.ones(len(points), bool))
    offset = 1e-4 * scene_diagonal([(fine[0].vertices, fine[0].faces)])
    cache = VisibilityCache(scene, receivers, d.directions, offset)
    view = view_directions(points, eye)
    out = {name: [] for name in NAMES}
    t0 = time.perf_counter()
    step = 64  # receivers per chunk: bounds the [n, M] masks at M = 131072
    for s in range(0, len(points), step):
        sl = slice(s, s + step)
        sub = Receivers(points[sl], normals[sl], receivers.defined[sl])
        c = VisibilityCache(scene, sub, d.directions, offset)
        need = F.needed_pairs(sub, reflect(view[sl], sub.normals), d.directions, d.lit, settings)
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


def write_plot(path: Path, rows: list[dict], machine: dict):
    """Seconds per pose against each feature's relative RMS error, per mesh (log-log)."""
    fig, axes = B.figure(2)
    for ax, mesh in zip(axes, ("coarse", "fine")):
        B.plot(ax, {name: [(r["seconds"], r["err_" + name], r["env_res"]) for r in rows
                           if r["mesh"] == mesh] for name in NAMES},
               "seconds per pose", "relative RMS error vs the reference",
               f"{mesh} mesh, env grid H x W")
    B.save(fig, path, machine)


load_average = B.load_average


def speed_study(env, coarse, eye, settings, rounds: int) -> dict:
    """New-pose time, extra-env time and throughput against raw embree, default settings.

    Interleaved rounds (so a load spike from another process hits every configuration
    alike); each round times, on the same rays:
      * ``bake_T``: a new pose (FeatureBaker + bake, i.e. scene build, cull, trace,
        transport, shade) with T = every available CPU as worker threads;
      * ``bake_1``: the same with one thread;
      * ``raw_1``: one flat ``RayScene.occluded`` call on the bake's rays, prebuilt;
      * ``raw_T``: the same rays in 4·T equal contiguous chunks traced by T threads,
        i.e. the most embree does on this machine with these rays;
      * ``extra_T`` / ``extra_1``: one more env map on the cached pose.
    Throughput fraction = raw seconds / bake seconds for the same thread count
    (rays are identical, so that is the ratio of rays per second).
    """
    from concurrent.futures import ThreadPoolExecutor
    threads = trace_threads()
    env16 = discretize_env(env, 16, 32)
    meshes = [F.PoseMesh(m.vertices, m.faces, m.normals, m.name) for m in coarse]
    extra_envs = [DiscreteEnv(env16.directions, env16.solid_angle,
                              env16.radiance * (1 + 0.1 * k) + k, 16, 32, f"v{k}")
                  for k in range(1, 5)]
    probe = F.FeatureBaker(meshes, settings, env_res=(16, 32), threads=1)
    probe.bake([env16], eye)
    todo = np.flatnonzero(probe.cache.traced)
    m = len(probe.directions)
    origins = np.ascontiguousarray(probe.cache.ray_origins()[todo // m])
    dirs = np.ascontiguousarray(probe.directions.astype(np.float32)[todo % m])
    rays = len(todo)
    scene = RayScene([(mm.vertices, mm.faces) for mm in meshes])
    scene.occluded(origins[:1], dirs[:1])   # BVH build (the bake's "scene" stage)
    bounds = np.linspace(0, rays, 4 * threads + 1).astype(int)
    chunks = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
    pool = ThreadPoolExecutor(threads)
    list(pool.map(lambda sl: None, chunks))   # start the threads before timing
    load_before = load_average()
    times = {k: [] for k in ("bake_T", "bake_1", "raw_1", "raw_T", "extra_T", "extra_1")}
    stages = {"bake_T": [], "bake_1": []}
    for _ in range(rounds):
        for key, th in (("bake_T", threads), ("bake_1", 1)):
            t0 = time.perf_counter()
            baker = F.FeatureBaker(meshes, settings, env_res=(16, 32), threads=th)
            baker.bake([env16], eye)
            times[key].append(time.perf_counter() - t0)
            stages[key].append(dict(baker.stats.seconds))
            assert baker.stats.rays_traced == rays
            t0 = time.perf_counter()
            for e in extra_envs:
                baker.bake([e], eye)
            times["extra" + key[4:]].append((time.perf_counter() - t0) / len(extra_envs))
        t0 = time.perf_counter()
        scene.occluded(origins, dirs)
        times["raw_1"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        list(pool.map(lambda sl: scene.occluded(origins[sl], dirs[sl]), chunks))
        times["raw_T"].append(time.perf_counter() - t0)
    pool.shutdown()
    med = {k: float(np.median(v)) for k, v in times.items()}
    stage_med = {key: {s: float(np.median([d.get(s, 0.0) for d in v])) for s in v[0]}
                 for key, v in stages.items()}
    # including discretizing the full-resolution env map each time
    t0 = time.perf_counter()
    for _ in range(4):
        baker.bake([env], eye)
    med["extra_full_1"] = (time.perf_counter() - t0) / 4
    return {"threads": threads, "rounds": rounds, "rays": rays,
            "pairs": len(probe.receivers) * m, "vertices": len(probe.receivers),
            "median": med, "min": {k: float(np.min(v)) for k, v in times.items()},
            "stages": stage_med, "load": (load_before, load_average())}


def speed_lines(sp: dict, env) -> list[str]:
    med, mn, T = sp["median"], sp["min"], sp["threads"]
    st = sp["stages"]
    fmt = ", ".join
    return [
        f"Speed at default settings (coarse proxy, {sp['vertices']} vertices, env 16x32, "
        f"Phong 16/32/64): median of {sp['rounds']} interleaved rounds (min in brackets); "
        f"load average {sp['load'][0]} before, {sp['load'][1]} after; {T} CPU(s).",
        f"- new pose, {T} thread(s): {med['bake_T']:.3f} s ({mn['bake_T']:.3f}); "
        f"1 thread: {med['bake_1']:.3f} s ({mn['bake_1']:.3f})  [target ≤ 0.5 s]",
        f"- rays traced: {sp['rays']} of {sp['pairs']} pairs ({sp['rays'] / sp['pairs']:.0%})",
        f"- raw embree on the same rays: {T} thread(s) {med['raw_T']:.3f} s "
        f"({sp['rays'] / med['raw_T'] / 1e6:.2f} Mrays/s); 1 thread {med['raw_1']:.3f} s "
        f"({sp['rays'] / med['raw_1'] / 1e6:.2f} Mrays/s)",
        f"- whole-bake throughput as a fraction of raw embree at the same thread count: "
        f"{T} thread(s) {med['raw_T'] / med['bake_T']:.0%}, 1 thread "
        f"{med['raw_1'] / med['bake_1']:.0%}  [target ≥ 70 %]; "
        f"{T}-thread bake vs 1-thread raw: {med['raw_1'] / med['bake_T']:.0%}",
        f"- extra env map on the cached pose: {T} thread(s) {med['extra_T'] * 1000:.1f} ms, "
        f"1 thread {med['extra_1'] * 1000:.1f} ms (pre-discretized)  [target ≤ 20 ms]; "
        f"{med['extra_full_1'] * 1000:.1f} ms including discretizing the "
        f"{env.height}x{env.width} source",
        "- stages of the 1-thread bake (s): "
        f"{fmt(f'{k} {v:.3f}' for k, v in st['bake_1'].items())}",
        f"- stages of the {T}-thread bake (thread-seconds, summed over workers): "
        f"{fmt(f'{k} {v:.3f}' for k, v in st['bake_T'].items())}",
    ]


def print_speed(sp: dict, env):
    print()
    print("\n".join(speed_lines(sp, env)))


def main():
    ap = B.parser(__doc__, "fewer configurations, 64 reference texels at 128x256, 3 rounds")
    ap.add_argument("--env", default=DEFAULT_ENV,
                    help="env map (default: the shared StageEnvLatLong.exr, else builtin:sky)")
    ap.add_argument("--pose", default="relaxed", choices=POSE_NAMES)
    ap.add_argument("--texels", type=B.integer(1), default=None,
                    help="reference texels (random subset) [default: 256; quick 64]")
    ap.add_argument("--res", type=B.integer(1), default=128)
    ap.add_argument("--ref-env-res", type=B.integers(1, "x", 2), default=None,
                    help="[default: 256x512; quick 128x256]")
    ap.add_argument("--rounds", type=B.integer(1), default=None,
                    help="interleaved rounds of the speed study (medians are reported) "
                         "[default: 9; quick 3]")
    ap.add_argument("--speed-only", action="store_true",
                    help="only the speed study at default settings (no reference, no files)")
    args = ap.parse_args()
    args.texels = args.texels or (64 if args.quick else 256)
    args.ref_env_res = args.ref_env_res or ("128x256" if args.quick else "256x512")
    args.rounds = args.rounds or (3 if args.quick else 9)
    # the shared env map when this checkout sits beside it, else builtin:sky; an --env
    # that was given must be there (one line, exit 1, before any work)
    env_spec = args.env if Path(args.env).exists() or args.env.startswith("builtin:") \
        else "builtin:sky"
    if args.env != DEFAULT_ENV and env_spec != args.env:
        B.fail("bench_features.py", "--env: no such file", args.env, 1)
    out = B.start(args, "bench_features.py")
    machine = B.machine_limits(embree=True)
    env = load_env(env_spec)
    hand = builtin_hand("right", args.pose)
    coarse = posed_meshes(hand, 0, "coarse")
    fine = posed_meshes(hand, 0, "fine")
    eye = preview_camera(coarse).center
    settings = F.FeatureSettings(shininess=(16, 32, 64), specular="phong")
    ref_res = tuple(int(v) for v in args.ref_env_res.split("x"))
    print(f"env {env_spec}; hand {args.pose}: coarse {len(coarse[0].vertices)} vertices, "
          f"fine {len(fine[0].vertices)}; eye {np.round(eye, 3).tolist()}")
    if args.speed_only:
        print_speed(speed_study(env, coarse, eye, settings, args.rounds), env)
        return

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

    # -- speed at default settings (coarse, 16x32, phong 16/32/64): see speed_study
    speed = speed_study(env, coarse, eye, settings, args.rounds)
    print_speed(speed, env)
    # -- files
    keys = ["mesh", "env_res", "seconds", "rays", "rays_possible"] + ["err_" + n for n in NAMES]
    with open(out / "features_time_vs_error.csv", "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=keys)
        wr.writeheader()
        for r in results:
            wr.writerow(r)
    lines = [f"# bake-features: time vs error ({env_spec}, hand {args.pose})", "",
             B.machine_line(machine), "",
             f"Reference: {len(points)} random covered texels at {args.res}², fine-mesh surface "
             f"and visibility, env {ref_res[0]}x{ref_res[1]} ({ref_seconds:.1f} s). "
             "Error: relative RMS over those texels.", "",
             "| mesh | env | s / pose | rays | " + " | ".join(NAMES) + " |",
             "|---|---|---|---|" + "---|" * len(NAMES)]
    for r in results:
        lines.append(f"| {r['mesh']} | {r['env_res']} | {r['seconds']:.3f} | {r['rays']} | "
                     + " | ".join(f"{r['err_' + n]:.4f}" for n in NAMES) + " |")
    lines += [""] + speed_lines(speed, env) + ["", "Plot: features_time_vs_error.png."]
    (out / "features_time_vs_error.md").write_text("\n".join(lines) + "\n")
    write_plot(out / "features_time_vs_error.png", results, machine)
    print(f"\nwrote {out / 'features_time_vs_error.md'}, .csv, .png")


if __name__ == "__main__":
    B.run_main("bench_features.py", main)
