"""The model registry: one entry per learned model kind, found by every layer here.

A learned model is registered once (as Mitsuba registers a plugin): its CLI name (``relight
HAND --model NAME``) and checkpoint kind, the architectures a checkpoint of that kind may
hold, its configuration dataclass and presets, the command that trains it, the loader
that builds it from a checkpoint, and the job that renders a hand with it.  Commands,
jobs, the checkpoint loaders and the benchmarks iterate over :data:`MODELS` or look a
name up with :func:`get`; nobody compares kind names as strings.  Adding a learned model
is one entry here plus its module.

    name      kind      architectures (config field)   trained by      renders with
    teacher   teacher   olat, ggx (``model``)          train-teacher   jobs.relight_hand.PerHandModels
    linear    linear    linear (``model``)             train-teacher   jobs.relight_hand.PerHandModels
    student   student   student, dram (``student``)    distill         jobs.relight_hand.StudentModel

The format's own vocabulary (which kinds and architectures a ``relight/checkpoint`` file
may declare) stays in :mod:`relight_cli.formats.checkpoint` (``KINDS``, ``MODELS``); a test
holds the two equal.  Entries name their parts as ``"module:attribute"`` and import them
only when asked (``relight --help`` imports no torch).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass


@dataclass(frozen=True)
class ModelSpec:
    """One learned model kind.

    Attributes:
        name: the CLI name (``relight relight HAND --model NAME``, ``relight CAPTURE/``).
        kind: the checkpoint's ``kind`` field (formats/checkpoint.md).
        architectures: the values the configuration's ``variant_field`` may take (the
            checkpoint's ``model`` field); the first is the paper's model, the others its
            baselines (GGX for the teacher, DRAM for the student).
        variant_field: the configuration field that names the architecture.
        title: what it is, with the paper it comes from (help texts and logs).
        trainer: the subcommand that writes its checkpoint.
        config: ``module:Class`` of its configuration dataclass.
        presets: ``module:attr`` of its presets (tiny, cpu, paper).
        loader: ``module:function``: a read checkpoint dict, device → (model, config, …).
        render: ``module:Class`` of the job that renders a hand with it
            (:class:`relight_cli.jobs.relight_hand.PerHandModels` or ``StudentModel``).
        one_per_hand: each hand may take its own checkpoint (the one trained on its
            handedness), as RelightableHands trains one teacher per hand.
        point_lights: renders point lights (``--lights``) as well as env maps.
        scores_captures: ``relight CAPTURE/`` scores it against a capture's images.
        hand_options: the ``relight`` hand options only this model (among the learned
            ones) takes, e.g. the student's ``precision``.
        trained_sampling: without ``--aa``, a hand is rendered with the sub-pixel samples
            its configuration trained with (``aa``; 2 when 0), else with 2.
        sums_features: linear in its shading features (URHand Eq. 4-6): the features of
            all the lights are summed and go through the model once; otherwise one pass
            per light, the textures summed (RelightableHands Eq. 2).
        subjects: conditions on each identity's mean texture T̄ (URHand Sec. 4): a
            checkpoint lists its trained subjects, and an unseen one is given its own T̄.
        resolve: ``module:function`` turning a preset, a config file and overrides into
            its configuration (what the trainer calls).
        trainer_options: the configuration fields its trainer's flags set that no other
            model of that trainer takes (train-teacher's ``--light-path`` …: linear only).
    """

    name: str
    kind: str
    architectures: tuple
    variant_field: str
    title: str
    trainer: str
    config: str
    presets: str
    loader: str
    render: str
    one_per_hand: bool
    point_lights: bool
    scores_captures: bool
    hand_options: tuple = ()
    trained_sampling: bool = False
    sums_features: bool = False
    subjects: bool = False
    resolve: str = ""
    trainer_options: tuple = ()

    def load_attr(self, which: str):
        """The object a ``module:attr`` field of this entry names (imported now)."""
        module, attr = getattr(self, which).split(":")
        return getattr(importlib.import_module(module), attr)

    def architecture(self, config) -> str:
        """The architecture a configuration of this kind describes (``olat``, ``dram``…)."""
        return str(getattr(config, self.variant_field))

    def is_baseline(self, config) -> bool:
        """Whether ``config`` describes one of this kind's baselines (not the paper's model)."""
        return self.architecture(config) != self.architectures[0]


MODELS: dict[str, ModelSpec] = {spec.name: spec for spec in (
    ModelSpec(
        name="teacher", kind="teacher", architectures=("olat", "ggx"), variant_field="model",
        title="RelightableHands' OLAT teacher (or its GGX baseline)",
        trainer="train-teacher",
        config="relight_cli.neural.model_config:TeacherConfig",
        presets="relight_cli.neural.config:PRESETS",
        loader="relight_cli.neural.checkpoints:teacher_model",
        render="relight_cli.jobs.relight_hand:PerHandModels",
        one_per_hand=True, point_lights=True, scores_captures=True, trained_sampling=True,
        resolve="relight_cli.neural.config:resolve_config"),
    ModelSpec(
        name="linear", kind="linear", architectures=("linear",), variant_field="model",
        title="URHand's linear lighting model",
        trainer="train-teacher",
        config="relight_cli.neural.model_config:LinearConfig",
        presets="relight_cli.neural.linear:PRESETS",
        loader="relight_cli.neural.checkpoints:linear_model",
        render="relight_cli.jobs.relight_hand:PerHandModels",
        one_per_hand=True, point_lights=True, scores_captures=True, sums_features=True,
        subjects=True, resolve="relight_cli.neural.linear:resolve_config",
        trainer_options=("light_path", "linearity_loss", "features", "specular", "refiner")),
    ModelSpec(
        name="student", kind="student", architectures=("student", "dram"),
        variant_field="student",
        title="RelightableHands' student (or its DRAM baseline)",
        trainer="distill",
        config="relight_cli.neural.model_config:StudentConfig",
        presets="relight_cli.neural.config:STUDENT_PRESETS",
        loader="relight_cli.neural.checkpoints:student_model",
        render="relight_cli.jobs.relight_hand:StudentModel",
        one_per_hand=False, point_lights=False, scores_captures=False,
        hand_options=("precision",), resolve="relight_cli.neural.config:resolve_student_config"),
)}


def get(name: str) -> ModelSpec:
    """The entry of ``--model NAME``; ValueError naming the known models."""
    if name not in MODELS:
        raise ValueError(f"--model {name!r} is not a learned model; known: "
                         f"{', '.join(MODELS)}")
    return MODELS[name]


def for_kind(kind: str) -> ModelSpec:
    """The entry of a checkpoint ``kind``; ValueError for a kind nobody registered."""
    for spec in MODELS.values():
        if spec.kind == kind:
            return spec
    raise ValueError(f"no model is registered for checkpoint kind {kind!r} (known: "
                     f"{', '.join(spec.kind for spec in MODELS.values())})")


def for_architecture(architecture: str) -> ModelSpec:
    """The entry whose checkpoints may hold ``architecture`` (``olat``, ``ggx``, ``linear``,
    ``student``, ``dram``); ValueError for an unknown one."""
    for spec in MODELS.values():
        if architecture in spec.architectures:
            return spec
    raise ValueError(f"no registered model has the architecture {architecture!r}")


def architectures(**where) -> tuple:
    """Every architecture of the entries whose attributes equal ``where``, in order (e.g.
    ``architectures(trainer="train-teacher")``: olat, ggx, linear)."""
    return tuple(a for name in names(**where) for a in MODELS[name].architectures)


def names(**where) -> tuple:
    """The registered names, in order, whose attributes equal ``where`` (e.g.
    ``names(scores_captures=True)``)."""
    return tuple(name for name, spec in MODELS.items()
                 if all(getattr(spec, k) == v for k, v in where.items()))
