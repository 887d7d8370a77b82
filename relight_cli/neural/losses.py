"""Losses of RelightableHands Eq. 5–6: masked MSE, VGG perceptual, L_neg.

L = λ_MSE L_MSE + λ_VGG L_VGG + λ_neg L_neg (Eq. 5; λ = 1, 1, 0.01 in the paper).

* L_MSE: mean squared error over the pixels inside the loss mask (captured hand mask
  or rendered coverage), linear radiance.
* L_VGG: Σ_l mean |φ_l(x̂) − φ_l(x)| over VGG-16's relu1_2, relu2_2, relu3_3, relu4_3
  (equal weights; the paper says "weighted sum" without the weights).  Images are
  tone-mapped x/(1 + x), the background (outside the loss mask) set to 0, then
  ImageNet-normalized.  Only with weights the user has: a torchvision ``vgg16`` state
  dict file (``features.N.weight`` / ``features.N.bias`` keys, e.g. torchvision's
  ``vgg16-397923af.pth`` copied from a machine that has it), loaded with
  ``weights_only=True``.  Nothing is downloaded; without weights the term is off and the
  checkpoint's config says so.
* L_neg (Eq. 6): γ/(N S³) Σ ‖max(−x, 0)‖².  Eq. 10's C = σ(S)(ReLU(λ_s T) + λ_b) is
  non-negative by construction, so read literally L_neg is identically 0; we apply it to
  the pre-ReLU λ_s T, whose negative values are dead ReLUs no image gradient revives —
  the only place a negativity penalty changes training.  γ follows the schedule of
  :func:`neg_weight`.
"""

from __future__ import annotations

import math

import torch
from torch.nn import functional as F

from relight_cli.errors import DataError

# torchvision vgg16 ``features`` conv indices and the ReLUs we tap (relu1_2 … relu4_3).
_VGG_CONVS = [(0, 3, 64), (2, 64, 64), (5, 64, 128), (7, 128, 128), (10, 128, 256),
              (12, 256, 256), (14, 256, 256), (17, 256, 512), (19, 512, 512), (21, 512, 512)]
_VGG_POOL_AFTER = {2, 7, 14}        # max-pool after these convs (indices 4, 9, 16)
_VGG_TAPS = {2, 7, 14, 21}          # feature after these convs' ReLU
_MEAN = (0.485, 0.456, 0.406)
_STD = (0.229, 0.224, 0.225)


def masked_mse(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of (pred − target)² over mask pixels; pred/target [H, W, 3], mask [H, W] bool."""
    m = mask.to(pred.dtype)[..., None]
    count = torch.clamp(m.sum() * pred.shape[-1], min=1.0)
    return (((pred - target) ** 2) * m).sum() / count


def neg_weight(step: int, eta: float, start: int, schedule: str = "decay") -> float:
    """γ of Eq. 6 at iteration ``step`` (t_s = ``start``).

    ``decay``: exp(−max(η (t − t_s)/t, 0)) — 1 until t_s, then decaying towards e^−η.
    ``literal``: exp(−max(η t/(t − t_s), 0)) as printed — 1 before t_s, then ≈ 0 just
    after it, rising towards e^−η (we believe the printed fraction is inverted).
    ``constant``: 1 (the authors' public code weights L_neg by a constant).
    """
    if schedule == "constant":
        return 1.0
    t = float(step)
    ts = float(start)
    if schedule == "literal":
        if t <= ts:
            return 1.0
        return math.exp(-max(eta * t / (t - ts), 0.0))
    if t <= ts or t <= 0:
        return 1.0
    return math.exp(-max(eta * (t - ts) / t, 0.0))


def negativity(raw: torch.Tensor, region: torch.Tensor) -> torch.Tensor:
    """Mean over region texels of ‖max(−raw, 0)‖²; raw [B, C, N, N], region [B, 1, N, N]."""
    r = region.to(raw.dtype)
    count = torch.clamp(r.sum() * raw.shape[1], min=1.0)
    return ((F.relu(-raw) ** 2) * r).sum() / count


class VGGLoss(torch.nn.Module):
    """VGG-16 feature loss from a local torchvision state dict (see module docstring)."""

    def __init__(self, state: dict):
        super().__init__()
        self.convs = torch.nn.ModuleList()
        for idx, cin, cout in _VGG_CONVS:
            conv = torch.nn.Conv2d(cin, cout, 3, padding=1)
            conv.weight.data.copy_(state[f"features.{idx}.weight"])
            conv.bias.data.copy_(state[f"features.{idx}.bias"])
            conv.requires_grad_(False)
            self.convs.append(conv)
        self.register_buffer("mean", torch.tensor(_MEAN).reshape(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(_STD).reshape(1, 3, 1, 1))

    def features(self, x: torch.Tensor) -> list:
        out = []
        h = (x - self.mean) / self.std
        for (idx, _, _), conv in zip(_VGG_CONVS, self.convs):
            h = F.relu(conv(h))
            if idx in _VGG_TAPS:
                out.append(h)
            if idx in _VGG_POOL_AFTER:
                h = F.max_pool2d(h, 2)
            if idx == 21:
                break
        return out

    def forward(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor):
        """pred/target [H, W, 3] linear radiance, mask [H, W] bool → scalar."""
        m = mask.to(pred.dtype)[None, None]

        def prep(img):
            img = torch.clamp(img, min=0)
            return (img / (1 + img)).permute(2, 0, 1)[None] * m

        loss = pred.new_zeros(())
        for a, b in zip(self.features(prep(pred)), self.features(prep(target))):
            loss = loss + (a - b).abs().mean()
        return loss


def vgg_required_keys() -> list[str]:
    return [f"features.{i}.{p}" for i, _, _ in _VGG_CONVS for p in ("weight", "bias")]


def load_vgg(path: str) -> VGGLoss:
    """The VGG loss from a local torchvision vgg16 state dict.  Raises DataError."""
    from relight_cli.formats.checkpoint import read_state_dict
    state = read_state_dict(path, "VGG weights")
    missing = [k for k in vgg_required_keys() if k not in state]
    if missing:
        raise DataError(f"VGG weights lack {len(missing)} key(s), e.g. {missing[0]} (expected "
                        "torchvision vgg16 names)", path)
    for idx, cin, cout in _VGG_CONVS:
        shape = tuple(state[f"features.{idx}.weight"].shape)
        if shape != (cout, cin, 3, 3):
            raise DataError(f"features.{idx}.weight has shape {shape}, expected "
                            f"{(cout, cin, 3, 3)}", path)
    return VGGLoss({k: v.float() for k, v in state.items() if k in vgg_required_keys()})
