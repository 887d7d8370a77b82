"""The Disney/UE4 GGX lobe of URHand as elementwise terms (numpy and torch).

The same lobe, clamps and cancelled form as :func:`relight_cli.features.ggx_weights`
(which evaluates it for receivers × a shared direction grid); here every
(normal, view, light) triple carries its own light direction, as point lights at
finite distance need.  Tests check both agree to rounding.

For perceptual roughness ρ (clamped to [``MIN_ROUGHNESS``, 1]) and α = ρ²:
  D = α² / (π ((n·h)²(α² − 1) + 1)²),  F = F0 + (1 − F0)(1 − v·h)⁵,
  G = G1(l) G1(v),  G1(x) = n·x / ((n·x)(1 − k) + k),  k = (ρ + 1)²/8,
  f_s · (n·l) = D F (n·l) / (4 ((n·l)(1−k)+k) ((n·v)(1−k)+k)),  0 where n·l ≤ 0 or n·v ≤ 0.
"""

from __future__ import annotations

import math

import numpy as np

# Perceptual roughness floor: below it the lobe is narrower than any env texel, and
# clamping keeps α² > 0 so D stays finite.
MIN_ROUGHNESS = 1e-3


def ggx_cosine(normal, view, light, roughness, f0: float = 0.04) -> np.ndarray:
    """f_s(l, v)·max(n·l, 0), broadcasting over leading dimensions.

    Args:
        normal, view, light: [..., 3] unit vectors (view and light point away from the surface).
        roughness: [...] or scalar perceptual roughness ρ.
        f0: Fresnel reflectance at normal incidence.

    Returns:
        [...] float64.
    """
    n = np.asarray(normal, np.float64)
    v = np.asarray(view, np.float64)
    l = np.asarray(light, np.float64)
    rho = np.clip(np.asarray(roughness, np.float64), MIN_ROUGHNESS, 1.0)
    a2 = rho ** 4
    k = (rho + 1) ** 2 / 8
    half = v + l
    hlen = np.linalg.norm(half, axis=-1)
    hlen = np.where(hlen > 1e-12, hlen, 1.0)
    nl = np.sum(n * l, -1)
    nv = np.sum(n * v, -1)
    nh = np.sum(n * half, -1) / hlen
    vh = np.clip(np.sum(v * half, -1) / hlen, 0, 1)
    D = a2 / (math.pi * (nh * nh * (a2 - 1) + 1) ** 2)
    F = f0 + (1 - f0) * (1 - vh) ** 5
    nlp = np.clip(nl, 0, None)
    nvp = np.clip(nv, 0, None)
    w = D * F * nlp / (4 * (nlp * (1 - k) + k) * (nvp * (1 - k) + k))
    return np.where((nl > 0) & (nv > 0), w, 0.0)


def ggx_cosine_torch(normal, view, light, roughness, f0: float = 0.04):
    """Torch twin of :func:`ggx_cosine` (differentiable in normal and roughness).

    D's denominator is evaluated as |n × h|² + (n·h)² α², which equals the module doc's
    form for unit vectors but stays > 0 in float32 down to ``MIN_ROUGHNESS`` (the usual
    form divides by zero there, as Filament's ``D_GGX`` notes for half floats)."""
    import torch

    n = torch.nn.functional.normalize(normal, dim=-1)
    rho = torch.clamp(torch.as_tensor(roughness, dtype=n.dtype, device=n.device),
                      MIN_ROUGHNESS, 1.0)
    a2 = rho ** 4
    k = (rho + 1) ** 2 / 8
    half = torch.nn.functional.normalize(view + light, dim=-1)
    nl = (n * light).sum(-1)
    nv = (n * view).sum(-1)
    nh = (n * half).sum(-1)
    vh = torch.clamp((view * half).sum(-1), 0, 1)
    # (n·h)²(α² − 1) + 1 = |n × h|² + (n·h)² α² for unit n, h: in float32 the left side
    # cancels to 0 (D = inf) where n·h rounds to 1 and α² < 2⁻²⁴ (ρ below ~0.016); the
    # right side has no cancellation, and it is at least α² (the clamp covers a zero n or
    # h, where the lobe is masked below anyway)
    nxh = torch.linalg.cross(*torch.broadcast_tensors(n, half), dim=-1)
    den = torch.maximum((nxh * nxh).sum(-1) + nh * nh * a2, a2)
    D = a2 / (math.pi * den ** 2)
    F = f0 + (1 - f0) * (1 - vh) ** 5
    nlp = torch.clamp(nl, min=0)
    nvp = torch.clamp(nv, min=0)
    w = D * F * nlp / (4 * (nlp * (1 - k) + k) * (nvp * (1 - k) + k))
    return torch.where((nl > 0) & (nv > 0), w, torch.zeros_like(w))
