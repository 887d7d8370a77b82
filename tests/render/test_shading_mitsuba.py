"""Cross-check against Mitsuba 3 (optional: skipped when `mitsuba` is not installed).

1. One point light: the built-in hand's proxy ('point' pose, vertex normals), the same
   OpenCV camera, Lambertian albedo 0.5, direct light only with shadows.
2. Env maps.  First the convention that carries our env map into Mitsuba
   (benchmarks/bench_mitsuba.py's :func:`mitsuba_envmap`, which the benchmark trusts and
   these tests use): Mitsuba's own envmap emitter looked up in known directions, and the
   irradiance of six axis-facing planes rendered by Mitsuba against our integral of the
   same map.  Then the fist (fine mesh) under env maps, diffuse and specular only (GGX,
   F = 1), SSS and bounce off, against Mitsuba's ``direct`` integrator, inside the hand
   mask, with tolerances that add the reference's own noise (measured from two seeds)
   to our renderer's measured discretization error.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba", reason="mitsuba is optional (pip install mitsuba)")

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import bench_mitsuba as BM  # noqa: E402


def _point_light_view(tmp_path, lobe: str | None, other: str | None = None):
    """Ours and Mitsuba's render of the proxy hand under one point light: Lambert 0.5
    (``lobe`` None) or GGX only (albedo 0, ρ 0.45, F0 = 1, our ``lobe`` = its shadowing term,
    against Mitsuba's ``roughconductor`` GGX α = ρ², ``material: none``: F ≡ 1); → (ours' red
    channel, Mitsuba's, the comparable pixels[, ours with the ``other`` shadowing term])."""
    import plyfile
    from scipy.ndimage import binary_erosion, maximum_filter, minimum_filter

    from relight_cli.formats.camera import Camera
    from relight_cli.formats.lights_json import Lights
    from relight_cli.hand.model import builtin_hand
    from relight_cli.hand.scene import posed_meshes
    from relight_cli.render import appearance as A
    from relight_cli.render.shading import HandRenderer, RenderSettings

    mi.set_variant("scalar_rgb")
    meshes = posed_meshes(builtin_hand(pose="point"), 0, "coarse")
    mesh = meshes[0]
    c = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
    eye, light = c + [0.1, 0.05, 0.5], c + np.array([0.2, 0.3, 0.4])
    size = 48
    cam = Camera.look_at(eye, c, fov_y_deg=18, width=size, height=size)
    if lobe is None:
        material = A.constant_material((0.5, 0.5, 0.5))
        settings = RenderSettings(tex_res=256, aa=8, specular=False, sss=False)
        bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}
    else:
        material = A.constant_material((0.0, 0.0, 0.0), 0.45, 1.0)
        settings = RenderSettings(tex_res=256, aa=8, sss=False, shadowing=lobe)
        bsdf = {"type": "roughconductor", "distribution": "ggx", "alpha": 0.45 ** 2,
                "material": "none", "sample_visible": True}
    renderer = HandRenderer(meshes, [material], settings)
    lights = Lights.from_radiant_intensity([light], 1.0)
    ours = renderer.render(cam, renderer.light(lights))
    extra = None
    if other is not None:
        import dataclasses
        variant = HandRenderer(meshes, [material], dataclasses.replace(settings, shadowing=other))
        extra = variant.render(cam, variant.light(lights)).image[..., 0]

    vert = np.array([tuple(p) + tuple(n) for p, n in zip(mesh.vertices, mesh.normals)],
                    dtype=[(k, "f4") for k in ("x", "y", "z", "nx", "ny", "nz")])
    face = np.array([(list(f),) for f in mesh.faces], dtype=[("vertex_indices", "i4", (3,))])
    plyfile.PlyData([plyfile.PlyElement.describe(vert, "vertex"),
                     plyfile.PlyElement.describe(face, "face")]).write(str(tmp_path / "h.ply"))
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {"type": "perspective", "fov": 18, "fov_axis": "y",
                   "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(),
                                                              target=c.tolist(), up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size, "height": size,
                            "rfilter": {"type": "box"}, "pixel_format": "rgba"},
                   "sampler": {"type": "stratified", "sample_count": 64}},
        "light": {"type": "point", "position": light.tolist(),
                  "intensity": {"type": "rgb", "value": [1.0, 1.0, 1.0]}},
        "hand": {"type": "ply", "filename": str(tmp_path / "h.ply"), "face_normals": False,
                 "bsdf": bsdf}})
    ref = np.array(mi.render(scene))
    assert np.abs(ref[..., 3] - ours.mask).mean() < 0.01           # same view, same silhouette

    # Compare away from silhouettes (pixels fully covered, and their neighbours too), shadow
    # outlines (the shadow state of all samples in the 3×3 neighbourhood agrees), occlusion
    # edges (depth range < 1 cm in the 3×3 neighbourhood) and grazing light (mean n·l >
    # 0.1), where the two renderers' different pixel samples see different surfaces.
    gb = ours.gbuffer
    d = light - gb.position
    r = np.linalg.norm(d, axis=1)
    l = d / np.maximum(r, 1e-9)[:, None]
    cos = np.einsum("ij,ij->i", gb.normal, l)
    off = renderer.offsets[0]
    lit = (gb.hit & (cos > 0) & ~renderer.scene.occluded(gb.position + off * gb.normal, l, r - off))
    lit = lit.reshape(size, size, gb.spp).mean(-1)
    cos_pixel = np.where(gb.hit, cos, 0).reshape(size, size, gb.spp).mean(-1)
    depth = np.where(gb.hit, gb.depth, 1e3).reshape(size, size, gb.spp)
    jump = maximum_filter(depth.max(-1), 3) - minimum_filter(depth.min(-1), 3)
    full = (ours.mask == 1) & (ref[..., 3] == 1)
    core = (binary_erosion(full) & (minimum_filter(lit, 3) == maximum_filter(lit, 3))
            & (cos_pixel > 0.1) & (jump < 0.01))
    dark = core & (lit == 0)
    core &= lit == 1
    assert core.sum() > 150
    # In the shadow both are black (a point light, direct light only).
    assert np.abs(ours.image[dark]).max(initial=0) < 1e-6 and np.abs(ref[dark, :3]).max(initial=0) < 1e-6
    if other is not None:
        return ours.image[..., 0], ref[..., 0], core, extra
    return ours.image[..., 0], ref[..., 0], core


def test_matches_mitsuba_direct_diffuse(tmp_path):
    ours, ref, core = _point_light_view(tmp_path, None)
    rel = np.abs(ours - ref)[core] / ref[core]
    # Measured (aa 8 vs Mitsuba's 64 stratified samples): median 0.014%, 90th percentile
    # 0.09%, 98% of pixels within 1.05%; a 7-pixel band where the palm meets the fingers
    # is 1–2.7% brighter than Mitsuba (cause not pinned down; a ~1° difference in the
    # shading normal there would explain it).
    assert np.median(rel) < 1e-3
    assert np.percentile(rel, 90) < 0.005
    assert np.mean(rel > 0.011) <= 0.03
    assert rel.max() < 0.03


def test_ggx_lobe_matches_mitsubas_ggx(tmp_path):
    """The lobe alone, no env map between: one point light, GGX only with F ≡ 1, per pixel
    sample, against Mitsuba's own GGX microfacet BSDF (``roughconductor``; Smith's separable
    G, as :mod:`relight_cli.brdf`'s ``smith``).  URHand's Schlick–Smith remap, the lobe
    before issue 50, is visibly darker than Mitsuba's."""
    ours, ref, core, schlick = _point_light_view(tmp_path, "smith", other="schlick")
    rel = np.abs(ours - ref)[core] / ref[core]
    # Measured (aa 8 against Mitsuba's 64 stratified samples, both pixel sampling only):
    # median 0.078 %, 90th percentile 0.57 %, 98th 4.0 % (the highlight's steep flanks, where
    # the two sample patterns see the lobe at different points), overall 1.000
    assert np.median(rel) < 2e-3
    assert np.percentile(rel, 90) < 0.01
    assert np.percentile(rel, 98) < 0.06
    assert abs(ours[core].sum() / ref[core].sum() - 1) < 0.005
    # URHand's remap: 0.936 of Mitsuba's light here (its G1 is 0.79 where Smith's is 0.97
    # at 60°, nearer 1 towards normal incidence)
    ratio = schlick[core].sum() / ref[core].sum()
    assert ratio < 0.96, ratio


# ---------------------------------------------------------------- env maps: the convention


def test_mitsuba_envmap_samples_where_its_source_says():
    """Mitsuba 3's envmap emitter, as src/emitters/envmap.cpp reads: a world direction d
    (identity to_world) is looked up at uv = (atan2(d.x, −d.z)/2π, acos(d.y)/π), wrapped,
    bilinearly between samples at u = (x + ½)/W, v = y/(H − 1); float32 data are used as
    they are (no sRGB curve, no rescaling, HDR values kept).  bench_mitsuba.mitsuba_envmap
    is built on exactly this."""
    mi.set_variant("scalar_rgb")
    h, w = 16, 32
    rng = np.random.default_rng(1)
    bitmap = rng.uniform(0.0, 1000.0, (h, w, 3)).astype(np.float32)
    mb = mi.Bitmap(bitmap)
    assert not mb.srgb_gamma()
    emitter = mi.load_dict({"type": "envmap", "bitmap": mb})

    def look(u, v):
        theta, phi = math.pi * v, 2 * math.pi * u
        d = np.array([math.sin(phi) * math.sin(theta), math.cos(theta),
                      -math.cos(phi) * math.sin(theta)])
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(-d))                  # wi points back along the ray
        return np.array(emitter.eval(si), np.float64)

    for y in range(1, h - 1):
        for x in range(0, w, 3):
            u, v = (x + 0.5) / w, y / (h - 1)
            # (float32 directions: weights off by ~1e-6, × values up to 1000)
            assert np.allclose(look(u, v), bitmap[y, x], rtol=1e-4, atol=0.01), (x, y)
            # halfway to the next column (wrapping at the seam): the mean of the two
            assert np.allclose(look(u + 0.5 / w, v), 0.5 * (bitmap[y, x] + bitmap[y, (x + 1) % w]),
                               rtol=1e-4, atol=0.01), (x, y)


def _smooth(d):
    """A map that tells every axis and sign apart: (1 + ½x, 1 + ½y, 1 + ½z) × 100 (HDR)."""
    return 100.0 * (1.0 + 0.5 * np.asarray(d, np.float64))


def test_our_envmap_reaches_mitsuba_in_the_same_directions():
    """mitsuba_envmap's bitmap, in Mitsuba's envmap emitter, gives our radiance in every
    direction (no axis swapped or mirrored) and keeps our map's power."""
    from relight_cli import envmap as E
    from relight_cli.formats.envmap import EnvMap

    mi.set_variant("scalar_rgb")
    env = EnvMap(_smooth(E.latlong_directions(64, 128)).astype(np.float32))
    bitmap = BM.mitsuba_envmap(env)
    assert bitmap.shape == (512, 1024, 3) and bitmap.dtype == np.float32
    # the bitmap's cells hold our map's power (area means; float32 rounding)
    assert np.allclose(BM.bitmap_power(bitmap), E.power(env), rtol=1e-5)
    emitter = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(bitmap)})
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = []
    for v in d:
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(-v))
        got.append(np.array(emitter.eval(si), np.float64))
    err = np.abs(np.array(got) - _smooth(d))
    # our map is piecewise constant on 2.8° texels, so it is off the smooth function by up
    # to 50·sin(2.8°/√2)·√2 ≈ 1.7 at a texel's corner (measured: max 1.08, mean 0.35);
    # x or z mirrored gives a mean error of 17, x and z swapped 23
    assert err.max() < 2.0
    assert err.mean() < 0.6


AXES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)


def _plane_radiance(bitmap, n, spp=512, size=8):
    """Mitsuba: a white Lambertian rectangle facing ``n`` under the env map, seen from
    its front; [size², 3] pixels of radiance E(n)/π (nothing else in the scene)."""
    up = [0, 0, 1] if abs(n[1]) > 0.5 else [0, 1, 0]
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "fov": 10,
                   "to_world": mi.ScalarTransform4f().look_at(origin=(3 * n).tolist(),
                                                              target=[0, 0, 0], up=up),
                   "film": {"type": "hdrfilm", "width": size, "height": size,
                            "rfilter": {"type": "box"}, "pixel_format": "rgba"},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(bitmap)},
        "plane": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0],
                                                             target=n.tolist(), up=up),
                  "bsdf": {"type": "diffuse",
                           "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}})
    image = np.array(mi.render(scene, seed=1))
    assert (image[..., 3] == 1).all()                          # the plane fills the view
    return image[..., :3].reshape(-1, 3).astype(np.float64)


@pytest.mark.parametrize("name", ["builtin:sky", "builtin:studio", "builtin:point"])
def test_envmap_convention_irradiance_of_six_planes(name):
    """The lighting Mitsuba renders from the bitmap is our map's: the irradiance of planes
    facing ±x, ±y, ±z matches E(n) = Σ L max(n·ω, 0) Δω over our map
    (relight_cli.envmap.irradiance).  builtin:point is one 1° source at (0.3, 0.8, 0.5)
    (lights +x, +y, +z only); builtin:sky's sun and builtin:studio's three lamps make
    every axis and sign differ by 1.4× to 40×, so a mirrored or turned map fails."""
    from relight_cli import envmap as E
    from relight_cli.builtin_envs import builtin_envmap

    mi.set_variant("scalar_rgb")
    env = builtin_envmap(name)
    bitmap = BM.mitsuba_envmap(env)
    ours = E.irradiance(env, AXES) / math.pi
    for n, expected in zip(AXES, ours):
        pixels = _plane_radiance(bitmap, n)
        got = pixels.mean(0)
        if not expected.any():                                  # below a point source
            assert np.abs(got).max() < 1e-6, (n, got)
            continue
        # the reference's noise: the 64 pixels' standard error at 512 spp, measured
        # ≤ 0.81 % of the mean (studio), 0.34 % (sky), 0.02 % (point); the deviations
        # measured: ≤ 2.6 standard errors (studio), 1.4 (sky), 1.1 (point).  So: 4
        # standard errors, + 0.2 % for our texel-centre sum of the cosine and Mitsuba's
        # bilinear lookup (point, nearly noise-free: 0.02 %)
        se = pixels.std(0) / math.sqrt(len(pixels))
        assert np.all(np.abs(got - expected) <= 4 * se + 2e-3 * expected), (n, got, expected)


# ---------------------------------------------------------------- env maps: the fist

def _has_new_fields() -> bool:
    from relight_cli.render.shading import RenderSettings
    return {"shadowing", "env_sources"} <= {f.name for f in dataclasses.fields(RenderSettings)}


#: the fields of the renderer's env-map work (another change): without them the old
#: defaults (Schlick's G remap, the sun on its 32x16 cell) miss the tolerances below
NEW_FIELDS = _has_new_fields()
SIZE, SPP = 64, 256
WAREHOUSE = pytest.param(str(BM.WAREHOUSE), marks=pytest.mark.skipif(
    not BM.WAREHOUSE.is_file(), reason="../shared/data (Poly Haven HDRIs) is absent"))

#: our renderer's own error at the defaults (32x16 grid, tex_res 256, aa 2), 64² view, rel.
#: RMS inside the mask with the reference's noise taken out, measured against a 4096-spp
#: reference and three 2×256-spp seed pairs: diffuse 0.028–0.033 (sky, studio, warehouse)
#: — the shadow edges of 512 directions; specular 0.045–0.059 (sky: the sun's highlights
#: on the knuckles), 0.048–0.078 (studio: its lamps' grazing highlights on the knuckles'
#: tops, lamps 8–18° wide on 11° cells, too wide to be extracted as sources), 0.027–0.069
#: (warehouse).  The budgets: the largest + ~35 %.  (The old lobe and no sources: sky
#: 0.10 diffuse, 0.18 specular; studio specular 0.33.)
BUDGET = {"diffuse": 0.045, "specular": 0.105}
#: measured |mean ratio − 1| at the defaults ≤ 1.25 % (warehouse, diffuse: its windows on
#: the 32x16 grid; 0.03 % at 128x64; specular ≤ 1.13 %), ≤ 0.9 % otherwise; Schlick's remap
#: gives 0.87 and the sun left on its cell 0.958 (builtin:sky)
RATIO_BUDGET = 0.02


@pytest.fixture(scope="module")
def fist(tmp_path_factory):
    meshes, camera, eye, target = BM.fist_view(SIZE)
    ply = tmp_path_factory.mktemp("mitsuba") / "fist.ply"
    BM.write_ply(meshes[0], ply)
    return meshes, camera, eye, target, ply


@pytest.mark.xfail(not NEW_FIELDS, strict=False,
                   reason="needs RenderSettings.shadowing (exact Smith G) and env_sources "
                          "(the sun kept as a source): another change, not in yet")
@pytest.mark.parametrize("case", ["diffuse", "specular"])
@pytest.mark.parametrize("name", ["builtin:sky", "builtin:studio", WAREHOUSE])
def test_fist_under_env_maps_matches_mitsuba(fist, case, name):
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.formats.envmap import read_envmap
    from relight_cli.render import appearance as A
    from relight_cli.render.shading import HandRenderer, RenderSettings

    mi.set_variant("scalar_rgb")
    meshes, camera, eye, target, ply = fist
    env = builtin_envmap(name) if name.startswith("builtin:") else read_envmap(name)
    scene = BM.mitsuba_scene(mi, ply, eye, target, SIZE, SPP, BM.mitsuba_envmap(env),
                             BM.CASES[case])
    r1, r2 = (np.array(mi.render(scene, seed=s), np.float64) for s in (1, 2))
    material = (A.constant_material((0.5, 0.5, 0.5)) if case == "diffuse"
                else A.constant_material((0.0, 0.0, 0.0), BM.ROUGHNESS, 1.0))
    settings = RenderSettings(sss=False, bounce=False, env_space="texels",
                              **({"specular": False} if case == "diffuse" else {}))
    renderer = HandRenderer(meshes, [material], settings)
    ours = renderer.render(camera, renderer.light(env=env))

    full = (r1[..., 3] >= 1) & (r2[..., 3] >= 1) & (ours.mask >= 1)
    assert np.abs(r1[..., 3] - ours.mask).mean() < 0.01         # same view, same silhouette
    assert full.sum() > 1000
    ref = 0.5 * (r1[..., :3] + r2[..., :3])[full]
    mine = ours.image[full].astype(np.float64)
    scale = math.sqrt(float((ref ** 2).mean()))
    # the reference's own noise (rel. RMS): relRMS(r1, r2) is √2 × one render's, the mean
    # of the two has half its variance; at 256 spp, measured 0.021 (sky, diffuse) to 0.086
    # (warehouse, specular)
    noise = math.sqrt(float(((r1 - r2)[..., :3][full] ** 2).mean())) / scale / 2
    rel = math.sqrt(float(((mine - ref) ** 2).mean())) / scale
    ratio = float(mine.mean() / ref.mean())
    # RATIO_BUDGET, + 3σ of the reference's own mean over N pixels (noise/√N: ≤ 0.3 %)
    assert abs(ratio - 1) <= RATIO_BUDGET + 3 * noise / math.sqrt(full.sum()), ratio
    # rel² ≈ ours² + noise² (independent): ours with the noise taken out, against BUDGET
    assert math.sqrt(max(rel ** 2 - noise ** 2, 0.0)) <= BUDGET[case], (rel, noise)
