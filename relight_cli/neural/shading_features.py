"""URHand's physically based shading features in torch (supp. 8.2, Eq. 10–15), texel-aligned.

Everything is evaluated at one hand's inside texels (K of them), in each texel's tangent
frame (:class:`~relight_cli.neural.geometry.PoseTexels`: rows t, b, n), where the coarse
normal is +z and the refined normal n̂ comes from the physical branch's displacement.
Dot products do not depend on the frame, so the features equal world-space ones.

For lights i with RGB intensity I_i (point lights: radiant intensity, W sr⁻¹; an env
map's direction m: L_m Δω_m, the discretization of ``bake-features --env-res``,
:func:`relight_cli.features.discretize_env`), local direction ω_i, falloff f_i (1/r² for
a point light, 1 for a distant one) and ray-traced visibility V_i (fixed: traced on the
coarse geometry, as bake-features does), channel c of the features is

    C^d_c = Σ_i I_ic f_i V_i max(ω_i·n̂, 0)                         (Eq. 10)
    C^s_c = Σ_i I_ic f_i V_i D F G max(ω_i·n̂, 0)                   (Eq. 11–15)

with D F G (ω·n̂) the GGX lobe of :func:`relight_cli.brdf.ggx_cosine_torch` (perceptual
roughness β, α = β², F0 = 0.04) with the paper's Schlick–Smith G, K = (β+1)²/8
(``brdf.URHAND_SHADOWING``; the renderer and the stage use the exact Smith G).  Irradiance is in the capture's units
(a synthetic stage's fully lit frame gives ≈ π, formats/capture.md).

Departure: Eq. 13's Fresnel is UE4's spherical-Gaussian fit 2^((−5.55473 v·h − 6.98316)
v·h); :mod:`relight_cli.brdf` uses Schlick's (1 − v·h)⁵, which it approximates within 8 %
of F; ``fresnel="sg"`` selects the paper's form.

``features="phong"`` (URHand Table 3 / RelightableHands' features) replaces them with
C^d as above (coarse normal) and the normalized Phong lobe of bake-features,
(α+2)/(2π) max(r·ω, 0)^α with r the mirrored view, α = ``shininess``, times F0 (the
GGX lobe's reflectance at normal incidence, so that C_pb = C^d ⊙ T̄ + C^s stays a
plausible render; the light path does not care about a constant factor).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from relight_cli.brdf import MIN_ROUGHNESS

F_SG = (-5.55473, -6.98316)


def map_to_texels(maps: torch.Tensor, inside: np.ndarray) -> torch.Tensor:
    """[C, N, N] maps → [K, C] values at the ``inside`` [N, N] texels (row-major order,
    the order of :class:`~relight_cli.render.shading.TexelSurface`)."""
    flat = torch.from_numpy(np.flatnonzero(inside)).to(maps.device)
    return maps.reshape(maps.shape[0], -1)[:, flat].T


def texels_to_map(values: torch.Tensor, surface) -> torch.Tensor:
    """[K, C] inside-texel values → [C, N, N] maps; outside texels copy their nearest
    exposed texel (:meth:`PoseTexels.to_maps`, differentiably)."""
    n0, n1 = surface.inside.shape
    device = values.device
    full = values.new_zeros(n0 * n1, values.shape[1])
    full = full.index_copy(0, torch.from_numpy(np.flatnonzero(surface.inside)).to(device), values)
    iy, ix = surface.fill_index
    gather = torch.from_numpy((np.asarray(iy) * n1 + np.asarray(ix)).ravel()).to(device)
    return full[gather].T.reshape(values.shape[1], n0, n1)


def refined_normals(displacement: torch.Tensor, uv_derivatives: np.ndarray,
                    surface) -> torch.Tensor:
    """n̂ [K, 3] in the texel frames from a displacement map δd [N, N] (metres), Eq. 2.

    x̂ = x + δd n (Eq. 2), so x̂_u ≈ x_u + δd_u n and x̂_v ≈ x_v + δd_v n (dropping δd n_u,
    second order in the curvature × 3 mm), and n̂ ∝ x̂_u × x̂_v = x_u × x_v + δd_v (x_u × n)
    + δd_u (n × x_v).  x_u, x_v are the mesh's UV derivatives in the texel frame (n = +z);
    δd_u, δd_v are central differences of the map (row 0 is v = 1), where outside texels
    hold their nearest exposed neighbour's value (no gradient across a chart border).
    δd ≡ 0 gives n̂ = +z exactly (the coarse normal).
    """
    n = displacement.shape[-1]
    filled = texels_to_map(map_to_texels(displacement[None], surface.inside), surface)[0]
    pad = torch.nn.functional.pad(filled[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    d_u = (pad[1:-1, 2:] - pad[1:-1, :-2]) * (n / 2.0)                    # ∂δd/∂u
    d_v = -(pad[2:, 1:-1] - pad[:-2, 1:-1]) * (n / 2.0)                   # ∂δd/∂v (rows go down)
    grads = map_to_texels(torch.stack([d_u, d_v]), surface.inside)           # [K, 2]
    xd = torch.as_tensor(uv_derivatives, dtype=displacement.dtype, device=displacement.device)
    xu, xv = xd[:, 0], xd[:, 1]                                            # [K, 3]
    det = xu[:, 0] * xv[:, 1] - xu[:, 1] * xv[:, 0]                        # (x_u × x_v)·n
    det = torch.where(det.abs() > 1e-12, det, torch.full_like(det, 1e-12))
    tx = (grads[:, 1] * xu[:, 1] - grads[:, 0] * xv[:, 1]) / det
    ty = (-grads[:, 1] * xu[:, 0] + grads[:, 0] * xv[:, 0]) / det
    normal = torch.stack([tx, ty, torch.ones_like(tx)], 1)
    return torch.nn.functional.normalize(normal, dim=1)


def _fresnel_sg_ggx(normal, view, light, roughness, f0):
    """The GGX lobe with Eq. 13's spherical-Gaussian Fresnel (``fresnel="sg"``)."""
    from relight_cli.brdf import URHAND_SHADOWING, ggx_cosine_torch
    half = torch.nn.functional.normalize(view + light, dim=-1)
    vh = torch.clamp((view * half).sum(-1), 0, 1)
    schlick = f0 + (1 - f0) * (1 - vh) ** 5
    sg = f0 + (1 - f0) * torch.pow(2.0, (F_SG[0] * vh + F_SG[1]) * vh)
    return (ggx_cosine_torch(normal, view, light, roughness, f0, URHAND_SHADOWING)
            * sg / schlick)


def light_terms(normal: torch.Tensor, view: torch.Tensor, local_light: torch.Tensor,
                roughness: torch.Tensor, features: str = "pbr", shininess: float = 32.0,
                fresnel: str = "schlick", f0: float = 0.04) -> torch.Tensor:
    """Per-light (diffuse, specular) terms [L, 2, K] before intensity and visibility.

    normal [K, 3] unit (texel frame), view [K, 3] unit, local_light [L, K, 3] unit,
    roughness [K] (β).  ``features="phong"``: the coarse normal +z and the Phong lobe.
    """
    from relight_cli.brdf import URHAND_SHADOWING, ggx_cosine_torch

    if features == "phong":
        normal = torch.zeros_like(normal)
        normal[:, 2] = 1.0
    cos = torch.clamp((local_light * normal[None]).sum(-1), min=0)           # [L, K]
    if features == "phong":
        mirror = 2 * (normal * view).sum(-1, keepdim=True) * normal - view
        rl = torch.clamp((local_light * mirror[None]).sum(-1), min=0)
        spec = f0 * (shininess + 2) / (2 * math.pi) * rl ** shininess
    else:
        rho = torch.clamp(roughness, MIN_ROUGHNESS, 1.0)[None]
        n_, v_ = normal[None].expand_as(local_light), view[None].expand_as(local_light)
        if fresnel == "sg":
            spec = _fresnel_sg_ggx(n_, v_, local_light, rho, f0)
        else:   # URHand's code's lobe (relight_cli.brdf: the Schlick-Smith remap)
            spec = ggx_cosine_torch(n_, v_, local_light, rho, f0, URHAND_SHADOWING)
    return torch.stack([cos, spec], 1)


def shading_features(normal: torch.Tensor, view, lights, intensity, roughness: torch.Tensor,
                     features: str = "pbr", specular: bool = True, shininess: float = 32.0, fresnel: str = "schlick",
                     chunk: int = 64) -> torch.Tensor:
    """Per-channel shading features [3, 2, K] (C^d, C^s) of one hand under ``lights``.

    Args:
        normal: [K, 3] refined normals n̂ (texel frame); gradients flow to it.
        view: [K, 3] local view directions (numpy or tensor).
        lights: :class:`~relight_cli.neural.geometry.LightInputs` of L lights.
        intensity: [L, 3] RGB I_i.
        roughness: [K] β; gradients flow to it.
        features: ``pbr`` (Eq. 10–15) or ``phong``.
        specular: False zeroes C^s (URHand Table 3, w/o specular).  The w/o visibility
            ablation needs nothing here: a ``visibility=False`` CaptureData's light inputs
            hold V = 1 wherever the coarse normal faces the light.
        chunk: lights per block (memory is [chunk, K, 3]).

    Returns:
        [3, 2, K] tensor: features[c] is what a monochrome light of channel c's
        intensities gives (one light path per channel keeps RGB lights exact).
    """
    device, dtype = normal.device, normal.dtype
    view = torch.as_tensor(np.asarray(view) if not torch.is_tensor(view) else view,
                           dtype=dtype, device=device)
    intensity = torch.as_tensor(np.asarray(intensity, np.float64), dtype=dtype, device=device)
    L, K = lights.visibility.shape
    out = normal.new_zeros(3, 2, K)
    for start in range(0, L, chunk):
        sl = slice(start, min(L, start + chunk))
        local = torch.as_tensor(lights.local_light[sl], dtype=dtype, device=device)
        scale = torch.as_tensor(lights.visibility[sl] * lights.falloff[sl], dtype=dtype,
                                device=device)                                # [l, K]
        terms = light_terms(normal, view, local, roughness, features, shininess, fresnel)
        out = out + torch.einsum("lc,lk,ldk->cdk", intensity[sl], scale, terms)
    if not specular:
        out = torch.stack([out[:, 0], torch.zeros_like(out[:, 1])], 1)
    return out
