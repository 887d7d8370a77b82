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
    tiny    the same model at a quarter of the widths on a 32² texture, 150 iterations at
            the paper's lr 1e-3 (2e-3 collapsed the shadow logit on a dim capture: σ(S)
            saturates at 0 everywhere and no gradient brings it back), a minute or two on
            2 CPU cores, for tests and ``make demo``.
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


class _Config:
    """JSON round trip shared by every configuration dataclass (lists ↔ tuples)."""

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, values: dict, where: str = "config"):
        check_field_types(cls, values, where)
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise UsageProblem(f"unknown {where} field(s): {', '.join(unknown)}")
        base = asdict(cls())
        base.update(values)
        for name, value in base.items():
            if isinstance(getattr(cls(), name), tuple) and isinstance(value, list):
                base[name] = tuple(value)
        cfg = cls(**base)
        cfg.validate(where)
        return cfg


#: Longest list and string a configuration field may hold (the longest real one is
#: light_decoder's 8 widths; a longer value is no configuration and must not reach a
#: message or a model builder whole).
MAX_LIST = 64
MAX_TEXT = 64


def check_field_types(cls, values, where: str = "config") -> None:
    """UsageProblem unless ``values`` is a JSON object whose known fields each have their
    default's JSON type: true/false for flags, integers for counts, numbers for reals,
    strings for choices (≤ MAX_TEXT characters), lists of numbers for widths and sizes
    (≤ MAX_LIST items).  Run before a configuration is built, so that no field of a file
    (a checkpoint's ``config``, ``--config``) reaches ``validate`` or a model with a type
    it does not expect; ranges and choices are ``validate``'s.  Unknown fields are left
    to ``from_dict``'s own message."""
    if not isinstance(values, dict):
        raise UsageProblem(f"{where} must be a JSON object of fields, got "
                           f"{type(values).__name__}")
    defaults = asdict(cls())

    def number(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    for name, value in values.items():
        if name not in defaults:
            continue
        default = defaults[name]
        if isinstance(default, bool):
            ok, what = isinstance(value, bool), "true or false"
        elif isinstance(default, int):
            ok, what = isinstance(value, int) and not isinstance(value, bool), "an integer"
        elif isinstance(default, float):
            ok, what = number(value), "a number"
        elif isinstance(default, str):
            ok, what = isinstance(value, str) and len(value) <= MAX_TEXT, "a short string"
        elif isinstance(default, (tuple, list)):
            ok = isinstance(value, (list, tuple)) and len(value) <= MAX_LIST and \
                all(number(v) for v in value)
            what = f"a list of at most {MAX_LIST} numbers"
        else:
            continue
        if not ok:
            text = repr(value)
            raise UsageProblem(f"{where}: {name} must be {what}, got "
                               f"{text if len(text) <= 60 else text[:57] + '...'}")


@dataclass
class TrainingConfig(_Config):
    """The optimization fields every learned model shares (see :class:`TeacherConfig`)."""

    iters: int = 150
    batch: int = 2
    lr: float = 1e-3
    lr_schedule: str = "constant"
    lr_final: float = 1e-5
    channels_last: bool = False
    lambda_mse: float = 1.0
    lambda_vgg: float = 1.0
    lambda_neg: float = 0.01
    neg_eta: float = 5.0
    neg_start: int = 40
    neg_schedule: str = "decay"
    val_every: int = 0
    val_samples: int = 8
    save_every: int = 0
    seed: int = 0


@dataclass
class TeacherConfig(TrainingConfig):
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
        head: where Eq. 10's bias sits.  ``printed``: C = σ(S)·(ReLU(λ_s T) + λ_b), as the
            paper prints it, L_neg on λ_s T; ``code``: C = σ(S)·ReLU(λ_s T + λ_b), the
            reading of the authors' public code (facebookresearch/goliath), L_neg on the
            pre-ReLU λ_s T + λ_b (use it with ``neg_schedule: constant``, as that code
            does).  See :mod:`relight_cli.neural.models` for the measurement that chose
            the default.
        untied_bias: the OLAT U-Net's decoder and head carry one bias per texel (the
            authors' code) instead of one per channel.
        iters, batch, lr: Adam iterations, samples (frame × camera) per step, learning rate.
        lr_schedule, lr_final: ``constant`` keeps ``lr`` (the paper: 1e-3 for 100k
            iterations); ``cosine`` (ours, for the ``cpu`` preset's short runs) decays it
            from ``lr`` to ``lr_final`` over ``iters`` as ½(1 + cos(π t / iters)), a pure
            function of the step so ``--resume`` keeps it exact.
        channels_last: train with the convolutions' weights (and so their activations)
            in NHWC order, which oneDNN's CPU kernels run faster (a speed setting: the
            numbers differ from NCHW's only by float rounding; a run and its resume use
            the same order, so resume stays exact).
        lambda_mse, lambda_vgg, lambda_neg: Eq. 5's weights (VGG only with local weights).
        neg_eta, neg_start: Eq. 6's γ schedule η_neg and t_s (an iteration, so that a run
            extended by ``--resume --iters`` keeps the schedule it started with).
        neg_schedule: ``decay`` γ = exp(−max(η (t − t_s)/t, 0)) (1 until t_s, then decaying
            to e^−η: our reading of "starts decaying"), ``literal`` γ = exp(−max(η t/(t −
            t_s), 0)) as printed (1 until t_s, ≈ 0 just after, rising to e^−η), or
            ``constant`` γ = 1 (the authors' code: a constant weight).
        aa: G-buffer samples per pixel axis when rendering textures into images; 0 (the
            default): the capture's own (``settings.aa``, see
            :func:`relight_cli.neural.data.capture_aa`), so training and scoring sample
            pixels as the images were made.  The trained checkpoint records the value used.
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
    head: str = "printed"
    untied_bias: bool = False
    aa: int = 0
    holdout: float = 0.25
    cache_poses: int = 64

    def validate(self, where: str = "config") -> None:
        """Raise UsageProblem naming the first impossible field."""
        check = _Checker(self, where)
        check.choice("model", ("olat", "ggx"))
        check.choice("falloff", ("analytic", "none"))
        check.choice("head", ("printed", "code"))
        check.choice("neg_schedule", ("decay", "literal", "constant"))
        check.integer("tex_res", 8, 4096)
        for name in ("encoder", "decoder", "pose_channels"):
            check.widths(name)
        if len(self.pose_channels) != 2:
            check.bad("pose_channels", "must hold two widths (App. A.1: 16, 64)")
        if len(self.decoder) != len(self.encoder):
            check.bad("decoder", "must have as many widths as the encoder")
        if self.tex_res % (2 ** (len(self.encoder) - 1)):
            check.bad("tex_res", f"must be divisible by 2^{len(self.encoder) - 1} (the U-Net "
                      f"levels)")
        check.training()
        check.number("lambda_s", 0.0, 1e6, open_lo=True)
        check.number("lambda_b", 0.0, 1e6)
        check.number("holdout", 0.0, 0.9)
        check.integer("aa", 0, 8)
        check.integer("cache_poses", 1, 100000)
        check.boolean("visibility")
        check.boolean("untied_bias")


class _Checker:
    """Field checks shared by every configuration (UsageProblem naming the field)."""

    def __init__(self, config, where: str):
        self.config = config
        self.where = where

    def bad(self, name, why):
        raise UsageProblem(f"{self.where}: {name} {why}, got {getattr(self.config, name)!r}")

    def integer(self, name, lo=1, hi=10 ** 9):
        v = getattr(self.config, name)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            self.bad(name, f"must be an integer in [{lo}, {hi}]")

    def number(self, name, lo=0.0, hi=math.inf, open_lo=False):
        v = getattr(self.config, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or v < lo or v > hi or (open_lo and v == lo):
            self.bad(name, f"must be a finite number in {'(' if open_lo else '['}{lo}, {hi}]")

    def choice(self, name, options):
        if getattr(self.config, name) not in options:
            self.bad(name, "must be " + " or ".join(options))

    def boolean(self, name):
        if not isinstance(getattr(self.config, name), bool):
            self.bad(name, "must be true or false")

    def widths(self, name, lo=1, hi=4096):
        v = getattr(self.config, name)
        if not v or not all(isinstance(c, int) and not isinstance(c, bool) and lo <= c <= hi
                            for c in v):
            self.bad(name, f"must be a list of channel widths in [{lo}, {hi}]")

    def training(self):
        """iters, batch, lr, the loss weights, the L_neg schedule, cadences and the seed."""
        self.integer("iters")
        self.integer("batch", 1, 4096)
        self.number("lr", 0.0, 10.0, open_lo=True)
        self.choice("lr_schedule", ("constant", "cosine"))
        self.number("lr_final", 0.0, 10.0)
        self.boolean("channels_last")
        for name in ("lambda_mse", "lambda_vgg", "lambda_neg", "neg_eta"):
            self.number(name, 0.0, 1e6)
        self.integer("neg_start", 0)
        self.integer("val_every", 0)
        self.integer("val_samples", 1, 100000)
        self.integer("save_every", 0)
        self.integer("seed", 0, 2 ** 63 - 1)


PRESETS = {
    "tiny": {},
    # A workstation CPU: the 64² texture with per-texel decoder biases, tiny widths, a
    # cosine decay from 2e-3 over 6000 iterations, NHWC convolutions (21 % faster per
    # iteration here).  Measured (one core of the shared 2-core machine, before NHWC:
    # results differ by float rounding only) on the study's converged capture
    # (benchmarks/studies/scales.json "converged": 96 frames, 8 cameras, 64² images at
    # aa 2), held-out poses, 16 samples, seed 0: OLAT teacher 29.52 dB against a 33.12 dB
    # ceiling (gap 3.60 dB; 31.86 dB on the trained poses, gap 2.31) in 14 min; GGX 32.57
    # dB (gap 0.55 dB) in 18 min.  Wider OLAT widths (32/64) were no better after 1000
    # iterations (26.77 vs 26.98 dB) at 2.3× the cost.  benchmarks/bench_presets.py
    # re-measures every preset against its ceiling.
    "cpu": {"tex_res": 64, "untied_bias": True, "iters": 6000, "lr": 2e-3,
            "lr_schedule": "cosine", "lr_final": 1e-5, "neg_start": 1500, "val_every": 1000,
            "val_samples": 16, "save_every": 1000, "channels_last": True},
    "paper": {"tex_res": 1024, "encoder": (64, 64, 64), "decoder": (128, 128, 128),
              "pose_channels": (16, 64), "iters": 100_000, "batch": 2, "lr": 1e-3,
              "neg_start": 25_000, "val_every": 5000, "val_samples": 64, "save_every": 5000},
}


def resolve_config(preset: str = "tiny", config_file: str | None = None,
                   overrides: dict | None = None, presets: dict | None = None,
                   config_class=None, cls=None):
    """Preset, then the JSON object of ``config_file``, then ``overrides`` (flags).
    ``presets``/``config_class`` (alias ``cls``): another model's (default: the teacher's)."""
    config_class = config_class or cls or TeacherConfig
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


@dataclass
class StudentConfig(TrainingConfig):
    """How a student (``distill``) is built and trained (RelightableHands App. A.2–A.3).

    Attributes:
        student: ``student`` (texel-aligned features, App. A.2) or ``dram`` (App. A.3).
        tex_res: N of the N×N feature maps and predicted texture (paper 128); DRAM's
            decoder (untied per-texel biases) is built for this size.
        decoder: the 8-layer decoder's widths between input and output (paper 256, 256,
            128, 128, 64, 64, 32); DRAM: the first is its 4×4 code grid, each next one
            up-samples ×2 until tex_res.
        pose_channels: J_s(θ)'s widths (paper 16, 64; DRAM does not use J_s).
        specular: Phong features (False: Table 2's "w/o specular").
        visibility: features baked with visibility (False: Table 2's "w/o visibility").
        shininess: Phong exponents (paper 16, 32, 64).
        env_res: (H, W) of the env discretization (paper 16×32).
        env_holdout: fraction of the env maps kept for evaluation (paper 534 / 3094).
        rotations: augment training env maps with random rotations about +Y by whole
            longitude steps (exact: a column roll of the 16×32 grid).
        untied_bias: the student's decoder convolutions and head get one bias per texel
            and channel (the authors' code builds its decoders so) instead of one per
            channel: its only other input with spatial structure is the lighting
            features, so without them it cannot hold a per-texel albedo.  Measured
            (med_aa1, tiny, 32², 400 iterations, 5 training and 3 held-out env maps, the
            150-iteration tiny teacher): tied 18.87 dB vs the teacher, untied 17.69 dB —
            off by default until a converged comparison says otherwise.
        dram_code: DRAM's light code size (512).
        lambda_s, lambda_b: Eq. 11 in the paper's units, applied × PAPER_UNIT (the
            teacher's conversion: λ_b = 100 is a floor of 0.125 where a white texel
            under a uniform env is 1, π× below the paper's 100/255 — see
            :mod:`relight_cli.neural.student`); λ_b = 0 by default (without a shadow
            gate λ_b is a radiance floor).
        cache_mb: memory budget of the teacher's per-direction textures (pseudo ground
            truth); beyond it they go to the disk cache (``distill --cache DIR``) or are
            recomputed.
        iters, batch, lr, lambda_*, neg_*, val_every, val_samples, save_every, seed: as
            :class:`TeacherConfig` (paper: batch 4, 100k iterations, lr 1e-3).
    """

    student: str = "student"
    tex_res: int = 32
    decoder: tuple = (32, 32, 16, 16, 16, 16, 8)
    pose_channels: tuple = (8, 16)
    specular: bool = True
    visibility: bool = True
    shininess: tuple = (16, 32, 64)
    env_res: tuple = (16, 32)
    env_holdout: float = 0.17
    rotations: bool = True
    untied_bias: bool = False
    dram_code: int = 64
    cache_mb: int = 2048
    lambda_s: float = 25.0
    lambda_b: float = 0.0
    lr: float = 2e-3

    def validate(self, where: str = "config") -> None:
        check = _Checker(self, where)
        check.choice("student", ("student", "dram"))
        check.choice("neg_schedule", ("decay", "literal", "constant"))
        check.integer("tex_res", 8, 4096)
        check.widths("decoder")
        check.widths("pose_channels")
        if len(self.pose_channels) != 2:
            check.bad("pose_channels", "must hold two widths (App. A.1: 16, 64)")
        if not self.shininess or not all(isinstance(a, (int, float)) and not isinstance(a, bool)
                                         and 0 < a <= 1e4 for a in self.shininess):
            check.bad("shininess", "must be a list of Phong exponents in (0, 10000]")
        if len(self.env_res) != 2 or not all(isinstance(v, int) and 2 <= v <= 1024
                                             for v in self.env_res):
            check.bad("env_res", "must be [H, W] with 2 ≤ H, W ≤ 1024")
        check.number("env_holdout", 0.0, 0.9)
        check.integer("dram_code", 1, 65536)
        check.integer("cache_mb", 0, 10 ** 7)
        check.number("lambda_s", 0.0, 1e6, open_lo=True)
        check.number("lambda_b", 0.0, 1e6)
        for name in ("specular", "visibility", "rotations", "untied_bias"):
            check.boolean(name)
        check.training()


STUDENT_PRESETS = {
    "tiny": {},
    # A workstation CPU: 64² maps (distill from a ``cpu`` teacher), a decoder between the
    # tiny and the paper widths, a cosine decay from 2e-3 over 4000 iterations, 8×16 env
    # directions (the teacher's per-direction textures of a (pose, camera) pair cost
    # 0.4–3 s each on one CPU core at 64²: 16×32 would make distillation 4× slower).
    # Not yet measured to convergence: benchmarks/bench_presets.py.
    "cpu": {"tex_res": 64, "decoder": (64, 64, 32, 32, 32, 32, 16), "iters": 4000,
            "lr": 2e-3, "lr_schedule": "cosine", "lr_final": 1e-5, "neg_start": 1000,
            "env_res": (8, 16), "val_every": 1000, "val_samples": 16, "save_every": 1000,
            "channels_last": True},
    "paper": {"tex_res": 128, "decoder": (256, 256, 128, 128, 64, 64, 32),
              "pose_channels": (16, 64), "dram_code": 512, "iters": 100_000, "batch": 4,
              "lr": 1e-3, "neg_start": 25_000, "val_every": 5000, "val_samples": 64,
              "save_every": 5000},
}


def resume_config(checkpoint: dict, cls, overrides: dict, config_file: str | None,
                  iters: int | None, source: str):
    """The configuration a ``--resume`` continues: the checkpoint's own, where only
    ``iters`` may grow.  UsageProblem for other changed fields or a finished run."""
    import json as _json
    raw = checkpoint["config"]
    try:
        values = _json.loads(raw) if isinstance(raw, str) else raw
        check_field_types(cls, values, "checkpoint config")
        config = cls.from_dict(values, "checkpoint config")
    except UsageProblem as exc:
        raise DataError(exc.message, source) from None
    except (TypeError, ValueError) as exc:    # not JSON (read_checkpoint checked it before)
        raise DataError(f"checkpoint config: {str(exc).splitlines()[0][:120]}",
                        source) from None
    changed = sorted(k for k, v in overrides.items()
                     if v is not None and k != "iters" and getattr(config, k) != v)
    if changed or config_file is not None:
        raise UsageProblem("--resume continues the checkpoint's own configuration; only "
                           "--iters may change (got " + ", ".join(changed or ["--config"]) + ")")
    step = checkpoint["step"]
    if isinstance(step, bool) or not isinstance(step, int) or not 0 <= step <= config.iters:
        raise DataError(f"checkpoint step must be an integer in [0, {config.iters}], got "
                        f"{step!r}"[:160], source)
    if iters is not None:
        if iters <= step:
            raise UsageProblem(f"--iters {iters} is not beyond the checkpoint's step {step}")
        config.iters = iters
    elif step >= config.iters:
        raise UsageProblem(f"the checkpoint already ran its {config.iters} iterations; give "
                           f"--iters to continue further", source)
    return config
