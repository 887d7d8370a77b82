"""URHand's lighting-aware adversarial loss (Sec. 4.3, Eq. 8), hinge form.

The discriminator F_D sees an image with its lighting prompt: the Phong diffuse and
specular features {A, S} of the frame's lights (RelightableHands' features, coarse
normal, monochrome: channel-mean intensities; :func:`lighting_prompt`) rendered into the
same view, divided by the model's ``feature_scale``.  Images are tone-mapped x/(1 + x)
and masked to the hand (the background says nothing about lighting).  It is a
multi-scale patch discriminator: one small conv net per scale (4×4 stride-2 convs,
LeakyReLU 0.2, a 1-channel patch logit map), the input halved (average pooling) between
scales.  ``conditioned=False`` drops {A, S}: supp. 10.2's "w/o light-aware L_GAN".

Hinge loss [26] (the paper writes the log form of Eq. 8 and says it uses the hinge):
    L_D = mean relu(1 − F_D(I | A, S)) + mean relu(1 + F_D(Î | A, S))
    L_G = −mean F_D(Î | A, S)           (weighted by λ_GAN = 0.01 in Eq. 7)
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F


class LightingAwareDiscriminator(nn.Module):
    """F_D(I | A, S) over ``scales`` resolutions; see the module docstring."""

    def __init__(self, width: int = 16, scales: int = 2, conditioned: bool = True):
        super().__init__()
        self.conditioned = conditioned
        cin = 3 + (2 if conditioned else 0)
        self.nets = nn.ModuleList(nn.Sequential(
            nn.Conv2d(cin, width, 4, stride=2, padding=1), nn.LeakyReLU(0.2),
            nn.Conv2d(width, 2 * width, 4, stride=2, padding=1), nn.LeakyReLU(0.2),
            nn.Conv2d(2 * width, 1, 3, padding=1)) for _ in range(scales))

    def forward(self, image: torch.Tensor, prompt: torch.Tensor | None, mask: torch.Tensor):
        """image [H, W, 3] radiance, prompt [H, W, 2] (A, S), mask [H, W] bool → list of
        patch logit maps [1, 1, h, w], one per scale."""
        m = mask.to(image.dtype)[..., None]
        x = torch.clamp(image, min=0)
        x = x / (1 + x)
        if self.conditioned:
            x = torch.cat([x, prompt.to(image.dtype)], -1)
        x = (x * m).permute(2, 0, 1)[None]
        out = []
        for i, net in enumerate(self.nets):
            if i:
                x = F.avg_pool2d(x, 2)
            out.append(net(x))
        return out


def generator_loss(disc, fake, prompt, mask) -> torch.Tensor:
    return -sum(d.mean() for d in disc(fake, prompt, mask)) / len(disc.nets)


def discriminator_loss(disc, real, fake, prompt, mask) -> torch.Tensor:
    real_term = sum(F.relu(1 - d).mean() for d in disc(real, prompt, mask))
    fake_term = sum(F.relu(1 + d).mean() for d in disc(fake.detach(), prompt, mask))
    return (real_term + fake_term) / len(disc.nets)


@torch.no_grad()
def lighting_prompt(texels, gbuffer, light_inputs: list, intensity, scale: float,
                    shininess: float = 32.0, device="cpu") -> torch.Tensor:
    """{A, S} [H, W, 2]: Phong diffuse and specular features of the lights in the view."""
    from .shading_features import shading_features, texels_to_map
    from .teacher import composite

    mono = np.repeat(np.asarray(intensity, np.float64).mean(1, keepdims=True), 3, 1)
    maps = []
    for k in range(texels.n_hands):
        surf = texels.surfaces[k]
        n = len(surf.points)
        normal = torch.zeros(n, 3, device=device)
        normal[:, 2] = 1
        feats = shading_features(normal, texels.local_view(k, gbuffer.eye), light_inputs[k],
                                 mono, torch.ones(n, device=device), "phong", True, shininess)
        maps.append(texels_to_map(feats[0].T, surf))                       # [2, N, N]
    return composite(maps, gbuffer) / scale
