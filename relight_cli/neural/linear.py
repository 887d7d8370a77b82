"""URHand's linear lighting model with its physical branch (Chen et al. 2024, Sec. 4, supp. 8).

Shapes: H hands, N texture size, K inside texels of a hand, C = 3 colour channels.

Physical branch (Sec. 4.1, supp. 8.2): a U-Net F_G (:class:`~relight_cli.neural.models.UNet`,
pose at the bottleneck) on the mean texture T̄ [H, 3, N, N] predicts a displacement map
δd = 3 mm · (2σ(x) − 1) ∈ (−3, 3) mm (Eq. 2: "a sigmoid followed by a scaling factor of
3 … ±3 mm"; a sigmoid times 3 alone would only push outwards, so we centre it) and a
roughness map β = σ(y).  Refined normals n̂ come from the displaced positions
(:func:`~relight_cli.neural.shading_features.refined_normals`); the features
F_pb = {C^d, C^s} (Eq. 10–15, :mod:`~relight_cli.neural.shading_features`) give the
physical texture C_pb = C^d ⊙ T̄ + C^s (Eq. 3), supervised by the images too.  F_G's
decoder upsamples bilinearly then convolves (the paper: transposed conv + bilinear).

Neural branch (Sec. 4.2, supp. 8.3): with the features' gradients stopped, the linear
light path F_l — an encoder of bias-free 3×3 convolutions with 2× average pooling
between levels (linear), and a 7-layer bias-free decoder of widths ``light_decoder``
(paper: 128 → 256, 128, 128, 64, 32, 16, 4), transposed 4×4 stride-2 convolutions for
the first ``light_levels`` layers and 3×3 convolutions after — is fused with the
non-linear branch F_nl by Eq. 5:

    F_dec^{j+1} = 1/√2 · ConvT_j(F_enc^j + F_dec^j) ⊙ F_nl^j,

F_enc^j the encoder level of F_dec^j's resolution (none beyond the encoder's levels;
F_dec^0 = 0).  F_nl is a 1×1 stem to ``light_decoder[0]`` then 7 layers of the same
widths and resolutions (with bias, LeakyReLU 0.2) on F_G's bottleneck (F_θ,id: encoder
⊕ tiled pose).  Initialization (ours; the paper gives none): F_nl's layers start at
≈ 1 (bias 1, weights × 0.1) and F_l's weights are variance preserving, so the product
of seven modulated layers starts at a usable scale.  Nothing on the light path has a bias or a nonlinearity, so the output
is exactly linear in the features.  The output's 4 channels are a gain g (3) and a bias
b (1), and (Eq. 6)

    C = g ⊙ T̄ + b · σ_T,   σ_T = 64 paper units = 64/(255π) ≈ 0.080 sr⁻¹ in ours.

Units: T̄ is radiance per unit irradiance (sr⁻¹; the capture's fully lit radiance over
its irradiance, :func:`albedo_texture`), features are irradiance, so C is radiance.
Features enter F_l divided by a fixed ``feature_scale`` (the training frames' mean
diffuse irradiance; stored in the checkpoint) and g, b come out multiplied by it: the
same linear map, at unit scale for the initialization.

Colour: one monochrome light path per colour channel.  Channel c's features (lights of
channel c's intensities) give (g⁽ᶜ⁾, b⁽ᶜ⁾) and C_c = g⁽ᶜ⁾_c T̄_c + b⁽ᶜ⁾ σ_T: linear in
every channel of the lighting, so RGB env maps are exact.  White lights (equal
channels) take one pass.

Ablations (URHand Tables 2–3, supp. 10.2): ``light_path="nonlinear"`` (LeakyReLU after
every light-path layer), ``linearity_loss`` (Eq. 17 on that model), ``light_path="mlp"``
(the holistic baseline: the lighting as a 16×32 lat-long map — point lights binned by
their direction from the hand, weight I/r² averaged over its texels; env directions
L Δω — through one bias-free linear layer to the decoder's bottleneck, no encoder skips,
no spatial features, no residual start), ``features="phong"``,
``specular=False``, ``visibility=False``, ``refiner=False`` (coarse normals, δd ≡ 0).
``residual=True`` is ours (not the paper's): g and b start from the physical branch's
own C^d and C^s/σ_T (still linear in the features), so a short CPU run starts from the
physically based render instead of from zero.

Eq. 9 (L_reg = Σ_j ‖F_l-enc^j‖₁): the text says "intermediate features from all layers in
the linear branch" but the equation writes the encoder's maps F_l-enc, and the authors'
code (facebookresearch/goliath, URHand) penalizes only the maps its encoder adds into the
decoder; we follow the equation and the code (``reg_layers="encoder"``).  Penalizing the
modulated decoder maps too (``reg_layers="all"``) is minimized by zeroing F_l's output: the
model then renders its physical branch only.  λ_reg is the paper's number in its 8-bit
units, converted in the loss (:func:`~relight_cli.neural.linear_train.reg_weight`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from relight_cli.neural.model_config import LinearConfig   # re-exported: the config's home

from .config import PAPER_UNIT
from .models import UNet, pose_vector
from .shading_features import map_to_texels, refined_normals, shading_features, texels_to_map

HOLISTIC_RES = (16, 32)


PRESETS = {
    "tiny": {},
    # A workstation CPU: the 64² maps, 6000 iterations, lr 2e-3 dropping to 2e-4 at 4500
    # (the paper's multistep drop at the same fraction).  Measured (one core of the
    # shared 2-core machine, 12.5 min) on the study's converged capture, held-out poses,
    # 16 samples, seed 0: 33.63 dB against a 33.12 dB point-sampled ceiling (gap −0.51
    # dB); fully lit 33.29 (gap −0.62); env maps 31.73 (gap 2.48).
    # benchmarks/bench_presets.py re-measures it.
    "cpu": {"tex_res": 64, "iters": 6000, "lr": 2e-3, "lr_final": 2e-4, "lr_drop": 4500,
            "val_every": 1000, "val_samples": 16, "save_every": 1000},
    # supp. 8.2–8.3 widths, Sec. 4.3 optimization (2M iterations, batch 24 over 8 GPUs: 3 a
    # rank; lr 1e-4 → 3e-5), σ_T 64, λ 1 / 0.01; the 1024² maps of the paper.
    "paper": {"tex_res": 1024, "encoder": (64,) * 6, "decoder": (64,) * 6,
              "pose_channels": (16, 64), "light_decoder": (128, 256, 128, 128, 64, 32, 16, 4),
              "light_levels": 6, "residual": False, "lambda_gan": 0.01, "gan_width": 64, "iters": 2_000_000, "batch": 3, "lr": 1e-4,
              "lr_final": 3e-5, "lr_drop": 1_500_000, "val_every": 10000, "val_samples": 64, "save_every": 10000},
}


def resolve_config(preset: str = "tiny", config_file: str | None = None,
                   overrides: dict | None = None) -> LinearConfig:
    """Preset, then the JSON object of ``config_file``, then ``overrides`` (flags)."""
    from .config import resolve_config as resolve
    values = {k: v for k, v in (overrides or {}).items() if v is not None}
    return resolve(preset, config_file, values, PRESETS, LinearConfig)


# ---------------------------------------------------------------- networks


def _up(cin: int, cout: int, upsample: bool, bias: bool) -> nn.Module:
    if upsample:
        return nn.ConvTranspose2d(cin, cout, 4, stride=2, padding=1, bias=bias)
    return nn.Conv2d(cin, cout, 3, padding=1, bias=bias)


class LightPath(nn.Module):
    """F_l: bias-free encoder and 7-layer decoder fused with F_nl by Eq. 5.

    ``nonlinear=True`` puts LeakyReLU(0.2) after every layer (Table 2's ablation).
    """

    def __init__(self, cin: int, widths, levels: int, nonlinear: bool = False,
                 holistic: tuple | None = None):
        super().__init__()
        self.levels = levels
        self.nonlinear = nonlinear
        self.holistic = holistic
        # encoder level e at N/2^e outputs the width of decoder input levels − e
        self.enc = nn.ModuleList()
        prev = cin
        for e in range(levels + 1 if holistic is None else 0):
            self.enc.append(nn.Conv2d(prev, widths[levels - e], 3, padding=1, bias=False))
            prev = widths[levels - e]
        if holistic is not None:
            # supp. 10.2: [H·W] lighting → [w0, s, s] by one bias-free linear layer
            inputs, size = holistic
            self.mlp = nn.Linear(inputs, widths[0] * size * size, bias=False)
            nn.init.normal_(self.mlp.weight, 0.0, 1.0 / math.sqrt(inputs))
        self.dec = nn.ModuleList(_up(widths[j], widths[j + 1], j < levels, False)
                                 for j in range(7))
        # variance-preserving initialization of a linear chain: each output sums cin·9
        # (3×3 conv) or cin·4 (4×4 stride-2 transposed conv) inputs
        for layer in [*self.enc, *self.dec]:
            taps = 4 if isinstance(layer, nn.ConvTranspose2d) else 9
            cin = layer.in_channels
            nn.init.normal_(layer.weight, 0.0, 1.0 / math.sqrt(cin * taps))

    def _act(self, x):
        return F.leaky_relu(x, 0.2) if self.nonlinear else x

    def forward(self, features: torch.Tensor, modulation: list, return_intermediate=False):
        """features [B, cin, N, N], modulation: 7 maps [B, widths[j+1], ·, ·] → [B, 4, N, N]
        (and the intermediate maps for Eq. 9: ``{"encoder": F_l-enc^j of every level (the
        ``mlp`` path: its one linear layer's map), "decoder": the first 6 F_l-dec^j}``)."""
        skips = []
        h = features
        if self.holistic is not None:
            size = self.holistic[1]
            skips = [None] * self.levels + [self.mlp(h).reshape(len(h), -1, size, size)]
        for e, conv in enumerate(self.enc):
            if e:
                h = F.avg_pool2d(h, 2)
            h = self._act(conv(h))
            skips.append(h)
        inter = {"encoder": [x for x in skips if x is not None], "decoder": []}
        h = skips[-1]                                   # F_enc^0 + F_dec^0 (F_dec^0 = 0)
        for j, layer in enumerate(self.dec):
            h = self._act(layer(h) * modulation[j]) / math.sqrt(2)
            nxt = self.levels - (j + 1)
            if j < 6:
                inter["decoder"].append(h)
                if nxt >= 0 and skips[nxt] is not None:
                    h = h + skips[nxt]                  # F_enc^{j+1} + F_dec^{j+1}
        return (h, inter) if return_intermediate else h


class NonLinearBranch(nn.Module):
    """F_nl: the modulation maps of Eq. 5 from F_θ,id (stem + 7 layers, LeakyReLU)."""

    def __init__(self, cin: int, widths, levels: int):
        super().__init__()
        self.stem = nn.Conv2d(cin, widths[0], 1)
        self.layers = nn.ModuleList(_up(widths[j], widths[j + 1], j < levels, True)
                                    for j in range(7))
        self.levels = levels
        # modulations start near 1 (bias 1, small weights): the product of seven Eq. 5
        # factors neither vanishes nor explodes at initialization
        for layer in self.layers:
            layer.weight.data.mul_(0.1)
            nn.init.ones_(layer.bias)

    def forward(self, joint: torch.Tensor, tex_res: int) -> list:
        size = tex_res >> self.levels
        h = F.interpolate(joint, size=(size, size), mode="bilinear", align_corners=False)
        h = F.leaky_relu(self.stem(h), 0.2)
        out = []
        for layer in self.layers:
            h = F.leaky_relu(layer(h), 0.2)
            out.append(h)
        return out


class URHandModel(nn.Module):
    """F_G (physical branch) + F_nl + F_l (neural branch); see the module docstring."""

    kind = "linear"

    def __init__(self, config: LinearConfig, pose_dim: int):
        super().__init__()
        self.config = config
        self.geometry = UNet(3, 2, config.encoder, config.decoder, pose_dim, config.pose_channels)
        joint = config.encoder[-1] + config.pose_channels[1]
        self.nonlinear = NonLinearBranch(joint, config.light_decoder, config.light_levels)
        holistic = None
        if config.light_path == "mlp":
            holistic = (HOLISTIC_RES[0] * HOLISTIC_RES[1], config.tex_res >> config.light_levels)
        self.light = LightPath(2, config.light_decoder, config.light_levels,
                               config.light_path == "nonlinear", holistic)
        self.sigma_t = config.sigma_t * PAPER_UNIT
        self.register_buffer("feature_scale", torch.ones(()))

    # -- physical branch

    def physical(self, mean_texture: torch.Tensor, pose: torch.Tensor):
        """(δd [H, N, N] metres, β [H, N, N], F_θ,id) from T̄ [H, 3, N, N], pose [H, P]."""
        hands = torch.arange(mean_texture.shape[0], device=mean_texture.device)
        raw, joint = self.geometry(mean_texture, pose, hands, return_bottleneck=True)
        scale = self.config.displacement_mm * 1e-3
        disp = scale * (2 * torch.sigmoid(raw[:, 0]) - 1)
        if not self.config.refiner:
            disp = torch.zeros_like(disp)
        return disp, torch.sigmoid(raw[:, 1]), joint

    # -- neural branch

    def neural(self, feature_maps: torch.Tensor, mean_texture: torch.Tensor, modulation: list,
               return_intermediate: bool = False, holistic: torch.Tensor | None = None):
        """C [3, N, N] of one hand from its per-channel features [C', 2, N, N] (C' = 1 for
        white light, else 3), T̄ [3, N, N] and its 7 modulation maps [1, w, ·, ·] (Eq. 6);
        the ``mlp`` light path takes its per-channel lat-long ``holistic`` [C', 512]
        lighting instead of the features."""
        scale = self.feature_scale
        mod = [m.expand(feature_maps.shape[0], -1, -1, -1) for m in modulation]
        lighting = feature_maps if holistic is None else holistic
        out, inter = self.light(lighting / scale, mod, return_intermediate=True)
        out = out * scale                                                  # [C', 4, N, N]
        gain, bias = out[:, :3], out[:, 3]
        if self.config.residual and holistic is None:
            gain = gain + feature_maps[:, 0:1]
            bias = bias + feature_maps[:, 1] / self.sigma_t
        if feature_maps.shape[0] == 1:
            colour = gain[0] * mean_texture + bias * self.sigma_t
        else:
            idx = torch.arange(3, device=gain.device)
            colour = gain[idx, idx] * mean_texture + bias * self.sigma_t
        return (colour, inter) if return_intermediate else colour


def _channels(intensity) -> np.ndarray:
    """[L, 3] → which colour channels need their own light-path pass ([0] if all equal)."""
    i = np.asarray(intensity, np.float64)
    return np.array([0]) if np.array_equal(i[:, 0], i[:, 1]) and np.array_equal(
        i[:, 0], i[:, 2]) else np.arange(3)


@dataclass
class Textures:
    """What one forward pass of :func:`render_textures` gives, per hand."""

    neural: list           # [3, N, N] C (Eq. 6)
    physical: list         # [3, N, N] C_pb (Eq. 3)
    features: list         # [C', 2, N, N] F_pb (gradients stopped)
    intermediate: list     # per hand: the light path's maps {"encoder", "decoder"} (Eq. 9)


def render_textures(model: URHandModel, texels, views: list, light_inputs: list, intensity,
                    poses, mean_texture: torch.Tensor, physical: bool = True) -> Textures:
    """Per-hand textures of a posed scene under one set of lights.

    Args:
        model: :class:`URHandModel`.  texels: :class:`PoseTexels` of the pose.
        views: per hand [K, 3] local view directions.
        light_inputs: per hand :class:`LightInputs` of the same L lights.
        intensity: [L, 3] RGB I_i (point: W sr⁻¹; env direction: L Δω).
        poses: [H, J, 3] axis-angle poses.  mean_texture: T̄ [1 or H, 3, N, N] (sr⁻¹).
        physical: also build C_pb (training; inference needs only C).
    """
    cfg = model.config
    device = mean_texture.device
    n_hands = texels.n_hands
    pose = pose_vector(poses).to(device)
    tex = mean_texture.expand(n_hands, -1, -1, -1) if mean_texture.shape[0] == 1 else mean_texture
    disp, rough, joint = model.physical(tex, pose)
    channels = _channels(intensity)
    modulations = model.nonlinear(joint, cfg.tex_res)
    out = Textures([], [], [], [])
    for k in range(n_hands):
        surf = texels.surfaces[k]
        normal = refined_normals(disp[k], texels.uv_derivatives[k], surf)
        beta = map_to_texels(rough[k][None], surf.inside)[:, 0]
        feats = shading_features(normal, views[k], light_inputs[k], intensity, beta,
                                 cfg.features, cfg.specular, cfg.shininess, cfg.fresnel)
        feats = feats[torch.from_numpy(channels).to(device)]                   # [C', 2, K]
        maps = texels_to_map(feats.reshape(-1, feats.shape[-1]).T, surf)
        maps = maps.reshape(len(channels), 2, *maps.shape[-2:])                # [C', 2, N, N]
        if physical:
            # Eq. 3 with the live features (gradients reach n̂ and β)
            pb = maps[:, 0] * tex[k] + maps[:, 1]
            out.physical.append(pb)
        stopped = maps.detach()
        modulation = [m[k:k + 1] for m in modulations]
        holistic = None
        if cfg.light_path == "mlp":
            holistic = holistic_lighting(texels.frames[k], light_inputs[k], intensity)
            holistic = torch.from_numpy(holistic[channels]).to(device)
        colour, inter = model.neural(stopped, tex[k], modulation, return_intermediate=True,
                                     holistic=holistic)
        out.neural.append(colour)
        out.features.append(stopped)
        out.intermediate.append(inter)
    return out


def holistic_lighting(frames: np.ndarray, lights, intensity) -> np.ndarray:
    """[3, 16·32] float32 lat-long lighting of the ``mlp`` light path (supp. 10.2).

    Light i lands in the pixel of its mean world direction over the hand's texels
    (R_kᵀ times the local direction; a distant light's own direction) with weight
    I_i · mean_k(1/r²) (an env direction: L Δω), in OpenEXR's lat-long convention
    (longitude atan2(x, z) from +π at the left edge, latitude +π/2 at the top row).
    Linear in the intensities.
    """
    h, w = HOLISTIC_RES
    world = np.einsum("kji,lkj->lki", frames, lights.local_light).mean(1)      # [L, 3]
    world /= np.maximum(np.linalg.norm(world, axis=1, keepdims=True), 1e-12)
    lon = np.arctan2(world[:, 0], world[:, 2])
    lat = np.arcsin(np.clip(world[:, 1], -1, 1))
    col = np.clip(((np.pi - lon) / (2 * np.pi) * w).astype(int), 0, w - 1)
    row = np.clip(((np.pi / 2 - lat) / np.pi * h).astype(int), 0, h - 1)
    weight = np.asarray(intensity, np.float64) * lights.falloff.mean(1)[:, None]  # [L, 3]
    out = np.zeros((3, h * w))
    for c in range(3):
        np.add.at(out[c], row * w + col, weight[:, c])
    return out.astype(np.float32)


