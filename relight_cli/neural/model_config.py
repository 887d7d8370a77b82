"""The configuration of a learned model: a checkpoint's ``config`` field, a ``--config`` file.

One flat dataclass of JSON values per model (:class:`TeacherConfig` for
``train-teacher``'s OLAT and GGX teachers, :class:`StudentConfig` for ``distill``,
:class:`LinearConfig` for URHand's linear model), its JSON types
(:func:`check_field_types`) and its ranges (``validate``).  A configuration is
resolved once (preset, then ``--config FILE.json``, then command-line flags: the
presets are beside it, ``relight_cli.neural.config``), stored verbatim in the
checkpoint's ``config`` field and read back from it, so a checkpoint says exactly how
it was trained and ``--resume`` continues the same run.  The fields' meaning in the
paper's terms is in each class's docstring; ``relight_cli.neural.config`` and
``relight_cli.neural.linear`` re-export the classes.

These are the models' research knobs, so they live with the models, not with the file
formats: the checkpoint format (``formats/checkpoint.md``, version 1) holds the envelope
and checks the configuration through the class the model registry names for its kind
(:func:`relight_cli.neural.checkpoints.read_checkpoint`), before any network is built.
A new knob is a change here, not a new format version; a checkpoint from before a knob
existed reads with its default.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields

from relight_cli.errors import UsageProblem


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

#: Size limits of a configuration, checked before any model is built (a checkpoint's
#: config asking for more is refused naming the file instead of running out of memory):
#: ``tex_res² × the widest layer`` — the elements of one feature tensor of one sample — at
#: most MAX_FEATURE_ELEMENTS (2^28: 1 GiB of float32; the paper presets need at most
#: 2^28, the linear model's 1024² maps × its 256-wide light decoder), and the 3×3
#: convolutions between consecutive widths of each list at most MAX_PARAMETERS weights
#: (2^28: 1 GiB of float32; the paper presets hold under 2^20).
MAX_FEATURE_ELEMENTS = 2 ** 28
MAX_PARAMETERS = 2 ** 28


def check_sizes(where: str, tex_res: int, *widths) -> None:
    """UsageProblem when ``tex_res`` and the width lists exceed :data:`MAX_FEATURE_ELEMENTS`
    or :data:`MAX_PARAMETERS` (call after the fields themselves are checked)."""
    widest = max((max(w) for w in widths if w), default=1)
    if tex_res * tex_res * widest > MAX_FEATURE_ELEMENTS:
        raise UsageProblem(f"{where}: tex_res² × the widest layer must be at most "
                           f"{MAX_FEATURE_ELEMENTS} elements per feature tensor (1 GiB of "
                           f"float32), got {tex_res}² × {widest}")
    weights = sum(9 * a * b for w in widths for a, b in zip(w, w[1:]))
    if weights > MAX_PARAMETERS:
        raise UsageProblem(f"{where}: the layer widths make about {weights} convolution "
                           f"parameters, more than the limit of {MAX_PARAMETERS} (1 GiB of "
                           f"float32)")


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
        inputs: the OLAT U-Net's per-texel input.  ``paper``: local light direction,
            local view direction and visibility (App. A.1, 7 channels); ``half`` (ours)
            adds the local half vector h = (l + v)/‖l + v‖ (10 channels), on which a
            microfacet lobe is a function of one coordinate (h_z = n·h); ``shading``
            (ours) adds one light's share of the student's shading features (Sec. 4.2,
            Eq. 8–9): V·max(n·l, 0) and the same times the three Phong lobes
            max(r·l, 0)^{16,32,64} (11 channels; Eq. 9's lobe has no cosine, ours does).  See :mod:`relight_cli.neural.models` for the measurements.
            The OLAT teacher's only (the GGX baseline builds its own inputs).
        pose: what the teacher's pose encoder sees.  ``joints``: θ (App. A.1); ``none``
            (ours, an ablation): zeros, so the pose reaches the texture only through the
            per-texel inputs (directions in the posed texel frames and visibility).
        view: what the OLAT teacher sees of the view.  ``direction``: the local view
            direction v at every texel (App. A.1); ``none`` (ours, an ablation): zeros
            for v (and so for the Phong lobes of ``inputs: shading``), a teacher whose
            texture cannot depend on the camera — no highlights, and no view-dependent
            error in its diffuse response either.
        iters, batch, lr: Adam iterations, samples (frame × camera) per step, learning rate.
        lr_schedule, lr_final: ``constant`` keeps ``lr`` (the paper: 1e-3 for 100k
            iterations); ``cosine`` (ours, for the ``cpu`` preset's short runs) decays it
            from ``lr`` to ``lr_final`` over ``iters`` as ½(1 + cos(π t / iters)), a pure
            function of the step so ``--resume`` keeps it exact.
        channels_last: train with the convolutions' weights (and so their activations)
            in NHWC order, which oneDNN's CPU kernels run faster (a speed setting: the
            numbers differ from NCHW's only by float rounding; a run and its resume use
            the same order, so resume stays exact); a checkpoint that trained so is
            loaded so for inference too (``relight_cli.neural.checkpoints``).
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
    inputs: str = "paper"
    pose: str = "joints"
    view: str = "direction"
    aa: int = 0
    holdout: float = 0.25
    cache_poses: int = 64

    def validate(self, where: str = "config") -> None:
        """Raise UsageProblem naming the first impossible field."""
        check = _Checker(self, where)
        check.choice("model", ("olat", "ggx"))
        check.choice("falloff", ("analytic", "none"))
        check.choice("head", ("printed", "code"))
        check.choice("inputs", ("paper", "half", "shading"))
        check.choice("pose", ("joints", "none"))
        check.choice("view", ("direction", "none"))
        if self.model == "ggx" and self.inputs != "paper":
            check.bad("inputs", "is the OLAT teacher's; the GGX baseline builds its own")
        if self.model == "ggx" and self.view != "direction":
            check.bad("view", "is the OLAT teacher's; the GGX lobe needs the view")
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
        check_sizes(where, self.tex_res, self.encoder, self.decoder, self.pose_channels)
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

    def training(self, min_iters: int = 1):
        """iters, batch, lr, the loss weights, the L_neg schedule, cadences and the seed."""
        self.integer("iters", min_iters)
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
        env_res: (H, W) of the env discretization the student is trained on: its
            features and the teacher's pseudo ground truth Σ_m b_m C_m (paper 16×32).
        render_env_res: (H, W) of the env grid its features are baked on when it renders
            after training (``relight --model student``, distill's ``vs_ground_truth``);
            empty: ``env_res`` (the paper's reading: one grid, M = 512 = 16×32 for the
            features and the pseudo ground truth, RelightableHands Sec. 5).  Ours: the features are
            physically based integrals over the sphere, so a texel-aligned student
            trained on a coarse grid (cheap pseudo ground truth) renders on a finer one
            (sharper shadows and highlights); DRAM's light code is its training grid's
            radiance, so it renders on ``env_res`` only.
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
        env_augment: ``paper`` (the training maps as given, with ``rotations``) or ``mix``
            (ours): every sample's env map synthesized from the training maps — a mixture
            of up to three, each rotated, mirrored and tinted, and a random sun cell
            (:func:`relight_cli.neural.distill.mix_env`); exact pseudo ground truth at no
            teacher cost.  The paper distills on 2,560 real maps; a capture here has a few.
        head: ``eq11`` (the paper's: the CNN maps features and J_s(θ) to the texture,
            Eq. 11) or ``linear`` (ours): the CNN maps J_s(θ) alone, with per-texel
            biases, to per-texel weights of each feature map and the texture is
            ReLU(Σ_k W_k ⊙ F_k), linear in the env map
            (:class:`relight_cli.neural.student.LinearHeadStudent`).
        head_init: the linear head's start: ``grey`` (a grey Lambertian texture) or
            ``lsq`` (the per-texel least-squares fit of the teacher's textures by the
            features, :func:`relight_cli.neural.distill.fit_linear_head`); with ``lsq``,
            ``iters`` may be 0: the closed-form fit is the student.
        loss_space: where the distillation loss compares the student with its teacher:
            ``image`` (the paper's, Sec. 4.3: the composited image under the sample's
            camera, over the hand's pixels) or ``texture`` (ours): the texture itself,
            over every texel inside the UV charts — the teacher's view-dependent texture
            for the sample's camera, Σ_m b_m C_m, resampled to the student's N when the
            teacher's differs.  Every texel is supervised on every sample, not only those
            the camera sees at the image's resolution — including texels facing away
            from the camera, whose teacher targets are views it never trained on: 5 dB
            worse for the linear-head student, a tie for DRAM (README).
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
    render_env_res: tuple = ()
    env_holdout: float = 0.17
    rotations: bool = True
    untied_bias: bool = False
    env_augment: str = "paper"
    head: str = "eq11"
    head_init: str = "grey"
    loss_space: str = "image"
    dram_code: int = 64
    cache_mb: int = 2048
    lambda_s: float = 25.0
    lambda_b: float = 0.0
    lr: float = 2e-3

    def validate(self, where: str = "config") -> None:
        check = _Checker(self, where)
        check.choice("student", ("student", "dram"))
        check.choice("env_augment", ("paper", "mix"))
        check.choice("head", ("eq11", "linear"))
        if self.head == "linear" and self.student != "student":
            check.bad("head", "linear is a head of the texel-aligned student, not of dram")
        check.choice("head_init", ("grey", "lsq"))
        if self.head_init == "lsq" and self.head != "linear":
            check.bad("head_init", "lsq starts the linear head (head: linear)")
        check.choice("loss_space", ("image", "texture"))
        check.choice("neg_schedule", ("decay", "literal", "constant"))
        check.integer("tex_res", 8, 4096)
        check.widths("decoder")
        check.widths("pose_channels")
        if len(self.pose_channels) != 2:
            check.bad("pose_channels", "must hold two widths (App. A.1: 16, 64)")
        check_sizes(where, self.tex_res, self.decoder, self.pose_channels)
        if not self.shininess or not all(isinstance(a, (int, float)) and not isinstance(a, bool)
                                         and 0 < a <= 1e4 for a in self.shininess):
            check.bad("shininess", "must be a list of Phong exponents in (0, 10000]")
        if len(self.env_res) != 2 or not all(isinstance(v, int) and 2 <= v <= 1024
                                             for v in self.env_res):
            check.bad("env_res", "must be [H, W] with 2 ≤ H, W ≤ 1024")
        if self.render_env_res and (len(self.render_env_res) != 2 or not all(
                isinstance(v, int) and 2 <= v <= 1024 for v in self.render_env_res)):
            check.bad("render_env_res", "must be [] or [H, W] with 2 ≤ H, W ≤ 1024")
        if (self.student == "dram" and self.render_env_res
                and tuple(self.render_env_res) != tuple(self.env_res)):
            check.bad("render_env_res", "DRAM renders on its training grid (env_res): its "
                      "light code is that grid's radiance")
        check.number("env_holdout", 0.0, 0.9)
        check.integer("dram_code", 1, 65536)
        check.integer("cache_mb", 0, 10 ** 7)
        check.number("lambda_s", 0.0, 1e6, open_lo=True)
        check.number("lambda_b", 0.0, 1e6)
        for name in ("specular", "visibility", "rotations", "untied_bias"):
            check.boolean(name)
        # a least-squares start is a student by itself: iters 0 is the closed form alone
        check.training(0 if self.head_init == "lsq" else 1)


LIGHT_PATHS = ("linear", "nonlinear", "mlp")
FEATURES = ("pbr", "phong")
REG_LAYERS = ("encoder", "all")


@dataclass
class LinearConfig:
    """How URHand's model (``train-teacher --model linear``) is built and trained.

    Attributes:
        model: always ``linear`` (the checkpoint's kind and model).
        tex_res: N of the N×N UV maps.
        encoder, decoder, pose_channels: F_G's U-Net widths per level and pose encoder
            (supp. 8.2: six levels of 64).
        light_decoder: F_l's decoder widths, bottleneck first, 8 entries ending in 4
            (supp. 8.3: 128, 256, 128, 128, 64, 32, 16, 4); F_nl has the same widths.
        light_levels: upsampling layers of the decoder (the bottleneck is N / 2^levels;
            paper 6: 1024 → 16², the 128×16×16 of supp. 10.2).
        light_path: ``linear``, ``nonlinear`` (Table 2's non-linear ablation) or ``mlp``
            (Table 2's holistic MLP-based linear model of [64], supp. 10.2).
        features: ``pbr`` (Eq. 10–15) or ``phong`` (Table 3).
        specular, visibility, refiner: Table 3's ablations when False.
        fresnel: ``schlick`` (relight_cli.brdf) or ``sg`` (Eq. 13 as printed).
        shininess: Phong exponent of ``features=phong``.
        displacement_mm: δd range (Eq. 2: 3 mm).
        sigma_t: σ_T of Eq. 6 in the paper's 8-bit units (64; × PAPER_UNIT in ours).
        residual: ours: g, b start from C^d, C^s/σ_T (see the module docstring).
        iters, batch, lr, lr_final, lr_drop: Adam; lr drops to lr_final at iteration
            lr_drop (the paper's multistep 1e-4 → 3e-5; an iteration, not a fraction, so a
            run extended by ``--resume --iters`` keeps its schedule).
        lambda_img, lambda_pb: Eq. 7's L1 weights of the neural and physical renders.
        lambda_vgg: perceptual loss (only with local weights; the paper's is EfficientNet).
        lambda_reg: Eq. 9's L1 weight on the light path's intermediate maps, in the paper's
            units (0.01); the loss converts it to ours (× PAPER_UNIT × feature_scale, see
            :func:`~relight_cli.neural.linear_train.reg_weight`).
        reg_layers: which maps Eq. 9 penalizes: ``encoder`` (the default: F_l-enc, as Eq. 9
            writes and the authors' code does) or ``all`` (every encoder and decoder map,
            a literal reading of "all layers in the linear branch"; it lets the loss zero
            the modulated decoder and so the whole learned light path).
        linearity_loss: weight of Eq. 17 (0: off); applied every ``linearity_every`` steps.
        lambda_gan: Eq. 8's lighting-aware hinge adversarial loss (paper 0.01; 0: off,
            the tiny default: seconds matter more than sharpness there).
        gan_conditioned: the discriminator sees the Phong lighting prompt {A, S} (False:
            supp. 10.2's w/o light-aware L_GAN).  gan_width: its first conv width.
        aa, holdout, val_every, val_samples, save_every, cache_poses, seed: as for the
            teacher (:class:`TeacherConfig`).
        env_res: [H, W] env-map discretization of validation renders.
        ema: ours, not the paper's (0: off, the presets' default): decay of an
            exponential moving average of the weights (Polyak averaging, torch's
            ``AveragedModel``), updated after every step; validations score it and the
            checkpoint's weights are it, the raw weights kept in ``extra.training_weights``
            for an exact ``--resume``.  At the ``cpu`` preset's final lr (2e-4, batch 2)
            the raw weights' held-out PSNR moves ±0.5 dB from one validation to the next,
            every subject of a seed together (benchmarks/README.md, identity table).
    """

    model: str = "linear"
    tex_res: int = 32
    encoder: tuple = (16, 16, 16)
    decoder: tuple = (16, 16, 16)
    pose_channels: tuple = (8, 16)
    light_decoder: tuple = (16, 32, 16, 16, 8, 8, 8, 4)
    light_levels: int = 3
    light_path: str = "linear"
    features: str = "pbr"
    specular: bool = True
    visibility: bool = True
    refiner: bool = True
    fresnel: str = "schlick"
    shininess: float = 32.0
    displacement_mm: float = 3.0
    sigma_t: float = 64.0
    residual: bool = True
    iters: int = 150
    batch: int = 2
    lr: float = 2e-3
    lr_final: float = 6e-4
    lr_drop: int = 100
    lambda_img: float = 1.0
    lambda_pb: float = 1.0
    lambda_vgg: float = 1.0
    lambda_reg: float = 0.01
    reg_layers: str = "encoder"
    linearity_loss: float = 0.0
    linearity_every: int = 1
    lambda_gan: float = 0.0
    gan_conditioned: bool = True
    gan_width: int = 16
    aa: int = 0
    holdout: float = 0.25
    val_every: int = 0
    val_samples: int = 8
    save_every: int = 0
    cache_poses: int = 64
    seed: int = 0
    env_res: tuple = (16, 32)
    ema: float = 0.0

    @property
    def falloff(self) -> str:
        """1/r² is part of the features (Eq. 10), never learned."""
        return "analytic"

    def to_dict(self) -> dict:
        """The fields as JSON values; ``ema`` only when on (a run without it writes the
        checkpoint, and keys the study caches, exactly as before the field existed)."""
        out = {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}
        if not out["ema"]:
            del out["ema"]
        return out

    @classmethod
    def from_dict(cls, values: dict, where: str = "config") -> "LinearConfig":
        check_field_types(cls, values, where)
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise UsageProblem(f"unknown {where} field(s): {', '.join(unknown)}")
        base = asdict(cls())
        base.update(values)
        base = {k: tuple(v) if isinstance(v, list) else v for k, v in base.items()}
        cfg = cls(**base)
        cfg.validate(where)
        return cfg

    def validate(self, where: str = "config") -> None:
        """Raise UsageProblem naming the first impossible field."""
        def is_int(v):
            return isinstance(v, int) and not isinstance(v, bool)

        def is_num(v):
            return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

        choices = {"model": ("linear",), "light_path": LIGHT_PATHS, "features": FEATURES,
                   "fresnel": ("schlick", "sg"), "reg_layers": REG_LAYERS}
        ints = {"tex_res": (8, 4096), "light_levels": (0, 7), "iters": (1, 10 ** 9),
                "lr_drop": (0, 10 ** 9),
                "batch": (1, 4096), "linearity_every": (1, 10 ** 9), "gan_width": (1, 4096), "aa": (0, 8),
                "val_every": (0, 10 ** 9), "val_samples": (1, 100000), "save_every": (0, 10 ** 9),
                "cache_poses": (1, 100000), "seed": (0, 2 ** 63 - 1)}
        numbers = {"lr": (0, 10, True), "lr_final": (0, 10, True), "shininess": (0, 1e4, True),
                   "displacement_mm": (0, 100, False), "sigma_t": (0, 1e6, True),
                   "holdout": (0, 0.9, False), "ema": (0, 0.99999, False)}
        for name in ("lambda_img", "lambda_pb", "lambda_vgg", "lambda_reg", "linearity_loss",
                     "lambda_gan"):
            numbers[name] = (0, 1e6, False)
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise UsageProblem(f"{where}: {name} must be one of {', '.join(allowed)}, got "
                                   f"{getattr(self, name)!r}")
        for name, (lo, hi) in ints.items():
            v = getattr(self, name)
            if not is_int(v) or not lo <= v <= hi:
                raise UsageProblem(f"{where}: {name} must be an integer in [{lo}, {hi}], got {v!r}")
        for name, (lo, hi, open_lo) in numbers.items():
            v = getattr(self, name)
            if not is_num(v) or v < lo or v > hi or (open_lo and v == lo):
                raise UsageProblem(f"{where}: {name} must be a finite number in "
                                   f"{'(' if open_lo else '['}{lo}, {hi}], got {v!r}")
        for name in ("specular", "visibility", "refiner", "residual", "gan_conditioned"):
            if not isinstance(getattr(self, name), bool):
                raise UsageProblem(f"{where}: {name} must be true or false")
        for name in ("encoder", "decoder", "pose_channels", "light_decoder", "env_res"):
            v = getattr(self, name)
            if not v or not all(is_int(c) and 1 <= c <= 4096 for c in v):
                raise UsageProblem(f"{where}: {name} must be a list of sizes in [1, 4096], "
                                   f"got {v!r}")
        if len(self.decoder) != len(self.encoder):
            raise UsageProblem(f"{where}: decoder must have as many widths as the encoder")
        if len(self.pose_channels) != 2 or len(self.env_res) != 2:
            raise UsageProblem(f"{where}: pose_channels and env_res hold two numbers each")
        if len(self.light_decoder) != 8 or self.light_decoder[-1] != 4:
            raise UsageProblem(f"{where}: light_decoder holds 8 widths ending in 4 (gain 3, "
                               f"bias 1; supp. 8.3), got {list(self.light_decoder)}")
        step = 2 ** max(len(self.encoder) - 1, self.light_levels)
        if self.tex_res % step:
            raise UsageProblem(f"{where}: tex_res must be divisible by {step} (the U-Net and "
                               f"light-path levels), got {self.tex_res}")
        check_sizes(where, self.tex_res, self.encoder, self.decoder, self.pose_channels,
                    self.light_decoder)
        if self.linearity_loss > 0 and self.light_path == "linear":
            raise UsageProblem(f"{where}: linearity_loss (Eq. 17) constrains the non-linear "
                               f"light path; the linear one is linear by construction")
