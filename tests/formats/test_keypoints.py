"""relight/keypoints: a two-hand file's ``hands`` list (read one hand, which sides, errors)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_errors import _one_error

from relight_cli.errors import DataError
from relight_cli.formats.keypoints import keypoint_sides, read_keypoints
from relight_cli.hand.model import PARENTS, builtin_hand
from relight_cli.hand.skinning import posed_joints


def _joints(n, seed):
    from relight_cli.hand import poses as P
    rest = builtin_hand(pose=None).rest_joints
    return posed_joints(P.random_poses(n, seed=seed), np.zeros((n, 3)), rest, PARENTS)


def _write(tmp_path, obj, name="kp.json"):
    path = tmp_path / name
    path.write_text(json.dumps(obj))
    return str(path)


def test_two_hand_file_reads_each_hand_with_its_side_and_frames(tmp_path):
    right, left = _joints(3, 1), _joints(2, 2) * [-1.0, 1.0, 1.0]
    conf = np.ones((2, 25, 1))
    conf[1, 7] = 0                                            # one missing joint, left frame 9
    path = _write(tmp_path, {"format": "relight/keypoints", "version": 1, "hands": [
        {"side": "left", "frames": [4, 9],
         "keypoints": np.concatenate([left, conf], -1).tolist()},
        {"side": "right", "keypoints": right.tolist()}]})
    assert keypoint_sides(path) == ["left", "right"]
    kp = read_keypoints(path, hand="left")
    assert kp.side == "left" and kp.source == {"format": "relight/keypoints", "hand": "left",
                                               "rows": 2}
    np.testing.assert_array_equal(kp.frames, [4, 9])
    np.testing.assert_allclose(kp.positions, left)
    assert kp.confidence[1, 7] == 0 and kp.confidence.sum() == 49
    kp = read_keypoints(path, hand="right")
    np.testing.assert_array_equal(kp.frames, [0, 1, 2])       # default frame numbers
    np.testing.assert_allclose(kp.positions, right)
    # one unnamed hand, .npy, a missing file: not a two-hand file
    one = _write(tmp_path, {"keypoints": right.tolist()}, "one.json")
    np.save(tmp_path / "kp.npy", right)
    for other in (one, str(tmp_path / "kp.npy"), str(tmp_path / "absent.json")):
        assert keypoint_sides(other) is None
    # a 'hands' list of one hand reads without --hand
    single = _write(tmp_path, {"hands": [{"side": "left", "keypoints": left.tolist()}]}, "s.json")
    assert keypoint_sides(single) == ["left"] and read_keypoints(single).side == "left"


@pytest.mark.parametrize("hands, hand, needle", [
    ([{"side": "left"}], None, "'side' (right or left) and 'keypoints'"),
    ([{"side": "up", "keypoints": []}], None, "'side' (right or left)"),
    ([{"side": "left", "keypoints": "K"}, {"side": "left", "keypoints": "K"}], None,
     "two left hands"),
    ([], None, "one or two hands"),
    ("K", None, "one or two hands"),
    ([{"side": "left", "keypoints": "K"}, {"side": "right", "keypoints": "K"}], None,
     "--hand both"),
    ([{"side": "left", "keypoints": "K"}], "right", "no right hand"),
    ([{"side": "left", "keypoints": "K"}], 7, "a Leap hand id"),
    ([{"side": "left", "keypoints": "K", "frames": [3, 1]}], None, "strictly increasing"),
])
def test_bad_hands_lists(tmp_path, hands, hand, needle):
    good = _joints(2, 3).tolist()
    if isinstance(hands, list):
        hands = [{**h, "keypoints": good} if h.get("keypoints") == "K" else h for h in hands]
    path = _write(tmp_path, {"format": "relight/keypoints", "version": 1, "hands": hands})
    with pytest.raises(DataError, match=None) as err:
        read_keypoints(path, hand=hand)
    assert needle in str(err.value) and "kp.json" in str(err.value)


def test_hands_and_keypoints_together_are_refused(tmp_path):
    path = _write(tmp_path, {"keypoints": _joints(1, 0).tolist(),
                             "hands": [{"side": "left", "keypoints": _joints(1, 0).tolist()}]})
    with pytest.raises(DataError, match="not both"):
        read_keypoints(path)


def test_cli_errors_of_two_hand_fits(run_cli, tmp_path):
    """One line, the exit code, nothing written."""
    out = tmp_path / "x.npz"
    right = _joints(2, 4)
    only_right = _write(tmp_path, {"hands": [{"side": "right", "keypoints": right.tolist()}]},
                        "r.json")
    _one_error(run_cli("fit-geometry", "--keypoints", only_right, "--hand", "both", "-o", out),
               1, "no left hand")
    apart = _write(tmp_path, {"hands": [
        {"side": "right", "frames": [0, 1], "keypoints": right.tolist()},
        {"side": "left", "frames": [2, 3], "keypoints": (right * [-1, 1, 1]).tolist()}]},
        "apart.json")
    _one_error(run_cli("fit-geometry", "--keypoints", apart, "--iterations", "5", "-o", out),
               1, "no common frame")
    _one_error(run_cli("fit-geometry", "--keypoints", apart, "--hand", "both", "--two-hands",
                       "-o", out), 2, "--hand both")
    _one_error(run_cli("fit-geometry", "--keypoints", apart, "--hand", "sideways", "-o", out),
               2, "left, right, both")
    np.save(tmp_path / "kp.npy", right)
    _one_error(run_cli("fit-geometry", "--keypoints", tmp_path / "kp.npy", "--hand", "both",
                       "-o", out), 2, "Leap recordings only")
    assert not out.exists()
