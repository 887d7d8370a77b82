"""``relight distill`` (commands/distill.py): help and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models import STUDENT_CAPTURE, STUDENT_TEACHER, STUDENT_TEACHER_CONFIG, copy_entry  # noqa: E402

# the capture and its 10-iteration teacher, made once per run (tests/models.py)
CAPTURE_ARGS = STUDENT_CAPTURE
TEACHER = STUDENT_TEACHER_CONFIG
STUDENT = {"tex_res": 16, "decoder": [8, 8, 8, 8, 8, 8, 8], "pose_channels": [4, 8],
           "dram_code": 16, "val_samples": 2, "env_holdout": 0.34, "env_res": [8, 16]}
ENVS = ["--envs", "builtin:sky", "--envs", "builtin:studio", "--envs", "builtin:uniform"]


@pytest.fixture(scope="module")
def setup(tmp_path_factory, tiny_models):
    """cap/ and teacher.pt (``train-teacher cap --config teacher.json --iters 10``, made once
    per run: tests/models.py) copied into a folder of this module, with the two configs."""
    root = tmp_path_factory.mktemp("student")
    (root / "teacher.json").write_text(json.dumps(TEACHER))
    (root / "student.json").write_text(json.dumps(STUDENT))
    copy_entry(tiny_models.get("capture", CAPTURE_ARGS), root / "cap")
    copy_entry(tiny_models.get(STUDENT_TEACHER[0], CAPTURE_ARGS, *STUDENT_TEACHER[1:]),
               root / "teacher.pt")
    return root


def _invoke(*args):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    return CliRunner().invoke(cli, [str(a) for a in args])


def _distill(setup, out, *extra):
    r = _invoke("distill", setup / "teacher.pt", setup / "cap", *ENVS, "--config",
                setup / "student.json", "-q", "-o", out, *extra)
    assert r.exit_code == 0, r.output
    return out


def test_help(run_cli):
    r = run_cli("distill", "--help")
    assert r.exit_code == 0 and "--envs" in r.output and "--student" in r.output


@pytest.mark.parametrize("case", ["nan-env", "student-as-teacher", "no-training-envs",
                                  "missing-envs", "missing-eval-envs", "bad-output-name",
                                  "cache-is-a-file", "output-is-the-teacher",
                                  "env-res-height-first", "bad-env-augment",
                                  "bad-loss-space",
                                  "linear-head-on-dram", "lsq-start-without-linear-head",
                                  "zero-iters-without-lsq", "negative-iters",
                                  "render-grid-on-dram", "render-grid-bad-shape"])
def test_distill_bad_input(setup, tmp_path, case):
    args = ["distill", setup / "teacher.pt", setup / "cap", *ENVS, "--config",
            setup / "student.json", "--iters", "2"]
    code = 1
    if case == "nan-env":
        rad = np.ones((8, 16, 3), np.float32)
        rad[2, 3, 1] = np.nan
        bad = tmp_path / "nan.exr"
        from relight_cli.formats.exr import write_exr
        write_exr(str(bad), {"R": rad[..., 0], "G": rad[..., 1], "B": rad[..., 2]},
                  envmap="latlong")
        args += ["--envs", bad]
    elif case == "student-as-teacher":
        ckpt = _distill(setup, tmp_path / "s.pt", "--iters", "1")
        args[1] = ckpt
    elif case == "no-training-envs":
        (tmp_path / "c.json").write_text(json.dumps({**STUDENT, "env_holdout": 0.9}))
        args[args.index("--config") + 1] = tmp_path / "c.json"
    elif case == "missing-envs":
        args += ["--envs", tmp_path / "nope.exr"]
    elif case == "missing-eval-envs":
        args += ["--eval-envs", tmp_path / "nope.exr"]
    elif case == "bad-output-name":
        code = 2
    elif case == "bad-env-augment":
        (tmp_path / "c.json").write_text(json.dumps({**STUDENT, "env_augment": "rotate"}))
        args[args.index("--config") + 1] = tmp_path / "c.json"
        code = 2
    elif case == "bad-loss-space":
        (tmp_path / "c.json").write_text(json.dumps({**STUDENT, "loss_space": "pixels"}))
        args[args.index("--config") + 1] = tmp_path / "c.json"
        code = 2
    elif case in ("linear-head-on-dram", "lsq-start-without-linear-head",
                  "render-grid-on-dram", "render-grid-bad-shape"):
        bad = {"linear-head-on-dram": {"student": "dram", "head": "linear"},
               "lsq-start-without-linear-head": {"head_init": "lsq"},
               "render-grid-on-dram": {"student": "dram", "render_env_res": [16, 32]},
               "render-grid-bad-shape": {"render_env_res": [16, 32, 2]}}[case]
        (tmp_path / "c.json").write_text(json.dumps({**STUDENT, **bad}))
        args[args.index("--config") + 1] = tmp_path / "c.json"
        code = 2
    elif case in ("zero-iters-without-lsq", "negative-iters"):
        args[args.index("--iters") + 1] = "0" if case == "zero-iters-without-lsq" else "-1"
        code = 2
    elif case == "env-res-height-first":
        args += ["--env-res", "8x16"]                      # HxW: refused, WxH is 16x8
        code = 2
    elif case == "cache-is-a-file":
        (tmp_path / "cache").write_text("x")
        args += ["--cache", tmp_path / "cache"]
        code = 2
    out = tmp_path / "out" / ("s.json" if case == "bad-output-name" else "s.pt")
    out.parent.mkdir()
    if case == "output-is-the-teacher":
        teacher = tmp_path / "out" / "t.pt"
        teacher.write_bytes((setup / "teacher.pt").read_bytes())
        args[1], out, code = teacher, teacher, 2
    before = out.read_bytes() if out.exists() else None
    r = _invoke(*args, "-q", "-o", out)
    assert r.exit_code == code, r.output
    lines = [ln for ln in r.output.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "error:" in lines[0] and "Traceback" not in r.output, r.output
    if case in ("bad-env-augment", "bad-loss-space", "linear-head-on-dram",
                "lsq-start-without-linear-head", "render-grid-on-dram",
                "render-grid-bad-shape"):      # issue 52 cause 12: the line names the file
        assert lines[0].endswith(f"({tmp_path / 'c.json'})"), lines[0]
    if before is None:
        assert list(out.parent.iterdir()) == []
    else:
        assert out.read_bytes() == before and "also an input" in lines[0]


def test_lsq_start_with_a_teacher_of_another_texture_size(setup, tmp_path):
    """Issue 52 cause 7: the least-squares start of a student whose tex_res (32) is not the
    teacher's (16) fits the teacher's textures resampled to the student's N, as the
    texture loss compares them (no shape error)."""
    from relight_cli.neural.checkpoints import read_checkpoint
    (tmp_path / "lsq.json").write_text(json.dumps({**STUDENT, "tex_res": 32, "head": "linear",
                                                   "head_init": "lsq"}))
    out = tmp_path / "lsq.pt"
    r = _invoke("distill", setup / "teacher.pt", setup / "cap", *ENVS, "--config",
                tmp_path / "lsq.json", "--iters", "0", "-q", "-o", out)
    assert r.exit_code == 0, r.output
    w = read_checkpoint(str(out))["weights"]["weight_bias"]
    assert w.shape[-2:] == (32, 32) and torch.isfinite(w).all()
    grey = torch.zeros_like(w)
    grey[:, :3] = 0.5
    assert not torch.equal(w, grey)
