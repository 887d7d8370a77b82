"""relight_cli.jobs.train_teacher called from Python on loaded inputs: it makes what the CLI
writes for the same inputs and seed, resumes exactly, learns, and refuses a checkpoint of
another capture."""

from __future__ import annotations

import json

import pytest

torch = pytest.importorskip("torch")

from relight_cli.errors import DataError  # noqa: E402
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
    from relight_cli.neural.checkpoints import read_checkpoint
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
