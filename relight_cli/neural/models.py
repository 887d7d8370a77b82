"""The teacher networks: pose encoder J(θ), OLAT U-Net (App. A.1, Eq. 10), GGX baseline (App. B).

Shapes: B = lights × hands in one pass, N = texture size, P = pose dimension.

Pose encoder (App. A.1): the hand pose θ — the local axis-angle rotations of every
joint but the wrist (the global rotation changes no texel frame, so it carries no
appearance) — is tiled over the bottleneck's grid and passed through a 2-layer CNN
(widths 16, 64).  RelightableHands tiles θ ∈ R²⁵; our skeleton is the 25-joint WebXR
one, θ ∈ R^{24·3}.

U-Net (App. A.1 with S = 1): encoder convs (7 → 64 → 64 → 64), each level after the
first at half the previous resolution (bilinear); the pose features are concatenated
at the bottleneck (64 + 64 = 128); decoder convs (128, 128, 128) back up (bilinear),
each level concatenating the encoder's skip of the same resolution, to 4 channels:
raw texture T (3) and shadow logit S (1).  The paper lists widths, not the number of
resolution levels: we read "4-layer" as the input plus three levels, so a 1024²
texture has its bottleneck at 256².  3×3 convolutions, LeakyReLU(0.2) between.

Eq. 10:  C_i = σ(S_i) · (ReLU(λ_s T_i) + λ_b), with λ_s, λ_b converted from the paper's
8-bit units (:data:`relight_cli.neural.config.PAPER_UNIT`); L_neg (Eq. 6) on λ_s T_i.  The
authors' public code places the bias inside the ReLU, C_i = σ(S_i)·ReLU(λ_s T_i + λ_b),
with L_neg on λ_s T_i + λ_b at a constant weight (``head: code``).  As printed, λ_b is a
floor under every unshadowed texel (σ(S)·λ_b); inside the ReLU it is only a starting
offset, so a dark texel can reach 0 without the shadow gate.  Measured (tiny widths, held-out
PSNR, medium right-hand capture of ``benchmarks/studies/scales.json`` at aa 1, 32²,
1000 iterations, seed 0, 2 shared CPU cores): printed 24.09 dB, code (with a constant
L_neg weight) 23.91 dB, against a 24.26 dB ceiling; on the test capture after 150
iterations 22.26 vs 22.29 dB (a tie) and after 300 at lr 3e-3 23.23 vs 22.62 dB.  The
printed head is never worse by more than the spread, so it stays the default.
Per-texel (untied) decoder biases, as the authors' code builds its decoders
(``untied_bias``), measured +0.55 dB on the same 32² run (24.64 dB, 0.38 dB above the
point-sampled ceiling: a texture fitted through the bilinear lookup can beat point
samples); they are off by default because at the paper's 1024² they would add 128·1024²
parameters per decoder level.  C_i is radiance per unit
irradiance (sr⁻¹).  A frame's texture is Eq. 2, Σ_i b_i C_i, where our b_i is the light's
RGB intensity times its 1/r² falloff at the texel (``falloff="analytic"``), or the
intensity alone (``"none"``, the paper's form).

Input (App. A.1): per texel and light, the local light direction l, the local view
direction v and the visibility: 7 channels (``inputs: paper``, every preset's).  ``inputs:
half`` (ours, an option) appends the local half vector h = (l + v)/‖l + v‖: a microfacet
lobe is a function of h_z = n·h, which the paper's input makes the U-Net build from l and
v through 3×3 convolutions.  Why it was tried: per image, the paper-input teacher's
held-out error sits in a few images 10–16 dB below the ceiling (point-light highlights
and bright rims) while most are within 1 dB of it.  Measured (converged capture, right
hand, ``cpu`` preset, five seeds, benchmarks/results/converged/teacher_inputs.md): on
every held-out sample, 30.19 against 29.91 dB (+0.29 ± 0.14 dB, higher on every seed;
gap to the ceiling 1.76 against 2.05 dB), SSIM 0.946 against 0.939; a tie under the
fully lit frames (+0.19 ± 0.13) and the held-out env maps (+0.11 ± 0.36), the lighting a
student distills, at 7 % more time per run.  So the paper's input stays the default.
``inputs: shading`` (ours) appends one light's share of the student's
physics-inspired features (Sec. 4.2, Eq. 8–9): V·max(n·l, 0) and that times the Phong lobes
max(r·l, 0)^α, α = 16, 32, 64, r the mirrored view (Eq. 9's lobe with the cosine added,
:func:`teacher_inputs`); the U-Net then
modulates shading it is given instead of building a lobe and a shadow-masked cosine from
l, v and V.  Measured (same capture and preset, three seeds, 2-core AMD EPYC,
benchmarks/results/converged/teacher_shading/): on every held-out sample 30.80 ± 0.19
against 29.96 ± 0.01 dB (+0.85 ± 0.20 dB, better; gap 2.00 → 1.15 dB), under the fully
lit frames +0.68 ± 0.14 dB (better), on the training poses gap 0.46 → 0.03 dB, and a tie
under the held-out env maps (+0.00 ± 0.22 dB).  ``pose: none`` (an ablation: zeros into
the pose encoder) ties with θ on every split (−0.12 ± 0.21 dB held out): the teacher's
held-out gap is not a pose code overfitted to the 48 training poses.  ``view: none`` (an
ablation) zeros the view direction (and so the Phong lobes): a teacher blind to the camera.
Measured with the shading input (two seeds, benchmarks/results/converged/teacher_noview/):
−1.89 ± 0.22 dB on every held-out sample (worse), a tie under the held-out env maps
(−0.68 ± 0.44 dB); the camera-dependent part of its env-map error stays
(teacher_directions_noview/), so the view input is kept.

GGX baseline (App. B, Eq. 12): the same U-Net twice — a shadow U-Net on (local light
direction, visibility) → S, and a material U-Net on the capture's mean texture T̄ →
albedo (3), roughness (1), tangent-space normal (3) — then
C_i = σ(S_i) · (A/π · max(n·l, 0) + f_GGX(n, v, l, ρ)·max(n·l, 0)), the lobe of
:mod:`relight_cli.brdf` (F0 0.04).  The paper's separate normal/roughness decoders
share one material U-Net here (same inputs, same architecture; one pass instead of
three).  The paper gives no range for ρ; ours is ``GGX_MIN_ROUGHNESS`` + (1 −
``GGX_MIN_ROUGHNESS``)·σ(y): a plain σ(y) drifted to ρ ≈ 1e-16 on texels of the
converged-scale study (issue 21's GGX row, seed 0, step 466), where the lobe's peak
(1/(π ρ⁴)) and its gradients overflow float32 and training diverged.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from .config import PAPER_UNIT, TeacherConfig

#: the GGX teacher's roughness floor: Filament's fp32 ``MIN_PERCEPTUAL_ROUGHNESS``
#: (α² ≥ 4.1e-6, a peak D ≤ 7.7e4 sr⁻¹ that float32 and its gradients hold).
GGX_MIN_ROUGHNESS = 0.045

N_INPUT = 7          # local light dir 3, local view dir 3, visibility 1
#: the Phong exponents of ``inputs: shading``: the student's specular features' (Eq. 9)
SHADING_EXPONENTS = (16, 32, 64)
#: input channels of the OLAT U-Net per ``TeacherConfig.inputs``
N_INPUTS = {"paper": N_INPUT, "half": N_INPUT + 3, "shading": N_INPUT + 1 + len(SHADING_EXPONENTS)}


def teacher_inputs(inputs: torch.Tensor, kind: str) -> torch.Tensor:
    """The OLAT U-Net's input from the assembled [B, 7, N, N] (light l, view v, visibility
    V, in each texel's tangent frame where the coarse normal is +z): as is (``paper``);
    with the local half vector appended (``half``); or with one light's share of the
    student's shading features appended (``shading``): V·max(l_z, 0) and
    V·max(l_z, 0)·max(r·l, 0)^α for α in :data:`SHADING_EXPONENTS`, r = (−v_x, −v_y, v_z)
    the mirrored view: one light's term of Eq. 8 (diffuse) and of Eq. 9 (Phong), each in
    [0, 1].  Departure: Eq. 9 has no cosine; ours multiplies the lobes by max(n·l, 0) so
    that no lobe lights a texel facing away from the light.
    All are zero outside the UV charts, where l and v are."""
    if kind == "paper":
        return inputs
    light, view, vis = inputs[:, 0:3], inputs[:, 3:6], inputs[:, 6:7]
    if kind == "half":
        return torch.cat([inputs, F.normalize(light + view, dim=1, eps=1e-8)], 1)
    cos = vis * torch.clamp(light[:, 2:3], min=0)
    mirror = (view[:, 2:3] * light[:, 2:3] - view[:, 0:1] * light[:, 0:1]
              - view[:, 1:2] * light[:, 1:2]).clamp(0, 1)
    lobes = [cos * mirror ** a for a in SHADING_EXPONENTS]
    return torch.cat([inputs, cos, *lobes], 1)


def seen_pose(pose: torch.Tensor, kind: str) -> torch.Tensor:
    """The pose features a teacher sees: θ (``joints``, App. A.1) or zeros (``none``:
    the pose encoder then adds the same learned features for every pose, and the
    pose reaches the texture only through the per-texel inputs)."""
    return pose if kind == "joints" else torch.zeros_like(pose)


def pose_vector(poses) -> torch.Tensor:
    """[H, (J−1)·3] float32 pose features of H hands from their [H, J, 3] axis-angle poses."""
    p = torch.as_tensor(poses, dtype=torch.float32)
    return p[:, 1:].reshape(p.shape[0], -1)


def _conv(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, padding=1)


def _resize(x: torch.Tensor, size: int) -> torch.Tensor:
    return F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False)


def _bias_like(bias: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """A per-texel bias [C, n, n] in ``h``'s memory layout ([1, C, n, n], NHWC when ``h``
    is), so that ``h + bias`` stays in it: adding the plain [C, n, n] bias to an NHWC
    ``h`` gives an NCHW sum, twice as slow, that the next convolution copies back to
    NHWC.  The sum's values are the same either way (one addition per element)."""
    if h.dim() == 4 and not h.is_contiguous() \
            and h.is_contiguous(memory_format=torch.channels_last):
        return bias.unsqueeze(0).contiguous(memory_format=torch.channels_last)
    return bias


class _LayoutGrad(torch.autograd.Function):
    """The identity whose backward hands on its gradient NHWC-contiguous (it is applied
    to NHWC inputs only, :func:`_cat_channels`).

    A channel concatenation's gradient reaches each input as a channel slice of the
    output's: in NHWC a strided view that is neither NCHW- nor NHWC-contiguous, where the
    bilinear resize's backward takes a generic path (measured on one core: 4.3 ms for the
    ``cpu`` teacher's [4, 32, 64, 64] decoder resize instead of 0.5 ms).  One copy into
    NHWC avoids it; the values are unchanged."""

    @staticmethod
    def forward(ctx, x):
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):
        return grad.contiguous(memory_format=torch.channels_last)


def _cat_channels(tensors: list) -> torch.Tensor:
    """``torch.cat(tensors, 1)``; for NHWC inputs that need gradients, each gets its
    gradient back NHWC-contiguous (:class:`_LayoutGrad`)."""
    if tensors[0].dim() == 4 and torch.is_grad_enabled() and not tensors[0].is_contiguous() \
            and tensors[0].is_contiguous(memory_format=torch.channels_last):
        tensors = [_LayoutGrad.apply(t) if t.requires_grad else t for t in tensors]
    return torch.cat(tensors, 1)


class PoseEncoder(nn.Module):
    """J(θ): tiled pose → conv (16) → LeakyReLU → conv (64), on the bottleneck grid."""

    def __init__(self, pose_dim: int, channels=(16, 64)):
        super().__init__()
        self.conv1 = _conv(pose_dim, channels[0])
        self.conv2 = _conv(channels[0], channels[1])

    def forward(self, pose: torch.Tensor, size: int) -> torch.Tensor:
        """pose [H, P] → [H, C, size, size]."""
        tiled = pose[:, :, None, None].expand(-1, -1, size, size)
        return self.conv2(F.leaky_relu(self.conv1(tiled), 0.2))


class UNet(nn.Module):
    """The teacher's U-Net with the pose at its bottleneck.

    Args:
        cin: input channels.  cout: output channels.
        encoder: widths per level (level i > 0 at N / 2^i).
        decoder: widths per level, bottleneck first.
        pose_dim, pose_channels: the pose encoder.
        size: N, needed only with ``untied_bias``.
        untied_bias: the decoder convolutions and the head get one bias per texel and
            channel ([C, n, n] at their resolution) instead of one per channel, as the
            authors' public code builds its decoders: a texel-aligned texture can then
            hold spatial detail that no input carries.
    """

    def __init__(self, cin: int, cout: int, encoder, decoder, pose_dim: int, pose_channels,
                 size: int = 0, untied_bias: bool = False):
        super().__init__()
        self.enc = nn.ModuleList()
        prev = cin
        for width in encoder:
            self.enc.append(_conv(prev, width))
            prev = width
        self.pose = PoseEncoder(pose_dim, pose_channels)
        self.dec = nn.ModuleList()
        prev = encoder[-1] + pose_channels[1]
        levels = len(encoder)
        for i, width in enumerate(decoder):
            self.dec.append(_conv(prev, width))
            # the next level up concatenates the encoder skip of its resolution
            skip = encoder[levels - 2 - i] if i < levels - 1 else 0
            prev = width + skip
        self.head = nn.Conv2d(prev, cout, 3, padding=1)
        self.levels = levels
        self.untied = None
        if untied_bias:
            # decoder layer i runs at the bottleneck's resolution for i = 0, then each
            # following one at the level above; the head at N
            sizes = [size >> max(levels - 1 - i, 0) for i in range(len(decoder))] + [size]
            convs = list(self.dec) + [self.head]
            self.untied = nn.ParameterList()
            for conv, n in zip(convs, sizes):
                conv.bias = None
                self.untied.append(nn.Parameter(torch.zeros(conv.out_channels, n, n)))

    def forward(self, x: torch.Tensor, pose: torch.Tensor, hand_of: torch.Tensor,
                return_bottleneck: bool = False):
        """x [B, cin, N, N], pose [H, P], hand_of [B] int64 (which pose row) → [B, cout, N, N];
        with ``return_bottleneck`` also the bottleneck (encoder ⊕ pose features, URHand's
        joint feature F_θ,id) [B, encoder[-1] + pose_channels[1], s, s]."""
        n = x.shape[-1]
        skips = []
        h = x
        for i, conv in enumerate(self.enc):
            if i:
                h = _resize(h, n >> i)
            h = F.leaky_relu(conv(h), 0.2)
            skips.append(h)
        size = h.shape[-1]
        joint = self.pose(pose, size)[hand_of]                                 # [B, C, s, s]
        h = bottleneck = torch.cat([h, joint], 1)
        for i, conv in enumerate(self.dec):
            h = conv(h)
            if self.untied is not None:
                h = h + _bias_like(self.untied[i], h)
            h = F.leaky_relu(h, 0.2)
            level = self.levels - 2 - i
            if level >= 0:
                h = _resize(h, n >> level)
                h = _cat_channels([h, skips[level]])
        out = self.head(h)
        if self.untied is not None:
            out = out + _bias_like(self.untied[-1], out)
        return (out, bottleneck) if return_bottleneck else out


class OLATTeacher(nn.Module):
    """RelightableHands' OLAT teacher on a mesh (App. A.1, Eq. 10; URHand supp. 10.1 Eq. 16)."""

    kind = "olat"

    def __init__(self, config: TeacherConfig, pose_dim: int):
        super().__init__()
        self.config = config
        self.inputs = getattr(config, "inputs", "paper")
        self.net = UNet(N_INPUTS[self.inputs], 4, config.encoder, config.decoder, pose_dim,
                        config.pose_channels, config.tex_res,
                        getattr(config, "untied_bias", False))
        self.lambda_s = config.lambda_s * PAPER_UNIT
        self.lambda_b = config.lambda_b * PAPER_UNIT
        self.head = getattr(config, "head", "printed")
        self.pose_input = getattr(config, "pose", "joints")
        self.view_input = getattr(config, "view", "direction")

    def forward(self, inputs: torch.Tensor, pose: torch.Tensor, hand_of: torch.Tensor,
                mean_texture=None, return_raw: bool = False):
        """Per-light textures C_i [B, 3, N, N] (sr⁻¹) from inputs [B, 7, N, N] (Eq. 10);
        with ``return_raw`` also the pre-ReLU λ_s T_i [B, 3, N, N] (for L_neg)."""
        pose = seen_pose(pose, self.pose_input)
        if self.view_input == "none":
            inputs = torch.cat([inputs[:, :3], torch.zeros_like(inputs[:, 3:6]),
                                inputs[:, 6:]], 1)
        raw = self.net(teacher_inputs(inputs, self.inputs), pose, hand_of)
        scaled, shadow = self.lambda_s * raw[:, :3], raw[:, 3:4]
        if self.head == "code":
            scaled = scaled + self.lambda_b
            colour = torch.sigmoid(shadow) * F.relu(scaled)
        else:
            colour = torch.sigmoid(shadow) * (F.relu(scaled) + self.lambda_b)
        return (colour, scaled) if return_raw else colour


class GGXTeacher(nn.Module):
    """The physically based baseline of RelightableHands App. B (Eq. 12)."""

    kind = "ggx"

    def __init__(self, config: TeacherConfig, pose_dim: int):
        super().__init__()
        self.config = config
        self.shadow_net = UNet(4, 1, config.encoder, config.decoder, pose_dim, config.pose_channels)
        self.material_net = UNet(3, 7, config.encoder, config.decoder, pose_dim,
                                 config.pose_channels)

    def materials(self, mean_texture: torch.Tensor, pose: torch.Tensor):
        """(albedo [H, 3, N, N] ∈ (0, 1), roughness [H, 1, N, N] ∈
        (``GGX_MIN_ROUGHNESS``, 1), tangent-space unit normal [H, 3, N, N] with n_z > 0)
        from T̄ [H, 3, N, N]."""
        hands = torch.arange(mean_texture.shape[0])
        raw = self.material_net(mean_texture, pose, hands)
        albedo = torch.sigmoid(raw[:, :3])
        roughness = GGX_MIN_ROUGHNESS + (1 - GGX_MIN_ROUGHNESS) * torch.sigmoid(raw[:, 3:4])
        # tangent-space normal around +z (the interpolated normal): small tilts at init
        tilt = torch.tanh(raw[:, 4:6])
        normal = torch.cat([tilt, torch.ones_like(tilt[:, :1])], 1)
        return albedo, roughness, F.normalize(normal, dim=1)

    def forward(self, inputs: torch.Tensor, pose: torch.Tensor, hand_of: torch.Tensor,
                mean_texture=None, return_raw: bool = False):
        """Per-light textures C_i [B, 3, N, N] (Eq. 12); ``return_raw`` adds None (no
        pre-activation can go negative here: L_neg does not apply)."""
        from relight_cli.brdf import URHAND_SHADOWING, ggx_cosine_torch

        pose = seen_pose(pose, getattr(self.config, "pose", "joints"))
        light, view, vis = inputs[:, 0:3], inputs[:, 3:6], inputs[:, 6:7]
        shadow = self.shadow_net(torch.cat([light, vis], 1), pose, hand_of)
        albedo, rough, normal = self.materials(mean_texture, pose)
        albedo, rough, normal = albedo[hand_of], rough[hand_of], normal[hand_of]
        cos = torch.clamp((normal * light).sum(1, keepdim=True), min=0)
        spec = ggx_cosine_torch(normal.permute(0, 2, 3, 1), view.permute(0, 2, 3, 1),
                                light.permute(0, 2, 3, 1), rough[:, 0],
                                shadowing=URHAND_SHADOWING)[:, None]
        colour = torch.sigmoid(shadow) * (albedo / math.pi * cos + spec)
        return (colour, None) if return_raw else colour


def build_model(config: TeacherConfig, pose_dim: int) -> nn.Module:
    return (OLATTeacher if config.model == "olat" else GGXTeacher)(config, pose_dim)
