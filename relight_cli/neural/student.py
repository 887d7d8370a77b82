"""RelightableHands' student (App. A.2, Eq. 11) and the DRAM bottleneck baseline (App. A.3).

Student: input = bake-features' texel maps of the pose under the env map — diffuse (3)
and Phong α = 16, 32, 64 (9), Eq. 8–9, visibility-aware — concatenated with the joint
features J_s(θ) (the teacher's pose encoder, widths 16, 64, on the feature grid) =
76 channels at 128²; decoder: an 8-layer CNN (76 → 256 → 256 → 128 → 128 → 64 → 64 →
32 → 3), 3×3 convs, LeakyReLU(0.2) between; head Eq. 11: C = ReLU(λ_s T) + λ_b (no
shadow map: shadows are in the features).  Departure: the student has no shadow gate
σ(S), so a positive λ_b is a floor under every texel's radiance — in our units
(radiance over the env's mean radiance, see :mod:`relight_cli.neural.distill`) the
paper's 100 is 0.125, brighter than a shadow under a sunny sky.  Our default is λ_b = 0
with the head's bias initialized to λ_b,paper / λ_s, so training starts from the
paper's mid-grey yet can reach black; ``lambda_b: 100`` in the config is the paper's
form.  ``--no-specular`` drops the Phong maps
(3 + 64 = 67 channels).

DRAM (Bi et al. 2021) as RelightableHands adapted it: the 16×32 env map rotated into
the wrist's frame, flattened (1536) → 2-layer MLP → a 512-d light code; the pose θ in
place of DRAM's expression code.  DRAM's hypernetwork generates the decoder's conv
weights; we generate per-channel scale and shift (FiLM) of every decoder layer from
[code, θ] instead: the same information enters through the same bottleneck (the claim
under test is the bottleneck, not the weight parameterization), while generating full
256×256×3×3 kernels per frame would make the baseline ~30× larger than the student
it is compared with.  The decoder's spatial input is J_s(θ) alone — DRAM has no
texel-aligned lighting features.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from .config import PAPER_UNIT
from .models import PoseEncoder


#: Eq. 11's λ_b in the paper's units, used as the starting grey when λ_b = 0.
PAPER_LAMBDA_B = 100.0


class Eq11Head(nn.Module):
    """Eq. 11: a 3×3 conv to T, then C = ReLU(λ_s T) + λ_b (paper units × PAPER_UNIT).
    With λ_b = 0 the conv's bias starts at λ_b,paper / λ_s (the paper's grey)."""

    def __init__(self, cin: int, lambda_s: float, lambda_b: float):
        super().__init__()
        self.conv = _conv(cin, 3)
        self.lambda_s = lambda_s * PAPER_UNIT
        self.lambda_b = lambda_b * PAPER_UNIT
        if lambda_b == 0:
            with torch.no_grad():
                self.conv.bias.fill_(PAPER_LAMBDA_B / lambda_s)

    def forward(self, h: torch.Tensor, return_raw: bool = False):
        scaled = self.lambda_s * self.conv(h)
        texture = F.relu(scaled) + self.lambda_b
        return (texture, scaled) if return_raw else texture


def _conv(cin, cout):
    return nn.Conv2d(cin, cout, 3, padding=1)


class StudentNet(nn.Module):
    """Texel features + J_s(θ) → texture (Eq. 11).

    Args:
        feature_channels: 12 (diffuse + 3 Phong) or 3 (``--no-specular``).
        decoder: widths after the input (paper: 256, 256, 128, 128, 64, 64, 32).
        pose_dim, pose_channels: the joint encoder (paper: 16, 64).
        lambda_s, lambda_b: Eq. 11 in the paper's units.
    """

    kind = "student"

    def __init__(self, feature_channels: int, decoder, pose_dim: int, pose_channels,
                 lambda_s: float = 25.0, lambda_b: float = 100.0):
        super().__init__()
        self.pose = PoseEncoder(pose_dim, pose_channels)
        widths = [feature_channels + pose_channels[1], *decoder]
        self.convs = nn.ModuleList(_conv(a, b) for a, b in zip(widths[:-1], widths[1:]))
        self.head = Eq11Head(widths[-1], lambda_s, lambda_b)

    def forward(self, features: torch.Tensor, pose: torch.Tensor, env_code=None,
                return_raw: bool = False):
        """features [H, C, N, N], pose [H, P] → textures [H, 3, N, N] (sr⁻¹)."""
        h = torch.cat([features, self.pose(pose, features.shape[-1])], 1)
        for conv in self.convs:
            h = F.leaky_relu(conv(h), 0.2)
        return self.head(h, return_raw)


class DRAMNet(nn.Module):
    """The DRAM baseline: a bottleneck light code modulating a pose-only decoder."""

    kind = "dram"

    def __init__(self, env_size: int, decoder, pose_dim: int, pose_channels, code: int = 512,
                 lambda_s: float = 25.0, lambda_b: float = 100.0):
        super().__init__()
        self.pose = PoseEncoder(pose_dim, pose_channels)
        self.encode = nn.Sequential(nn.Linear(env_size, code), nn.LeakyReLU(0.2),
                                    nn.Linear(code, code))
        widths = [pose_channels[1], *decoder]
        self.convs = nn.ModuleList(_conv(a, b) for a, b in zip(widths[:-1], widths[1:]))
        self.film = nn.ModuleList(nn.Linear(code + pose_dim, 2 * w) for w in decoder)
        self.head = Eq11Head(widths[-1], lambda_s, lambda_b)

    def forward(self, features: torch.Tensor, pose: torch.Tensor, env_code=None,
                return_raw: bool = False):
        """``features`` only gives the grid size; env_code [H, 1536] is the wrist-frame env
        map (log1p-compressed radiance) per hand → textures [H, 3, N, N]."""
        n = features.shape[-1]
        code = self.encode(env_code)
        cond = torch.cat([code, pose], 1)
        h = self.pose(pose, n)
        for conv, film in zip(self.convs, self.film):
            scale, shift = film(cond).chunk(2, dim=1)
            h = F.leaky_relu(conv(h) * (1 + scale[..., None, None]) + shift[..., None, None], 0.2)
        return self.head(h, return_raw)
