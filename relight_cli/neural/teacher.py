"""Rendering with a teacher: textures per light, summed (Eq. 2), looked up through a G-buffer.

One function renders every case, because they differ only in their lights:
    * a capture frame (training): its grouped or fully lit LEDs;
    * point lights near or far (RelightableHands Fig. 11–12): one pass per light with its
      own 1/r² falloff and visibility;
    * an env map: by the linearity of light transport, a sum over its directions,
      discretized exactly as ``bake-features --env-res`` (default 16×32, exact texel solid
      angles, :func:`relight_cli.envmap.discretize_env`): direction m is a distant light
      of RGB weight b_m = L_m Δω_m with its own ray-traced visibility.  Directions with zero
      radiance are skipped (they add nothing).

The texture of hand k is Σ_i b_i(x) C_i(x) [N, N, 3]; the image is the box-filtered
bilinear lookup of every hand's texture at the camera's G-buffer samples
(:func:`relight_cli.render.shading.lookup_torch` / ``resolve_torch``), the same
differentiable path training uses.  Passes are batched (``chunk`` lights per U-Net call).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from .data import assemble_inputs
from .geometry import LightInputs
from .models import pose_vector


@dataclass
class Timing:
    """Seconds per stage of a render (stderr reports; never stored in outputs)."""

    seconds: dict = field(default_factory=dict)

    def add(self, stage: str, dt: float):
        self.seconds[stage] = self.seconds.get(stage, 0.0) + dt


def _slice(li: LightInputs, sl) -> LightInputs:
    return LightInputs(li.local_light[sl], li.visibility[sl], li.falloff[sl])


def composite(textures_per_hand: list, gbuffer, background=0.0) -> torch.Tensor:
    """[H, W, 3] image from per-hand textures [3, N, N] through the G-buffer."""
    from relight_cli.render.shading import lookup_torch, resolve_torch

    total = None
    for k, tex in enumerate(textures_per_hand):
        term = lookup_torch(tex.permute(1, 2, 0), gbuffer, k)
        total = term if total is None else total + term
    return resolve_torch(total, gbuffer, background)


def forward_textures(model, inputs: torch.Tensor, weights: torch.Tensor, hand_of: torch.Tensor,
                     pose: torch.Tensor, n_hands: int, mean_texture=None,
                     return_raw: bool = False):
    """Per-hand textures Σ_i b_i C_i [3, N, N] from one batch of (light, hand) rows."""
    colour, raw = model(inputs, pose, hand_of, mean_texture, return_raw=True)
    weighted = colour * weights
    textures = [weighted[hand_of == k].sum(0) for k in range(n_hands)]
    return (textures, raw) if return_raw else textures


def render_sample(model, sample, device="cpu", mean_texture=None, return_raw: bool = False):
    """Differentiable render of a :class:`~relight_cli.neural.data.Sample` → [H, W, 3]."""
    inputs = torch.from_numpy(sample.inputs).to(device)
    weights = torch.from_numpy(sample.weights).to(device)
    hand_of = torch.from_numpy(sample.hand_of).to(device)
    pose = pose_vector(sample.poses).to(device)
    textures, raw = forward_textures(model, inputs, weights, hand_of, pose, sample.n_hands,
                                     _mean(mean_texture, sample.n_hands, device), True)
    image = composite(textures, sample.gbuffer)
    return (image, raw) if return_raw else image


def _mean(mean_texture, n_hands, device):
    if mean_texture is None:
        return None
    t = torch.as_tensor(mean_texture, dtype=torch.float32, device=device)
    if t.ndim == 3:
        t = t[None]
    return t.expand(n_hands, -1, -1, -1) if t.shape[0] == 1 else t


@torch.no_grad()
def render_lights(model, texels, gbuffer, poses, light_inputs: list, intensity: np.ndarray,
                  visibility: bool, falloff: str, device="cpu", chunk: int = 32,
                  mean_texture=None, view_eye=None, progress=None, timing: Timing | None = None,
                  background=0.0) -> torch.Tensor:
    """Render ``texels``' pose under lights given per hand as :class:`LightInputs`.

    Args:
        model: a teacher (eval mode).  texels: :class:`PoseTexels`.  gbuffer: the view.
        poses: [H, J, 3] per-hand axis-angle poses.
        light_inputs: per hand LightInputs of the same L lights.
        intensity: [L, 3] RGB weights b_i.
        visibility, falloff: the model's input settings (its config).
        chunk: lights per U-Net call.  progress: optional callable(n) per finished light
            and hand.
        view_eye: the eye for view directions (default: the G-buffer's camera centre).

    Returns:
        [H, W, 3] float32 tensor (on ``device``).
    """
    timing = timing or Timing()
    eye = gbuffer.eye if view_eye is None else view_eye
    textures = [hand_texture(model, texels, k, poses[k], light_inputs[k], intensity, visibility,
                             falloff, eye, device, chunk, mean_texture, progress, timing)
                for k in range(texels.n_hands)]
    t0 = time.perf_counter()
    image = composite(textures, gbuffer, background)
    timing.add("composite", time.perf_counter() - t0)
    return image


@torch.no_grad()
def hand_texture(model, texels, k: int, pose, light_inputs: LightInputs, intensity: np.ndarray,
                 visibility: bool, falloff: str, eye, device="cpu", chunk: int = 32,
                 mean_texture=None, progress=None, timing: Timing | None = None) -> torch.Tensor:
    """Hand k's texture Σ_i b_i C_i [3, N, N] (Eq. 2) under L lights seen from ``eye``.

    Args:
        pose: [J, 3] hand k's axis-angle pose.  light_inputs: its LightInputs of the L
            lights.  intensity: [L, 3] b_i.  mean_texture: T̄ of a GGX teacher, [1 or H,
            3, N, N] (row k of several).  Other arguments as :func:`render_lights`.
    """
    timing = timing or Timing()
    view = texels.local_view(k, eye)
    pose_row = pose_vector(np.asarray(pose)[None]).to(device)
    mean = None
    if mean_texture is not None:
        mean = _mean(mean_texture, 1, device)
        mean = mean[k:k + 1] if mean.shape[0] > 1 else mean[:1]
    texture = torch.zeros(3, texels.tex_res, texels.tex_res, device=device)
    n_lights = len(intensity)
    for start in range(0, n_lights, chunk):
        sl = slice(start, min(n_lights, start + chunk))
        t0 = time.perf_counter()
        x, w = assemble_inputs(texels, k, _slice(light_inputs, sl), view, intensity[sl],
                               visibility, falloff)
        inputs = torch.from_numpy(x).to(device)
        weights = torch.from_numpy(w).to(device)
        hand_of = torch.zeros(len(x), dtype=torch.int64, device=device)
        timing.add("inputs", time.perf_counter() - t0)
        t0 = time.perf_counter()
        texture = texture + forward_textures(model, inputs, weights, hand_of, pose_row, 1,
                                             mean)[0]
        timing.add("network", time.perf_counter() - t0)
        if progress is not None:
            progress(sl.stop - sl.start)
    return texture


def point_light_inputs(texels, positions, visibility: bool, timing: Timing | None = None):
    """Per-hand LightInputs of point lights at ``positions`` [L, 3]."""
    t0 = time.perf_counter()
    out = [texels.point_lights(k, positions, visibility=visibility) for k in range(texels.n_hands)]
    if timing is not None:
        timing.add("visibility", time.perf_counter() - t0)
    return out


def env_light_inputs(texels, denv, visibility: bool, timing: Timing | None = None):
    """(per-hand LightInputs, [M', 3] weights L_m Δω_m) of an env map's lit directions."""
    t0 = time.perf_counter()
    lit = np.nonzero(denv.lit)[0]
    directions = denv.directions[lit]
    weights = denv.radiance[lit] * denv.solid_angle[lit, None]
    out = [texels.directional_lights(k, directions, visibility=visibility)
           for k in range(texels.n_hands)]
    if timing is not None:
        timing.add("visibility", time.perf_counter() - t0)
    return out, weights
