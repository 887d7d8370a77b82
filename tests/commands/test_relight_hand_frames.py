"""``relight HAND ENV --frames``: a motion rendered in one process, every frame's pixels
equal to its single ``--frame`` call's, for the physical renderer and every learned model."""

from __future__ import annotations


import numpy as np
import pytest

pytest.importorskip("torch")

from conftest import run_relight  # noqa: E402
from models import STUDENT_CAPTURE, STUDENT_TEACHER, copy_entry  # noqa: E402

# the student tests' capture and 10-iteration teacher (tests/models.py: made once per run)
CAPTURE_ARGS = STUDENT_CAPTURE
STUDENT = {"tex_res": 16, "decoder": [8, 8, 8, 8, 8, 8, 8], "pose_channels": [4, 8],
           "val_samples": 1, "env_res": [4, 8]}
LINEAR = {"tex_res": 16, "val_samples": 1}
VIEW = ["--size", "20x16", "--env-res", "8x4"]


def _invoke(*args):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module")
def models(tmp_path_factory, tiny_models):
    """A small capture and tiny checkpoints of each learned model (their renders need not
    be good: the test compares a sequence with single-frame calls): the student tests'
    capture and teacher, a one-iteration linear model and student, all made once per run
    (tests/models.py) and copied here."""
    root = tmp_path_factory.mktemp("sequence")
    copy_entry(tiny_models.get("capture", CAPTURE_ARGS), root / "cap")
    made = {"teacher": tiny_models.get(STUDENT_TEACHER[0], CAPTURE_ARGS, *STUDENT_TEACHER[1:]),
            "linear": tiny_models.get("linear", CAPTURE_ARGS, ["--iters", "1", "-q"],
                                      config=LINEAR),
            "student": tiny_models.get("student", CAPTURE_ARGS,
                                       ["--envs", "builtin:sky", "--envs", "builtin:studio",
                                        "--iters", "1", "-q"], config=STUDENT,
                                       teacher=STUDENT_TEACHER)}
    for name, path in made.items():
        copy_entry(path, root / f"{name}.pt")
    return root


def _pixels(path):
    from relight_cli.formats.exr import read_exr
    image = read_exr(str(path))
    return image.channels, image.attributes


MODELS = {"physical": ["--tex-res", "32"], "teacher": [], "linear": [], "student": []}


@pytest.mark.parametrize("model", list(MODELS))
def test_sequence_pixels_equal_single_frame_calls(models, tmp_path, model):
    extra = list(MODELS[model])
    if model != "physical":
        extra += ["--checkpoint", models / f"{model}.pt"]
    view = VIEW if model != "student" else VIEW[:2]       # the student has its own grid
    hand = models / "cap" / "hand.npz"
    seq = tmp_path / "seq"
    seq.mkdir()
    r = _invoke("relight", hand, "builtin:sky", "--model", model, *extra, *view,
                "--frames", "1:6:2", "-o", seq / "f_{frame:02d}.exr",
                "--preview", seq / "f_{frame:02d}.png")
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in seq.iterdir()) == [
        "f_01.exr", "f_01.png", "f_03.exr", "f_03.png", "f_05.exr", "f_05.png"]
    assert "3 frames" in r.output and "frames/s" in r.output
    for frame in (5,):          # the last of the three: every cache has been reused
        single = tmp_path / f"single_{frame}.exr"
        r = _invoke("relight", hand, "builtin:sky", "--model", model, *extra, *view,
                    "--frame", frame, "-o", single, "-q")
        assert r.exit_code == 0, r.output
        a, ha = _pixels(seq / f"f_{frame:02d}.exr")
        b, hb = _pixels(single)
        assert set(a) == set(b) and set(a) >= {"R", "G", "B", "A"}
        for name in a:
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"{model} {name}")
        assert ha["relight.camera"] == hb["relight.camera"]


def test_sequence_subprocess_and_all_frames(models, tmp_path):
    out = tmp_path / "all"
    out.mkdir()
    r = run_relight("relight", str(models / "cap" / "hand.npz"), "builtin:studio", *VIEW,
                    "--tex-res", "32", "--frames", "all", "-o", str(out / "{frame}.exr"))
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == [f"{i}.exr" for i in range(6)]
    assert "wrote 6 frames" in r.stderr


@pytest.mark.parametrize("args, message", [
    (["--frames", "0:2", "--frame", "1", "-o", "{frame}.exr"], "--frame works on one frame"),
    (["--frames", "0:2", "-o", "out.exr"], "must hold {frame}"),
    (["--frames", "0:2", "-o", "{frame:q}.exr"], "may only use {frame}"),
    (["--frames", "0:2", "-o", "{frame[0]}.exr"], "may only use {frame}"),
    (["--frames", "0:2", "-o", "{frame:c}.exr"], "may only use {frame}"),
    (["--frames", "0:2", "-o", "{frame}.exr", "--preview", "same.png"], "must hold {frame}"),
    (["--frames", "4:2", "-o", "{frame}.exr"], "selects no frame"),
    (["--frames", "0:9:0", "-o", "{frame}.exr"], "step must be"),
    (["--frames", "x", "-o", "{frame}.exr"], "takes all, A:B or A:B:S"),
    (["--frames", "-1:2", "-o", "{frame}.exr"], "≥ 0"),
])
def test_sequence_bad_usage(models, tmp_path, args, message):
    hand = models / "cap" / "hand.npz"
    r = _invoke("relight", hand, "builtin:sky", *VIEW, *[a.replace("{frame", str(tmp_path / "{frame"))
                                                        if a.endswith((".exr", ".png")) else a
                                                        for a in args])
    assert r.exit_code == 2, r.output
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("relight relight: error: "), r.output
    assert message in lines[0], lines[0]
    assert not list(tmp_path.iterdir())


def test_sequence_refuses_an_existing_frame_with_no_clobber(models, tmp_path):
    (tmp_path / "3.exr").write_bytes(b"keep")
    r = _invoke("relight", models / "cap" / "hand.npz", "builtin:sky", *VIEW, "--tex-res", "32",
                "--frames", "0:6", "--no-clobber", "-o", tmp_path / "{frame}.exr")
    assert r.exit_code == 2, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["3.exr"]
    assert (tmp_path / "3.exr").read_bytes() == b"keep"


def _cuda() -> bool:
    import torch
    return torch.cuda.is_available()


@pytest.mark.skipif(not _cuda(), reason="needs a CUDA device")
@pytest.mark.parametrize("model", ["student", "teacher", "linear"])
def test_sequence_on_cuda_matches_cpu(models, tmp_path, model):
    """``--device cuda`` renders the same frames as the CPU path (to float32 rounding of
    the network; geometry and visibility are the same CPU arrays)."""
    hand = models / "cap" / "hand.npz"
    view = VIEW if model != "student" else VIEW[:2]
    out = {}
    for device in ("cpu", "cuda"):
        folder = tmp_path / device
        folder.mkdir()
        r = _invoke("relight", hand, "builtin:sky", "--model", model, "--checkpoint",
                    models / f"{model}.pt", *view, "--device", device, "--frames", "0:6:5",
                    "-o", folder / "{frame}.exr", "-q")
        assert r.exit_code == 0, r.output
        out[device] = [_pixels(folder / f"{k}.exr")[0] for k in (0, 5)]
    for a, b in zip(out["cpu"], out["cuda"]):
        scale = max(float(np.abs(a[c]).max()) for c in "RGB")
        for c in "RGBA":
            np.testing.assert_allclose(b[c], a[c], atol=1e-3 * max(scale, 1e-6), rtol=1e-3,
                                       err_msg=f"{model} {c}")


def test_student_precision(models, tmp_path):
    """--precision: bfloat16 autocast renders within a few per cent of float32 (a 1-iteration
    student; the trained cpu-preset student measured 68–70 dB apart), auto resolves to one of
    them and is recorded, and the option is refused for other models."""
    from relight_cli.jobs.relight_hand import decoder_precision
    hand = models / "cap" / "hand.npz"
    out = {}
    for p in ("float32", "bfloat16", "auto"):
        r = _invoke("relight", hand, "builtin:sky", "--model", "student", "--checkpoint",
                    models / "student.pt", "--size", "20x16", "--precision", p, "-o",
                    tmp_path / f"{p}.exr")
        assert r.exit_code == 0, r.output
        out[p], attrs = _pixels(tmp_path / f"{p}.exr")
        assert f'"precision": "{decoder_precision(p, "cpu")}"' in attrs["relight.provenance"]
    a, b = (np.stack([out[p][c] for c in "RGB"]) for p in ("float32", "bfloat16"))
    assert not np.array_equal(a, b)                       # bfloat16 really ran
    np.testing.assert_allclose(b, a, atol=0.02 * float(np.abs(a).max()))
    np.testing.assert_array_equal(out["float32"]["A"], out["bfloat16"]["A"])
    assert decoder_precision("auto", "cuda:0") == "float32"
    r = _invoke("relight", hand, "builtin:sky", "--precision", "bfloat16", "-o",
                tmp_path / "x.exr")
    assert r.exit_code == 2 and "--precision only apply to --model student" in r.output
