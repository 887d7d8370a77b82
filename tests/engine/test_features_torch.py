"""The differentiable GGX feature (torch) against the numpy engine, and its gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from relight_cli import envmap as E  # noqa: E402
from relight_cli.features import MIN_ROUGHNESS, ggx_specular_torch, ggx_weights  # noqa: E402


def _setup(n=40, seed=0):
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    view = normals + rng.normal(size=(n, 3)) * 0.8          # mostly front-facing, some grazing
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    dirs = E.latlong_directions(8, 16).reshape(-1, 3)
    omega = E.latlong_solid_angles(8, 16).reshape(-1)
    radiance = rng.random((len(dirs), 3)) * 5
    visibility = (rng.random((n, len(dirs))) > 0.3).astype(np.float64)
    rough = rng.uniform(0.1, 1.0, n)
    return normals, view, dirs, omega, radiance, visibility, rough


def test_torch_matches_numpy():
    normals, view, dirs, omega, radiance, vis, rough = _setup()
    expect = (vis * ggx_weights(normals, view, dirs, rough)) @ (radiance * omega[:, None])
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)   # noqa: E731
    got = ggx_specular_torch(t(normals), t(view), t(dirs), t(radiance * omega[:, None]),
                             t(vis), t(rough)).numpy()
    # Same formula, same float64 operations up to ordering: 1e-10 relative.
    np.testing.assert_allclose(got, expect, rtol=1e-10, atol=1e-14)
    # Unnormalized normals give the same result (normalized inside).
    got2 = ggx_specular_torch(t(normals * 3.0), t(view), t(dirs), t(radiance * omega[:, None]),
                              t(vis), t(rough)).numpy()
    np.testing.assert_allclose(got2, expect, rtol=1e-10, atol=1e-14)


def test_gradients_match_finite_differences():
    normals, view, dirs, omega, radiance, vis, rough = _setup(n=6, seed=1)
    # Keep away from the n·ω = 0 and n·v = 0 kinks where the function is not differentiable.
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)   # noqa: E731
    n_t = t(normals).requires_grad_(True)
    r_t = t(np.clip(rough, 0.2, 0.9)).requires_grad_(True)

    def f(n, r):
        return ggx_specular_torch(n, t(view), t(dirs), t(radiance * omega[:, None]), t(vis), r)

    # gradcheck: analytic vs central differences, float64 (eps 1e-6, atol 1e-5 default).
    assert torch.autograd.gradcheck(f, (n_t, r_t), eps=1e-6, atol=1e-5, rtol=1e-3,
                                    nondet_tol=0.0)


def test_visibility_is_fixed_and_roughness_clamped():
    normals, view, dirs, omega, radiance, vis, rough = _setup(n=4, seed=2)
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)   # noqa: E731
    v_t = t(vis).requires_grad_(True)
    out = ggx_specular_torch(t(normals), t(view), t(dirs), t(radiance * omega[:, None]), v_t,
                             torch.tensor(0.0, dtype=torch.float64))
    assert torch.isfinite(out).all()
    assert not out.requires_grad  # visibility is detached: no gradient path at all
    # Roughness 0 is clamped to MIN_ROUGHNESS: same as asking for it directly.
    out2 = ggx_specular_torch(t(normals), t(view), t(dirs), t(radiance * omega[:, None]), t(vis),
                              torch.tensor(MIN_ROUGHNESS, dtype=torch.float64))
    np.testing.assert_allclose(out.numpy(), out2.detach().numpy(), rtol=1e-12)
    assert math.isfinite(float(out.sum()))
