"""Distill RelightableHands' student (or the DRAM baseline) from a trained teacher:
``relight distill`` as an engine job.

    load_teacher(...)  a read teacher checkpoint → :class:`Teacher` (the model to distill)
    configure(...)     the student's configuration: preset, config file, flags; or,
                       resuming, the checkpoint's own (only ``iters`` may grow)
    run(...)           distill on a loaded capture under loaded env maps →
                       :class:`Distilled`: the final checkpoint dict, the validation
                       history and the settings its provenance records

The teacher's per-direction textures (the env grid's directions, each with its own
visibility) are computed once per pose and camera, so every env map's target is their
weighted sum (linearity of light transport).  The student sees bake-features' texel maps
of the pose under the env map and the joint features and predicts the texture (App.
A.2, Eq. 11); DRAM is the bottleneck hypernetwork baseline (App. A.3); both are compared
with the teacher's render (Eq. 5) by :func:`relight_cli.neural.train.fit` over a
:class:`relight_cli.neural.distill.StudentTask`.  Nothing here reads a path or prints:
log lines go to the ``log`` callable given, the progress bar through
:mod:`relight_cli.progress`.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

from relight_cli.jobs.train_teacher import Options as TrainOptions, provenance_record


@dataclass
class Teacher:
    """A loaded teacher: ``net`` (eval mode), its TeacherConfig ``config``, the GGX
    baseline's ``mean_texture`` (else None), the checkpoint's ``capture_key`` and
    ``pose_dim``, and its ``identity`` (the checkpoint file's SHA-256: stored in the
    student, and it keys the teacher-texture cache)."""

    net: object
    config: object
    mean_texture: object
    capture_key: str
    pose_dim: int
    identity: str = ""


@dataclass
class Options(TrainOptions):
    """How to distill, past the student's configuration: the fields of
    :class:`relight_cli.jobs.train_teacher.Options` (``config`` a StudentConfig from
    :func:`configure`, not changed; ``resume`` a read student checkpoint), and

    Attributes:
        n_eval: the last ``n_eval`` env maps are for evaluation only (a fixed split);
            0: ``config.env_holdout``'s seeded split of all of them.
        cache_dir: a folder for the teacher's textures beyond ``config.cache_mb`` (None:
            recomputed).
    """

    n_eval: int = 0
    cache_dir: str | None = None


@dataclass
class Distilled:
    """What :func:`run` made: ``result`` (:class:`~relight_cli.neural.train.TrainResult`:
    ``checkpoint`` dict to write, ``history``, final ``metrics``, ``steps_run``,
    ``seconds``), the ``config`` as trained, the ``settings`` and the provenance
    ``record`` stored in the checkpoint, how many teacher texture sets were ``computed``
    and the env-map ``split`` ({"train": names, "eval": names})."""

    result: object
    config: object
    settings: dict
    record: dict
    computed: int = 0
    split: dict = field(default_factory=dict)


def load_teacher(checkpoint: dict, device="cpu", identity: str = "",
                 name: str | None = None) -> Teacher:
    """The :class:`Teacher` of a read teacher checkpoint
    (:func:`relight_cli.neural.checkpoints.read_checkpoint` with ``kind="teacher"``) on
    ``device``; DataError naming ``name`` for weights its configuration does not build."""
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.neural.checkpoints import teacher_model
    try:
        net, config, mean_texture = teacher_model(checkpoint, device)
    except (ValueError, UsageProblem) as exc:
        raise DataError(getattr(exc, "message", str(exc)), name) from None
    return Teacher(net, config, mean_texture, checkpoint["capture_key"],
                   int(checkpoint["pose_dim"]), identity)


def configure(preset: str = "tiny", config_file: str | None = None,
              overrides: dict | None = None, resume: dict | None = None,
              resume_name: str | None = None):
    """The StudentConfig of a run: ``preset``, then ``config_file``'s JSON object, then
    ``overrides`` (None: not given; ``student``, ``iters``, ``seed``, ``env_res`` as
    (H, W) …); with ``resume`` (a read student checkpoint) its own configuration, where
    only ``iters`` may change (UsageProblem otherwise)."""
    from relight_cli.neural import registry
    from relight_cli.neural.config import resume_config
    spec = registry.get("student")
    overrides = dict(overrides or {})
    if resume is not None:
        return resume_config(resume, spec.load_attr("config"), overrides, config_file,
                             overrides.get("iters"), resume_name)
    return spec.load_attr("resolve")(preset, config_file, overrides)


def run(teacher: Teacher, data, envs: dict, options: Options, provenance=None, save=None,
        log=None, names: dict | None = None) -> Distilled:
    """Distill ``options.config``'s student from ``teacher`` on ``data``'s poses and
    cameras under ``envs`` → :class:`Distilled`.

    Args:
        teacher: :func:`load_teacher`.
        data: CaptureData at the teacher's geometry settings (``tex_res``, ``aa``,
            ``visibility``, ``falloff``, ``holdout``, ``cache_poses``).
        envs: name → EnvMap, in order (the last ``options.n_eval`` for evaluation only);
            each is discretized on ``config.env_res``.
        options: :class:`Options`.
        provenance: callable(settings dict) → the provenance record stored in the
            checkpoint, or a record; None: a record of no input files.
        save: callable(checkpoint dict) for the periodic saves, or None.
        log: callable(str) for log lines, or None.
        names: what messages call the inputs: ``capture``, ``teacher``, ``envs``
            (default: the folder, None, the env names).

    DataError when the resumed checkpoint was distilled on another capture, the capture's
    hand does not match the teacher's joints, or the split leaves no training map;
    UsageProblem when a resumed run's training maps differ.
    """
    import json

    import torch

    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.envmap import discretize_env
    from relight_cli.neural import distill as DI
    from relight_cli.neural.train import fit, resolve_device

    say = log if log is not None else (lambda message: None)
    names = dict(names or {})
    ckpt = options.resume
    config = copy.deepcopy(options.config)
    device = options.device if isinstance(options.device, torch.device) \
        else resolve_device(options.device)
    if teacher.capture_key != data.key:
        say(f"note: the teacher was trained on another capture (key {teacher.capture_key}); "
            f"distilling on this one")
    if ckpt is not None and ckpt["capture_key"] != data.key:
        raise DataError("checkpoint was distilled on another capture", options.resume_name)
    if (data.hand.n_joints - 1) * 3 != int(teacher.pose_dim):
        raise DataError("the capture's hand does not match the teacher's joints",
                        names.get("teacher"))
    env_names = list(envs)
    grids = [discretize_env(env, *config.env_res) for env in envs.values()]
    if options.n_eval:
        n_train = len(env_names) - int(options.n_eval)
        train_idx, eval_idx = list(range(n_train)), list(range(n_train, len(env_names)))
    else:
        train_idx, eval_idx = DI.split_envs(env_names, config.env_holdout, config.seed,
                                            names.get("envs", ", ".join(env_names)))
    if ckpt is not None:
        saved = json.loads(ckpt.get("extra", {}).get("envs", "{}") or "{}")
        if saved and saved.get("train") != [env_names[i] for i in train_idx]:
            raise UsageProblem("--resume needs the same --envs as the run it continues")
    grid = grids[0]
    targets = DI.TeacherTargets(teacher.net, teacher.config, data, grid, options.cache_dir,
                                config.cache_mb, device, teacher.mean_texture,
                                identity=teacher.identity, log=log)
    if options.vgg is None and ckpt is None:
        config.lambda_vgg = 0.0
    task = DI.StudentTask(data, config, targets, grids, train_idx, eval_idx, env_names,
                          options.vgg, teacher.identity)
    say(f"read {names.get('capture', data.folder)}: {len(task.items)} (pose, camera) pairs; "
        f"{len(train_idx)} training and {len(eval_idx)} evaluation env map(s); student "
        f"{config.student}, {config.tex_res}² features, {config.iters} iterations on "
        f"{device}; pseudo ground truth {_texture_mb(data, teacher.config, grid):.1f} MB per "
        f"pose and camera")
    note = cache_note(len(task.items), _texture_mb(data, teacher.config, grid), config.cache_mb,
                      options.cache_dir)
    if note:
        say(note)
    settings = {"preset": options.preset, **config.to_dict()}
    record = provenance_record(provenance, settings)
    result = fit(task, config, device, resume=ckpt, provenance=record, save=save,
                 show_progress=options.progress, log=log)
    return Distilled(result, config, settings, record, targets.computed,
                     {"train": [env_names[i] for i in train_idx],
                      "eval": [env_names[i] for i in eval_idx]})


def summary(distilled: Distilled) -> str:
    """The closing log line's tail: steps, seconds, iterations per second, teacher
    texture sets computed, and the last validation."""
    from .train_teacher import summary as steps
    return steps(distilled.result, f"{distilled.computed} teacher texture set(s) computed; ")


def cache_note(pairs: int, mb_each: float, cache_mb: int, cache_dir: str | None) -> str:
    """The log line for a memory budget that cannot hold every training pair's teacher
    textures with no ``--cache`` folder ("" otherwise): the share a uniformly sampled
    pair misses (each miss is a whole teacher pass) and the budget that holds them all."""
    if cache_dir is not None or pairs == 0 or mb_each <= 0:
        return ""
    held = min(pairs, int(cache_mb // mb_each))
    if held >= pairs:
        return ""
    need = math.ceil(pairs * mb_each)
    return (f"the teacher-texture memory budget (cache_mb {cache_mb}) holds {held} of "
            f"{pairs} pairs: about {100 * (pairs - held) / pairs:.0f} % of samples recompute "
            f"a teacher pass; a config with cache_mb {need} or --cache DIR keeps them all")


def _texture_mb(data, tconfig, grid) -> float:
    """Megabytes of the teacher's per-direction textures of one (pose, camera) pair."""
    return data.n_hands * len(grid.directions) * 3 * tconfig.tex_res ** 2 * 4 / 2 ** 20
