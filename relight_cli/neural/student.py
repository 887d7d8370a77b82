"""RelightableHands' student (App. A.2, Eq. 11) and the DRAM bottleneck baseline (App. A.3).

Student: input = bake-features' texel maps of the pose under the env map — diffuse (3)
and Phong α = 16, 32, 64 (9), Eq. 8–9, visibility-aware — concatenated with the joint
features J_s(θ) (the teacher's pose encoder, widths 16, 64, on the feature grid) =
76 channels at 128²; decoder: an 8-layer CNN (76 → 256 → 256 → 128 → 128 → 64 → 64 →
32 → 3), 3×3 convs, LeakyReLU(0.2) between; head Eq. 11: C = ReLU(λ_s T) + λ_b (no
shadow map: shadows are in the features).

Units of Eq. 11.  The paper's λ_s, λ_b are 8-bit pixel units (255 = white).  The
head converts them with the teacher's :data:`~relight_cli.neural.config.PAPER_UNIT`
= 1/(255π), whose white is a white Lambertian texel's radiance *per unit irradiance*
(1/π sr⁻¹).  The student's texture is instead radiance over the env's mean radiance s
(:mod:`relight_cli.neural.distill`), where a white Lambertian texel under a uniform
env of radiance s is 1 (E = πs, radiance ρE/π = s), so the paper's λ_b = 100 would
be 100/255 ≈ 0.39 here.  What the head applies for ``lambda_b: 100`` is 100 ·
PAPER_UNIT ≈ 0.125: the paper's number, on a scale π× smaller than the paper's
(likewise λ_s = 25 is 0.031 per raw unit, not 0.098).  Either way, with no shadow
gate σ(S) a positive λ_b is a floor under every texel's radiance — 12.5 % (or 39 %)
of a white texel under a uniform env, brighter than a shadow under a sunny sky.
Departure: our default is λ_b = 0, with the head's bias initialized to λ_b,paper / λ_s
so training starts from the texture value 100 · PAPER_UNIT ≈ 0.125 yet can reach
black.  ``--no-specular`` drops the Phong maps (3 + 64 = 67 channels).

``head: linear`` (ours, :class:`LinearHeadStudent`): the same features, but the decoder
sees only J_s(θ) (with per-texel biases) and predicts per-texel weights of each feature
map; the texture is ReLU(Σ_k W_k ⊙ F_k), linear in the env map as URHand's light path
is (URHand Sec. 4.2), where Eq. 11's CNN is free to learn the training maps instead of
light.  ``head_init: lsq`` starts it from the closed-form per-texel least-squares fit
(:func:`relight_cli.neural.distill.fit_linear_head`); with 0 iterations that fit is the
student.  The ``cpu`` preset uses it; ``tiny`` and ``paper`` keep Eq. 11.

DRAM (Bi et al. 2021, "Deep Relightable Appearance Models for Animatable Faces") as
RelightableHands App. A.3 adapted it.  App. A.3 specifies only two changes to DRAM:
the hand pose θ replaces DRAM's expression code z in its hyper-network, and the env
map is rotated into the hand's root-joint frame before it reaches that network.
RelightableHands Sec. 4.2 describes DRAM's student as a hyper-network conditioned on
a 512-d bottleneck code of the 16×32 env map.  DRAM's decoder, like that of the Deep
Appearance Models it extends (Lombardi et al. 2018), decodes a texture from codes
alone: they are mapped to a small spatial grid and up-sampled by (transposed)
convolutions with *untied* biases — one bias per channel and texel — so it produces a
spatially varying texture (albedo, creases) although no input is spatial.  (DRAM's
own text was not at hand; this reading follows the two papers above.)

What we do: the 16×32 env map in the wrist's frame, log1p(L/s), flattened (1536) →
2-layer MLP → the light code (``dram_code``, paper 512); cond = [code, θ]; a linear
layer maps cond to the decoder's first width on a 4×4 (at least) grid, then each
further decoder width is a bilinear ×2 up-sampling (until the texture size) + 3×3
conv with an untied per-texel bias, LeakyReLU(0.2); the Eq. 11 head adds an untied
per-texel bias too.  In place of DRAM's generated conv kernels, cond generates a
per-channel scale and shift (FiLM) of every decoder layer: the same information
enters through the same bottleneck (the claim under test is the light bottleneck —
no texel-aligned lighting or visibility — not the weight parameterization), while
generating full 256×256×3×3 kernels per frame would make the baseline ~30× larger
than the student it is compared with (as built, at the paper's widths and 128²: 7.8 M
parameters against the student's 1.4 M, most in the code → grid map, FiLM and the
untied biases).  Spatial structure comes from the per-texel grid weights and the
untied biases; the light enters only through the code.  The decoder is tied to its
texture size (``tex_res``); a texture asked at another size is resized bilinearly.
J_s(θ) is not used: tiled θ through 3×3 convs is spatially constant and adds nothing
spatial; θ enters with the code.  The previous DRAM started from tiled J_s(θ) with
tied biases and per-channel FiLM: its texture was constant away from the border.
Measured on the capture med_aa1 (tiny preset, 32², teacher: tiny, 150 iterations; sky
and studio trained with rotations, 300 iterations): std over texels 4 inside the
charts 0.07 (previous design, 100 iterations: 0.0000–0.0001; the teacher's: 0.31).

FiLM's scale is bounded: each layer multiplies by 1 + tanh(a) ∈ (0, 2), not 1 + a.  The
scale is a linear map of cond (the 512-d light code and θ, unnormalized), so one Adam
step moves it by about lr · Σ|cond|, and eight layers multiply their scales: with the
unbounded form both seeds of the converged study's DRAM rows (``cpu`` preset, lr 2e-3)
jumped mid-run and never came back — held-out MSE against the teacher 0.34 → 5.7·10⁶
(seed 0, between steps 1,200 and 1,600) and 0.33 → 0.95 (seed 1, at 2,000).

The head's scale (ours): DRAM's presets set λ_s = 255π
(:data:`relight_cli.neural.config.DRAM_LAMBDA_S`), so λ_s · PAPER_UNIT = 1 and the
decoder's output is in texture units.  App. A.3 does not give DRAM's head; with the
student's λ_s = 25 the head scales the decoder's output by 0.031.  At ``tiny`` the
texture-unit head lets DRAM's light path train (the change between two training maps
0.96–0.98 of the teacher's, against 0.39–0.74 at 25, seeds 0–2); at ``cpu`` on the
converged capture its light path stays near constant in most runs either way (the
texture's standard deviation over 21 training lightings 0.028–0.041 against the teacher's
0.21; one of the five runs measured reached 0.141; config.py's
:data:`~relight_cli.neural.config.DRAM_LAMBDA_S` gives the runs).  Measured over four
seeds (benchmarks/results/converged/student_dram_b8/, the study's light-response table):
the preset's DRAM trains its light path in some runs (share of the teacher's variation
explained 0.01–0.34); batches of 8 (the same 8,000 samples in 1,000 steps) on every seed
(0.33–0.39); the texture-space loss (``loss_space: texture``) with them most
(0.58–0.66).  None of them scores better under held-out env maps (ties, +0.4 to
+1.1 dB): a light code that fits the seven training maps does not generalize — the
overfitting App. A.3's baseline is shown for.
DRAM never reads texel features, so none are baked for it
(:func:`relight_cli.neural.distill.student_forward`).
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from .config import PAPER_UNIT
from .models import PoseEncoder


#: Eq. 11's λ_b in the paper's units, used as the starting grey when λ_b = 0.
PAPER_LAMBDA_B = 100.0


class Eq11Head(nn.Module):
    """Eq. 11: a 3×3 conv to T, then C = ReLU(λ_s T) + λ_b (paper units × PAPER_UNIT).
    With λ_b = 0 the conv's bias starts at λ_b,paper / λ_s (the paper's grey).
    ``untied``: N adds an untied per-texel bias [3, N, N] (zero at start; DRAM) to λ_s T,
    i.e. in texture units: the same functions as a bias on T, but Adam moves it at the
    texture's scale — on T (× λ_s · PAPER_UNIT = 0.031) DRAM's interior std on
    med_aa1 after 300 iterations was 0.005 instead of 0.07 (the teacher's: 0.31)."""

    def __init__(self, cin: int, lambda_s: float, lambda_b: float, untied: int = 0):
        super().__init__()
        self.conv = _conv(cin, 3)
        self.lambda_s = lambda_s * PAPER_UNIT
        self.lambda_b = lambda_b * PAPER_UNIT
        if lambda_b == 0:
            with torch.no_grad():
                self.conv.bias.fill_(PAPER_LAMBDA_B / lambda_s)
        self.untied = nn.Parameter(torch.zeros(1, 3, untied, untied)) if untied else None

    def forward(self, h: torch.Tensor, return_raw: bool = False):
        scaled = self.lambda_s * self.conv(h)
        if self.untied is not None:
            scaled = scaled + self.untied
        texture = F.relu(scaled) + self.lambda_b
        return (texture, scaled) if return_raw else texture


def _conv(cin, cout, bias: bool = True):
    return nn.Conv2d(cin, cout, 3, padding=1, bias=bias)


class StudentNet(nn.Module):
    """Texel features + J_s(θ) → texture (Eq. 11).

    Args:
        feature_channels: 12 (diffuse + 3 Phong) or 3 (``--no-specular``).
        decoder: widths after the input (paper: 256, 256, 128, 128, 64, 64, 32).
        pose_dim, pose_channels: the joint encoder (paper: 16, 64).
        lambda_s, lambda_b: Eq. 11 in the paper's units.
        untied: N > 0: every decoder conv gets an untied per-texel bias [C, N, N] and the
            head one in texture units (``StudentConfig.untied_bias``): the spatial capacity
            J_s(θ) — tiled θ through 3×3 convs, constant in space — does not give.
    """

    kind = "student"

    def __init__(self, feature_channels: int, decoder, pose_dim: int, pose_channels,
                 lambda_s: float = 25.0, lambda_b: float = 100.0, untied: int = 0):
        super().__init__()
        self.pose = PoseEncoder(pose_dim, pose_channels)
        widths = [feature_channels + pose_channels[1], *decoder]
        self.convs = nn.ModuleList(_conv(a, b) for a, b in zip(widths[:-1], widths[1:]))
        self.biases = None
        if untied:
            self.biases = nn.ParameterList(nn.Parameter(torch.zeros(1, w, untied, untied))
                                           for w in widths[1:])
        self.head = Eq11Head(widths[-1], lambda_s, lambda_b, untied=untied)

    def forward(self, features: torch.Tensor, pose: torch.Tensor, env_code=None,
                return_raw: bool = False):
        """features [H, C, N, N], pose [H, P] → textures [H, 3, N, N] (sr⁻¹)."""
        h = torch.cat([features, self.pose(pose, features.shape[-1])], 1)
        for i, conv in enumerate(self.convs):
            h = conv(h)
            if self.biases is not None:
                h = h + self.biases[i]
            h = F.leaky_relu(h, 0.2)
        return self.head(h, return_raw)


class LinearHeadStudent(nn.Module):
    """``head: linear`` (ours): per-texel weights of the student's own features, from
    light-independent inputs only, so the texture is linear in the env map.

    C = ReLU(Σ_k W_k(θ) ⊙ F_k): F_k the normalized feature maps (diffuse, Phong α …; 3
    channels each), W_k [3, N, N] the k-th map's per-texel, per-channel weights, decoded
    from J_s(θ) by the student's CNN (``decoder`` widths, 3×3 convs, LeakyReLU(0.2)) with
    untied per-texel biases — its input is spatially constant, so they carry the texel's
    identity (albedo, specular strength).  As Eq. 11 scales T by λ_s, the CNN's output is
    scaled by λ_s (× PAPER_UNIT, 0.031 at λ_s = 25) before it is added to the untied
    weights: Adam moves every output weight by about lr per step whatever its gradient,
    so unscaled, one step of the 64 × 9 output weights could move W by more than its own
    size.  The last conv starts at zero and the untied weights at a grey diffuse weight
    (0.5) and no specular, so training starts from a grey Lambertian texture.

    The ReLU clips the rendered texture, not the trained one: the distillation loss sees
    Σ_k W_k ⊙ F_k unclipped (``StudentTask.loss``), with L_neg on it as on Eq. 11's λ_s T.
    A clipped texel passes no gradient, and the first build (clipped in training, the
    CNN's output unscaled) died on seed 0 of the converged study between steps 1,000 and
    2,000: 26.77 dB against the teacher, then 8.51 dB — a black texture — to the end.

    Why: the paper's student (App. A.2, Eq. 11) maps features to texture through a CNN
    whose only per-texel inputs are lighting, and on the converged capture it fits its
    teacher worse than the closed-form per-texel least-squares fit of the same features
    (no pose, no CNN; ``head_init: lsq`` at 0 iterations): 25.88 against 26.91 dB on
    held-out poses under training maps, 23.40 against 25.25 under held-out maps.  URHand
    (Sec. 4.2) makes the same point for its light path: linear in physically based
    shading features, with spatially varying weights from light-independent inputs, it
    generalizes to unseen illumination.  Measured
    (benchmarks/results/converged/student_linear/, three seeds, ``cpu`` preset): against
    the stage's ground truth on held-out poses under held-out env maps, 27.58 ± 0.15 dB
    where Eq. 11's head has 23.55 ± 0.81 (+4.03 ± 0.95 dB), gap to the ceiling 10.67 →
    6.64 dB, in 12.9 instead of 16.7 min; the ``cpu`` preset uses it
    (:data:`relight_cli.neural.config.STUDENT_PRESET_MODEL`).
    """

    kind = "student"

    def __init__(self, feature_channels: int, decoder, pose_dim: int, pose_channels,
                 tex_res: int, lambda_s: float = 25.0):
        super().__init__()
        self.lambda_s = lambda_s * PAPER_UNIT
        if feature_channels % 3:
            raise ValueError("feature maps must have 3 channels each")
        self.maps = feature_channels // 3
        self.pose = PoseEncoder(pose_dim, pose_channels)
        widths = [pose_channels[1], *decoder]
        self.convs = nn.ModuleList(_conv(a, b) for a, b in zip(widths[:-1], widths[1:]))
        self.biases = nn.ParameterList(nn.Parameter(torch.zeros(1, w, tex_res, tex_res))
                                       for w in widths[1:])
        self.out = _conv(widths[-1], 3 * self.maps)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        start = torch.zeros(1, self.maps, 3, tex_res, tex_res)
        start[:, 0] = 0.5
        self.weight_bias = nn.Parameter(start.reshape(1, 3 * self.maps, tex_res, tex_res))

    def weights(self, pose: torch.Tensor, size: int) -> torch.Tensor:
        """pose [H, P] → per-texel weights [H, K, 3, N, N]."""
        h = self.pose(pose, size)
        for conv, bias in zip(self.convs, self.biases):
            h = F.leaky_relu(conv(h) + bias, 0.2)
        w = self.lambda_s * self.out(h) + self.weight_bias
        return w.reshape(w.shape[0], self.maps, 3, size, size)

    def forward(self, features: torch.Tensor, pose: torch.Tensor, env_code=None,
                return_raw: bool = False):
        """features [H, 3K, N, N] → textures [H, 3, N, N], ReLU(Σ_k W_k ⊙ F_k) (and the
        unclipped sum as ``raw``)."""
        n = features.shape[-1]
        feats = features.reshape(features.shape[0], self.maps, 3, n, n)
        raw = (self.weights(pose, n) * feats).sum(1)
        texture = F.relu(raw)
        return (texture, raw) if return_raw else texture


def dram_sizes(tex_res: int, layers: int, start: int = 4) -> list[int]:
    """Grid size of each of ``layers`` decoder layers: ×2 per layer from ≥ ``start``
    texels up to ``tex_res`` (the last up-sampling lands exactly on it), then kept."""
    ups = max(0, min(layers - 1, int(math.floor(math.log2(max(tex_res / start, 1))))))
    sizes = [max(1, math.ceil(tex_res / 2 ** (ups - i))) for i in range(ups + 1)]
    return sizes + [tex_res] * (layers - len(sizes))


class DRAMNet(nn.Module):
    """The DRAM baseline: a light code (and θ) decoded from a small grid by up-sampling
    convolutions with untied per-texel biases, the code also modulating every layer
    (FiLM).  See the module docstring.

    Args:
        env_size: H·W·3 of the wrist-frame env map.  decoder: widths (the first is the
        grid the codes are mapped to).  pose_dim: θ's size.  pose_channels: unused (kept
        for the shared signature).  code: the light code's size.  lambda_s, lambda_b:
        Eq. 11.  tex_res: the texture size the decoder produces.
    """

    kind = "dram"

    def __init__(self, env_size: int, decoder, pose_dim: int, pose_channels, code: int = 512,
                 lambda_s: float = 25.0, lambda_b: float = 100.0, tex_res: int = 128):
        super().__init__()
        decoder = list(decoder)
        self.tex_res = int(tex_res)
        self.sizes = dram_sizes(self.tex_res, len(decoder))
        self.encode = nn.Sequential(nn.Linear(env_size, code), nn.LeakyReLU(0.2),
                                    nn.Linear(code, code))
        cond = code + pose_dim
        s0 = self.sizes[0]
        self.grid = nn.Linear(cond, decoder[0] * s0 * s0)      # per-texel weights and biases
        self.convs = nn.ModuleList(_conv(a, b, bias=False) for a, b in zip(decoder[:-1],
                                                                            decoder[1:]))
        self.biases = nn.ParameterList(nn.Parameter(torch.zeros(1, w, s, s))
                                       for w, s in zip(decoder[1:], self.sizes[1:]))
        self.film = nn.ModuleList(nn.Linear(cond, 2 * w) for w in decoder)
        for film in self.film:                                 # FiLM starts as identity
            nn.init.zeros_(film.weight)
            nn.init.zeros_(film.bias)
        self.head = Eq11Head(decoder[-1], lambda_s, lambda_b, untied=self.tex_res)

    def forward(self, features: torch.Tensor, pose: torch.Tensor, env_code=None,
                return_raw: bool = False):
        """``features`` only gives the grid size; env_code [H, 1536] is the wrist-frame env
        map (log1p-compressed radiance) per hand → textures [H, 3, N, N]."""
        n = features.shape[-1]
        cond = torch.cat([self.encode(env_code), pose], 1)
        s0 = self.sizes[0]
        h = self.grid(cond).reshape(cond.shape[0], -1, s0, s0)
        h = F.leaky_relu(self._film(h, 0, cond), 0.2)
        for i, (conv, bias) in enumerate(zip(self.convs, self.biases), start=1):
            if h.shape[-1] != self.sizes[i]:
                h = F.interpolate(h, size=(self.sizes[i],) * 2, mode="bilinear",
                                  align_corners=False)
            h = F.leaky_relu(self._film(conv(h) + bias, i, cond), 0.2)
        tex, raw = self.head(h, return_raw=True)
        if n != self.tex_res:
            tex, raw = (F.interpolate(t, size=(n, n), mode="bilinear", align_corners=False)
                        for t in (tex, raw))
        return (tex, raw) if return_raw else tex

    def _film(self, h, i, cond):
        """FiLM with the scale bounded to (0, 2): h·(1 + tanh(a)) + b (see the module doc)."""
        scale, shift = self.film[i](cond).chunk(2, dim=1)
        return h * (1 + torch.tanh(scale)[..., None, None]) + shift[..., None, None]


def build_student(config, feature_channels: int, pose_dim: int):
    """The module a StudentConfig describes: :class:`StudentNet` on ``feature_channels``
    texel features, or :class:`DRAMNet` (``student: dram``)."""
    h, w = config.env_res
    if config.student == "dram":
        net = DRAMNet(h * w * 3, config.decoder, pose_dim, config.pose_channels, config.dram_code,
                      config.lambda_s, config.lambda_b, config.tex_res)
    elif getattr(config, "head", "eq11") == "linear":
        net = LinearHeadStudent(feature_channels, config.decoder, pose_dim,
                                config.pose_channels, config.tex_res, config.lambda_s)
    else:
        net = StudentNet(feature_channels, config.decoder, pose_dim, config.pose_channels,
                         config.lambda_s, config.lambda_b,
                         config.tex_res if getattr(config, "untied_bias", False) else 0)
    return net
