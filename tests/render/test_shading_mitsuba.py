"""Cross-check against Mitsuba 3 (optional: skipped when `mitsuba` is not installed).

Same mesh (the built-in hand's proxy, 'point' pose, vertex normals), same OpenCV
camera, one point light, Lambertian albedo 0.5, direct light only with shadows.
"""

from __future__ import annotations

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba", reason="mitsuba is optional (pip install mitsuba)")


def test_matches_mitsuba_direct_diffuse(tmp_path):
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
    renderer = HandRenderer(meshes, [A.constant_material((0.5, 0.5, 0.5))],
                            RenderSettings(tex_res=256, aa=8, specular=False, sss=False))
    ours = renderer.render(cam, renderer.light(Lights.from_radiant_intensity([light], 1.0)))

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
                 "bsdf": {"type": "diffuse",
                          "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}}})
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
    rel = np.abs(ours.image[..., 0] - ref[..., 0])[core] / ref[..., 0][core]
    # Measured (aa 8 vs Mitsuba's 64 stratified samples): median 0.014%, 90th percentile
    # 0.09%, 98% of pixels within 1.05%; a 7-pixel band where the palm meets the fingers
    # is 1–2.7% brighter than Mitsuba (cause not pinned down; a ~1° difference in the
    # shading normal there would explain it).
    assert np.median(rel) < 1e-3
    assert np.percentile(rel, 90) < 0.005
    assert np.mean(rel > 0.011) <= 0.03
    assert rel.max() < 0.03
