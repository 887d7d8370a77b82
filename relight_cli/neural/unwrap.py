"""Images unwrapped into a hand's UV layout, and the capture's lighting divided out.

The mean texture T̄ URHand conditions on (Sec. 4, Fig. 2) is the visibility-aware average
of what the cameras saw per texel.  A light-stage capture unwraps its fully lit frames
(:meth:`relight_cli.neural.data.CaptureData.mean_texture`); a phone scan
(``relight personalize``, supp. 9) unwraps a few photos of a hand fitted to them.  Both
use :func:`view_samples`: a texel counts in a view where the camera's ray reaches it
first (no occluder, same hand), it faces the camera and it projects inside the image
(and the view's mask), weighted by the cosine between its normal and the view.

Dividing the lighting out (T̄ in sr⁻¹, so a white Lambertian texel gets 1/π):

* the stage's LEDs: :func:`relight_cli.neural.linear_train.albedo_texture`;
* a known environment map (:func:`env_irradiance`): the unwrapped radiance over each
  texel's irradiance under the map, visibility traced — exact for a diffuse surface;
* unknown lighting (:func:`shading_map`, supp. 9's recipe): a one-channel shading map
  fitted in UV space to the darkness of the unwrapped texture relative to the images'
  mean foreground colour, total-variation regularised so it keeps broad shading and
  shadows but not sharp texture, and divided out.
"""

from __future__ import annotations

import numpy as np


def view_samples(texels, k: int, camera, image: np.ndarray, mask: np.ndarray | None = None):
    """Hand k's texels ``camera`` sees, and what it saw there.

    Args:
        texels: a :class:`~relight_cli.neural.geometry.PoseTexels` of the posed scene.
        camera: a relight/camera; image: [H, W, 3] linear RGB of its size.
        mask: optional [H, W] bool foreground mask (a texel counts where it projects
            inside it).
    Returns:
        (rows, cols, colour [M, 3] float64, cos [M]) of the M seen texels, or None.
    """
    from relight_cli.render.appearance import bilinear

    surf = texels.surfaces[k]
    eye = np.asarray(camera.center, np.float64)
    d = surf.points - eye
    dist = np.linalg.norm(d, axis=1)
    d /= np.maximum(dist, 1e-300)[:, None]
    cos = -np.sum(d * surf.normals, 1)
    hits = texels.renderer.scene.intersect(np.broadcast_to(eye, d.shape), d)
    seen = (hits.hit & (hits.mesh == texels.scene_index[k]) & (cos > 0)
            & (np.abs(hits.t - dist) < 1e-3 * np.maximum(dist, 1e-6) + 1e-4))
    cam = surf.points @ np.asarray(camera.R).T + np.asarray(camera.t)
    z = np.maximum(cam[:, 2], 1e-9)
    K = np.asarray(camera.K)
    px = K[0, 0] * cam[:, 0] / z + K[0, 1] * cam[:, 1] / z + K[0, 2]
    py = K[1, 1] * cam[:, 1] / z + K[1, 2]
    # pixel centres at integers (camera.md): pixel i covers [i − ½, i + ½)
    inside = ((px >= -0.5) & (px < camera.width - 0.5) & (py >= -0.5)
              & (py < camera.height - 0.5))
    ok = seen & inside & (cam[:, 2] > 0)
    if mask is not None and ok.any():
        ix = np.clip(np.rint(px[ok]).astype(np.int64), 0, camera.width - 1)
        iy = np.clip(np.rint(py[ok]).astype(np.int64), 0, camera.height - 1)
        ok[np.nonzero(ok)[0]] = mask[iy, ix]
    if not ok.any():
        return None
    # bilinear() samples a map at UV (texel centres at (i + ½)/W); a pixel position maps
    # to (u, v) = ((px + ½) / W, 1 − (py + ½) / H).
    uv = np.stack([(px[ok] + 0.5) / camera.width, 1 - (py[ok] + 0.5) / camera.height], 1)
    colour = bilinear(np.asarray(image, np.float64), uv)
    rows, cols = np.nonzero(surf.inside)
    return rows[ok], cols[ok], colour, cos[ok]


class Accumulator:
    """Cosine-weighted sums of what the views saw, per hand: [H, N, N, 3] and [H, N, N]."""

    def __init__(self, n_hands: int, n: int):
        self.total = np.zeros((n_hands, n, n, 3))
        self.weight = np.zeros((n_hands, n, n))

    def add(self, k: int, samples) -> None:
        if samples is None:
            return
        rr, cc, colour, cos = samples
        np.add.at(self.total[k], (rr, cc), colour * cos[:, None])
        np.add.at(self.weight[k], (rr, cc), cos)

    def mean(self, k: int, fill: bool = True) -> np.ndarray:
        """[N, N, 3] the weighted mean; texels no view saw copy their nearest seen texel
        (``fill``) or stay 0."""
        from scipy.ndimage import distance_transform_edt
        seen = self.weight[k] > 0
        mean = np.divide(self.total[k], self.weight[k][..., None],
                         out=np.zeros_like(self.total[k]), where=seen[..., None])
        if fill and seen.any() and not seen.all():
            _, (iy, ix) = distance_transform_edt(~seen, return_indices=True)
            mean = mean[iy, ix]
        return mean


def env_irradiance(texels, k: int, denv, visibility: bool = True) -> np.ndarray:
    """[N, N, 3] irradiance E(x) = Σ_m L_m Δω_m V(x, ω_m) max(0, n·ω_m) of hand k's texels
    under a discretized env map (:func:`relight_cli.envmap.discretize_env`), the lit
    directions as distant lights, visibility traced against the whole scene."""
    lit = np.nonzero(denv.lit)[0]
    n = texels.tex_res
    if len(lit) == 0:
        return np.zeros((n, n, 3))
    inputs = texels.directional_lights(k, denv.directions[lit], visibility=visibility)
    cos = np.clip(inputs.local_light[..., 2], 0, None).astype(np.float64)
    weights = denv.radiance[lit] * denv.solid_angle[lit, None]                 # [M, 3]
    e = np.einsum("mk,mc->kc", cos * inputs.visibility, weights)               # [K, 3]
    return np.transpose(texels.to_maps(k, e), (1, 2, 0))


def divide(radiance: np.ndarray, irradiance: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """T̄ = L / E per channel [N, N, 3], E clamped to ≥ ¼ of its median over ``inside``
    texels (as :func:`relight_cli.neural.linear_train.albedo_texture`: crevices the light
    barely reaches do not blow up)."""
    e = np.asarray(irradiance, np.float64)
    floor = np.array([0.25 * np.median(e[..., c][inside]) if inside.any() else 1.0
                      for c in range(e.shape[-1])])
    return radiance / np.maximum(e, np.maximum(floor, 1e-12))


def luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


def shading_map(radiance: np.ndarray, seen: np.ndarray, reference: np.ndarray,
                weight: float = 0.2, iterations: int = 300) -> np.ndarray:
    """[N, N] one-channel shading S of an unwrapped texture (URHand supp. 9): S fits the
    luminance of ``radiance`` [N, N, 3] over that of ``reference`` [3] (the images' mean
    foreground colour) on the ``seen`` texels, minimising Σ (S − Y/Y_ref)² + weight ·
    TV(S) (isotropic, smoothed), so broad shading and cast shadows go into S while sharp
    texture (below the TV's scale) stays in radiance / S.  Solved by gradient descent
    (Adam) from the data term's own values; unseen texels are filled from the nearest
    seen one before."""
    import torch
    ratio = luminance(radiance) / max(float(luminance(np.asarray(reference))), 1e-12)
    target = torch.tensor(ratio, dtype=torch.float64)
    w = torch.tensor(seen.astype(np.float64))
    s = target.clone().requires_grad_(True)
    opt = torch.optim.Adam([s], lr=0.02)
    count = max(float(w.sum()), 1.0)
    for _ in range(iterations):
        opt.zero_grad()
        dx = s[:, 1:] - s[:, :-1]
        dy = s[1:, :] - s[:-1, :]
        tv = torch.sqrt(dx[:-1, :] ** 2 + dy[:, :-1] ** 2 + 1e-6).sum()
        loss = ((s - target) ** 2 * w).sum() / count + weight * tv / count
        loss.backward()
        opt.step()
    return np.maximum(s.detach().numpy(), 1e-3)
