"""The training jobs (relight_cli.jobs.train_teacher, relight_cli.jobs.distill): called from
Python on loaded inputs, they make what the CLI writes for the same inputs and seed, resume
exactly, learn, and refuse a checkpoint of another capture."""

from __future__ import annotations

import json

import pytest

torch = pytest.importorskip("torch")

from relight_cli.errors import DataError  # noqa: E402

# The smallest capture the jobs train on: 2 cameras, 8 LEDs in groups of 4, 4 frames.
CAPTURE_ARGS = ["--cameras", "2", "--leds", "8", "--group", "4", "--frames", "4", "--size", "24",
                "--tex-res", "32", "--aa", "1", "--eval-poses", "1", "--eval-cameras", "1",
                "--eval-envs", "builtin:sky", "--eval-env-res", "16x8", "-q"]
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
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("jobs_training")
    for name, fields in (("teacher", TEACHER), ("linear", LINEAR), ("student", STUDENT)):
        (root / f"{name}.json").write_text(json.dumps(fields))
    _cli("synth-capture", "-o", root / "cap", *CAPTURE_ARGS)
    return root


def _subjects(root, config):
    from relight_cli.neural.data import CaptureData
    return [CaptureData(str(root / "cap"), config.tex_res, config.aa, config.visibility,
                        config.falloff, config.holdout, config.cache_poses)]


def _train(root, model, fields, iters, resume=None, **options):
    from relight_cli.jobs import train_teacher as J
    config = J.configure(model, "tiny", None if resume else str(root / f"{fields}.json"),
                         {"iters": iters}, resume=resume)
    return J.run(_subjects(root, config), J.Options(config, "tiny", "cpu", resume=resume,
                                                     progress=False, **options))


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


@pytest.mark.parametrize("model,fields", [("olat", "teacher"), ("linear", "linear")])
def test_train_job_equals_cli(root, model, fields):
    """The job's checkpoint and validation history are the CLI's for the same inputs and
    seed (weights bit for bit)."""
    from relight_cli.formats.checkpoint import read_checkpoint
    out = root / f"{model}_cli.pt"
    _cli("train-teacher", root / "cap", "--model", model, "--config", root / f"{fields}.json",
         "--iters", 3, "-q", "-o", out, "--metrics-out", root / f"{model}_cli.json")
    trained = _train(root, model, fields, 3)
    _same_state(trained.result.checkpoint, read_checkpoint(str(out)))
    assert json.loads(json.dumps(trained.result.history)) == _history(root / f"{model}_cli.json")
    assert trained.settings == {"preset": "tiny", **trained.config.to_dict()}
    assert trained.config.lambda_vgg == 0.0 and trained.result.steps_run == 3


def test_train_job_resumes_exactly(root):
    """2 + 2 resumed iterations are 4 uninterrupted ones."""
    first = _train(root, "olat", "teacher", 2)
    whole = _train(root, "olat", "teacher", 4)
    resumed = _train(root, "olat", "teacher", 4, resume=first.result.checkpoint)
    assert resumed.result.steps_run == 2
    for k, v in whole.result.checkpoint["weights"].items():
        assert torch.equal(v, resumed.result.checkpoint["weights"][k]), k
    assert whole.result.metrics == resumed.result.metrics


def test_train_job_learns(root):
    """After 20 steps the held-out error is below the first validation's (at step 5)."""
    from relight_cli.jobs import train_teacher as J
    lines = []
    config = J.configure("olat", "tiny", str(root / "teacher.json"),
                         {"iters": 20, "batch": 2})
    config.val_every = 5
    trained = J.run(_subjects(root, config), J.Options(config, progress=False),
                    log=lines.append)
    mse = [h["heldout"]["mse"] for h in trained.result.history]
    assert mse[-1] < mse[0], mse
    assert any(m.startswith("read ") for m in lines)      # log lines go to the callable


def test_train_job_refuses_another_captures_checkpoint(root):
    """A resumed checkpoint of another capture is a DataError naming it."""
    from relight_cli.jobs import train_teacher as J
    ckpt = dict(_train(root, "olat", "teacher", 1).result.checkpoint, capture_key="other")
    config = J.configure("olat", "tiny", None, {"iters": 2}, resume=ckpt, resume_name="old.pt")
    with pytest.raises(DataError, match="another capture") as info:
        J.run(_subjects(root, config), J.Options(config, resume=ckpt, resume_name="old.pt",
                                                 progress=False))
    assert info.value.path == "old.pt"


@pytest.mark.parametrize("student", ["student", "dram"])
def test_distill_job_equals_cli(root, student):
    """The distill job's student (or DRAM) is the CLI's for the same teacher, capture, env
    maps and seed: weights bit for bit, the same validation history and split."""
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.formats.checkpoint import read_checkpoint
    from relight_cli.jobs import distill as J
    from relight_cli.provenance import file_sha256
    teacher = root / "teacher.pt"
    if not teacher.is_file():
        _cli("train-teacher", root / "cap", "--config", root / "teacher.json", "--iters", 2,
             "-q", "-o", teacher)
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


def test_distill_logs_a_budget_that_cannot_hold_the_teacher_textures(root):
    """A run whose cache_mb holds none of its pairs says so (and what would hold them);
    the same run with --cache DIR does not."""
    teacher = root / "teacher.pt"
    if not teacher.is_file():
        _cli("train-teacher", root / "cap", "--config", root / "teacher.json", "--iters", 2,
             "-q", "-o", teacher)
    small = root / "student_small_cache.json"
    small.write_text(json.dumps({**STUDENT, "cache_mb": 0}))
    envs = [a for e in ENVS for a in ("--envs", e)]
    r = _cli("distill", teacher, root / "cap", *envs, "--config", small, "--iters", 1,
             "-o", root / "small_cache.pt")
    assert "(cache_mb 0) holds 0 of" in r.output and "recompute a teacher pass" in r.output
    r = _cli("distill", teacher, root / "cap", *envs, "--config", small, "--iters", 1,
             "--cache", root / "spill", "-o", root / "spilled.pt")
    assert "cache_mb" not in r.output
