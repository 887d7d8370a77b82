"""Files that declare what they should not (issue 23, "Nothing trusted that a file declares").

Each row damages one input in a way its format's reader must catch: a capture.json
whose grouped frame has no light on, that names no hand, whose held-out hand or
render is gone, or that is a folder; Leap recordings with no measured joint of the
hand (also inside --frames); nerfstudio fields of view at 0 or π and focal
lengths ≤ 0; a Gaussians PLY whose ``relight.format`` line has no value; and
``synth-capture`` on a full disk.  Each goes through every command that reads that
kind of file (they share one reader) and must end with one line
``relight <cmd>: error: <what> (<file>)``, exit 1 (bad data) or 2 (usage), no
traceback, nothing written and the inputs untouched.

Inputs are tiny (a 1-camera, 3-LED, 8×8 capture, a 1-step teacher with 8×8 maps,
a 20-Gaussian ball) so the module runs in well under a minute on one core.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from relight_cli.cli import cli

TINY_STAGE = ["--cameras", "1", "--leds", "3", "--group", "1", "--n-frames", "3", "--size", "8",
              "--tex-res", "8", "--aa", "1"]
TINY_CAPTURE = TINY_STAGE + ["--eval-poses", "1", "--eval-cameras", "1", "--eval-envs",
                             "builtin:sky", "--eval-env-res", "8x4"]


def _ok(*args):
    r = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    return r


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A tiny capture with held-out renders, a teacher trained on it for one step, a
    Gaussian ball and an SH probe (read-only sources; each row copies what it damages)."""
    folder = tmp_path_factory.mktemp("hostile-base")
    _ok("synth-capture", "-o", folder / "cap", *TINY_CAPTURE, "-q")
    (folder / "small.json").write_text(json.dumps(
        {"tex_res": 8, "encoder": [2, 2], "decoder": [2, 2], "pose_channels": [2, 2],
         "val_samples": 1, "aa": 1}))
    _ok("train-teacher", folder / "cap", "--config", folder / "small.json", "--iters", "1",
        "-o", folder / "teacher.pt", "-q")
    import trimesh

    from relight_cli.formats.gaussians_ply import write_gaussians
    from relight_cli.gaussians.from_mesh import gaussians_from_mesh
    ball = trimesh.creation.icosphere(subdivisions=0, radius=0.1)
    write_gaussians(str(folder / "ball.ply"), gaussians_from_mesh(ball.vertices, ball.faces))
    _ok("envmap", "builtin:sky", "--size", "8x4", "-o", folder / "sky.exr", "-q")
    _ok("sh-probe", folder / "sky.exr", "--degree", "1", "-o", folder / "probe.json", "-q")
    return folder


# ----------------------------------------------------------------------------- damaged inputs


def _capture(b: Path, t: Path, change=None, remove=()) -> Path:
    """A copy of the base capture in ``t``: ``change(obj)`` edits its capture.json,
    ``remove`` lists files to delete (relative to the capture)."""
    cap = t / "cap"
    shutil.copytree(b / "cap", cap)
    if change is not None:
        index = cap / "capture.json"
        obj = json.loads(index.read_text())
        change(obj)
        index.write_text(json.dumps(obj))
    for rel in remove:
        os.remove(cap / rel)
    return cap


def _no_light(obj):
    next(f for f in obj["frames"] if f["lit"] == "group")["lights_on"] = []


def _no_hand(obj):
    del obj["hand"]


def _index_is_folder(b: Path, t: Path) -> Path:
    cap = _capture(b, t)
    os.remove(cap / "capture.json")
    (cap / "capture.json").mkdir()
    return cap


def _leap(t: Path, pointables_per_frame) -> Path:
    """A LeapJS recording of one right hand (id 7) with the given pointables per frame."""
    obj = {"metadata": {"formatVersion": 0.1, "generatedBy": "LeapJS Playback 0.1-pre",
                        "protocolVersion": 6},
           "frames": [{"id": 100 + i, "timestamp": 8700 * i,
                       "hands": [{"id": 7, "type": "right", "palmPosition": [0, 200, 0]}],
                       "pointables": ps} for i, ps in enumerate(pointables_per_frame)]}
    path = t / "rec.json"
    path.write_text(json.dumps(obj))
    return path


def _finger(finger: int, tool=False, positions=True) -> dict:
    p = {"handId": 7, "id": 70 + finger, "type": finger, "tool": tool}
    if positions:
        for k, key in enumerate(("mcpPosition", "pipPosition", "dipPosition", "tipPosition")):
            p[key] = [20.0 * finger - 40, 180.0 + 20 * k, -10.0]
    return p


def _hand(**kw) -> list:
    return [_finger(f, **kw) for f in range(5)]


def _transforms(t: Path, **fields) -> Path:
    """A one-frame nerfstudio transforms.json with the given intrinsics."""
    obj = {"w": 8, "h": 8, **fields,
           "frames": [{"file_path": "images/a.png",
                       "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1],
                                            [0, 0, 0, 1]]}]}
    path = t / "transforms.json"
    path.write_text(json.dumps(obj))
    return path


def _ply(b: Path, t: Path, old: bytes, new: bytes) -> Path:
    data = (b / "ball.ply").read_bytes()
    assert old in data
    path = t / "ball.ply"
    path.write_bytes(data.replace(old, new, 1))
    return path


_FORMAT_LINE = b"obj_info relight.format relight/gaussians 1\n"


def _ply_with_provenance(b: Path, t: Path, line: bytes) -> Path:
    return _ply(b, t, _FORMAT_LINE, _FORMAT_LINE + line)


def _train(cap):
    return ["train-teacher", cap, "--iters", "1", "-o", "OUT.pt"]


def _relight_capture(b):
    return lambda cap: ["relight", cap, "--model", "teacher", "--checkpoint", b / "teacher.pt",
                        "--eval-samples", "1", "-o", "OUT.json"]


def _camera(index):
    return ["camera", "--from", index, "-o", "OUT.json"]


def _distill(b):
    return lambda cap: ["distill", b / "teacher.pt", cap, "--envs", "builtin:sky",
                        "--eval-envs", "builtin:studio", "-o", "OUT.pt"]


def _fit(rec, *extra):
    return ["fit-geometry", "--keypoints", rec, *extra, "-o", "OUT.npz"]


def _zero_confidence_keypoints(t):
    """A relight/keypoints file whose every joint has confidence 0 (nothing measured)."""
    import numpy as np

    from relight_cli.formats.keypoints import Keypoints, write_keypoints
    path = t / "kp.json"
    write_keypoints(str(path), Keypoints(np.zeros((2, 25, 3)), np.zeros((2, 25)),
                                         np.arange(2), None, None, None))
    return path


def _one_empty_frame_keypoints(t):
    """Two keypoint frames; the second measures no joint."""
    import numpy as np

    from relight_cli.formats.keypoints import Keypoints, write_keypoints
    from relight_cli.hand.model import builtin_hand
    from relight_cli.hand.scene import posed_joints_world
    path = t / "kp.json"
    joints = posed_joints_world(builtin_hand(), 0)[0]
    conf = np.ones((2, 25))
    conf[1] = 0
    write_keypoints(str(path), Keypoints(np.stack([joints, joints]), conf, np.arange(2),
                                         None, None, None))
    return path


def _scan(t):
    """A PLY point cloud (the relaxed hand's vertices) to pass as a scan."""
    import trimesh

    from relight_cli.hand.model import builtin_hand
    path = t / "scan.ply"
    if not path.exists():
        trimesh.PointCloud(builtin_hand().coarse.vertices).export(str(path))
    return path


# Each row: id -> (make(base, work folder) -> argv with OUT.ext for the output, exit code,
# words the error line must hold, the file it must name relative to the work folder).
ROWS = {
    # -- capture: a grouped frame with no light on (was an internal ValueError)
    "capture-no-light/train-teacher": (
        lambda b, t: _train(_capture(b, t, _no_light)), 1, "no light on", "cap/capture.json"),
    "capture-no-light/relight": (
        lambda b, t: _relight_capture(b)(_capture(b, t, _no_light)), 1, "no light on",
        "cap/capture.json"),
    "capture-no-light/distill": (
        lambda b, t: _distill(b)(_capture(b, t, _no_light)), 1, "no light on",
        "cap/capture.json"),
    "capture-no-light/camera": (
        lambda b, t: _camera(_capture(b, t, _no_light) / "capture.json"), 1, "no light on",
        "cap/capture.json"),
    "capture-light-twice/train-teacher": (
        lambda b, t: _train(_capture(b, t, lambda o: o["frames"][1].update(lights_on=[1, 1]))),
        1, "twice", "cap/capture.json"),
    # -- capture: the held-out hand is gone (env scores were dropped silently, exit 0)
    "capture-no-eval-hand/train-teacher": (
        lambda b, t: _train(_capture(b, t, remove=["eval/hand.npz"])), 1,
        "held-out hand.npz that is missing", "cap/eval/hand.npz"),
    "capture-no-eval-hand/relight": (
        lambda b, t: _relight_capture(b)(_capture(b, t, remove=["eval/hand.npz"])), 1,
        "held-out hand.npz that is missing", "cap/eval/hand.npz"),
    "capture-no-eval-render/relight": (
        lambda b, t: _relight_capture(b)(_capture(b, t, remove=["eval/000/sky/cam000.exr"])),
        1, "render that is missing", "cap/eval/000/sky/cam000.exr"),
    "capture-no-eval-env/train-teacher": (
        lambda b, t: _train(_capture(b, t, remove=["eval/envs/sky.exr"])), 1,
        "env map ('sky') that is missing", "cap/eval/envs/sky.exr"),
    "capture-eval-unknown-camera/train-teacher": (
        lambda b, t: _train(_capture(b, t, lambda o: o["evaluation"]["renders"][0].update(
            camera="nope"))), 1, "evaluation.renders[0].camera", "cap/capture.json"),
    "capture-eval-pose-out-of-range/train-teacher": (
        lambda b, t: _train(_capture(b, t, lambda o: o["evaluation"]["renders"][0].update(
            pose=5))), 1, "held-out pose 5", "cap/eval/hand.npz"),
    # -- capture: no 'hand' (required by capture.md)
    "capture-no-hand/train-teacher": (
        lambda b, t: _train(_capture(b, t, _no_hand)), 1, "'hand' is missing",
        "cap/capture.json"),
    "capture-no-hand/camera": (
        lambda b, t: _camera(_capture(b, t, _no_hand) / "capture.json"), 1, "'hand' is missing",
        "cap/capture.json"),
    "capture-fps-not-a-number/train-teacher": (
        lambda b, t: _train(_capture(b, t, lambda o: o.update(fps="fast"))), 1, "'fps'",
        "cap/capture.json"),
    # -- capture: capture.json is a folder (was "no such file" of capture.json/capture.json)
    "capture-index-folder/train-teacher CAP": (
        lambda b, t: _train(_index_is_folder(b, t)), 1, "is a folder, not a file",
        "cap/capture.json"),
    "capture-index-folder/train-teacher CAP/capture.json": (
        lambda b, t: _train(_index_is_folder(b, t) / "capture.json"), 1,
        "is a folder, not a file", "cap/capture.json"),
    "capture-index-folder/relight CAP": (
        lambda b, t: _relight_capture(b)(_index_is_folder(b, t)), 1, "is a folder, not a file",
        "cap/capture.json"),
    "keypoints-no-confidence": (
        lambda b, t: _fit(_zero_confidence_keypoints(t)), 1, "measures any joint",
        "kp.json"),
    "keypoints-frame-no-joint/--scans": (
        lambda b, t: _fit(_one_empty_frame_keypoints(t), "--scans", _scan(t), "--scans",
                          _scan(t)), 1, "keypoint frame 1 measures no joint", "kp.json"),
    "capture-index-folder/camera": (
        lambda b, t: _camera(_index_is_folder(b, t) / "capture.json"), 1, "directory",
        "cap/capture.json"),
    # -- Leap: no frame measures a joint of the hand (was fitted, exit 0)
    "leap-no-pointables": (
        lambda b, t: _fit(_leap(t, [[], []])), 1, "measures any joint", "rec.json"),
    "leap-only-tools": (
        lambda b, t: _fit(_leap(t, [_hand(tool=True)] * 2)), 1, "measures any joint",
        "rec.json"),
    "leap-no-positions": (
        lambda b, t: _fit(_leap(t, [_hand(positions=False)] * 2)), 1, "measures any joint",
        "rec.json"),
    "leap-no-positions/--hand ID": (
        lambda b, t: _fit(_leap(t, [_hand(positions=False)] * 2), "--hand", "7"), 1,
        "measures any joint", "rec.json"),
    "leap-frame-range-unmeasured": (
        lambda b, t: _fit(_leap(t, [[], [], _hand()]), "--frames", "0:2"), 1,
        "no keypoint frames in --frames", "rec.json"),
    # -- nerfstudio: fields of view outside (0, π), focal lengths ≤ 0
    "nerfstudio-angle-0": (
        lambda b, t: _camera(_transforms(t, camera_angle_x=0)), 1, "'camera_angle_x'",
        "transforms.json"),
    "nerfstudio-angle-pi": (
        lambda b, t: _camera(_transforms(t, camera_angle_x=math.pi)), 1, "'camera_angle_x'",
        "transforms.json"),
    "nerfstudio-angle-negative": (
        lambda b, t: _camera(_transforms(t, camera_angle_x=-0.5)), 1, "'camera_angle_x'",
        "transforms.json"),
    "nerfstudio-angle-y-0": (
        lambda b, t: _camera(_transforms(t, camera_angle_x=1.0, camera_angle_y=0)), 1,
        "'camera_angle_y'", "transforms.json"),
    "nerfstudio-fl_x-0": (
        lambda b, t: _camera(_transforms(t, fl_x=0)), 1, "'fl_x'", "transforms.json"),
    "nerfstudio-fl_y-negative": (
        lambda b, t: _camera(_transforms(t, fl_x=10, fl_y=-10)), 1, "'fl_y'",
        "transforms.json"),
    # -- Gaussians PLY: a relight.format line without its value
    "ply-format-no-value/sh-probe": (
        lambda b, t: ["sh-probe", _ply(b, t, _FORMAT_LINE, b"obj_info relight.format\n"),
                      "--at", "0,0,0", "--degree", "1", "-o", "OUT.json"], 1,
        "relight.format", "ball.ply"),
    "ply-format-no-value/relight": (
        lambda b, t: ["relight", _ply(b, t, _FORMAT_LINE, b"obj_info relight.format\n"),
                      "--probe", b / "probe.json", "-o", "OUT.ply"], 1, "relight.format",
        "ball.ply"),
    "ply-format-version-0/sh-probe": (
        lambda b, t: ["sh-probe", _ply(b, t, _FORMAT_LINE,
                                       b"obj_info relight.format relight/gaussians 0\n"),
                      "--at", "0,0,0", "--degree", "1", "-o", "OUT.json"], 1,
        "relight.format", "ball.ply"),
    "ply-provenance-no-value/sh-probe": (
        lambda b, t: ["sh-probe", _ply_with_provenance(b, t, b"obj_info relight.provenance\n"),
                      "--at", "0,0,0", "--degree", "1", "-o", "OUT.json"], 1,
        "relight.provenance", "ball.ply"),
}


def _snapshot(folder: Path) -> dict:
    """Every entry under ``folder`` (hidden ones too): kind and content hash."""
    seen = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs:
            seen[os.path.relpath(os.path.join(root, name), folder)] = "dir"
        for name in files:
            path = os.path.join(root, name)
            seen[os.path.relpath(path, folder)] = hashlib.sha256(
                Path(path).read_bytes()).hexdigest()
    return seen


def _assert_one_error(result, command: str, code: int, words: str, file: Path):
    stderr = result.stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert result.exit_code == code, stderr
    assert len(lines) == 1, stderr
    assert "traceback" not in stderr.lower() and "internal error" not in stderr, stderr
    line = lines[0]
    assert line.startswith(f"relight {command}: error: "), line
    assert words in line, line
    assert f"({file})" in line, line


@pytest.mark.parametrize("row", sorted(ROWS))
def test_a_hostile_file_is_one_line_and_writes_nothing(base, tmp_path, run_cli, row):
    make, code, words, culprit = ROWS[row]
    work = tmp_path / "work"
    work.mkdir()
    argv = make(base, work)
    argv = [work / a if a in ("OUT.pt", "OUT.json", "OUT.npz", "OUT.ply") else a for a in argv]
    before, base_before = _snapshot(work), _snapshot(base)
    r = run_cli(*argv)
    _assert_one_error(r, argv[0], code, words, work / culprit)
    assert _snapshot(work) == before, "a failed run changed its folder"
    assert _snapshot(base) == base_before


# ----------------------------------------------------------------------------- a full disk


@pytest.fixture
def full_disk(monkeypatch):
    """Every flushed write fails with ENOSPC, as on a full file system (fsync is where the
    atomic writer learns it)."""
    def no_space(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(os, "fsync", no_space)


@pytest.mark.parametrize("existing", [False, True], ids=["new-folder", "given-empty-folder"])
def test_synth_capture_on_a_full_disk(tmp_path, run_cli, full_disk, existing):
    """A folder synth-capture made is removed when nothing could be written in it; a folder
    the user gave (existing, empty) stays, empty."""
    out = tmp_path / "cap"
    if existing:
        out.mkdir()
    before = _snapshot(tmp_path)
    r = run_cli("synth-capture", "-o", out, *TINY_STAGE, "--eval-poses", "0", "-q")
    _assert_one_error(r, "synth-capture", 1, "no space left on device", out / "capture.json")
    assert _snapshot(tmp_path) == before
    assert out.is_dir() == existing
