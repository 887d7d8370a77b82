"""Light estimation from a scene (relight_cli/gaussians/lights.py, paper Sec. 3.1): compact
emitters found, ROI, errors, the paper's details."""

from __future__ import annotations

import numpy as np
import pytest

from relight_cli.formats.gaussians_ply import Gaussians, rgb_to_sh_dc
from relight_cli.formats.lights_json import Lights


# ------------------------------------------------------------------ light estimation (Sec. 3.1)


def room_with_lamps(seed=0):
    """A 4×3×4 m grey room (floor + walls), a bright extended window, and two compact lamps."""
    rng = np.random.default_rng(seed)
    parts = []

    def add(means, rgb, scale=0.05, opacity=0.9, sh_rest=None):
        n = len(means)
        sh = rgb_to_sh_dc(np.broadcast_to(rgb, (n, 3)))[:, None, :]
        if sh_rest is not None:
            sh = np.concatenate([sh, np.broadcast_to(sh_rest, (n, 3, 3))], axis=1)
        else:
            sh = np.concatenate([sh, np.zeros((n, 3, 3))], axis=1)
        parts.append(Gaussians(means, np.full((n, 3), scale), np.tile([1.0, 0, 0, 0], (n, 1)),
                               np.full(n, opacity), sh, 1))

    u = rng.uniform(-2, 2, (3000, 2))
    add(np.column_stack([u[:, 0], np.zeros(3000), u[:, 1]]), [0.3, 0.3, 0.3])                  # floor
    w = rng.uniform([-2, 0], [2, 3], (2000, 2))
    add(np.column_stack([w[:, 0], w[:, 1], np.full(2000, -2.0)]), [0.3, 0.3, 0.3])             # wall
    win = rng.uniform([-0.5, 1.0], [0.5, 2.0], (600, 2))
    add(np.column_stack([win[:, 0], win[:, 1], np.full(600, -1.99)]), [1.8, 1.8, 1.9])       # window
    lamp_a, lamp_b = np.array([1.2, 2.6, 0.5]), np.array([-1.5, 1.8, 1.0])
    add(lamp_a + rng.normal(0, 0.01, (12, 3)), [4.0, 3.0, 2.0], scale=0.01)
    add(lamp_b + rng.normal(0, 0.01, (12, 3)), [2.0, 3.0, 5.0], scale=0.01)
    # A specular glint: bright only from +x (degree-1 SH), dim on average.
    add(np.array([[0.5, 0.3, -1.0]]) + rng.normal(0, 0.005, (5, 3)), [0.3, 0.3, 0.3],
        sh_rest=np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-6.0, -6.0, -6.0]]), scale=0.01)
    from relight_cli.formats.gaussians_ply import concatenate
    return concatenate(parts), lamp_a, lamp_b


def test_estimate_lights_finds_compact_emitters():
    from relight_cli.gaussians.lights import LUMA, estimate_lights
    scene, lamp_a, lamp_b = room_with_lamps()
    est = estimate_lights(scene, 2)
    # one light record (formats.lights_json.Lights), the diagnostics beside it: the
    # positions are the chosen Gaussians' centres, unnamed, with no extra fields
    assert isinstance(est.lights, Lights) and len(est.lights) == 2
    assert est.lights.names == ["", ""] and est.lights.extra == {}
    np.testing.assert_array_equal(est.lights.positions, scene.means[est.indices])
    found = sorted(est.lights.positions.tolist(), key=lambda p: p[0])
    # Positions are Gaussian centres of the lamp clusters (σ = 1 cm jitter): within 4 cm.
    np.testing.assert_allclose(found[0], lamp_b, atol=0.04)
    np.testing.assert_allclose(found[1], lamp_a, atol=0.04)
    np.testing.assert_allclose(est.lights.colors @ LUMA, 1.0, atol=1e-12)
    a = int(np.argmin(np.linalg.norm(est.lights.positions - lamp_a, axis=1)))
    np.testing.assert_allclose(est.lights.colors[a] / est.lights.colors[a].max(),
                               [1.0, 0.75, 0.5], atol=1e-6)
    # paper: intensity = the base score b = opacity·(Ȳ + Ŷ)/2·(½ + ½s)·(½ + ½δ); a lamp looks
    # the same from everywhere (s = 1) and has no view-dependent SH energy (δ = 1)
    assert est.lights.intensities[a] == pytest.approx(0.9 * np.array([4.0, 3.0, 2.0]) @ LUMA,
                                                      rel=1e-6)
    v1 = estimate_lights(scene, 2, variant="v1")            # the earlier variant: mean luminance
    np.testing.assert_allclose(sorted(v1.lights.positions.tolist()),
                               sorted(est.lights.positions.tolist()))
    a1 = int(np.argmin(np.linalg.norm(v1.lights.positions - lamp_a, axis=1)))
    assert v1.lights.intensities[a1] == pytest.approx(np.array([4.0, 3.0, 2.0]) @ LUMA, rel=1e-6)
    # K = 3: the window (bright but extended) comes after both lamps; the glint never wins.
    est3 = estimate_lights(scene, 3)
    assert -0.6 < est3.lights.positions[2, 0] < 0.6 and est3.lights.positions[2, 2] < -1.9
    assert est3.scores[0] >= est3.scores[1] >= est3.scores[2]


def test_estimate_lights_roi_and_errors():
    from relight_cli.gaussians.lights import estimate_lights, parse_auto
    scene, lamp_a, _ = room_with_lamps()
    est = estimate_lights(scene, 1, roi_center=lamp_a, roi_radius=0.5)
    np.testing.assert_allclose(est.lights.positions[0], lamp_a, atol=0.04)
    with pytest.raises(ValueError, match="no scene Gaussians"):
        estimate_lights(scene, 1, roi_center=[50.0, 0, 0], roi_radius=1.0)
    assert parse_auto("auto:3") == 3 and parse_auto("lights.json") is None
    with pytest.raises(ValueError):
        parse_auto("auto:0")
    with pytest.raises(ValueError):
        parse_auto("auto:x")


def test_estimate_lights_paper_details():
    """Sec. 3.1: ROI and viewpoints at the character, soft clipping, colour toward the character."""
    from relight_cli.gaussians.lights import colour_toward, estimate_lights, soft_clip
    scene, lamp_a, lamp_b = room_with_lamps()
    # the character stands next to lamp b: a 0.8 m ROI around it finds only that lamp
    char = Gaussians(lamp_b + [0.3, -0.5, 0.0] + np.random.default_rng(1).normal(0, 0.1, (50, 3)),
                     np.full((50, 3), 0.02), np.tile([1.0, 0, 0, 0], (50, 1)), np.full(50, 0.9),
                     np.zeros((50, 1, 3)), 0)
    est = estimate_lights(scene, 1, roi_radius=0.8, character=char)
    np.testing.assert_allclose(est.lights.positions[0], lamp_b, atol=0.04)
    # soft clipping: below the fence untouched, order kept, bounded above
    v = np.r_[np.linspace(0, 1, 200), 5.0, 50.0, 1e6]
    c = soft_clip(v)
    fence = 10 * np.percentile(v, 99)
    np.testing.assert_array_equal(c[v <= fence], v[v <= fence])
    assert c[200] == 5.0                                      # a lamp 5× the bulk: kept
    assert np.all(np.diff(c) >= 0) and c.max() <= 2 * fence
    # a blown-out floater (luminance 1e4): clipping keeps the order but not its 1000× margin,
    # so its score no longer swamps the lamps (what an intensity-from-score light inherits)
    from relight_cli.formats.gaussians_ply import concatenate
    floater = Gaussians(np.array([[0.0, 1.5, 1.5]]), np.full((1, 3), 0.01), [[1.0, 0, 0, 0]],
                        [0.9], np.concatenate([rgb_to_sh_dc(np.full((1, 3), 1e4))[:, None, :],
                                               np.zeros((1, 3, 3))], axis=1), 1)
    with_floater = concatenate([scene, floater])
    paper = estimate_lights(with_floater, 2)
    v1 = estimate_lights(with_floater, 2, variant="v1")
    assert v1.lights.positions[0][2] == pytest.approx(1.5)
    assert paper.lights.positions[0][2] == pytest.approx(1.5)
    assert v1.scores[0] > 1000 * v1.scores[1]                 # unclipped (measured 3500×)
    assert paper.scores[0] < 50 * paper.scores[1]             # soft-clipped (measured 20×)
    # colour toward the character: the SH evaluated from the character's centroid
    # (the glint is bright for viewing directions along +x, i.e. seen from a camera at −x)
    glint = len(scene) - 5
    from_minus_x = colour_toward(scene, [glint], scene.means[glint] - [1.0, 0, 0])
    from_plus_x = colour_toward(scene, [glint], scene.means[glint] + [1.0, 0, 0])
    assert from_minus_x[0].min() > 1.0 and from_plus_x[0].max() == 0.0
    with pytest.raises(ValueError, match="estimator"):
        estimate_lights(scene, 1, variant="bogus")
