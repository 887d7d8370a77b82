"""Configurations of the learned models and the ``tiny`` / ``paper`` presets.

A configuration is a flat dataclass of JSON values: it is resolved once (preset, then
``--config FILE.json``, then command-line flags), stored verbatim in the checkpoint and
read back from it, so a checkpoint says exactly how it was trained and ``--resume``
continues the same run.  The dataclasses are in ``relight_cli.neural.model_config``,
re-exported here; the presets, their resolution and ``--resume``'s rules are here.

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

import math

from relight_cli.errors import DataError, UsageProblem
from relight_cli.neural.model_config import (MAX_LIST, MAX_TEXT, StudentConfig,  # noqa: F401
                                              TeacherConfig, TrainingConfig, check_field_types)

#: λ_s and λ_b of Eq. 10 are in the paper's 8-bit pixel units (255 = white).  Our
#: textures are radiance per unit irradiance (sr⁻¹), where a white Lambertian surface
#: facing the light is 1/π; one paper unit is therefore 1/(255 π) of ours.
PAPER_UNIT = 1.0 / (255.0 * math.pi)


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


#: A preset's fields for one teacher model, over the preset's own (the config file and
#: flags still override them).  GGX at ``cpu``: at the OLAT teacher's lr 2e-3 the GGX row
#: of the converged study (benchmarks/studies/scales.json, right hand, seed 0) collapsed
#: at step ~1,820: a gradient spike in the material U-Net's pose branch, then within 30
#: steps its albedo and roughness σ saturated (ρ = 1 on 98 % of texels, albedo 1.0) and
#: held-out PSNR fell from 30.5 to 19.6 dB for good (an earlier build diverged to NaN at
#: step 466 on the same row).  The same row at lr 5e-4 trains smoothly to 33.11 dB against
#: its 33.12 dB ceiling in 18 min on one core.  The paper trains its GGX baseline with the
#: teacher's hyperparameters (App. B): ``--lr 2e-3`` gives that.
#: The OLAT teacher at ``cpu`` takes the student's shading features as further input
#: (``inputs: shading``, ours; :mod:`relight_cli.neural.models`): on the converged capture
#: (three seeds, 2-core AMD EPYC, benchmarks/results/converged/teacher_shading/) every
#: held-out sample scores 30.80 ± 0.19 dB against the paper input's 29.96 ± 0.01 (gap to
#: the ceiling 2.00 → 1.15 dB), fully lit frames +0.68 dB, held-out env maps a tie, at no
#: extra time.  ``--config`` with ``{"inputs": "paper"}`` gives App. A.1's input; ``paper``
#: and ``tiny`` keep it.
PRESET_MODEL = {("cpu", "ggx"): {"lr": 5e-4}, ("cpu", "olat"): {"inputs": "shading"}}


def resolve_config(preset: str = "tiny", config_file: str | None = None,
                   overrides: dict | None = None, presets: dict | None = None,
                   config_class=None, cls=None):
    """Preset, then the JSON object of ``config_file``, then ``overrides`` (flags).
    ``presets``/``config_class`` (alias ``cls``): another model's (default: the teacher's).
    A preset's fields for one model (:data:`PRESET_MODEL`, :data:`STUDENT_PRESET_MODEL`)
    apply over the preset's own, under the file's and the flags'."""
    config_class = config_class or cls or TeacherConfig
    presets = PRESETS if presets is None else presets
    if preset not in presets:
        raise UsageProblem(f"unknown preset {preset!r}; use one of {', '.join(presets)}")
    from_file = {}
    if config_file is not None:
        from relight_cli.formats._common import read_json
        obj = read_json(config_file)
        if not isinstance(obj, dict):
            raise DataError("a config file holds one JSON object of fields", config_file)
        from_file = obj.get("config", obj) if "format" in obj else obj
        if not isinstance(from_file, dict):
            raise DataError("a config record's 'config' holds one JSON object of fields",
                            config_file)
    flags = {k: v for k, v in (overrides or {}).items() if v is not None}

    def build(given: dict):
        values = dict(presets[preset])
        if presets is PRESETS:
            model = given.get("model", values.get("model", TeacherConfig.model))
            values.update(PRESET_MODEL.get((preset, model), {}))
        elif presets is STUDENT_PRESETS:
            kind = given.get("student", values.get("student", "student"))
            values.update(STUDENT_PRESET_MODEL.get((preset, kind), {}))
        values.update(given)
        return config_class.from_dict(values)

    if config_file is not None:
        # The file is checked on its own first (the preset and the file, with the flags
        # that pick the model), and its line names the file: a field a flag overrides is
        # still the file's and must be valid (``"iters": "10"`` under ``--iters 2``); a
        # problem only the other flags bring stays the flags' (no file named).
        kind = {k: flags[k] for k in ("model", "student") if k in flags}
        try:
            build({**from_file, **kind})
        except UsageProblem as exc:
            if exc.path is not None:
                raise
            raise UsageProblem(exc.message, config_file, exc.hint) from None
    return build({**from_file, **flags})


def resolve_student_config(preset: str = "tiny", config_file: str | None = None,
                           overrides: dict | None = None):
    """:func:`resolve_config` for the student (its presets and configuration class)."""
    return resolve_config(preset, config_file, overrides, presets=STUDENT_PRESETS,
                          config_class=StudentConfig)


STUDENT_PRESETS = {
    "tiny": {},
    # A workstation CPU: 64² maps (distill from a ``cpu`` teacher), a decoder between the
    # tiny and the paper widths, a cosine decay from 2e-3 over 4000 iterations, 8×16 env
    # directions (the teacher's per-direction textures of a (pose, camera) pair cost
    # 0.4–3 s each on one CPU core at 64²: 16×32 would make distillation 4× slower).
    # cache_mb 8192: the teacher's textures of every training (pose, camera) pair stay in
    # memory (6.3 MB each at 64² and 8×16; the converged study capture's 584 pairs need
    # 3.7 GB): at the default 2048 MB 44 % of its samples recomputed a 0.8 s teacher pass,
    # 45 min per student instead of about 10.  The budget is a ceiling, not an allocation.
    # Measured to convergence (Eq. 11's head): benchmarks/results/converged/study_rh_t2.md;
    # the texel-aligned student's head at this preset: STUDENT_PRESET_MODEL below.
    "cpu": {"tex_res": 64, "decoder": (64, 64, 32, 32, 32, 32, 16), "iters": 4000,
            "lr": 2e-3, "lr_schedule": "cosine", "lr_final": 1e-5, "neg_start": 1000,
            "env_res": (8, 16), "val_every": 1000, "val_samples": 16, "save_every": 1000,
            "channels_last": True, "cache_mb": 8192},
    "paper": {"tex_res": 128, "decoder": (256, 256, 128, 128, 64, 64, 32),
              "pose_channels": (16, 64), "dram_code": 512, "iters": 100_000, "batch": 4,
              "lr": 1e-3, "neg_start": 25_000, "val_every": 5000, "val_samples": 64,
              "save_every": 5000},
}


#: A student preset's fields for one kind of student (the config file and flags still
#: override them).  The texel-aligned student at ``cpu`` has the linear head (ours,
#: :class:`relight_cli.neural.student.LinearHeadStudent`): on the converged capture
#: (three seeds, 2-core AMD EPYC, benchmarks/results/converged/student_linear/), against
#: the stage's ground truth under held-out env maps on held-out poses, 27.58 ± 0.15 dB
#: where the paper's Eq. 11 head has 23.55 ± 0.81 (+4.03 ± 0.95 dB, better on every
#: seed; gap to the 34.22 dB ceiling 10.67 → 6.64 dB), in 12.9 instead of 16.7 min per
#: student; the Eq. 11 head trained twice as long reaches 24.31 dB.  ``--config`` with
#: ``{"head": "eq11"}`` gives the paper's head; ``paper`` and ``tiny`` keep it.  It renders
#: on the paper's 16×32 feature grid (``render_env_res``) although it trains on 8×16 (the
#: teacher's pseudo ground truth is 4× cheaper there): the same checkpoints against the
#: same ground truth (consistent ``texels`` stage truth, three seeds,
#: benchmarks/results/converged/student_grid/) gain 1.5–2.0 dB over rendering on their
#: training grid, most of what the 8×16 grid costs.
#: DRAM's head at every preset: λ_s = 1/PAPER_UNIT = 255π, so λ_s · PAPER_UNIT = 1 and the
#: decoder's output is in the texture's own units (ours; App. A.3 does not give DRAM's
#: head, we reuse Eq. 11's form).  With the student's λ_s = 25 the head multiplies the
#: decoder's output by 0.031, so the light-dependent part of the texture has to be 32×
#: larger inside the decoder.  At ``tiny`` (tests/neural/test_student.py's light gate,
#: seeds 0–2) DRAM's texture change between its two training maps is 0.96–0.98 of the
#: teacher's with it and 0.39–0.74 at 25.  At ``cpu`` it does not settle whether DRAM's
#: light path trains: on the converged capture (seed 0, by hand: the texture's standard
#: deviation over 21 training lightings at a training pose, the teacher's 0.21) one run
#: learned the light (0.141, at λ_s = 800) and two did not (0.032 at 4,000 iterations,
#: 0.031 at 12,000), no better than λ_s = 25 (0.028; seed 1: 0.039 and 0.041 at 25).  The
#: two-seed table (benchmarks/results/converged/student_dram_head/) is a tie with λ_s = 25
#: on every split (consistent truth −0.34 ± 0.56 dB).  With four seeds of teachers
#: retrained on another machine (benchmarks/results/converged/student_dram_b8/) its light
#: path trained in two runs of four (share of the teacher's variation explained 0.01,
#: 0.34, 0.08, 0.30); batches of 8 train it on every seed (0.33–0.39) and tie on the
#: held-out maps (+1.10 ± 0.90 dB), so the preset keeps the paper's batch.  ``--config``
#: with ``{"lambda_s": 25}`` gives the Eq. 11 scale back.
DRAM_LAMBDA_S = 1.0 / PAPER_UNIT
STUDENT_PRESET_MODEL = {("cpu", "student"): {"head": "linear", "render_env_res": (16, 32)},
                        **{(p, "dram"): {"lambda_s": DRAM_LAMBDA_S}
                           for p in ("tiny", "cpu", "paper")}}


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
