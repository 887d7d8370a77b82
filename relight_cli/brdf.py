"""The GGX microfacet lobe as elementwise terms (numpy and torch).

The same lobe, clamps and cancelled form as :func:`relight_cli.features.ggx_weights`
(which evaluates it for receivers × a shared direction grid); here every
(normal, view, light) triple carries its own light direction, as point lights at
finite distance need.  Tests check both agree to rounding.

For perceptual roughness ρ (clamped to [``MIN_ROUGHNESS``, 1]) and α = ρ²:
  D = α² / (π ((n·h)²(α² − 1) + 1)²)           (Trowbridge–Reitz / GGX, Walter et al. 2007 Eq. 33)
  F = F0 + (1 − F0)(1 − v·h)⁵                  (Schlick)
  G = G1(l) G1(v)                              (separable Smith, Walter et al. 2007 Eq. 23)
  f_s · (n·l) = D F G / (4 (n·v)),  0 where n·l ≤ 0 or n·v ≤ 0,
which is written with G1(x) = 2 (n·x) / Λ(x) as
  f_s · (n·l) = D F (n·l) / (Λ(l) Λ(v))
so the n·x of G1's numerator cancels and grazing angles stay finite.  Two shadowing
terms (``shadowing``):

* ``"smith"`` (default): the exact Smith G1 of GGX (Walter et al. 2007 Eq. 34),
  Λ(x) = n·x + √(α² + (1 − α²)(n·x)²).  The separable product, not Heitz's (2014)
  height-correlated G2, because that is what Mitsuba 3 (``MicrofacetDistribution::G``)
  and pbrt-v3 use, so the renderer can be checked against them
  (tests/render/test_shading_mitsuba.py).
* ``"schlick"``: Schlick's approximation with the Disney/UE4 remap k = (ρ + 1)²/8
  (Karis 2013), Λ(x) = 2 ((n·x)(1 − k) + k).  The remap was made for point lights in
  real time; it is what URHand's public code (facebookresearch/goliath,
  ``ca_code/models/urhand.py``: ``ggx_k``) uses for the physical branch, so the
  learned models keep it.  At ρ = 0.45, 60° it gives G1 = 0.79 where Smith's is 0.97:
  rough highlights come out ~1.2–1.5× darker than a standard GGX renderer's.
"""

from __future__ import annotations

import math

import numpy as np

# Perceptual roughness floor: below it the lobe is narrower than any env texel, and
# clamping keeps α² > 0 so D stays finite.
MIN_ROUGHNESS = 1e-3

#: the shadowing terms :func:`ggx_cosine` knows (module doc)
SHADOWING = ("smith", "schlick")
#: the shadowing of URHand's public code (module doc): the learned models' lobe
URHAND_SHADOWING = "schlick"


def check_shadowing(shadowing: str) -> str:
    if shadowing not in SHADOWING:
        raise ValueError(f"GGX shadowing must be one of {', '.join(SHADOWING)}, got {shadowing!r}")
    return shadowing


def shadowing_denominator(cos, rho, shadowing: str = "smith"):
    """Λ(x) of the module doc: 2 (n·x) / G1(x) for cosines ``cos`` ≥ 0 (numpy or torch,
    broadcasting with the roughness ``rho``, already clamped)."""
    if shadowing == "schlick":
        k = (rho + 1) ** 2 / 8
        return 2 * (cos * (1 - k) + k)
    a2 = rho ** 4
    root = (a2 + (1 - a2) * cos * cos) ** 0.5
    return cos + root


def ggx_cosine(normal, view, light, roughness, f0: float = 0.04,
               shadowing: str = "smith") -> np.ndarray:
    """f_s(l, v)·max(n·l, 0), broadcasting over leading dimensions.

    Args:
        normal, view, light: [..., 3] unit vectors (view and light point away from the surface).
        roughness: [...] or scalar perceptual roughness ρ.
        f0: Fresnel reflectance at normal incidence.
        shadowing: ``"smith"`` or ``"schlick"`` (module doc).

    Returns:
        [...] float64.
    """
    n = np.asarray(normal, np.float64)
    v = np.asarray(view, np.float64)
    l = np.asarray(light, np.float64)
    rho = np.clip(np.asarray(roughness, np.float64), MIN_ROUGHNESS, 1.0)
    a2 = rho ** 4
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
    w = D * F * nlp / (shadowing_denominator(nlp, rho, check_shadowing(shadowing))
                       * shadowing_denominator(nvp, rho, shadowing))
    return np.where((nl > 0) & (nv > 0), w, 0.0)


def ggx_cosine_torch(normal, view, light, roughness, f0: float = 0.04,
                     shadowing: str = "smith"):
    """Torch twin of :func:`ggx_cosine` (differentiable in normal and roughness).

    D's denominator is evaluated as |n × h|² + (n·h)² α², which equals the module doc's
    form for unit vectors but stays > 0 in float32 down to ``MIN_ROUGHNESS`` (the usual
    form divides by zero there, as Filament's ``D_GGX`` notes for half floats)."""
    import torch

    n = torch.nn.functional.normalize(normal, dim=-1)
    rho = torch.clamp(torch.as_tensor(roughness, dtype=n.dtype, device=n.device),
                      MIN_ROUGHNESS, 1.0)
    a2 = rho ** 4
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
    w = D * F * nlp / (shadowing_denominator(nlp, rho, check_shadowing(shadowing))
                       * shadowing_denominator(nvp, rho, shadowing))
    return torch.where((nl > 0) & (nv > 0), w, torch.zeros_like(w))
