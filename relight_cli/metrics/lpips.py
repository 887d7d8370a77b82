"""Optional LPIPS (Zhang et al. 2018, AlexNet variant) with *user-supplied local* weights.

relight never downloads network weights.  The user passes one torch state dict
(loaded with ``weights_only=True``) holding the whole network under the key names
of the ``lpips`` Python package's ``LPIPS(net="alex")`` module:

* ``net.slice1.0.*``, ``net.slice2.3.*``, ``net.slice3.6.*``, ``net.slice4.8.*``,
  ``net.slice5.10.*`` — AlexNet's five conv layers (torchvision's ``features``
  indices 0, 3, 6, 8, 10), weight and bias each;
* ``lin0.model.1.weight`` … ``lin4.model.1.weight`` — the learned 1×1 channel weights;
* ``scaling_layer.shift`` / ``scaling_layer.scale`` optional (the package's constants
  are used when absent).

Inputs are display-referred images in [0, 1] (``--space srgb`` or ``display``);
with a mask the background of both images is set to 0 first.
"""

from __future__ import annotations

import numpy as np

from relight_cli.errors import DataError, UsageProblem

_CONVS = [("net.slice1.0", 3, 64, 11, 4, 2), ("net.slice2.3", 64, 192, 5, 1, 2),
          ("net.slice3.6", 192, 384, 3, 1, 1), ("net.slice4.8", 384, 256, 3, 1, 1),
          ("net.slice5.10", 256, 256, 3, 1, 1)]
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


def required_keys() -> list[str]:
    keys = []
    for name, *_ in _CONVS:
        keys += [f"{name}.weight", f"{name}.bias"]
    keys += [f"lin{i}.model.1.weight" for i in range(5)]
    return keys


def load_lpips(path: str) -> dict:
    """Load and check a local LPIPS state dict; returns {key: tensor}.  Raises DataError."""
    from relight_cli.formats.checkpoint import read_state_dict
    state = read_state_dict(path, "LPIPS weights")
    missing = [k for k in required_keys() if k not in state]
    if missing:
        raise DataError(f"LPIPS weights lack {len(missing)} key(s), e.g. {missing[0]} "
                        "(expected the lpips package's LPIPS(net='alex') names)", path)
    for name, cin, cout, k, _, _ in _CONVS:
        if tuple(state[f"{name}.weight"].shape) != (cout, cin, k, k):
            raise DataError(f"{name}.weight has shape {tuple(state[f'{name}.weight'].shape)}, "
                            f"expected {(cout, cin, k, k)}", path)
    for i, (_, _, cout, *_rest) in enumerate(_CONVS):
        if tuple(state[f"lin{i}.model.1.weight"].shape) != (1, cout, 1, 1):
            raise DataError(f"lin{i}.model.1.weight must have shape (1, {cout}, 1, 1)", path)
    return {k: v.float() for k, v in state.items() if hasattr(v, "float")}


def lpips_distance(state: dict, pred: np.ndarray, gt: np.ndarray, data_range: float = 1.0,
                   mask: np.ndarray | None = None) -> float:
    """LPIPS between two [H, W, 3] display images in [0, data_range] (lower = more similar)."""
    import torch
    import torch.nn.functional as F

    if pred.shape[-1] != 3:
        raise UsageProblem("LPIPS needs RGB images")
    if min(pred.shape[:2]) < 32:
        raise UsageProblem("LPIPS needs images of at least 32×32 pixels")

    def prepare(image):
        x = np.clip(np.asarray(image, np.float64) / data_range, 0, 1)
        if mask is not None:
            x = x * mask[..., None]
        t = torch.from_numpy(x.astype(np.float32)).permute(2, 0, 1)[None] * 2 - 1
        shift = state.get("scaling_layer.shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        scale = state.get("scaling_layer.scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        return (t - shift.view(1, 3, 1, 1)) / scale.view(1, 3, 1, 1)

    def features(x):
        out = []
        for i, (name, _, _, _, stride, pad) in enumerate(_CONVS):
            if i in (1, 2):
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(F.conv2d(x, state[f"{name}.weight"], state[f"{name}.bias"], stride, pad))
            out.append(x)
        return out

    with torch.no_grad():
        total = 0.0
        for i, (a, b) in enumerate(zip(features(prepare(pred)), features(prepare(gt)))):
            na = a / (a.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = b / (b.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total += float(F.conv2d((na - nb) ** 2, state[f"lin{i}.model.1.weight"]).mean())
    return total
