"""Configurations of the learned models and the ``tiny`` / ``paper`` presets.

A configuration is a flat dataclass of JSON values: it is resolved once (preset, then
``--config FILE.json``, then command-line flags), stored verbatim in the checkpoint and
read back from it, so a checkpoint says exactly how it was trained and ``--resume``
continues the same run.

Presets:
    paper   RelightableHands' numbers (Sec. 4.3, App. A.1): Adam, lr 1e-3, batch 2,
            100k iterations; U-Net encoder (7, 64, 64, 64), decoder (128, 128, 128, 4),
            pose encoder (16, 64); λ_MSE 1, λ_VGG 1, λ_neg 0.01; λ_s 25, λ_b 100.  The
            texture is 1024² as in URHand's mesh re-implementation (supp. 10.1, which
            predicts 1024² textures; RelightableHands' MVP atlas is wS = 64·16 = 1024 wide).
    tiny    the same model at a quarter of the widths on a 32² texture, 150 iterations:
            a minute or two on 2 CPU cores, for tests and ``make demo``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields

from relight_cli.errors import DataError, UsageProblem

#: λ_s and λ_b of Eq. 10 are in the paper's 8-bit pixel units (255 = white).  Our
#: textures are radiance per unit irradiance (sr⁻¹), where a white Lambertian surface
#: facing the light is 1/π; one paper unit is therefore 1/(255 π) of ours.
PAPER_UNIT = 1.0 / (255.0 * math.pi)


@dataclass
class TeacherConfig:
    """How a teacher (``train-teacher``) is built and trained.

    Attributes:
        model: ``olat`` (RelightableHands' OLAT teacher, App. A.1) or ``ggx`` (the
            physically based baseline of App. B, Eq. 12).
        tex_res: N of the N×N UV texture the U-Net predicts.
        encoder: U-Net encoder widths after the 7-channel input (App. A.1: 64, 64, 64);
            each level after the first halves the resolution (bilinear).
        decoder: decoder widths before the 4-channel head (App. A.1: 128, 128, 128); the
            first width is the bottleneck (encoder output ⊕ pose features).
        pose_channels: the pose encoder J(θ)'s two conv widths (App. A.1: 16, 64).
        visibility: feed ray-traced visibility (False: RelightableHands Table 1's ablation).
        falloff: ``analytic`` multiplies each light's texture by its 1/r² falloff outside
            the network (ours: near lights extrapolate); ``none`` is the paper's Eq. 2
            (intensity weight b_i only; the network sees directions only).
        lambda_s, lambda_b: Eq. 10's scale and bias in the paper's units (× PAPER_UNIT).
        iters, batch, lr: Adam iterations, samples (frame × camera) per step, learning rate.
        lambda_mse, lambda_vgg, lambda_neg: Eq. 5's weights (VGG only with local weights).
        neg_eta, neg_start: Eq. 6's γ schedule η_neg and t_s (an iteration, so that a run
            extended by ``--resume --iters`` keeps the schedule it started with).
        neg_schedule: ``decay`` γ = exp(−max(η (t − t_s)/t, 0)) (1 until t_s, then decaying
            to e^−η: our reading of "starts decaying") or ``literal`` γ = exp(−max(η t/(t −
            t_s), 0)) as printed (1 until t_s, ≈ 0 just after, rising to e^−η).
        aa: G-buffer samples per pixel axis when rendering textures into images.
        holdout: fraction of the grouped frames (the last ones in time: a held-out
            segment, as the paper excludes segments) kept for validation.
        val_every: validate every this many steps (0: only at the end).
        val_samples: at most this many (frame, camera) samples per validation split.
        save_every: write the checkpoint every this many steps (0: only at the end).
        cache_poses: texel G-buffers kept in memory (LRU).
        seed: initialization and sampling seed.
    """

    model: str = "olat"
    tex_res: int = 32
    encoder: tuple = (16, 16, 16)
    decoder: tuple = (32, 32, 32)
    pose_channels: tuple = (8, 16)
    visibility: bool = True
    falloff: str = "analytic"
    lambda_s: float = 25.0
    lambda_b: float = 100.0
    iters: int = 150
    batch: int = 2
    lr: float = 2e-3
    lambda_mse: float = 1.0
    lambda_vgg: float = 1.0
    lambda_neg: float = 0.01
    neg_eta: float = 5.0
    neg_start: int = 40
    neg_schedule: str = "decay"
    aa: int = 2
    holdout: float = 0.25
    val_every: int = 0
    val_samples: int = 8
    save_every: int = 0
    cache_poses: int = 64
    seed: int = 0

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, values: dict, where: str = "config") -> "TeacherConfig":
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise UsageProblem(f"unknown {where} field(s): {', '.join(unknown)}")
        base = asdict(cls())
        base.update(values)
        for name in ("encoder", "decoder", "pose_channels"):
            base[name] = tuple(base[name])
        cfg = cls(**base)
        cfg.validate(where)
        return cfg

    def validate(self, where: str = "config") -> None:
        """Raise UsageProblem naming the first impossible field."""
        def bad(name, why):
            raise UsageProblem(f"{where}: {name} {why}, got {getattr(self, name)!r}")

        def positive_int(name, lo=1, hi=10 ** 9):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                bad(name, f"must be an integer in [{lo}, {hi}]")

        def finite(name, lo=0.0, hi=math.inf, open_lo=False):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v < lo or v > hi or (open_lo and v == lo):
                bad(name, f"must be a finite number in {'(' if open_lo else '['}{lo}, {hi}]")

        if self.model not in ("olat", "ggx"):
            bad("model", "must be olat or ggx")
        if self.falloff not in ("analytic", "none"):
            bad("falloff", "must be analytic or none")
        if self.neg_schedule not in ("decay", "literal"):
            bad("neg_schedule", "must be decay or literal")
        positive_int("tex_res", 8, 4096)
        for name in ("encoder", "decoder", "pose_channels"):
            v = getattr(self, name)
            if not v or not all(isinstance(c, int) and not isinstance(c, bool) and 1 <= c <= 4096
                                for c in v):
                bad(name, "must be a list of channel widths in [1, 4096]")
        if len(self.pose_channels) != 2:
            bad("pose_channels", "must hold two widths (App. A.1: 16, 64)")
        if len(self.decoder) != len(self.encoder):
            bad("decoder", "must have as many widths as the encoder")
        if self.tex_res % (2 ** (len(self.encoder) - 1)):
            bad("tex_res", f"must be divisible by 2^{len(self.encoder) - 1} (the U-Net levels)")
        positive_int("iters")
        positive_int("batch", 1, 4096)
        finite("lr", 0.0, 10.0, open_lo=True)
        for name in ("lambda_s", "lambda_b"):
            finite(name, 0.0, 1e6, open_lo=name == "lambda_s")
        for name in ("lambda_mse", "lambda_vgg", "lambda_neg", "neg_eta"):
            finite(name, 0.0, 1e6)
        positive_int("neg_start", 0)
        finite("holdout", 0.0, 0.9)
        positive_int("aa", 1, 8)
        positive_int("val_every", 0)
        positive_int("val_samples", 1, 100000)
        positive_int("save_every", 0)
        positive_int("cache_poses", 1, 100000)
        positive_int("seed", 0, 2 ** 63 - 1)
        if not isinstance(self.visibility, bool):
            bad("visibility", "must be true or false")


PRESETS = {
    "tiny": {},
    "paper": {"tex_res": 1024, "encoder": (64, 64, 64), "decoder": (128, 128, 128),
              "pose_channels": (16, 64), "iters": 100_000, "batch": 2, "lr": 1e-3,
              "neg_start": 25_000, "val_every": 5000, "val_samples": 64, "save_every": 5000},
}


def resolve_config(preset: str = "tiny", config_file: str | None = None,
                   overrides: dict | None = None, presets: dict | None = None,
                   config_class=TeacherConfig):
    """Preset, then the JSON object of ``config_file``, then ``overrides`` (flags).
    ``presets``/``config_class``: another model's (default: the teacher's)."""
    presets = PRESETS if presets is None else presets
    if preset not in presets:
        raise UsageProblem(f"unknown preset {preset!r}; use one of {', '.join(presets)}")
    values = dict(presets[preset])
    if config_file is not None:
        from relight_cli.formats._common import read_json
        obj = read_json(config_file)
        if not isinstance(obj, dict):
            raise DataError("a config file holds one JSON object of fields", config_file)
        values.update(obj.get("config", obj) if "format" in obj else obj)
    values.update({k: v for k, v in (overrides or {}).items() if v is not None})
    return config_class.from_dict(values)
