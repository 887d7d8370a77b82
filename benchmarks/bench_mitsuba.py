"""How far the physically based hand renderer is from Mitsuba 3 under environment maps.

One view (``--size``², default 256²) of the built-in hand's fist (fine mesh, vertex
normals), subsurface scattering and the bounce off, a box pixel filter, rendered by
:class:`relight_cli.render.shading.HandRenderer` and by Mitsuba 3 (``scalar_rgb``, the
``direct`` integrator: emitter and BSDF sampling with MIS, ``independent`` sampler,
``--spp`` samples per pixel), in two cases:

* **diffuse**: constant albedo 0.5, specular off, against Mitsuba's ``diffuse`` BSDF of
  reflectance 0.5;
* **specular**: ``constant_material(albedo=0, roughness=0.45, f0=1)`` (with F0 = 1 our
  Schlick Fresnel is exactly 1) against ``roughconductor`` (``ggx``, α = 0.45² — our ρ
  is perceptual roughness, α = ρ² — ``material: none``, a perfect mirror's F = 1);

under two env maps: ``builtin:sky`` and Poly Haven's ``empty_warehouse_01_1k.hdr``
(``../shared/data/envmaps/polyhaven/``, read by our reader; its rows are skipped when the
file is absent).

The env map reaches Mitsuba as a lat-long bitmap in Mitsuba's own convention, each of its
texels the mean of OUR map over the texel's cell (:func:`mitsuba_envmap`, an integer
multiple of our resolution at least 1024 wide), so both renderers see the same radiance
(see that function for Mitsuba 3.9's convention; tests/render/test_shading_mitsuba.py
checks it).

Our configurations (rows) come from :class:`RenderSettings` as it is at run time:
``env_space`` vertices at 32x16 (the old CLI default) and 128x64, texels at 32x16, and,
where the fields exist, texels with the exact Smith shadowing (``shadowing="smith"``,
the specular case only) and with bright-source extraction (``env_sources="auto"``); the
old rows keep ``shadowing="schlick"``, ``env_sources=0``.  The row equal to
``RenderSettings(sss=False, bounce=False)`` (the defaults) is marked; if none is, the
defaults get a row of their own.

Metrics inside the hand mask (pixels fully covered in our render and in both
references), RGB: relative RMS error sqrt(mean((ours − ref)²)) / sqrt(mean(ref²)), the
same as dB (−20 log10), the mean ratio ours/ref, the share of the squared error in the
worst 5 % of pixels (near 1: a few edges; near 0.05: spread evenly), and our wall seconds
(renderer setup + lighting + render, one run).  The reference is the mean of two Mitsuba
renders with different sampler seeds; its own noise (rel. RMS) is relRMS(ref1, ref2)/2
(one render's: /√2), reported, and the error with that noise taken out (in quadrature).
Mitsuba references are cached as .npy under ``--work``, keyed by everything they depend
on, so a rerun only renders ours.

Writes mitsuba.{md,json,png} under --out (default benchmarks/out/); the plot: per case,
the rel. RMS error against our seconds, one curve per env map, the reference noise dotted.  Machine limits in the
same run (fp32 GEMM, memory bandwidth, raw embree rays/s: the renderer traces rays).
Needs ``mitsuba`` (pip install mitsuba); without it the script says so and exits 0.

Usage:  .venv/bin/python benchmarks/bench_mitsuba.py [--quick] [--spp N] [--size N]
            [--work DIR] [--out DIR]
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402

NAME = "bench_mitsuba.py"
WORK = B.OUT / "mitsuba_work"
WAREHOUSE = B.HDRI_DIR / "empty_warehouse_01_1k.hdr"
#: the view: preview_camera's framing of the fist (towards the camera, vertical fov)
VIEW_DIRECTION = (0.25, 0.35, 1.0)
FOV_Y_DEG = 30.0
#: the Mitsuba bitmap is our map's size times the smallest integer making it at least this
#: wide (1024: builtin:sky's 256 × 4, a 1k HDRI's own width; area means, so no detail of
#: ours is lost, and Mitsuba's bilinear lookups blur by at most ~0.35°)
BITMAP_MIN_WIDTH = 1024
#: the two sampler seeds of every reference
SEEDS = (1, 2)
ROUGHNESS = 0.45
CASES = {
    "diffuse": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}},
    "specular": {"type": "roughconductor", "distribution": "ggx", "alpha": ROUGHNESS ** 2,
                 "material": "none"},
}
#: bump when the same settings render a different reference (cached .npy)
REFERENCE_VERSION = 1


def _count(minimum: int):
    return B.integer(minimum) if hasattr(B, "integer") else int


# ------------------------------------------------------------------ the scene


def fist_view(size: int):
    """(meshes, camera, eye, target): the fist (fine mesh) framed as preview_camera does."""
    from relight_cli.formats.camera import Camera
    from relight_cli.hand.model import builtin_hand
    from relight_cli.hand.scene import posed_meshes

    meshes = posed_meshes(builtin_hand(pose="fist"), 0, "fine")
    pts = np.concatenate([m.vertices for m in meshes])
    target = 0.5 * (pts.min(0) + pts.max(0))
    radius = float(np.linalg.norm(pts - target, axis=1).max())
    d = np.asarray(VIEW_DIRECTION, np.float64)
    d /= np.linalg.norm(d)
    eye = target + radius / math.sin(math.radians(FOV_Y_DEG) / 2) * 1.05 * d
    camera = Camera.look_at(eye, target, fov_y_deg=FOV_Y_DEG, width=size, height=size)
    return meshes, camera, eye, target


def write_ply(mesh, path: Path) -> None:
    """The posed mesh as a binary PLY with vertex normals (Mitsuba interpolates them)."""
    import plyfile
    vert = np.empty(len(mesh.vertices), [(k, "f4") for k in ("x", "y", "z", "nx", "ny", "nz")])
    for i, k in enumerate(("x", "y", "z")):
        vert[k] = mesh.vertices[:, i]
        vert["n" + k] = mesh.normals[:, i]
    face = np.empty(len(mesh.faces), [("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = mesh.faces
    tmp = path.with_suffix(".tmp.ply")
    plyfile.PlyData([plyfile.PlyElement.describe(vert, "vertex"),
                     plyfile.PlyElement.describe(face, "face")]).write(str(tmp))
    os.replace(tmp, path)


def bitmap_scale(env) -> int:
    return max(1, math.ceil(BITMAP_MIN_WIDTH / env.width))


def mitsuba_envmap(env, scale: int | None = None) -> np.ndarray:
    """[H', W', 3] float32 (H' = scale·H, W' = scale·W; default scale :func:`bitmap_scale`):
    ``env`` as a bitmap for Mitsuba 3's ``envmap`` emitter, each texel the mean of ``env``
    over the texel's cell.

    Mitsuba 3.9 (``src/emitters/envmap.cpp``) looks a world direction d up (identity
    ``to_world``) at uv = (atan2(d.x, −d.z)/2π, acos(d.y)/π), wrapped to [0, 1), and
    interpolates the bitmap bilinearly between samples at u = (x + ½)/W', v = y/(H' − 1)
    (rows on the poles, like ours; columns half a texel in).  Sample (x, y) is thus the
    direction of latitude π/2 − πy/(H' − 1) — our row y of an H'-row grid — and longitude
    λ = π − 2π(x + ½)/W' (ours: direction (sin λ cos φ, sin φ, cos λ cos φ)): our
    (W' + 1)-column grid's column x after turning the map by +180/W' degrees about +Y.
    That grid's first and last columns are the two halves of the cell on the seam, so
    Mitsuba's column 0 is their mean.  Area means come from
    :func:`relight_cli.envmap.resample` (exact for lat-long, power preserved).
    """
    from relight_cli import envmap as E

    scale = scale or bitmap_scale(env)
    h, w = scale * env.height, scale * env.width
    turned = E.resample(env, "latlong", h, w + 1, rotation=E.rotation_y(180.0 / w)).radiance
    out = np.array(turned[:, :w], np.float32)
    out[:, 0] = 0.5 * (turned[:, 0] + turned[:, w])
    return np.ascontiguousarray(out)


def bitmap_power(bitmap: np.ndarray) -> np.ndarray:
    """[3] Σ L Δω of a Mitsuba bitmap, each texel the cell around its sample (our rows)."""
    from relight_cli import envmap as E
    h, w = bitmap.shape[:2]
    omega = E.latlong_solid_angles(h, w + 1)[:, 1]              # a full column's cell
    return np.einsum("hwc,h->c", bitmap.astype(np.float64), omega)


def mitsuba_scene(mi, ply: Path, eye, target, size: int, spp: int, bitmap, bsdf: dict):
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct"},           # 1 emitter + 1 BSDF sample, MIS
        "sensor": {"type": "perspective", "fov": FOV_Y_DEG, "fov_axis": "y",
                   "to_world": mi.ScalarTransform4f().look_at(
                       origin=np.asarray(eye).tolist(), target=np.asarray(target).tolist(),
                       up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size, "height": size,
                            "rfilter": {"type": "box"}, "pixel_format": "rgba"},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(bitmap)},
        "hand": {"type": "ply", "filename": str(ply), "face_normals": False, "bsdf": bsdf}})


def _sha(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def reference(mi, work: Path, ply: Path, mesh_sha: str, eye, target, size: int, spp: int,
              case: str, env, env_sha: str, log) -> dict:
    """The two Mitsuba renders of (case, env), from the cache under ``work`` or rendered
    now: {'images': [2 × [H, W, 4]], 'seconds': [per render], 'cached': [bool],
    'power_ratio': the bitmap's power / our map's (the channel farthest from 1)}."""
    from relight_cli import envmap as E

    bitmap = None
    images, seconds, cached = [], [], []
    for seed in SEEDS:
        key = B.digest({"v": REFERENCE_VERSION, "mitsuba": mi.__version__, "case": CASES[case],
                        "env": env_sha, "mesh": mesh_sha, "eye": np.round(eye, 12).tolist(),
                        "target": np.round(target, 12).tolist(), "fov": FOV_Y_DEG,
                        "size": size, "spp": spp, "seed": seed, "scale": bitmap_scale(env),
                        "integrator": "direct", "sampler": "independent", "filter": "box"})
        path = work / f"mitsuba-{case}-{key}.npy"
        meta = work / f"mitsuba-{case}-{key}.json"
        if path.is_file() and meta.is_file():
            images.append(np.load(path))
            seconds.append(float(B.read_report(NAME, meta)["seconds"]))
            cached.append(True)
            continue
        if bitmap is None:
            bitmap = mitsuba_envmap(env)
        scene = mitsuba_scene(mi, ply, eye, target, size, spp, bitmap, CASES[case])
        t0 = time.perf_counter()
        image = np.array(mi.render(scene, seed=seed), np.float32)
        seconds.append(time.perf_counter() - t0)
        log(f"  Mitsuba {case} {Path(env.name).name} seed {seed}: {seconds[-1]:.1f} s")
        tmp = path.with_suffix(".tmp.npy")
        np.save(tmp, image)
        os.replace(tmp, path)
        B.write_json(meta, {"seconds": seconds[-1], "mitsuba": mi.__version__, "spp": spp,
                            "size": size, "seed": seed, "case": case, "env": env.name})
        images.append(image)
        cached.append(False)
    if bitmap is None:
        bitmap = mitsuba_envmap(env)
    ratio = bitmap_power(bitmap) / E.power(env)
    return {"images": images, "seconds": seconds, "cached": cached,
            "bitmap": f"{bitmap.shape[1]}x{bitmap.shape[0]}",
            "power_ratio": float(ratio[np.argmax(np.abs(ratio - 1))])}


# ------------------------------------------------------------------ our configurations


def _fields() -> set:
    from relight_cli.render.shading import RenderSettings
    return {f.name for f in dataclasses.fields(RenderSettings)}


def lobe_shadowing(settings) -> str:
    """The GGX shadowing a render with ``settings`` uses: the field, or (before it existed)
    the library's default."""
    if hasattr(settings, "shadowing"):
        return settings.shadowing
    from relight_cli import brdf
    p = inspect.signature(brdf.ggx_cosine).parameters.get("shadowing")
    return p.default if p is not None else "schlick"


def configurations(case: str) -> list:
    """[(label, RenderSettings)] of ``case``'s rows (module doc); the defaults marked."""
    from relight_cli.render.shading import RenderSettings

    names = _fields()
    base = {"sss": False, "bounce": False}
    if case == "diffuse":
        base["specular"] = False
    old = {}
    if "shadowing" in names:
        old["shadowing"] = "schlick"
    if "env_sources" in names:
        old["env_sources"] = 0
    rows = [("vertices 32x16 (old CLI default)", dict(env_space="vertices", env_res=(16, 32), **old)),
            ("vertices 128x64", dict(env_space="vertices", env_res=(64, 128), **old)),
            ("texels 32x16", dict(env_space="texels", env_res=(16, 32), **old))]
    if "shadowing" in names and case == "specular":
        rows.append(("texels 32x16, Smith", dict(rows[-1][1], shadowing="smith")))
    if "env_sources" in names:
        rows.append(("texels 32x16" + (", Smith" if "shadowing" in names and case == "specular"
                                       else "") + ", sources",
                     dict(rows[-1][1], env_sources="auto",
                          **({"shadowing": "smith"} if "shadowing" in names else {}))))
    out = [(label, RenderSettings(**base, **over)) for label, over in rows]
    defaults = RenderSettings(**base)

    def same(a, b):
        if case == "diffuse" and "shadowing" in names:   # G does not matter without specular
            a = dataclasses.replace(a, shadowing=b.shadowing)
        return a == b

    for i, (label, s) in enumerate(out):
        if same(s, defaults):
            out[i] = (label + " (= defaults)", s)
            break
    else:
        out.append(("defaults", defaults))
    return out


def describe(settings, case: str) -> dict:
    names = _fields()
    h, w = settings.env_res
    d = {"env_space": settings.env_space, "env_res": f"{w}x{h}", "tex_res": settings.tex_res,
         "aa": settings.aa}
    if case == "specular":
        d["shadowing"] = lobe_shadowing(settings) + ("" if "shadowing" in names
                                                     else " (library default; no field)")
    if "env_sources" in names:
        d["env_sources"] = settings.env_sources
    return d


def render_ours(meshes, camera, material, settings, env):
    from relight_cli.render.shading import HandRenderer
    t0 = time.perf_counter()
    renderer = HandRenderer(meshes, [material], settings)
    result = renderer.render(camera, renderer.light(env=env))
    return result, time.perf_counter() - t0


def compare(ours, ref, mask, noise_used: float) -> dict:
    diff = (ours[mask] - ref[mask]).astype(np.float64)
    scale = math.sqrt(float((ref[mask].astype(np.float64) ** 2).mean()))
    rel = math.sqrt(float((diff ** 2).mean())) / scale
    per_pixel = (diff ** 2).sum(-1)
    worst = np.sort(per_pixel)[::-1][:max(1, int(math.ceil(0.05 * len(per_pixel))))]
    return {"rel_rms": rel, "db": -20 * math.log10(rel) if rel > 0 else math.inf,
            "rel_rms_noise_removed": math.sqrt(max(rel ** 2 - noise_used ** 2, 0.0)),
            "mean_ratio": float(ours[mask].mean() / ref[mask].mean()),
            "worst5_share": float(worst.sum() / max(per_pixel.sum(), 1e-300))}


# ------------------------------------------------------------------ main


def main():
    ap = B.parser(__doc__, "a 64×64 view at 256 samples per pixel (a smoke run)")
    ap.add_argument("--spp", type=_count(1), default=None,
                    help="Mitsuba samples per pixel [default 4096; --quick 256]")
    ap.add_argument("--size", type=_count(8), default=None,
                    help="view width = height in pixels [default 256; --quick 64]")
    ap.add_argument("--work", default=str(WORK), metavar="DIR",
                    help="cache of the Mitsuba references (.npy) "
                         "[default: benchmarks/out/mitsuba_work/]")
    args = ap.parse_args()
    B.check_out_dir(NAME, args.out, "--out")
    B.check_out_dir(NAME, args.work, "--work")
    try:
        import mitsuba as mi
    except ImportError:
        print(f"{NAME}: skipped: mitsuba is not installed (pip install mitsuba)", file=sys.stderr)
        return 0
    out = B.start(args, NAME, {"--work": args.work})
    started = time.perf_counter()
    spp = args.spp or (256 if args.quick else 4096)
    size = args.size or (64 if args.quick else 256)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    mi.set_variant("scalar_rgb")
    import drjit as dr

    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.formats.envmap import read_envmap
    from relight_cli.render import appearance as A

    log = B.Tee()
    machine = B.machine_limits(embree=True)
    machine.update({"mitsuba": mi.__version__, "mitsuba_threads": int(dr.thread_count())})
    command = B.run_command(NAME, sys.argv[1:])
    meshes, camera, eye, target = fist_view(size)
    mesh = meshes[0]
    mesh_sha = _sha(mesh.vertices, mesh.normals, mesh.faces)
    ply = work / f"fist-{mesh_sha}.ply"
    if not ply.is_file():
        write_ply(mesh, ply)
    envs = [("builtin:sky", builtin_envmap("builtin:sky"))]
    skipped = []
    if WAREHOUSE.is_file():
        envs.append((WAREHOUSE.name, read_envmap(str(WAREHOUSE))))
    else:
        skipped.append(f"{WAREHOUSE.name}: absent (../shared/data/envmaps/polyhaven is not "
                       "beside this checkout), its rows skipped")
        log(skipped[-1])
    materials = {"diffuse": A.constant_material((0.5, 0.5, 0.5)),
                 "specular": A.constant_material((0.0, 0.0, 0.0), ROUGHNESS, 1.0)}
    references, rows = [], []
    for env_label, env in envs:
        env_sha = _sha(env.radiance) + env.layout
        for case in CASES:
            ref = reference(mi, work, ply, mesh_sha, eye, target, size, spp, case, env,
                            env_sha, log)
            r1, r2 = ref["images"]
            mask = (r1[..., 3] >= 1 - 1e-6) & (r2[..., 3] >= 1 - 1e-6)
            pair = compare(r1[..., :3], r2[..., :3], mask, 0.0)["rel_rms"]
            # relRMS(r1, r2) measures √2 × one render's noise (independent seeds); the
            # mean of the two has half the variance of one
            noise_one, noise_used = pair / math.sqrt(2), pair / 2
            mean_ref = 0.5 * (r1[..., :3] + r2[..., :3])
            references.append({"case": case, "env": env_label, "spp": spp, "size": size,
                               "seconds": ref["seconds"], "cached": ref["cached"],
                               "noise_one": noise_one, "noise_used": noise_used,
                               "bitmap": ref["bitmap"],
                               "bitmap_power_ratio": ref["power_ratio"]})
            log(f"{case} {env_label}: Mitsuba {spp} spp, noise of one render {noise_one:.4f}, "
                f"of the reference used {noise_used:.4f}")
            for label, settings in configurations(case):
                result, seconds = render_ours(meshes, camera, materials[case], settings, env)
                full = mask & (result.mask >= 1)
                row = {"case": case, "env": env_label, "row": label,
                       "settings": describe(settings, case), "pixels": int(full.sum()),
                       "seconds": seconds,
                       **compare(result.image, mean_ref, full, noise_used)}
                rows.append(row)
                log(f"  {label:42s} rel RMS {row['rel_rms']:.4f} ({row['db']:.1f} dB), "
                    f"ratio {row['mean_ratio']:.4f}, worst 5 % {row['worst5_share']:.2f}, "
                    f"{seconds:.1f} s")
    total = time.perf_counter() - started
    record = {"command": command, "quick": bool(args.quick), "seconds": total,
              "machine": machine, "spp": spp, "size": size, "seeds": list(SEEDS),
              "bitmap_min_width": BITMAP_MIN_WIDTH, "roughness": ROUGHNESS, "cases": CASES,
              "skipped": skipped, "references": references, "rows": rows}
    text = table(record)
    B.write_json(out / "mitsuba.json", record)
    from relight_cli.fileio import write_text_atomic
    write_text_atomic(str(out / "mitsuba.md"), text)
    print(text)
    print(f"wrote {out / 'mitsuba.md'} and {out / 'mitsuba.json'}")
    write_plot(out / "mitsuba.png", record)
    return 0


def _short(label: str) -> str:
    return (label.replace(" (old CLI default)", "").replace(" (= defaults)", " (defaults)")
            .replace("vertices ", "vert ").replace("32x16, ", "32x16 "))


def write_plot(path: Path, r: dict) -> None:
    """Per case: rel. RMS against our seconds, one colour per env map, each point a
    configuration (points only: the configurations are not a sequence); dotted: the
    reference's own noise, below which an error is not resolved."""
    fig, axes = B.figure(2, 6.8, 4.8)
    envs = list(dict.fromkeys(row["env"] for row in r["rows"]))
    for ax, case in zip(axes, CASES):
        for i, env in enumerate(envs):
            pts = [(row["seconds"], row["rel_rms"], _short(row["row"])) for row in r["rows"]
                   if row["case"] == case and row["env"] == env]
            ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", linestyle="none",
                    color=f"C{i}", label=env)
            for x, y, text in pts:
                ax.annotate(text, (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7,
                            color=f"C{i}")
            for ref in r["references"]:
                if ref["case"] == case and ref["env"] == env:
                    ax.axhline(ref["noise_used"], linestyle=":", color=f"C{i}",
                               label=f"reference noise, {env}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.grid(True, which="major", alpha=0.5)
        ax.grid(True, which="minor", alpha=0.15)
        ax.set_xlabel("our seconds (setup + light + render)")
        ax.set_ylabel("rel. RMS vs Mitsuba inside the mask")
        ax.set_title(f"{case}: {r['size']}x{r['size']}, Mitsuba {r['spp']} spp", fontsize=10)
        ax.legend(fontsize=7, loc="best")
    B.save(fig, path, r["machine"])


def table(r: dict) -> str:
    m = r["machine"]
    lines = ["# The physically based renderer against Mitsuba 3 under env maps", "",
             B.run_description(r["command"], r["quick"], r["seconds"]), "",
             B.machine_line(m) + f" Mitsuba {m['mitsuba']} (scalar_rgb) on "
             f"{m['mitsuba_threads']} threads.", "",
             f"The built-in hand's fist (fine mesh, vertex normals), one {r['size']}×{r['size']} "
             "view (preview framing), SSS and bounce off, box filter. **diffuse**: albedo 0.5, "
             "specular off vs Mitsuba `diffuse` 0.5; **specular**: albedo 0, ρ = "
             f"{r['roughness']}, F0 = 1 vs `roughconductor` GGX α = ρ² = "
             f"{r['roughness'] ** 2:.4f}, `material: none` (F = 1). Mitsuba: `direct` "
             f"integrator (emitter + BSDF sampling, MIS), `independent` sampler, **{r['spp']} "
             f"spp**, seeds {r['seeds'][0]} and {r['seeds'][1]}, their mean the reference; the "
             "env map given as a bitmap of our map's cell means in Mitsuba's convention, at "
             f"an integer multiple of its resolution at least {r['bitmap_min_width']} wide.", "",
             "Inside the mask (pixels fully covered in all three renders), RGB: rel. RMS = "
             "sqrt(mean((ours − ref)²)) / sqrt(mean(ref²)); dB = −20 log10(rel. RMS); "
             "*noise removed* = sqrt(rel² − noise²) with the reference's own noise; ratio = "
             "mean(ours) / mean(ref); worst 5 % = the share of the squared error in the worst "
             "5 % of pixels; our s = renderer setup + lighting + render, wall seconds, one run.",
             ""]
    lines += ["## Mitsuba references", "",
              "| case | env | spp | Mitsuba s per render | noise, one render | noise, reference "
              "(mean of 2) | bitmap | bitmap power / ours |", "|---|---|---|---|---|---|---|---|"]
    for ref in r["references"]:
        secs = " + ".join(f"{s:.1f}" + (" (cached)" if c else "")
                          for s, c in zip(ref["seconds"], ref["cached"]))
        lines.append(f"| {ref['case']} | {ref['env']} | {ref['spp']} | {secs} | "
                     f"{ref['noise_one']:.4f} | {ref['noise_used']:.4f} | {ref['bitmap']} | "
                     f"{ref['bitmap_power_ratio']:.6f} |")
    lines += ["", "## Ours against the reference", "",
              "| case | env | configuration | settings | rel. RMS | dB | noise removed | ratio | "
              "worst 5 % | our s |", "|---|---|---|---|---|---|---|---|---|---|"]
    for row in r["rows"]:
        s = ", ".join(f"{k} {v}" for k, v in row["settings"].items())
        lines.append(f"| {row['case']} | {row['env']} | {row['row']} | {s} | "
                     f"{row['rel_rms']:.4f} | {row['db']:.1f} | {row['rel_rms_noise_removed']:.4f} | "
                     f"{row['mean_ratio']:.4f} | {row['worst5_share']:.2f} | "
                     f"{row['seconds']:.1f} |")
    if r["skipped"]:
        lines += [""] + [f"Skipped: {s}." for s in r["skipped"]]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(B.run_main(NAME, main))
