"""Weights against the module they are for: checked before anything is allocated or copied.

A leaf of :mod:`relight_cli.neural` (it imports nothing of it): every loader
(:mod:`~relight_cli.neural.checkpoints`) and the training loop's resume use it.
"""

from __future__ import annotations

import torch


def check_weights(expected: dict, weights: dict, what: str = "checkpoint") -> None:
    """Compare a state dict with a module's (``expected``: its ``state_dict()``, on any
    device, meta included): the same names, and each tensor of the same shape and dtype.
    ValueError naming the first difference; no tensor's values are touched."""
    if not isinstance(weights, dict) or not all(isinstance(v, torch.Tensor)
                                                for v in weights.values()):
        raise ValueError(f"{what} weights must map names to tensors")
    missing = [k for k in expected if k not in weights]
    if missing:
        raise ValueError(f"{what} lacks tensor {missing[0]} ({len(missing)} missing)")
    unexpected = [k for k in weights if k not in expected]
    if unexpected:
        raise ValueError(f"{what} has unexpected tensor {str(unexpected[0])[:80]}")
    for k, v in expected.items():
        if tuple(weights[k].shape) != tuple(v.shape):
            shape = tuple(weights[k].shape)
            text = str(shape) if len(str(shape)) <= 60 else str(shape)[:57] + "..."
            raise ValueError(f"{what} tensor {k} has shape {text}, the model expects "
                             f"{tuple(v.shape)}")
        if weights[k].dtype != v.dtype:
            raise ValueError(f"{what} tensor {k} is {weights[k].dtype}, the model expects "
                             f"{v.dtype}")


def load_weights(model, weights: dict) -> None:
    """Load a state dict, refusing missing, unexpected, mis-shaped or mis-typed tensors
    (ValueError) before any value is copied."""
    check_weights(model.state_dict(), weights)
    model.load_state_dict(weights)


def build_checked(build, weights: dict):
    """``build()``'s module with ``weights`` loaded — built for real only once the weights
    match the module it makes on the meta device (no memory): a configuration read from
    a file cannot make us allocate a model its file does not hold.  ValueError on a
    mismatch (the caller names the file)."""
    with torch.device("meta"):
        probe = build()
    check_weights(probe.state_dict(), weights)
    model = build()
    model.load_state_dict(weights)
    return model
