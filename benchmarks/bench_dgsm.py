"""DGSM speed and shadow-accuracy study (not a test; prints tables, optional JSON).

Part 1 — build time (issue 14 target: a 50k-Gaussian avatar, 128×128×64, one
light, ≤ 0.2 s on a 2-core machine; before issue 14 the volumetric scene took
0.44 s here, its cost in the per-cone texel enumeration, not in erf) for the
float32 torch and numpy inner loops and the float64 numpy reference twin, the
ROI and culling ablations, with the error of each against the float64 build
(max |ΔT| over table entries and at receivers).

Part 2 — the paper's shadow protocol (Sec. 4.2): an occluder mesh (the
built-in procedural hand, or a sphere) turned into flat Gaussians
(relight_cli.gaussians.from_mesh) casts a shadow on a floor; the pseudo ground
truth is the same mesh's embree ray-traced hard shadow (relight_cli.raytrace).
Mattes (1 = shadow) on a floor image are scored with relight_cli.metrics.shadow
(SAE, SM-IoU, boundary F at 2 px) for the ablations:
  A footprint (centre / 7-point stencil / Monte Carlo),
  B opacity→absorption mapping (the paper's avg = Eq. 5 / simple / mass / diag, and peak),
  C atlas (octahedral / cube),
plus "direct": the closed-form transmittance at every floor point without a
table (what the Gaussians themselves give, i.e. the table's upper bound).
B and C run with the paper's full method otherwise (Monte Carlo footprint).

Part 3 — beside the paper: Tables 3–5 and the Sec. 4.4 D timings (0.13 s,
29.1 s, 17.1 s on an A100) next to ours, over a spread (issue 49): part 2 runs on
every ``--scenes`` occluder (default: the hand at three poses and the sphere, each with
its own light placement) and part 1's ablation D on ``--speed-seeds`` volumetric
avatars; each table is the mean ± std over them, and each claim (the paper's best
setting beats each other setting, per metric; each ablation of D is slower) gets a
verdict on the paired differences (relight_cli.neural.judging.verdict): *reproduced*
when their mean exceeds max(2σ over scenes, a minimum effect: 0.005 for SAE, SM-IoU
and BF; for D, where the differences are 10·log10 of the time ratio as judging reads a
ratio metric, 0.79 dB = 20 % slower), *reversed* when it is as clearly the other way,
else a *tie*.

Writes dgsm.{md,json,png} under --out (default benchmarks/out/): the printed tables,
the results, and a plot of build seconds against the max |ΔT| at the receivers vs the
float64 build (part 1, one curve per scene) and against SAE (part 2, one curve per
ablation).  Machine limits in the same run: fp32 GEMM, memory bandwidth and scipy's
erf throughput (the closed form's inner function).

Usage:
  .venv/bin/python benchmarks/bench_dgsm.py [--quick] [--full-reference]
         [--scenes hand:relaxed,hand:fist,hand:spread,sphere] [--speed-seeds 3] [--out DIR]
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402

from relight_cli.gaussians import dgsm as D                     # noqa: E402
from relight_cli.gaussians import transmittance as TR           # noqa: E402
from relight_cli.gaussians.from_mesh import gaussians_from_mesh  # noqa: E402
from relight_cli.neural.judging import mean_std, verdict          # noqa: E402


# ------------------------------------------------------------------ scenes


def avatar_mesh(target_faces: int = 50_000):
    """A 1.75 m humanoid of capsules and a sphere, subdivided to about target_faces."""
    import trimesh
    parts = []

    def capsule(a, b, r):
        a, b = np.asarray(a, float), np.asarray(b, float)
        h = np.linalg.norm(b - a)
        m = trimesh.creation.capsule(height=h, radius=r, count=[16, 16])
        z = np.array([0, 0, 1.0])
        axis = (b - a) / h
        rot = trimesh.geometry.align_vectors(z, axis)
        m.apply_translation([0, 0, -h / 2])   # capsule is centred on its axis segment
        m.apply_transform(rot)
        m.apply_translation((a + b) / 2)
        return m

    parts.append(capsule([0, 0.95, 0], [0, 1.4, 0], 0.17))            # torso
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.11)
    s.apply_translation([0, 1.62, 0])
    parts.append(s)                                                    # head
    for x in (-0.1, 0.1):
        parts.append(capsule([x, 0.08, 0], [x, 0.9, 0], 0.065))       # legs
    for sx in (-1, 1):
        parts.append(capsule([0.22 * sx, 1.4, 0], [0.45 * sx, 0.95, 0.1], 0.045))  # arms
    mesh = trimesh.util.concatenate(parts)
    # pick the subdivision edge length that gives about target_faces
    edge = np.sqrt(4 * mesh.area / (np.sqrt(3) * target_faces))
    for _ in range(6):
        v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=edge)
        if len(f) <= target_faces * 1.1:
            break
        edge *= np.sqrt(len(f) / target_faces)
    return v, f


def floor_receivers(half: float, n: int, y: float = 0.0, centre=(0.0, 0.0)):
    """A floor image: n×n receiver Gaussians (flat, one per pixel), row 0 at −z... +z.

    Returns means [n*n, 3], scales, rotations (thin axis +Y), pixel size.
    """
    xs = centre[0] + (np.arange(n) + 0.5) / n * 2 * half - half
    zs = centre[1] + (np.arange(n) + 0.5) / n * 2 * half - half
    gx, gz = np.meshgrid(xs, zs)
    means = np.stack([gx.ravel(), np.full(gx.size, y), gz.ravel()], 1)
    px = 2 * half / n
    scales = np.tile([px / 2, px / 2, px * 0.01], (len(means), 1))
    rot = np.tile([np.cos(np.pi / 4), np.sin(np.pi / 4), 0, 0], (len(means), 1))  # local z → +Y
    return means, scales, rot, px


# ------------------------------------------------------------------ part 1: speed


def volumetric_avatar(n: int = 50_000, seed: int = 0):
    """n volumetric Gaussians on the humanoid's surface, as a trained 3DGS avatar has them:
    log-normal scales around 1.2 cm (σ_log 0.5), random orientations, opacity U(0.2, 1).

    Their cones cover several atlas texels each, unlike the flat one-per-face
    Gaussians of :func:`gaussians_from_mesh`, so the per-pair closed form
    (and its erf) is real work here: this is the issue's speed scenario.
    """
    import trimesh
    from relight_cli.formats.gaussians_ply import Gaussians, rgb_to_sh_dc
    v, f = avatar_mesh()
    rng = np.random.default_rng(seed)
    means, _ = trimesh.sample.sample_surface(trimesh.Trimesh(v, f), n, seed=seed)
    scales = np.exp(rng.normal(np.log(0.012), 0.5, (n, 3)))
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return Gaussians(np.asarray(means, float), scales, quats, rng.uniform(0.2, 1.0, n),
                     rgb_to_sh_dc(np.full((n, 3), 0.5))[:, None, :], 0)


def _best_of(fn, repeats):
    """(min seconds, last result) over ``repeats`` calls: the machine is shared, the minimum is
    the least disturbed run."""
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def part_speed(quick: bool, full_reference: bool, seeds: int = 1):
    """Part 1 on the volumetric avatar of each seed (ablation D's spread) and, in a full
    run, the mesh avatar once."""
    import torch   # imported up front: its import (≈ 1.5 s) is not build time
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    light = np.array([0.8, 3.0, 0.5])
    means, scales, rot, _ = floor_receivers(3.0, 200)
    pts, _ = D.footprint_samples(means, scales, rot, "stencil")
    pts = pts.reshape(-1, 3)
    scenes = [(f"volumetric avatar (trained-3DGS-like), seed {k}", volumetric_avatar(seed=k))
              for k in range(seeds)]
    if not quick:
        scenes.append(("mesh avatar (flat Gaussian per face)", gaussians_from_mesh(*avatar_mesh())))
    results = []
    repeats = 2 if quick else 5
    for scene_name, g in scenes:
        mix = TR.from_gaussians(g)       # default mapping: avg (paper Eq. 5)
        print(f"\n## Part 1: build time — {scene_name}: {len(g)} Gaussians, 128×128×64, one light, "
              f"{len(means)} floor receivers (7-point stencil → {len(pts)} ROI points), "
              f"{os.cpu_count()} CPU(s), torch {torch.get_num_threads()} thread(s); best of "
              f"{repeats}\n")
        ref_kw = dict(size=(128, 128), bins=64)
        ref = D.build_dgsm(mix, [light], pts, dtype=np.float64, backend="numpy", **ref_kw)
        t_max = float(ref.t_max[0])
        configs = [("ROI + culling, float32 torch", dict(backend="torch")),
                   ("ROI + culling, float32 numpy", dict(backend="numpy")),
                   ("ROI + culling, float64 numpy (reference)", dict(dtype=np.float64,
                                                                      backend="numpy")),
                   ("culling only, float32 torch", dict(roi=False, backend="torch"))]
        if not quick:
            configs.append(("ROI only (no culling), float32 torch", dict(cull=False, backend="torch")))
        if full_reference:
            configs.append(("neither, float32 torch", dict(roi=False, cull=False, backend="torch")))
        rows = []
        t_ref = D.lookup(ref, 0, means)
        for name, kw in configs:
            reps = 1 if kw.get("cull") is False else repeats
            seconds, m = _best_of(lambda: D.build_dgsm(mix, [light], pts, t_max=t_max,
                                                       **{**ref_kw, **kw}), reps)
            table_err = float(np.abs(m.transmittance - ref.transmittance).max())
            recv_err = float(np.abs(D.lookup(m, 0, means) - t_ref).max())
            rows.append({"config": name, "seconds": seconds, "texels": m.roi[0]["texels"],
                         "bins": m.roi[0]["bins"], "pairs_tested": m.stats["pairs_tested"],
                         "pairs_kept": m.stats["pairs_kept"], "max_dT_table": table_err,
                         "max_dT_receivers": recv_err})
        if not full_reference and not quick:
            r = next(r for r in rows if r["config"].startswith("ROI only"))
            per_pair = r["seconds"] / max(r["pairs_kept"], 1)
            full_pairs = 128 * 128 * len(g)
            rows.append({"config": "neither (estimated: per-pair cost × all pairs)",
                         "seconds": per_pair * full_pairs, "texels": 128 * 128, "bins": [0, 63],
                         "pairs_tested": full_pairs, "pairs_kept": full_pairs})
        print("| configuration | build s | texels | bins | pairs tested | pairs kept | "
              "max ΔT table vs float64 | max ΔT at receivers vs float64 |")
        print("|---|---|---|---|---|---|---|---|")
        for r in rows:
            e1, e2 = r.get("max_dT_table"), r.get("max_dT_receivers")
            print(f"| {r['config']} | {r['seconds']:.3f} | {r['texels']} | {r['bins'][0]}..{r['bins'][1]} | "
                  f"{r['pairs_tested']:,} | {r['pairs_kept']:,} | {'' if e1 is None else f'{e1:.1e}'} | "
                  f"{'' if e2 is None else f'{e2:.1e}'} |")
        goal = rows[0]["seconds"]
        print(f"\nissue 14 goal (≤ 0.2 s, ROI + culling, float32 torch): {goal:.3f} s — "
              f"{'met' if goal <= 0.2 else 'NOT met'}")
        results.append({"scene": scene_name, "gaussians": len(g), "rows": rows})
    return results


# ------------------------------------------------------------------ part 2: shadow protocol


SCENES = "hand:relaxed,hand:fist,hand:spread,sphere"
QUICK_SCENES = "hand:relaxed,sphere"


def occluder_mesh(spec: str):
    """``hand:POSE`` (the built-in hand's fine mesh at a named pose) or ``sphere``."""
    kind, _, pose = spec.partition(":")
    if kind == "hand":
        try:
            from relight_cli.hand.model import builtin_hand
            from relight_cli.hand.scene import posed_meshes
            pm = posed_meshes(builtin_hand(pose=pose or "relaxed"), 0, "fine")[0]
            return f"built-in hand, {pose or 'relaxed'} (fine mesh)", pm.vertices, pm.faces
        except ImportError:
            kind = "sphere"
    import trimesh
    s = trimesh.creation.icosphere(subdivisions=4, radius=0.06)
    s.apply_translation([0, 0.06, 0])
    return "sphere r = 6 cm", s.vertices, s.faces


def scene_list(text: str) -> str:
    """argparse ``type`` of ``--scenes``: ``hand:POSE`` or ``sphere``, comma-separated."""
    import argparse
    from relight_cli.hand.poses import POSE_NAMES
    for spec in text.split(","):
        kind, _, pose = spec.partition(":")
        if not (spec == "sphere" or (kind == "hand" and (not pose or pose in POSE_NAMES))):
            raise argparse.ArgumentTypeError(
                f"expected hand:POSE (POSE one of {', '.join(POSE_NAMES)}) or sphere, "
                f"comma-separated, got {spec!r}")
    return text


def part_protocol(kind: str, quick: bool, placement: int = 0):
    """The shadow protocol on one occluder; ``placement`` turns the light's horizontal
    offset by placement × 90° about the occluder (each scene of the spread its own)."""
    from relight_cli.metrics.shadow import shadow_metrics
    from relight_cli.raytrace import RayScene

    name, v, f = occluder_mesh(kind)
    v = np.asarray(v, float)
    lo, hi = v.min(0), v.max(0)
    centre = (lo + hi) / 2
    size = float((hi - lo).max())
    floor_y = lo[1] - 0.5 * size
    a = placement * np.pi / 2
    dx, dz = 0.4 * np.cos(a) - 0.3 * np.sin(a), 0.4 * np.sin(a) + 0.3 * np.cos(a)
    light = np.array([centre[0] + dx * size, hi[1] + 2.5 * size, centre[2] + dz * size])
    n = 128 if quick else 256
    # frame the floor image on the shadow: the occluder's centre projected from the light
    shadow_centre = light + (centre - light) * (floor_y - light[1]) / (centre[1] - light[1])
    half = 0.9 * size
    means, scales, rot, px = floor_receivers(half, n, floor_y, (shadow_centre[0], shadow_centre[2]))
    # pseudo GT: the mesh's embree hard shadow
    scene = RayScene([(v, f)])
    d = light - means
    dist = np.linalg.norm(d, axis=1)
    gt = scene.occluded(means + [0, 1e-5, 0], d / dist[:, None], dist).reshape(n, n).astype(float)
    g = gaussians_from_mesh(v, f)
    print(f"\n## Part 2: shadow protocol — {name}: {len(f)} faces → {len(g)} flat Gaussians; "
          f"floor {n}×{n} px ({px * 1000:.2f} mm/px), light {np.round(light, 3).tolist()}, "
          f"GT shadow {int(gt.sum())} px\n")
    rows = []

    def score(label, T, seconds=None):
        matte = 1 - np.asarray(T).reshape(n, n)
        s = shadow_metrics(matte, gt, threshold=0.5, tolerance=2.0)["metrics"]
        rows.append({"run": label, "sae": s["sae"], "sm_iou": s["sm_iou"],
                     "boundary_f": s["boundary_f"], "seconds": seconds})

    mix_avg = TR.from_gaussians(g)   # the default mapping (avg, paper Eq. 5)
    t0 = time.perf_counter()
    # closed form at every floor point, no table (culled; dense twin tested to 1e-5)
    direct = D.exact_transmittance(mix_avg, light, means)
    score("direct closed form (no table), avg", direct, time.perf_counter() - t0)
    for res in ((128,) if quick else (128, 512)):
        for fp in ("centre", "stencil", "mc"):
            t0 = time.perf_counter()
            pts, _ = D.footprint_samples(means, scales, rot, fp, 16, 0)
            m = D.build_dgsm(mix_avg, [light], pts.reshape(-1, 3), size=(res, res), bins=64)
            build = time.perf_counter() - t0
            T = D.sample_transmittance(m, means, scales, rot, fp, 16, 0, light_index=0)
            score(f"A: footprint {fp}, octahedral {res}², avg", T, build)
    # B and C with the paper's full method otherwise: Monte Carlo footprint, octahedral, avg
    mc_pts, _ = D.footprint_samples(means, scales, rot, "mc", 16, 0)
    mc_pts = mc_pts.reshape(-1, 3)
    for mapping in TR.MAPPINGS:
        mix = TR.from_gaussians(g, mapping)
        m = D.build_dgsm(mix, [light], mc_pts, size=(128, 128), bins=64)
        score(f"B: mapping {mapping}, octahedral 128², mc",
              D.sample_transmittance(m, means, scales, rot, "mc", 16, 0, light_index=0),
              m.build_seconds)
    for layout in ("octahedral", "cube"):
        m = D.build_dgsm(mix_avg, [light], mc_pts, size=(128, 128), bins=64, layout=layout)
        score(f"C: atlas {layout} ({m.height}×{m.width}), avg, mc",
              D.sample_transmittance(m, means, scales, rot, "mc", 16, 0, light_index=0),
              m.build_seconds)
    print("| run | SAE ↓ | SM-IoU ↑ | boundary F (2 px) ↑ | build s |")
    print("|---|---|---|---|---|")
    for r in rows:
        s = "" if r["seconds"] is None else f"{r['seconds']:.2f}"
        print(f"| {r['run']} | {r['sae']:.3f} | {r['sm_iou']:.3f} | {r['boundary_f']:.3f} | {s} |")
    print("\n(paper, full method: SAE 0.058, SM-IoU 0.830, BF 0.796 — on its own scenes)")
    return {"occluder": name, "scene": kind, "light": light.tolist(), "gaussians": len(g),
            "pixels": n, "rows": rows}


# ------------------------------------------------------------------ beside the paper

# The paper's Tables 3–5 (SAE ↓, SM-IoU ↑, BF 2 px ↑; ScanNet++ scenes, SMPL pseudo-GT)
# and its Sec. 4.4 D timings (A100, s/frame).
PAPER_TABLES = {
    "A": [("centre", (0.203, 0.622, 0.585)), ("stencil", (0.167, 0.712, 0.662)),
          ("mc", (0.058, 0.830, 0.796))],
    "B": [("simple", (0.182, 0.694, 0.642)), ("avg", (0.058, 0.830, 0.796)),
          ("mass", (0.171, 0.708, 0.660)), ("diag", (0.177, 0.701, 0.651))],
    "C": [("cube", (0.136, 0.811, 0.761)), ("octahedral", (0.058, 0.830, 0.796))],
}
PAPER_TIMES = {"ROI + culling": 0.13, "no ROI": 29.1, "no light-space culling": 17.1}
_METRICS = (("sae", "SAE ↓", -1), ("sm_iou", "SM-IoU ↑", 1), ("boundary_f", "BF ↑", 1))
#: the smallest difference of SAE, SM-IoU or BF a verdict may rest on (0.5 points)
MIN_EFFECT_SHADOW = 0.005
#: the smallest slow-down (time ratio − 1) of ablation D a verdict may rest on
MIN_EFFECT_D = 0.2


def _run_key(run: str):
    """(ablation, setting) of a part-2 row label, or None (the direct row)."""
    head, _, rest = run.partition(": ")
    if head not in ("A", "B", "C"):
        return None
    if head == "A" and "128²" not in rest:
        return None
    words = rest.split(",")[0].split()
    return head, words[1]


def spread(protocols: list) -> dict:
    """Every part-2 row over the scenes: {run: {metric: mean_std, "seconds": mean_std}}."""
    runs: dict = {}
    for p in protocols:
        for r in p["rows"]:
            runs.setdefault(r["run"], []).append(r)
    out = {}
    for run, rows in runs.items():
        out[run] = {m: mean_std([r[m] for r in rows]) for m, _, _ in _METRICS}
        out[run]["seconds"] = mean_std([r["seconds"] for r in rows])
    return out


def _pm(stats: dict, digits: int = 3) -> str:
    if stats["n"] == 0:
        return ""
    return f"{stats['mean']:.{digits}f} ± {stats['std']:.{digits}f}"


def _word(v) -> str:
    return {"better": "reproduced", "worse": "reversed"}.get(v.word, v.word)


def beside_the_paper(protocols: list, speed: list | None) -> list:
    """Tables 3–5 (and D) with our numbers beside the paper's, mean ± std over the
    scenes; one verdict per claim (module doc)."""
    table = spread(protocols)
    n = len(protocols)
    print(f"\n## Beside the paper (Tables 3–5, Sec. 4.4 D); ours: mean ± std over {n} scene(s) "
          f"({'; '.join(p['occluder'] for p in protocols)}), each over a floor, embree "
          f"pseudo-GT, one light\n")
    claims = []
    for ablation, title in (("A", "Table 3 — footprint sampling"),
                            ("B", "Table 4 — opacity→absorption mapping"),
                            ("C", "Table 5 — atlas")):
        print(f"### {title}\n")
        print("| setting | paper SAE | ours SAE | paper SM-IoU | ours SM-IoU | paper BF | "
              "ours BF |")
        print("|---|---|---|---|---|---|---|")
        paper = dict(PAPER_TABLES[ablation])
        ours = {}
        for run, stats in table.items():
            key = _run_key(run)
            if key and key[0] == ablation:
                ours[key[1]] = (run, stats)
        for key, (run, stats) in ours.items():
            p = paper.get(key)
            print(f"| {key} | {'' if p is None else f'{p[0]:.3f}'} | {_pm(stats['sae'])} | "
                  f"{'' if p is None else f'{p[1]:.3f}'} | {_pm(stats['sm_iou'])} | "
                  f"{'' if p is None else f'{p[2]:.3f}'} | {_pm(stats['boundary_f'])} |")
        print()
        best = min(paper, key=lambda k: paper[k][0])           # the paper's best row (all metrics)
        if best not in ours:
            continue
        for other in (k for k, _ in PAPER_TABLES[ablation] if k != best and k in ours):
            for m, label, sign in _METRICS:
                col = [x[0] for x in _METRICS].index(m)
                per_scene = []
                for p in protocols:
                    rb = next(r for r in p["rows"] if r["run"] == ours[best][0])
                    ro = next(r for r in p["rows"] if r["run"] == ours[other][0])
                    per_scene.append(sign * (rb[m] - ro[m]))
                v = verdict(per_scene, min_effect=MIN_EFFECT_SHADOW)
                claims.append({
                    "table": {"A": "Table 3", "B": "Table 4", "C": "Table 5"}[ablation],
                    "ablation": ablation, "claim": f"{best} beats {other}", "best": best,
                    "other": other, "metric": m, "label": label,
                    "paper": [paper[best][col], paper[other][col]],
                    "ours": [ours[best][1][m]["mean"], ours[other][1][m]["mean"]],
                    "diffs": per_scene, "mean": v.mean, "std": v.std, "n": v.n,
                    "margin": v.margin, "verdict": _word(v)})
    if speed:
        vols = [sc for sc in speed if sc["scene"].startswith("volumetric")]
        cols = {"full": "ROI + culling, float32 torch", "no ROI": "culling only, float32 torch",
                "no light-space culling": "ROI only (no culling), float32 torch"}
        t = {k: [next((r["seconds"] for r in sc["rows"] if r["config"] == c), None)
                 for sc in vols] for k, c in cols.items()}
        print(f"### Sec. 4.4 D — build time (s/frame), ours: mean ± std over {len(vols)} "
              f"volumetric avatar(s) (seeds)\n")
        print("| configuration | paper (A100) | ours (CPU, volumetric 50k) |")
        print("|---|---|---|")
        for key, paper_key in (("full", "ROI + culling"), ("no ROI", "no ROI"),
                               ("no light-space culling", "no light-space culling")):
            print(f"| {paper_key} | {PAPER_TIMES[paper_key]} | "
                  f"{_pm(mean_std(t[key]))} |")
        print()
        for key in ("no ROI", "no light-space culling"):
            if any(x is None for x in t[key]):
                continue
            # in dB of the time ratio, as judging reads a ratio metric (MSE): the slow-down
            # of a noisy denominator (a shared machine) is a ratio, not a difference
            ratios = [10 * np.log10(a / b) for a, b in zip(t[key], t["full"])]
            v = verdict(ratios, min_effect=10 * np.log10(1 + MIN_EFFECT_D))
            claims.append({"table": "D", "ablation": "D", "claim": f"{key} slows the build",
                           "best": "full", "other": key, "metric": "seconds",
                           "label": "build s ↓",
                           "paper": [PAPER_TIMES["ROI + culling"], PAPER_TIMES[key]],
                           "ours": [mean_std(t["full"])["mean"], mean_std(t[key])["mean"]],
                           "diffs": ratios, "mean": v.mean, "std": v.std, "n": v.n,
                           "margin": v.margin, "verdict": _word(v)})
    print("### Claims (verdict on the paired per-scene differences: the mean must exceed "
          f"max(2σ, {MIN_EFFECT_SHADOW}) for Tables 3–5 and max(2σ, "
          f"{10 * np.log10(1 + MIN_EFFECT_D):.2f} dB = {MIN_EFFECT_D:.0%} slower) for D, "
          "10·log10 of the time ratio)\n")
    print("| table | the paper's claim | metric | paper (best / other) | ours (best / other) | "
          "paired difference | verdict |")
    print("|---|---|---|---|---|---|---|")
    for c in claims:
        fmt = ".3f" if c["ablation"] != "D" else ".3g"
        diff = ("" if c["mean"] is None else
                f"{c['mean']:+.3f} ± {c['std']:.3f}" + (" dB of the time ratio"
                                                         if c["ablation"] == "D" else ""))
        print(f"| {c['table']} | {c['claim']} | {c['label']} | {c['paper'][0]:{fmt}} / "
              f"{c['paper'][1]:{fmt}} | {c['ours'][0]:{fmt}} / {c['ours'][1]:{fmt}} | {diff} | "
              f"**{c['verdict']}** |")
    print("\nB mass vs diag: the paper reports different numbers (0.171 vs 0.177 SAE); with A "
          "the local-frame covariance (Sec. 4.4) √det A = s_x s_y s_z, so here they are the "
          "same β and the same row (their claims can only tie each other).")
    return claims


def write_plot(path, out: dict, machine: dict) -> None:
    """Part 1: build seconds vs max |ΔT| at receivers; part 2: build seconds vs SAE
    (means over the scenes)."""
    panels = [k for k in ("speed", "table") if k in out]
    if not panels:
        return
    fig, axes = B.figure(len(panels))
    for ax, key in zip(axes, panels):
        if key == "speed":
            curves = {}
            for scene in out["speed"]:
                curves[scene["scene"]] = [(r["seconds"], r["max_dT_receivers"],
                                           r["config"].split(",")[0] + r["config"].split(",")[-1])
                                          for r in scene["rows"] if "max_dT_receivers" in r]
            B.plot(ax, curves, "build seconds (one light, 128x128x64)",
                   "max |ΔT| at receivers vs float64 build", "part 1: build time")
        else:
            curves = {}
            for run, stats in out["table"].items():
                group = run.split(":")[0]
                name = {"A": "A footprint", "B": "B opacity mapping", "C": "C atlas"}.get(
                    group, run.split(",")[0])
                label = run.split(": ")[-1].split(",")[0].replace("footprint ", "") \
                    .replace("mapping ", "").replace("atlas ", "")
                curves.setdefault(name, []).append((stats["seconds"]["mean"],
                                                    stats["sae"]["mean"], label))
            B.plot(ax, curves, "seconds (build; direct: closed form)",
                   "SAE (lower is better), mean over scenes",
                   f"part 2: shadow protocol, {len(out['protocol'])} scene(s)", logy=False)
    B.save(fig, path, machine)


def main():
    ap = B.parser(__doc__, f"fewer configurations, 128² floors, scenes {QUICK_SCENES}, "
                           "one speed seed")
    ap.add_argument("--full-reference", action="store_true",
                    help="also run the build with neither ROI nor culling (minutes)")
    ap.add_argument("--scenes", type=scene_list, default=None,
                    help=f"part 2's occluders, hand:POSE or sphere, comma-separated "
                         f"[default: {SCENES}; --quick: {QUICK_SCENES}]")
    ap.add_argument("--occluder", choices=["hand", "sphere"], default=None,
                    help="one occluder only (the relaxed hand or the sphere): no spread")
    ap.add_argument("--speed-seeds", type=B.integer(1), default=None,
                    help="volumetric avatars (seeds) of part 1 and ablation D "
                         "[default: 3; --quick: 1]")
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--skip-protocol", action="store_true")
    args = ap.parse_args()
    scenes = (args.occluder and [args.occluder]) or \
        (args.scenes or (QUICK_SCENES if args.quick else SCENES)).split(",")
    seeds = args.speed_seeds or (1 if args.quick else 3)
    out_dir = B.start(args, "bench_dgsm.py")
    t_start = time.perf_counter()
    command = B.run_command("bench_dgsm.py", sys.argv[1:])
    machine = B.machine_limits(erf=True)
    out = {"command": command, "quick": args.quick, "scenes": scenes, "speed_seeds": seeds,
           "machine": machine, "load_start": B.load_average()}
    with B.recorded() as rec:
        print("# Deep Gaussian Shadow Maps: build time and shadow accuracy\n")
        print("{run}\n")
        print(B.machine_line(machine))
        if not args.skip_speed:
            out["speed"] = part_speed(args.quick, args.full_reference, seeds)
        if not args.skip_protocol:
            out["protocol"] = [part_protocol(sc, args.quick, i) for i, sc in enumerate(scenes)]
            out["table"] = spread(out["protocol"])
        if not args.skip_protocol or not args.skip_speed:
            out["claims"] = beside_the_paper(out.get("protocol") or [], out.get("speed"))
        print("\nPlot: dgsm.png.")
    out["seconds"] = time.perf_counter() - t_start
    out["load_end"] = B.load_average()
    text = rec.text.replace("{run}", B.run_description(command, args.quick, out["seconds"]), 1)
    (out_dir / "dgsm.md").write_text(text)
    (out_dir / "dgsm.json").write_text(json.dumps(out, indent=2, default=float) + "\n")
    write_plot(out_dir / "dgsm.png", out, machine)


if __name__ == "__main__":
    B.run_main("bench_dgsm.py", main)
