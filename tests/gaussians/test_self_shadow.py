"""Self-shadowing through the DGSM (issue 49; ours, beyond the paper): an object's own
Gaussians shadowed by the object, each Gaussian looked up towards the light so that it
never shadows itself (relight_cli.gaussians.dgsm.sample_self_transmittance), against the
mesh pseudo ground truth (embree shadow rays against the object's own mesh)."""

from __future__ import annotations

import numpy as np
import pytest

from relight_cli.gaussians import dgsm as D
from relight_cli.gaussians.from_mesh import gaussians_from_mesh
from relight_cli.gaussians.shadow_matte import mesh_visibility
from relight_cli.jobs.dgsm_build import DgsmOptions, build
from relight_cli.formats.lights_json import Lights

LIGHT = [0.05, 1.2, 0.02]


def shelf():
    """One object of two horizontal plates facing up: a floor plate 20 cm wide at y = 0
    and a shelf 10 cm wide 6 cm above its left half (triangles of ≤ 1 cm); with the
    light above, the shelf casts a shadow on the floor plate of its own object.  Returns
    (its Gaussians, its mesh)."""
    def plate(x0, x1, z0, z1, y):
        v = np.array([[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]], float)
        return v, np.array([[0, 2, 1], [0, 3, 2]])
    (v0, f0), (v1, f1) = plate(-0.1, 0.1, -0.1, 0.1, 0.0), plate(-0.1, 0.0, -0.05, 0.05, 0.06)
    vertices, faces = np.concatenate([v0, v1]), np.concatenate([f0, f1 + 4])
    g = gaussians_from_mesh(vertices, faces, max_edge=0.01)
    import trimesh
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, 0.01))
    return g, (np.asarray(mesh.vertices), np.asarray(mesh.faces))


def test_self_shadow_matches_the_mesh_and_no_gaussian_shadows_itself():
    g, mesh = shelf()
    lights = Lights(np.array([LIGHT]))
    result = build([g], lights, DgsmOptions(size=(256, 256), self_shadow=True), g, quiet=True)
    assert all(r["self_shadow"] for r in result.shadow_map.roi)
    T = D.sample_self_transmittance(result.shadow_map, g.means, g.scales, g.rotations)[0]
    truth = mesh_visibility([mesh], np.array([LIGHT]), g.means, offset=1e-4)[0]
    agree = np.mean((T > 0.5) == (truth > 0.5))
    assert agree > 0.97, agree
    shelf_top = g.means[:, 1] > 0.03
    assert T[shelf_top].min() > 0.95                  # the shelf is lit: never self-shadowed
    under = (~shelf_top) & (truth == 0)
    assert under.sum() > 50 and np.median(T[under]) < 0.05   # the floor under it is dark
    # the same table looked up at the Gaussians' centres (no offset towards the light)
    # shadows every Gaussian by itself: the lit shelf's top reads as shadowed (0.70 measured)
    plain = D.sample_transmittance(result.shadow_map, g.means)[0]
    assert np.median(plain[shelf_top]) < 0.9


def test_a_map_built_without_self_shadow_is_refused_by_the_job():
    from relight_cli.formats.sh_probe_json import ShProbe
    from relight_cli.jobs.relight_gaussians import GaussianOptions, relight
    g, _ = shelf()
    lights = Lights(np.array([LIGHT]))
    plain = build([g], lights, DgsmOptions(size=(64, 64)), g, quiet=True).shadow_map
    coefficients = np.zeros((4, 3))
    coefficients[0] = 3.5                                   # uniform light
    probe = ShProbe(coefficients, 1, 0.0, "test")
    with pytest.raises(ValueError, match="self-shadowing"):
        relight([g], probe, GaussianOptions(self_shadow=True, shadow_strength=1.0), plain, g)
