"""relight_cli.neural.registry: one entry per learned model kind, found by every layer."""

from __future__ import annotations

import dataclasses

import click
import pytest

from relight_cli.neural import registry


def test_the_registry_is_the_formats_vocabulary():
    """Every kind and architecture a relight/checkpoint may declare has one entry, and
    each entry's configuration is the one the format validates that kind with."""
    from relight_cli.formats import checkpoint as C
    assert sorted(s.kind for s in registry.MODELS.values()) == sorted(C.KINDS)
    for spec in registry.MODELS.values():
        assert C.MODELS[spec.kind] == (spec.architectures, spec.variant_field), spec.name
        assert spec.load_attr("config").__module__ == "relight_cli.neural.model_config"


@pytest.mark.parametrize("name", list(registry.MODELS))
def test_every_entry_resolves_to_working_parts(name):
    spec = registry.MODELS[name]
    config_class = spec.load_attr("config")
    presets = spec.load_attr("presets")
    assert {"tiny", "cpu", "paper"} <= set(presets), name
    config = spec.load_attr("resolve")("tiny", None, {})
    assert isinstance(config, config_class)
    assert spec.architecture(config) == spec.architectures[0]
    assert not spec.is_baseline(config)
    assert callable(spec.load_attr("loader"))
    job = spec.load_attr("render")
    for method in ("env_grid", "samples_axis", "passes", "render", "settings"):
        assert callable(getattr(job, method)), (name, method)
    assert spec.trainer in ("train-teacher", "distill")
    assert registry.get(name) is spec and registry.for_kind(spec.kind) is spec
    for architecture in spec.architectures:
        assert registry.for_architecture(architecture) is spec


def test_lookups_name_what_is_known():
    with pytest.raises(ValueError, match="known: teacher, linear, student"):
        registry.get("neural")
    with pytest.raises(ValueError, match="checkpoint kind 'vae'"):
        registry.for_kind("vae")
    with pytest.raises(ValueError, match="architecture 'nerf'"):
        registry.for_architecture("nerf")
    assert registry.names(scores_captures=True) == ("teacher", "linear")
    assert registry.architectures(trainer="train-teacher") == ("olat", "ggx", "linear")
    assert registry.architectures(trainer="distill") == ("student", "dram")


def test_the_commands_take_their_models_from_the_registry(monkeypatch):
    """train-teacher's --model choices, relight's --model names and the option each
    learned model alone takes come from the entries: an entry that changes changes them."""
    from relight_cli.commands import relight_hand, train_teacher
    choice = next(p for p in train_teacher.command.params if p.name == "model").type
    assert isinstance(choice, click.Choice)
    assert tuple(choice.choices) == registry.architectures(trainer="train-teacher")
    helped = next(p for p in relight_hand.command.params if p.name == "model").help
    for spec in registry.MODELS.values():
        assert f"'{spec.name}'" in helped and spec.trainer in helped
    # give the teacher the student's --precision: the hand command takes it for both
    from click.testing import CliRunner

    from relight_cli.cli import cli
    r = CliRunner().invoke(cli, ["relight", "builtin:right", "builtin:sky", "--model",
                                 "teacher", "--precision", "float32", "-o", "x.exr"])
    assert r.exit_code == 2 and "--precision only apply to --model student" in r.output
    teacher = dataclasses.replace(registry.MODELS["teacher"], hand_options=("precision",))
    monkeypatch.setitem(registry.MODELS, "teacher", teacher)
    r = CliRunner().invoke(cli, ["relight", "builtin:right", "builtin:sky", "--model",
                                 "teacher", "--precision", "float32", "-o", "x.exr"])
    assert r.exit_code == 2 and "needs --checkpoint" in r.output, r.output
