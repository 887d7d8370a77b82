"""relight_cli.jobs.distill called from Python on loaded inputs: the student (and DRAM) the CLI
writes for the same teacher, capture, env maps and seed; the cache-budget note."""

from __future__ import annotations

import json

import pytest

torch = pytest.importorskip("torch")
from models import JOBS_CAPTURE, copy_entry  # noqa: E402

# The smallest capture the jobs train on: 2 cameras, 8 LEDs in groups of 4, 4 frames (made
# once per run, tests/models.py).
CAPTURE_ARGS = JOBS_CAPTURE
TEACHER = {"tex_res": 16, "encoder": [4, 4, 4], "decoder": [8, 8, 8], "pose_channels": [4, 4],
           "val_samples": 1}
LINEAR = {"tex_res": 16, "encoder": [4, 4, 4], "decoder": [4, 4, 4], "pose_channels": [4, 4],
          "light_decoder": [8, 8, 8, 8, 8, 8, 8, 4], "light_levels": 2, "val_samples": 1}
STUDENT = {"tex_res": 16, "decoder": [8, 8, 8, 8, 8, 8, 8], "pose_channels": [4, 8],
           "dram_code": 16, "val_samples": 1, "env_res": [4, 8]}
ENVS = ("builtin:sky", "builtin:studio", "builtin:uniform")


def _cli(*args):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    r = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    return r


@pytest.fixture(scope="module")
def root(tmp_path_factory, tiny_models):
    root = tmp_path_factory.mktemp("jobs_training")
    for name, fields in (("teacher", TEACHER), ("linear", LINEAR), ("student", STUDENT)):
        (root / f"{name}.json").write_text(json.dumps(fields))
    copy_entry(tiny_models.get("capture", CAPTURE_ARGS), root / "cap")
    return root


@pytest.fixture(scope="module")
def teacher(tiny_models):
    """``train-teacher cap --config teacher.json --iters 2``: the distill tests' teacher (an
    input, not their subject), made once per run (tests/models.py)."""
    return tiny_models.get("olat", CAPTURE_ARGS, ["--iters", 2, "-q"], config=TEACHER)


def _subjects(root, config):
    from relight_cli.neural.data import CaptureData
    return [CaptureData(str(root / "cap"), config.tex_res, config.aa, config.visibility,
                        config.falloff, config.holdout, config.cache_poses)]


def _same_state(a: dict, b: dict) -> None:
    """Two checkpoints' weights, step, configuration and extras are equal (the
    provenance's command line differs between the CLI and a job)."""
    assert a["step"] == b["step"] and a["kind"] == b["kind"] and a["model"] == b["model"]
    assert _plain(a["config"]) == _plain(b["config"]) and a["capture_key"] == b["capture_key"]
    assert a["weights"].keys() == b["weights"].keys()
    for k in a["weights"]:
        assert torch.equal(a["weights"][k], b["weights"][k]), k
    assert _plain(a["provenance"])["settings"] == _plain(b["provenance"])["settings"]


def _plain(value):
    """A checkpoint field as JSON values (a written checkpoint stores some as JSON text)."""
    return json.loads(value) if isinstance(value, str) else json.loads(json.dumps(value))


def _history(metrics_json) -> list:
    return json.loads(metrics_json.read_text())["details"]["history"]


@pytest.mark.parametrize("student", ["student", "dram"])
def test_distill_job_equals_cli(root, teacher, student):
    """The distill job's student (or DRAM) is the CLI's for the same teacher, capture, env
    maps and seed: weights bit for bit, the same validation history and split."""
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.jobs import distill as J
    from relight_cli.provenance import file_sha256
    out = root / f"{student}_cli.pt"
    _cli("distill", teacher, root / "cap", *[a for e in ENVS for a in ("--envs", e)],
         "--student", student, "--config", root / "student.json", "--iters", 2, "-q",
         "-o", out, "--metrics-out", root / f"{student}_cli.json")
    config = J.configure("tiny", str(root / "student.json"), {"student": student, "iters": 2})
    tck = J.load_teacher(read_checkpoint(str(teacher), kind="teacher"), "cpu",
                         file_sha256(str(teacher)))
    data = _subjects(root, tck.config)[0]
    envs = {e.split(":")[1]: builtin_envmap(e) for e in ENVS}
    distilled = J.run(tck, data, envs, J.Options(config, progress=False))
    _same_state(distilled.result.checkpoint, read_checkpoint(str(out), kind="student"))
    assert distilled.result.checkpoint["extra"] == read_checkpoint(str(out))["extra"]
    assert json.loads(json.dumps(distilled.result.history)) == \
        _history(root / f"{student}_cli.json")
    assert sorted(distilled.split["train"] + distilled.split["eval"]) == sorted(envs)
    assert distilled.computed > 0


def test_cache_note_says_what_a_short_budget_costs():
    """The log line names the share of samples that recompute a teacher pass and the
    budget that holds every pair; it is silent when the pairs fit or spill to a folder."""
    from relight_cli.jobs.distill import cache_note
    note = cache_note(584, 6.29, 2048, None)
    assert "holds 325 of 584 pairs" in note and "44 %" in note and "cache_mb 3674" in note
    assert cache_note(584, 6.29, 4096, None) == ""
    assert cache_note(584, 6.29, 2048, "cache") == ""
    assert cache_note(584, 6.29, 0, None).count("holds 0 of 584") == 1


def test_distill_logs_a_budget_that_cannot_hold_the_teacher_textures(root, teacher):
    """A run whose cache_mb holds none of its pairs says so (and what would hold them);
    the same run with --cache DIR does not."""
    small = root / "student_small_cache.json"
    small.write_text(json.dumps({**STUDENT, "cache_mb": 0}))
    envs = [a for e in ENVS for a in ("--envs", e)]
    r = _cli("distill", teacher, root / "cap", *envs, "--config", small, "--iters", 1,
             "-o", root / "small_cache.pt")
    assert "(cache_mb 0) holds 0 of" in r.output and "recompute a teacher pass" in r.output
    r = _cli("distill", teacher, root / "cap", *envs, "--config", small, "--iters", 1,
             "--cache", root / "spill", "-o", root / "spilled.pt")
    assert "cache_mb" not in r.output
