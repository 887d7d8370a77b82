"""The bad-input sweeps' shared inputs and checks (tests/system/test_outputs_and_bad_inputs.py,
tests/system/test_format_promises.py): the folder of tiny inputs every subcommand reads, the
in-process runner, the one-line error check, a snapshot of folders."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import stat
import subprocess
import tempfile
from pathlib import Path

import pytest
from click.testing import CliRunner

from models import SWEEP_CAPTURE, SWEEP_TEACHER, SWEEP_TEACHER_CONFIG, copy_entry
from relight_cli.cli import cli


@pytest.fixture(scope="module")
def data(tiny_models):
    """A folder of tiny inputs, readable by every user (the non-root case reads it)."""
    folder = Path(tempfile.mkdtemp(prefix="relight-sweep-", dir="/tmp"))
    os.chmod(folder, 0o755)
    run = _inproc
    for args in (["envmap", "builtin:sky", "--size", "8x4", "-o", folder / "sky.exr"],
                 ["envmap", "builtin:studio", "--size", "16x8", "-o", folder / "img.exr"],
                 ["envmap", "builtin:sky", "--size", "16x8", "-o", folder / "img2.exr"],
                 ["sh-probe", folder / "sky.exr", "--degree", "1", "-o", folder / "probe.json"],
                 ["fit-geometry", "--pose", "fist", "-o", folder / "hand.npz"]):
        r = run(*args)
        assert r.exit_code == 0, r.output
    import trimesh

    from relight_cli.formats.gaussians_ply import write_gaussians
    from relight_cli.gaussians.from_mesh import gaussians_from_mesh
    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    write_gaussians(str(folder / "ball.ply"), gaussians_from_mesh(ball.vertices, ball.faces))
    room = trimesh.creation.box((1.0, 0.05, 1.0)).subdivide().subdivide()   # ≥ 32 for order-3 SH fits
    write_gaussians(str(folder / "room.ply"),
                    gaussians_from_mesh(room.vertices - [0, 0.2, 0], room.faces))
    (folder / "lights.json").write_text(json.dumps(
        {"format": "relight/lights", "version": 1, "lights": [{"position": [0.0, 1.0, 0.0]}]}))
    from relight_cli.formats.camera import Camera, write_cameras
    write_cameras(str(folder / "cam.json"), [Camera.look_at([0, 0.1, 0.6], [0, 0.1, 0], width=8,
                                                            height=8)])
    r = run("metrics", "image", folder / "img.exr", folder / "img2.exr", "-o", folder / "m.json")
    assert r.exit_code == 0, r.output
    # a tiny capture and teacher (train-teacher, relight --model teacher): made once per run
    # (tests/models.py), copied here
    (folder / "small.json").write_text(json.dumps(SWEEP_TEACHER_CONFIG))
    copy_entry(tiny_models.get("capture", SWEEP_CAPTURE), folder / "cap")
    copy_entry(tiny_models.get(SWEEP_TEACHER[0], SWEEP_CAPTURE, *SWEEP_TEACHER[1:]),
               folder / "teacher.pt")
    for root, dirs, files in os.walk(folder):
        for name in dirs:
            os.chmod(os.path.join(root, name), 0o755)
        for name in files:
            os.chmod(os.path.join(root, name), 0o644)
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def _inproc(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def _snapshot(*folders) -> dict:
    """Every entry (hidden ones too) under the folders: type and content hash."""
    seen = {}
    for folder in folders:
        for root, dirs, files in os.walk(folder):
            for name in dirs + files:
                p = os.path.join(root, name)
                st = os.lstat(p)
                digest = None
                if stat.S_ISREG(st.st_mode):
                    digest = hashlib.sha256(Path(p).read_bytes()).hexdigest()
                seen[p] = (stat.S_IFMT(st.st_mode), digest)
    return seen


def _assert_one_error(code, stderr, expected_code, *words):
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert code == expected_code, stderr
    assert len(lines) == 1, stderr
    assert "traceback" not in stderr.lower() and "internal error" not in stderr, stderr
    for w in words:   # a tuple: any one of these
        assert any(a in lines[0] for a in ((w,) if isinstance(w, str) else w)), lines[0]


def _run_inproc_fail(args, expected_code, *words):
    r = CliRunner().invoke(cli, [str(a) for a in args])
    _assert_one_error(r.exit_code, r.stderr, expected_code, *words)
    return r


# The commands under test: name -> (argv builder given the data folder and the
# output, the output's extension).  One primary output each.
COMMANDS = {
    "envmap": (lambda d, o: ["envmap", d / "sky.exr", "--size", "8x4", "-o", o], ".exr"),
    "sh-probe": (lambda d, o: ["sh-probe", d / "sky.exr", "--degree", "1", "-o", o], ".json"),
    "fit-geometry": (lambda d, o: ["fit-geometry", "--pose", "fist", "-o", o], ".npz"),
    "bake-features": (lambda d, o: ["bake-features", d / "hand.npz", d / "sky.exr", "--res", "8",
                                    "--env-res", "8x4", "-o", o], ".exr"),
    "relight-hand": (lambda d, o: ["relight", d / "hand.npz", d / "sky.exr", "--size", "8x8",
                                   "--tex-res", "8", "--aa", "1", "--env-res", "8x4", "-o", o],
                     ".exr"),
    "relight-gaussians": (lambda d, o: ["relight", d / "ball.ply", "--probe", d / "probe.json",
                                        "-o", o], ".ply"),
    "dgsm-build": (lambda d, o: ["dgsm-build", d / "ball.ply", "--receivers", d / "room.ply",
                                 "--lights", d / "lights.json", "--size", "4", "--bins", "2",
                                 "-o", o], ".exr"),
    "metrics-image": (lambda d, o: ["metrics", "image", d / "img.exr", d / "img2.exr", "-o", o],
                      ".json"),
    "metrics-lighting": (lambda d, o: ["metrics", "lighting", "--scene", d / "room.ply",
                                       "--avatar", d / "ball.ply", "--max-points", "16",
                                       "--neighbours", "4", "-o", o], ".json"),
    "train-teacher": (lambda d, o: ["train-teacher", d / "cap", "--config", d / "small.json",
                                    "--iters", "1", "-o", o], ".pt"),
    "relight-teacher": (lambda d, o: ["relight", d / "hand.npz", d / "sky.exr", "--model",
                                      "teacher", "--checkpoint", d / "teacher.pt", "--size",
                                      "8x8", "--env-res", "8x4", "-o", o], ".exr"),
    "relight-capture": (lambda d, o: ["relight", d / "cap", "--model", "teacher",
                                      "--checkpoint", d / "teacher.pt", "--eval-samples", "1",
                                      "-o", o], ".json"),
    "camera": (lambda d, o: ["camera", "--eye", "0,0.1,0.5", "--size", "8x8", "-o", o], ".json"),
}
# An input of each command that the "output is an input" case writes over.
FIRST_INPUT = {"envmap": "sky.exr", "sh-probe": "sky.exr", "fit-geometry": None,
               "bake-features": "hand.npz", "relight-hand": "sky.exr",
               "relight-gaussians": "ball.ply", "dgsm-build": "ball.ply",
               "metrics-image": "img.exr", "metrics-lighting": "room.ply",
               "train-teacher": "small.json", "relight-teacher": "sky.exr", "camera": None,
               "relight-capture": "teacher.pt"}


DUPLICATES = {
    "envmap": lambda d, t: ["envmap", d / "sky.exr", "-o", t / "x.exr", "--preview",
                            t / "x.exr"],
    "dgsm-build-alias": lambda d, t: ["dgsm-build", d / "ball.ply", "--receivers", d / "room.ply",
                                      "--lights", d / "lights.json", "-o", t / "s.exr",
                                      "--occluders-out", t / "a.ply", "--receivers-out",
                                      f"{t}/./a.ply"],
    "fit-geometry": lambda d, t: ["fit-geometry", "-o", t / "h.npz", "--report", t / "h.npz"],
    "relight-hand": lambda d, t: ["relight", d / "hand.npz", d / "sky.exr", "-o", t / "r.exr",
                                  "--preview", t / "r.exr"],
    "dgsm-build": lambda d, t: ["dgsm-build", d / "ball.ply", "--receivers", d / "room.ply",
                                "--lights", d / "lights.json", "-o", t / "s.exr",
                                "--occluders-out", t / "a.ply", "--receivers-out", t / "a.ply"],
    "metrics-image": lambda d, t: ["metrics", "image", d / "img.exr", d / "img2.exr",
                                   "-o", t / "m.json", "--jsonl", t / "m.json"],
    "bake-features": lambda d, t: ["bake-features", d / "hand.npz", d / "sky.exr",
                                   "-o", t / "f.exr", "--preview", t / "f.exr"],
}


def _full_filesystem_available() -> str | None:
    if not shutil.which("unshare"):
        return "unshare(1) is not installed"
    probe = subprocess.run(["unshare", "-rm", "sh", "-c",
                            "d=$(mktemp -d) && mount -t tmpfs -o size=16k tmpfs $d && umount $d"],
                           capture_output=True, text=True)
    if probe.returncode != 0:
        return ("cannot mount a small tmpfs in an unprivileged user namespace: "
                + (probe.stderr.strip().splitlines() or ["?"])[-1])
    return None


def _quote(a) -> str:
    import shlex
    return shlex.quote(str(a))
