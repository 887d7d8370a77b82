"""Model checkpoints: format ``relight/checkpoint`` version 1 (spec: ``formats/checkpoint.md``).

A checkpoint is one ``torch.save`` archive of a dict of plain values and tensors, read
back only with ``torch.load(weights_only=True)``: loading never runs code from the
file.  Text fields (config, RNG states, provenance) are JSON strings so the archive
holds nothing but str/int/float/bool, lists, dicts and tensors.

torch is imported inside the functions (this module is imported by ``--help`` paths).
"""

from __future__ import annotations

import json
import os

from relight_cli.errors import DataError

from ._common import check_format_version

FORMAT = "relight/checkpoint"
VERSION = 1
KINDS = ("teacher", "student", "linear")
REQUIRED = ("format", "version", "kind", "model", "config", "step", "weights", "optimizer",
            "rng", "capture_key", "pose_dim", "provenance")


def make_checkpoint(kind: str, model_name: str, config: dict, step: int, weights: dict,
                    optimizer: dict, rng: dict, capture_key: str, pose_dim: int,
                    provenance: dict, extra: dict | None = None) -> dict:
    """The checkpoint dict (see the spec for each field)."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    return {"format": FORMAT, "version": VERSION, "kind": kind, "model": model_name,
            "config": json.dumps(config, sort_keys=True), "step": int(step),
            "weights": weights, "optimizer": optimizer,
            "rng": {k: (v if not isinstance(v, (dict, list)) else json.dumps(v))
                    for k, v in rng.items()},
            "capture_key": str(capture_key), "pose_dim": int(pose_dim),
            "provenance": json.dumps(provenance, sort_keys=True),
            "extra": dict(extra or {})}


def write_checkpoint(path: str, checkpoint: dict) -> None:
    """Write atomically (temp file in the same folder, then rename)."""
    import torch

    from relight_cli.provenance import atomic_path
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            torch.save(checkpoint, f)


def read_checkpoint(path: str, kind: str | None = None, model: str | None = None) -> dict:
    """Read and check a checkpoint; returns its dict with ``config`` and ``provenance``
    decoded from JSON.  Raises DataError naming the file for anything else: not a
    checkpoint, a pickle that needs code to load, a newer version, the wrong kind or
    model, missing fields."""
    import pickle

    import torch

    if not os.path.isfile(path):
        raise DataError("no such checkpoint file", path)
    import warnings
    try:
        with warnings.catch_warnings():
            # torch warns about foreign pickle protocols before refusing them: one line only
            warnings.simplefilter("ignore")
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        first = (str(exc).splitlines() or ["?"])[0][:120]
        raise DataError(f"refused: not a plain-data checkpoint (weights_only load failed: "
                        f"{first})", path) from None
    except Exception as exc:  # zip/pickle/EOF errors of damaged or foreign files
        first = (str(exc).splitlines() or [type(exc).__name__])[0][:120]
        raise DataError(f"not a relight checkpoint ({first})", path) from None
    if not isinstance(obj, dict) or obj.get("format") != FORMAT:
        raise DataError(f"not a {FORMAT} file", path)
    check_format_version(obj.get("format"), obj.get("version"), FORMAT, VERSION, path)
    missing = [k for k in REQUIRED if k not in obj]
    if missing:
        raise DataError(f"checkpoint lacks field(s) {', '.join(missing)}", path)
    if kind is not None and obj["kind"] != kind:
        raise DataError(f"checkpoint holds a {obj['kind']!r} model, expected {kind!r}", path)
    if model is not None and obj["model"] != model:
        raise DataError(f"checkpoint holds model {obj['model']!r}, expected {model!r}", path)
    try:
        obj["config"] = json.loads(obj["config"])
        obj["provenance"] = json.loads(obj["provenance"])
    except (TypeError, ValueError):
        raise DataError("checkpoint config/provenance is not valid JSON", path) from None
    if not isinstance(obj["weights"], dict) or not all(
            isinstance(v, torch.Tensor) for v in obj["weights"].values()):
        raise DataError("checkpoint weights must map names to tensors", path)
    for name, value in obj["weights"].items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise DataError(f"checkpoint weight {name} holds NaN/Inf", path)
    return obj


def read_state_dict(path: str, what: str = "weights") -> dict:
    """A plain torch state dict file (e.g. local VGG or LPIPS weights), loaded with
    ``weights_only=True``; DataError naming the file when it is anything else."""
    import warnings

    import torch
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for non-checkpoint files
        msg = (str(exc).splitlines() or [type(exc).__name__])[0][:160]
        raise DataError(f"not a loadable torch state dict: {msg}", path) from None
    if not isinstance(state, dict):
        raise DataError(f"{what} must be a state dict (key → tensor)", path)
    return state
