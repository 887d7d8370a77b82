"""relight_cli.gaussians.receiver_shadow: the one shadow of receivers that relight relight
delivers and dgsm-build --preview shows (tests/commands/test_dgsm_build.py compares the two)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from relight_cli.formats.gaussians_ply import Gaussians, rgb_to_sh_dc
from relight_cli.gaussians.receiver_shadow import receiver_shadow


def _flat_receivers(xs):
    """Flat discs at (x, 0, 0), thin axis +Y (quaternion: +90° about X)."""
    n = len(xs)
    return Gaussians(np.column_stack([xs, np.zeros(n), np.zeros(n)]),
                     np.tile([0.05, 0.05, 0.0025], (n, 1)),
                     np.tile([np.cos(np.pi / 4), np.sin(np.pi / 4), 0, 0], (n, 1)),
                     np.full(n, 0.9), rgb_to_sh_dc(np.full((n, 3), 0.6))[:, None, :], 0)


def test_receiver_shadow_known_answer():
    """One white light of intensity I at height h above flat receivers, a uniform probe of
    radiance R: auto strength s = E_d / (E_d + πR) with E_d = I·h/r³, and each receiver's
    factor 1 − s·(1 − T); a fixed strength s gives 1 − s·(1 − T)."""
    h, intensity, radiance = 1.5, 6.0, 0.2
    xs = np.array([0.0, 0.5, 1.0, 2.0])
    floor = _flat_receivers(xs)
    light = SimpleNamespace(lights=np.array([[0.0, h, 0.0]]), intensities=np.array([intensity]),
                            colors=np.ones((1, 3)))
    T = np.array([[0.0, 0.25, 0.5, 1.0]])
    coefficients = np.full((1, 3), radiance * np.sqrt(4 * np.pi))
    r = np.sqrt(xs ** 2 + h ** 2)
    e_direct = intensity * h / r ** 3
    s = e_direct / (e_direct + np.pi * radiance)
    auto = receiver_shadow(light, floor, T, "auto", probe_coefficients=coefficients)
    np.testing.assert_allclose(auto.factor, np.repeat((1 - s * (1 - T[0]))[:, None], 3, 1),
                               rtol=1e-9)
    assert auto.light_weights == "irradiance" and auto.describe().startswith("auto (median ")
    fixed = receiver_shadow(light, floor, T, 0.4)
    np.testing.assert_allclose(fixed.factor[:, 0], 1 - 0.4 * (1 - T[0]), rtol=1e-12)
    assert fixed.light_weights == "intensity" and fixed.describe() == "0.4"
    with pytest.raises(ValueError, match="give the probe"):
        receiver_shadow(light, floor, T, "auto")


def test_coloured_lights_and_bad_strength():
    """Two lights, one red: intensity weights w_l,c = I_l·C_l,c, so a receiver shadowed
    from the red light only loses red (strength 1: factor_c = Σ w T / Σ w per channel)."""
    floor = _flat_receivers(np.array([0.0]))
    lights = SimpleNamespace(lights=np.array([[0.0, 1.0, 0.0], [1.0, 1.0, 0.0]]),
                             intensities=np.array([2.0, 1.0]),
                             colors=np.array([[1.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
    T = np.array([[0.0], [1.0]])                          # the red light is blocked
    out = receiver_shadow(lights, floor, T, 1.0)
    np.testing.assert_allclose(out.factor, [[1 / 3, 1.0, 1.0]], rtol=1e-12)
    with pytest.raises(ValueError, match=r"in \[0, 1\]"):
        receiver_shadow(lights, floor, T, 1.5)
