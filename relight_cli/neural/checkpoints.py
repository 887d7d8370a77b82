"""The checkpoint loaders: a read checkpoint's ``kind`` → the model it holds.

Every reader of a learned model (``relight HAND --model …``, ``relight CAPTURE/``,
``distill``'s teacher, the benchmarks) goes through :func:`load` or one of its loaders;
which loader serves a kind is the model registry's entry
(:mod:`relight_cli.neural.registry`, ``loader``):

    kind      model (config ``model`` / ``student``)          loader
    teacher   OLAT teacher (``olat``) or GGX baseline (``ggx``)   :func:`teacher_model`
    linear    URHand's linear lighting model                   :func:`linear_model`
    student   RelightableHands' student or DRAM (``dram``)     :func:`student_model`

Each builds the module its configuration describes on the meta device first and
compares the checkpoint's weights with it (:func:`~relight_cli.neural.weights.
build_checked`), so a file cannot make us allocate a model it does not hold; each raises
ValueError (the caller names the file) on a checkpoint that does not build.  The
checkpoint dict itself is validated before by :func:`read_checkpoint`.
"""

from __future__ import annotations

import json

import torch

from .config import StudentConfig, TeacherConfig
from .linear import LinearConfig, URHandModel
from .models import build_model
from .student import build_student
from .weights import build_checked


def read_checkpoint(path: str, kind: str | None = None, model: str | None = None) -> dict:
    """Read and check a relight/checkpoint (:func:`relight_cli.formats.checkpoint.
    read_checkpoint`, the format's one validator) with each kind's configuration class
    from the model registry: everything the file declares is checked before any network
    is built.  DataError naming the file."""
    from relight_cli.formats.checkpoint import read_checkpoint as read

    from .registry import for_kind
    return read(path, kind, model, config_class=lambda k: for_kind(k).load_attr("config"))


def load(checkpoint: dict, device="cpu"):
    """(model in eval mode, config, mean texture T̄ or None) of any kind of checkpoint."""
    from .registry import for_kind
    out = for_kind(checkpoint["kind"]).load_attr("loader")(checkpoint, device)
    return out if len(out) == 3 else (*out, None)


def _config(checkpoint: dict, cls):
    """The checkpoint's configuration as ``cls`` (UsageProblem naming a bad field)."""
    raw = checkpoint["config"]
    return cls.from_dict(json.loads(raw) if isinstance(raw, str) else raw, "checkpoint config")


def _pose_dim(checkpoint: dict) -> int:
    pose_dim = checkpoint["pose_dim"]
    if isinstance(pose_dim, bool) or not isinstance(pose_dim, int) or not 3 <= pose_dim <= 300:
        raise ValueError(f"checkpoint pose_dim must be (joints − 1) × 3 ≤ 300, got "
                         f"{pose_dim!r}"[:120])
    return pose_dim


def _mean_texture(checkpoint: dict, config, required: bool):
    """``extra.mean_texture`` (T̄ [1..4, 3, N, N] float32 at the config's N) or None;
    ValueError when it is required and absent, or mis-shaped."""
    mean = checkpoint.get("extra", {}).get("mean_texture")
    if mean is None:
        if required:
            raise ValueError(f"a {getattr(config, 'model', 'linear')} checkpoint needs its "
                             f"mean texture (extra.mean_texture)")
        return None
    n = config.tex_res
    if not isinstance(mean, torch.Tensor) or mean.ndim != 4 or mean.dtype != torch.float32 \
            or not 1 <= mean.shape[0] <= 4 or tuple(mean.shape[1:]) != (3, n, n):
        raise ValueError(f"extra.mean_texture must be float32 [1..4, 3, {n}, {n}]")
    return mean


def teacher_model(checkpoint: dict, device="cpu"):
    """(model in eval mode, config, mean texture or None) from a read checkpoint dict
    (:func:`relight_cli.neural.checkpoints.read_checkpoint`).  The weights are compared
    with the module the configuration builds before it is allocated; ValueError (the
    caller names the file) on missing, extra or mis-shaped tensors or a missing or
    mis-shaped mean texture."""
    config = _config(checkpoint, TeacherConfig)
    pose_dim = _pose_dim(checkpoint)
    model = build_checked(lambda: build_model(config, pose_dim), checkpoint["weights"])
    model = _layout(model.to(device).eval(), config)
    mean = _mean_texture(checkpoint, config, required=config.model == "ggx")
    return model, config, (None if mean is None else mean.to(device))


def linear_model(checkpoint: dict, device="cpu"):
    """(model in eval mode, config, mean texture [1, 3, N, N]) from a read checkpoint
    (:func:`relight_cli.neural.checkpoints.read_checkpoint`).  The weights are compared
    with the module the configuration builds before it is allocated
    (:func:`~relight_cli.neural.weights.build_checked`).  Raises ValueError for
    missing/mismatched tensors or mean texture (the caller names the file)."""
    config = _config(checkpoint, LinearConfig)
    pose_dim = _pose_dim(checkpoint)
    model = build_checked(lambda: URHandModel(config, pose_dim), checkpoint["weights"])
    model.to(device).eval()
    return model, config, _mean_texture(checkpoint, config, required=True).to(device)


def subjects_from_checkpoint(checkpoint: dict, device="cpu") -> list:
    """The subjects a linear checkpoint was trained on (URHand Sec. 4.3, Table 2's
    "trained subject"): [(capture key, skin seed or None, T̄ [1, 3, N, N])], from
    ``extra.subjects`` / ``extra.mean_textures`` (several subjects), else the one subject
    of ``capture_key`` with ``extra.mean_texture`` (a checkpoint of one capture, which
    records no list).  Raises ValueError for a damaged list (the caller names the file;
    :func:`relight_cli.neural.checkpoints.read_checkpoint` checks the same first)."""
    extra = checkpoint.get("extra", {})
    mean = extra.get("mean_texture")
    if "subjects" not in extra and "mean_textures" not in extra:
        if not isinstance(mean, torch.Tensor):
            raise ValueError("a linear checkpoint needs its mean texture (extra.mean_texture)")
        return [(str(checkpoint["capture_key"]), None, mean.to(device))]
    subjects, means = extra.get("subjects"), extra.get("mean_textures")
    raw = checkpoint["config"]
    n = int((json.loads(raw) if isinstance(raw, str) else raw)["tex_res"])
    if not isinstance(means, torch.Tensor) or means.dtype != torch.float32 or \
            means.ndim != 5 or not 1 <= means.shape[1] <= 4 or \
            tuple(means.shape[2:]) != (3, n, n):
        raise ValueError(f"extra.mean_textures must be float32 [S, 1..4, 3, {n}, {n}]")
    if not isinstance(subjects, list) or not subjects or not all(
            isinstance(r, dict) and isinstance(r.get("capture_key"), str)
            and isinstance(r.get("mean_texture"), int) and not isinstance(r["mean_texture"], bool)
            and 0 <= r["mean_texture"] < means.shape[0] for r in subjects):
        raise ValueError("extra.subjects must list {capture_key, skin_seed, mean_texture: a "
                         "row of extra.mean_textures}")
    return [(r["capture_key"], r.get("skin_seed"), means[r["mean_texture"]].to(device))
            for r in subjects]


def student_model(checkpoint: dict, device="cpu"):
    """(model in eval mode, StudentConfig) from a read student checkpoint dict.
    The weights are compared with the module the configuration builds before it is
    allocated.  Raises ValueError on missing, extra or mis-shaped tensors."""
    config = _config(checkpoint, StudentConfig)
    channels = 3 * (1 + (len(config.shininess) if config.specular else 0))
    pose_dim = _pose_dim(checkpoint)
    model = build_checked(lambda: build_student(config, channels, pose_dim),
                          checkpoint["weights"])
    return _layout(model.to(device).eval(), config), config


def _layout(model, config):
    """The model in the memory layout it trained in: ``channels_last`` (the ``cpu``
    presets) serves inference too — oneDNN's bilinear resampling and convolutions are
    faster in NHWC (the ``cpu`` OLAT teacher's env render at 16×32: network 2.05 → 1.29 s
    per frame, benchmarks/results/teacher.md; the same numbers up to float rounding)."""
    if getattr(config, "channels_last", False):
        model = model.to(memory_format=torch.channels_last)
    return model
