"""relight_cli.jobs.fit_geometry called without click: a fit recovers a known pose as the CLI does."""

from __future__ import annotations

import json

import numpy as np

from relight_cli.cli import inputs as I


def _cli(run_cli, *args):
    r = run_cli(*args)
    assert r.exit_code == 0, r.output
    return r


# ---------------------------------------------------------------- fit-geometry


def _known_keypoints(n: int, seed: int):
    from relight_cli.hand import poses as P
    from relight_cli.hand.model import PARENTS, builtin_hand
    from relight_cli.hand.skinning import posed_joints
    rest = builtin_hand(pose=None).rest_joints
    poses = P.random_poses(n, seed=seed)
    trans = np.random.default_rng(seed).normal(0, 0.05, (n, 3))
    return poses, trans, posed_joints(poses, trans, rest, PARENTS)


def test_fit_job_recovers_a_known_pose_as_the_cli_does(run_cli, tmp_path):
    """Keypoints of a known pose: the fitted joints land on them (and the fitted hand is
    the one fit-geometry writes for the same keypoints and seed)."""
    from relight_cli.formats.hand_npz import read_hand
    from relight_cli.formats.keypoints import Keypoints
    from relight_cli.hand.skinning import posed_joints
    from relight_cli.jobs import fit_geometry as J

    _, _, joints = _known_keypoints(1, seed=4)
    np.save(tmp_path / "kp.npy", joints)
    _cli(run_cli, "fit-geometry", "--keypoints", tmp_path / "kp.npy", "--iterations", "40",
         "-o", tmp_path / "fit.npz", "--report", tmp_path / "fit.json", "-q")
    template = I.load_template("builtin:right")
    kp = I.load_keypoints(str(tmp_path / "kp.npy"), template)
    assert isinstance(kp, Keypoints) and kp.positions.shape == (1, 25, 3)
    lines = []
    fitted = J.fit(template, kp, None, J.FitGeometryOptions(iterations=40), log=lines.append)
    hand = fitted.hand
    got = posed_joints(hand.poses, hand.translations, hand.rest_joints, hand.parents)
    assert np.abs(got - joints).max() < 0.004                      # metres: within 4 mm
    assert fitted.report["mpjpe_mm"] < 3.0
    assert lines[0].startswith("template template: right hand") and "fitting 1" in lines[-1]
    written = read_hand(str(tmp_path / "fit.npz"))
    np.testing.assert_array_equal(written.poses, hand.poses)
    np.testing.assert_array_equal(written.coarse.vertices, hand.coarse.vertices)
    report = json.loads((tmp_path / "fit.json").read_text())
    assert report["per_frame"] == fitted.report["per_frame"]
    assert report["provenance"]["settings"]["iterations"] == fitted.settings["iterations"] == 40
