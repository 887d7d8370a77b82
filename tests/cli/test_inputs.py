"""The input loaders (relight_cli/cli/inputs.py): poses, keypoints, templates, scans, with their
one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relight_cli.cli import inputs as I
from relight_cli.errors import DataError, UsageProblem


def test_pose_job_and_pose_loader(tmp_path):
    from relight_cli.hand import poses as P
    from relight_cli.jobs import fit_geometry as J

    template = I.load_template("builtin:left")
    poses, trans = I.load_poses("random", 3, 5, template)
    assert poses.shape == (3, 25, 3) and not np.allclose(poses[0], poses[1])
    (tmp_path / "p.json").write_text(json.dumps({"names": ["fist", "ok"]}))
    poses, trans = I.load_poses(str(tmp_path / "p.json"), 1, 0, template)
    np.testing.assert_array_equal(poses[1], P.named_pose("ok", "left", template.rest_joints))
    fitted = J.pose(template, poses, trans, two_hands=True)
    assert fitted.settings == {"frames": 2}
    assert fitted.report == {"frames": 2, "fitted": False}
    assert [h.poses.shape for h in fitted.hand.hands] == [(2, 25, 3)] * 2
    with pytest.raises(UsageProblem, match="--pose must be"):
        I.load_poses("wave", 1, 0, template)
    (tmp_path / "bad.json").write_text(json.dumps({"poses": [[0, 0, 0]]}))
    with pytest.raises(DataError, match="shape"):
        I.load_poses(str(tmp_path / "bad.json"), 1, 0, template)


def test_keypoint_and_template_loaders(tmp_path):
    """Leap recordings cut to a frame range and checked against the template's side;
    the --frames and template specs' errors."""
    from conftest import shared_path

    from relight_cli.sequence import parse_frames
    assert parse_frames("0:300:10").as_slice() == slice(0, 300, 10)
    assert parse_frames("5:").as_slice() == slice(5, None, None)
    for bad in ("1", "a:b", "-1:4", "0:4:0"):
        with pytest.raises(UsageProblem, match="--frames"):
            parse_frames(bad)
    with pytest.raises(UsageProblem, match="unknown built-in template"):
        I.load_template("builtin:two")
    with pytest.raises(UsageProblem, match="--hand must be"):
        I.leap_hand("both")
    assert I.leap_hand("7") == 7
    leap = shared_path("hands", "leap", "pinch.json")
    if not leap.exists():
        pytest.skip("no shared Leap recording here")
    kp = I.load_keypoints(str(leap), I.load_template("builtin:right"),
                          frames=parse_frames("0:40:10").as_slice())
    np.testing.assert_array_equal(kp.frames, [0, 10, 20, 30])
    assert kp.source is not None and kp.positions.shape == (4, 25, 3)
    with pytest.raises(DataError, match="left hand"):
        I.load_keypoints(str(leap), I.load_template("builtin:left"))
    with pytest.raises(DataError, match="no keypoint frames"):
        I.load_keypoints(str(leap), I.load_template("builtin:right"),
                         frames=parse_frames("100000:").as_slice())


def test_scan_loaders(tmp_path):
    import trimesh

    from relight_cli.hand.model import builtin_hand
    rest = builtin_hand(pose=None)
    for i in range(2):
        trimesh.Trimesh(rest.coarse.vertices + i, rest.coarse.faces,
                        process=False).export(tmp_path / f"scan_{i}.ply")
    paths = I.scan_paths(str(tmp_path / "scan_*.ply"))
    assert [p.rsplit("/", 1)[1] for p in paths] == ["scan_0.ply", "scan_1.ply"]
    a, b = I.load_scans(paths, seed=1)
    assert a.shape == (5000, 3) and b.mean(0) == pytest.approx(a.mean(0) + 1, abs=0.01)
    np.testing.assert_array_equal(I.load_scans(paths, seed=1)[1], b)     # seeded
    with pytest.raises(UsageProblem, match="matches no files"):
        I.scan_paths(str(tmp_path / "none_*.ply"))
    (tmp_path / "empty.ply").write_text("")
    with pytest.raises(DataError):
        I.load_scans([str(tmp_path / "empty.ply")])
