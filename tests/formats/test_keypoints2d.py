"""``relight/keypoints-2d``: the MediaPipe → WebXR mapping, round trips, refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relight_cli.errors import DataError
from relight_cli.formats.joints import JOINT_NAMES
from relight_cli.formats.keypoints2d import (MEDIAPIPE_TO_WEBXR, Keypoints2D,
                                             dumps_keypoints2d, keypoints2d_from_json)

# MediaPipe Hands' landmark names, in its order (its documentation), and the WebXR joint
# at the same anatomical place.
MEDIAPIPE = ["wrist", "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
             *[f"{f}_{b}" for f in ("index", "middle", "ring", "pinky")
               for b in ("mcp", "pip", "dip", "tip")]]
SAME_PLACE = {"wrist": "wrist", "cmc": "metacarpal", "mcp": "phalanx-proximal",
              "ip": "phalanx-distal", "pip": "phalanx-intermediate", "dip": "phalanx-distal",
              "tip": "tip"}


def test_mediapipe_joints_land_on_the_webxr_joint_at_the_same_place():
    for i, name in enumerate(MEDIAPIPE):
        webxr = JOINT_NAMES[MEDIAPIPE_TO_WEBXR[i]]
        if name == "wrist":
            assert webxr == "wrist"
            continue
        finger, bone = name.split("_")
        if finger == "thumb" and bone == "mcp":
            assert webxr == "thumb-phalanx-proximal"
            continue
        assert webxr.startswith(finger) and webxr.endswith(SAME_PLACE[bone]), (name, webxr)
    missing = sorted(set(range(25)) - set(MEDIAPIPE_TO_WEBXR.tolist()))
    assert [JOINT_NAMES[j] for j in missing] == [f"{f}-finger-metacarpal"
                                                 for f in ("index", "middle", "ring", "pinky")]


def _obj(n=21, skeleton="mediapipe-21"):
    rng = np.random.default_rng(0)
    return {"format": "relight/keypoints-2d", "version": 1, "skeleton": skeleton,
            "views": [{"image": f"v{i}.png", "pose": 0,
                       "keypoints": np.c_[rng.uniform(0, 100, (n, 2)), np.ones(n)].tolist()}
                      for i in range(2)]}


def test_round_trip_keeps_every_number():
    kp = keypoints2d_from_json(_obj())
    assert kp.uv.shape == (2, 25, 2) and (kp.confidence[:, [5, 10, 15, 20]] == 0).all()
    back = keypoints2d_from_json(json.loads(dumps_keypoints2d(kp)))
    np.testing.assert_array_equal(back.uv, kp.uv)
    np.testing.assert_array_equal(back.confidence, kp.confidence)
    assert back.skeleton == "mediapipe-21" and back.images == kp.images


@pytest.mark.parametrize("edit, needle", [
    (lambda o: o.update(skeleton="coco"), "unknown skeleton"),
    (lambda o: o["views"][0]["keypoints"].pop(), "20 keypoints"),
    (lambda o: o["views"][1]["keypoints"][3].__setitem__(2, 1.5), "confidences"),
    (lambda o: o["views"][1].__setitem__("image", "v0.png"), "same image"),
    (lambda o: o["views"][0].__setitem__("pose", -1), "'pose'"),
    (lambda o: o.update(views=[]), "non-empty"),
    (lambda o: o.update(version=2), "version"),
])
def test_refusals(edit, needle):
    obj = _obj()
    edit(obj)
    with pytest.raises(DataError, match=needle.replace("(", r"\(")):
        keypoints2d_from_json(obj, "kp.json")


def test_nan_is_an_error_not_a_missing_joint():
    obj = _obj(25, "webxr-25")
    obj["views"][0]["keypoints"][7][1] = float("nan")
    with pytest.raises(DataError, match="keypoint 7 is NaN"):
        keypoints2d_from_json(obj)
    assert isinstance(keypoints2d_from_json(_obj(25, "webxr-25")), Keypoints2D)
