"""Train RelightableHands' OLAT teacher, its GGX baseline or URHand's linear model:
``relight train-teacher`` as an engine job.

    configure(...)  the run's configuration: preset, then a config file, then flags; or,
                    resuming, the checkpoint's own (only ``iters`` may grow)
    run(...)        train on loaded captures (:class:`~relight_cli.neural.data.CaptureData`,
                    one per subject) → :class:`Trained`: the final checkpoint dict, the
                    validation history and the settings its provenance records

The teacher (RelightableHands App. A.1, Eq. 10; a frame under several LEDs is their
intensity-weighted sum, Eq. 2; Eq. 5's losses) and the GGX baseline (App. B, Eq. 12)
train through :func:`relight_cli.neural.train.train`, URHand's linear model (Sec. 4, Eq.
4-17) through :func:`relight_cli.neural.linear_train.train`; both loops are
:func:`relight_cli.neural.train.fit` (seeded, exactly resumable, DDP under torchrun).
Nothing here reads a path or prints: log lines go to the ``log`` callable given, the
progress bar through :mod:`relight_cli.progress`.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field


@dataclass
class Options:
    """How to train, past the model's configuration.

    Attributes:
        config: a TeacherConfig (``olat``/``ggx``) or LinearConfig (:func:`configure`);
            not changed (:func:`run` trains a copy).
        preset: the preset the configuration started from (recorded in the settings).
        device: a torch.device or its name (``auto``, ``cpu``, ``cuda``).
        vgg: the VGG loss (:func:`relight_cli.neural.losses.load_vgg`, on ``device``);
            None: λ_VGG = 0 on a fresh run (a resumed one keeps its own).
        resume: a read checkpoint (:func:`relight_cli.neural.checkpoints.read_checkpoint`)
            to continue exactly (weights, Adam, step, RNG).
        resume_name: what errors call that checkpoint (its path).
        progress: a progress bar on stderr.
    """

    config: object
    preset: str = "tiny"
    device: object = "cpu"
    vgg: object = None
    resume: dict | None = None
    resume_name: str | None = None
    progress: bool = True


@dataclass
class Trained:
    """What :func:`run` made: ``result`` (:class:`~relight_cli.neural.train.TrainResult`:
    ``checkpoint`` dict to write, ``history``, final ``metrics``, ``steps_run``,
    ``seconds``), the ``config`` as trained (``aa`` = the capture's pixel sampling,
    λ_VGG), the ``settings`` and the provenance ``record`` stored in the checkpoint, and
    the first capture's ``sampling`` (model vs capture pixel sampling)."""

    result: object
    config: object
    settings: dict
    record: dict
    sampling: dict = field(default_factory=dict)


def configure(model: str | None, preset: str = "tiny", config_file: str | None = None,
              overrides: dict | None = None, only: dict | None = None,
              resume: dict | None = None, resume_name: str | None = None,
              n_subjects: int = 1):
    """The configuration of a run: ``preset``, then ``config_file``'s JSON object, then
    ``overrides`` (None: not given; ``model``, ``iters``, ``seed`` …); ``only``: the
    fields of one model's own flags (its registry entry's ``trainer_options``: the linear
    model's ``light_path``, ``features`` …), refused for another.  With ``resume`` (a read
    checkpoint) its own configuration, whose kind decides the model (only ``iters`` may
    change).  UsageProblem for flags of another model or several subjects of a teacher;
    DataError (naming ``resume_name``) for a checkpoint holding no teacher."""
    from relight_cli.errors import UsageProblem
    from relight_cli.neural import registry
    from relight_cli.neural.config import resume_config

    overrides = dict(overrides or {}, model=model)
    only = dict(only or {})
    default = registry.architectures(trainer="train-teacher")[0]
    spec = (_resumed_spec(resume, resume_name) if resume is not None
            else registry.for_architecture(model or default))
    config_class, resolve = spec.load_attr("config"), spec.load_attr("resolve")
    others = [o for name in registry.names(trainer="train-teacher")
              for o in registry.get(name).trainer_options
              if o not in spec.trainer_options and only.get(o) is not None]
    if n_subjects > 1 and not spec.subjects:
        what = (f"{resume_name} holds the {resume['model']} teacher" if resume is not None
                else f"not --model {model or default}")
        raise UsageProblem(f"several CAPTUREs (one per subject) train --model "
                           f"{' or '.join(registry.names(subjects=True))} only; "
                           f"{what}: give one capture")
    if others:
        owners = [n for n in registry.names(trainer="train-teacher")
                  if set(others) & set(registry.get(n).trainer_options)]
        raise UsageProblem("--light-path, --linearity-loss, --features, --no-specular and "
                           f"--no-refiner belong to --model {' or '.join(owners)}")
    overrides.update({k: v for k, v in only.items() if k in spec.trainer_options})
    if resume is not None:
        return resume_config(resume, config_class, overrides, config_file,
                             overrides.get("iters"), resume_name)
    return resolve(preset, config_file, overrides)


def _resumed_spec(resume: dict, resume_name):
    """The registry entry of a resumed checkpoint: one train-teacher trains (DataError
    naming the file otherwise)."""
    from relight_cli.errors import DataError
    from relight_cli.neural import registry
    kind = resume["kind"]
    try:
        spec = registry.for_kind(kind)
    except ValueError:
        spec = None
    if spec is None or spec.trainer != "train-teacher":
        raise DataError(f"checkpoint holds a {kind!r} model, expected a teacher", resume_name)
    return spec


def run(subjects, options: Options, provenance=None, save=None, log=None,
        names=None) -> Trained:
    """Train ``options.config``'s model on ``subjects`` (a CaptureData, or a list of them,
    one per subject: URHand's linear model only, Sec. 4.3) → :class:`Trained`.

    Args:
        subjects: CaptureData made with the configuration's geometry settings
            (``tex_res``, ``aa``, ``visibility``, ``falloff``, ``holdout``).
        options: :class:`Options`.
        provenance: callable(settings dict) → the provenance record stored in the
            checkpoint (e.g. :func:`relight_cli.provenance.provenance` with the input
            paths), or a record; None: a record of no input files.
        save: callable(checkpoint dict) for the periodic saves (``save_every``), or None.
        log: callable(str) for log lines (a note on pixel sampling, what was read, each
            validation), or None.
        names: what log lines call each capture (default: its folder).

    DataError (naming ``options.resume_name``) when the resumed checkpoint was trained on
    other captures; the subjects' compatibility is checked by
    :func:`relight_cli.neural.linear_train.check_subjects`.
    """
    import torch

    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.hand.scene import handedness
    from relight_cli.neural.linear import LinearConfig
    from relight_cli.neural.train import resolve_device, train

    say = log if log is not None else (lambda message: None)
    subjects = list(subjects) if isinstance(subjects, (list, tuple)) else [subjects]
    names = list(names) if names is not None else [d.folder for d in subjects]
    data, ckpt, source = subjects[0], options.resume, options.resume_name
    config = copy.deepcopy(options.config)
    device = options.device if isinstance(options.device, torch.device) \
        else resolve_device(options.device)
    train_model = train
    if isinstance(config, LinearConfig):
        from relight_cli.neural import linear_train
        train_model = linear_train.train
        if len(subjects) > 1:
            # what one model cannot share (joints, UV layout, hands, sampling), per capture
            linear_train.check_subjects(subjects)
    elif len(subjects) > 1:
        raise UsageProblem("several captures (one per subject) train the linear model only")
    if ckpt is not None and len(subjects) == 1 and "subjects" not in ckpt["extra"] \
            and ckpt["capture_key"] != data.key:
        raise DataError(f"checkpoint was trained on another capture (key {ckpt['capture_key']}, "
                        f"this one is {data.key})", source)
    if ckpt is not None and (len(subjects) > 1 or "subjects" in ckpt["extra"]):
        trained = [r["capture_key"] for r in ckpt["extra"].get("subjects") or
                   [{"capture_key": ckpt["capture_key"]}]]
        if trained != [d.key for d in subjects]:
            raise DataError(f"checkpoint was trained on other subjects (keys "
                            f"{', '.join(trained)}; these captures are "
                            f"{', '.join(d.key for d in subjects)}, in this order)", source)
    config.aa = data.aa        # the sampling used, recorded in the checkpoint
    if not data.sampling["matched"]:
        say(f"note: pixels sampled {data.aa}×{data.aa}, but the capture's images were made "
            f"with {data.sampling['capture_aa']}×{data.sampling['capture_aa']} (recorded in "
            f"the scores as sampling.matched = false)")
    splits = data.splits()
    say(f"read {names[0]}: {len(splits['train'])} training, {len(splits['heldout'])} held-out, "
        f"{len(splits['fully_lit'])} fully lit, {len(splits.get('env', []))} env-map samples; "
        f"{data.n_hands} hand(s) ({', '.join(handedness(data.hand))}, recorded in the "
        f"checkpoint); model {config.model}, {config.tex_res}² texture, "
        f"{config.iters} iterations on {device}"
        + ("" if options.vgg is not None else "; no VGG weights: λ_VGG = 0"))
    for s, other in enumerate(subjects[1:], 1):
        more = other.splits()
        say(f"read {names[s]} (subject {s}): {len(more['train'])} training, "
            f"{len(more['heldout'])} held-out, {len(more['fully_lit'])} fully lit, "
            f"{len(more.get('env', []))} env-map samples; each subject conditioned on its "
            f"own mean texture (URHand Sec. 4)")
    if options.vgg is None and ckpt is None:
        config.lambda_vgg = 0.0
    settings = {"preset": options.preset, **config.to_dict()}
    record = provenance_record(provenance, settings)
    result = train_model(data if len(subjects) == 1 else subjects, config, device,
                         resume=ckpt, vgg=options.vgg, provenance=record, save=save,
                         show_progress=options.progress, log=log)
    return Trained(result, config, settings, record, data.sampling)


def summary(result, more: str = "") -> str:
    """The closing log line's tail: steps, seconds, iterations per second (``more``
    after them), and the last validation."""
    from relight_cli.neural.train import _summary
    its = result.steps_run / result.seconds if result.seconds > 0 else float("inf")
    last = result.history[-1] if result.history else {"step": result.checkpoint["step"]}
    every = result.metrics.get("heldout_all")
    tail = ""
    if isinstance(every, dict) and "psnr" in every:
        tail = (f"; every held-out sample ({every['samples']}): PSNR {every['psnr']:.2f} dB"
                + (f", {every['gap_to_ceiling']:.2f} dB below its ceiling"
                   if "gap_to_ceiling" in every else ""))
    return (f"{result.steps_run} step(s) in {result.seconds:.1f} s ({its:.2f} it/s); {more}"
            + _summary(last) + tail)


def provenance_record(provenance, settings: dict) -> dict:
    """The provenance record a checkpoint stores: ``provenance(settings)`` when it is a
    callable, the record itself when given, else one naming no input files."""
    if callable(provenance):
        return provenance(settings)
    if provenance is not None:
        return provenance
    from relight_cli.provenance import provenance as make
    return make("relight/checkpoint", 1, {}, settings)
