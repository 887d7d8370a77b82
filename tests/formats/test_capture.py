"""The relight/capture format (formats/capture.py): round trip and rejections."""

from __future__ import annotations

import json

import pytest

from relight_cli.errors import DataError
from relight_cli.formats import capture as C


# ---------------------------------------------------------------- format


def _minimal():
    return {"format": "relight/capture", "version": 1, "hand": "hand.npz",
            "cameras": [{"name": "a", "K": [[10, 0, 4], [0, 10, 4], [0, 0, 1]],
                         "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 1],
                         "width": 8, "height": 8}],
            "lights": [{"position": [0, 1, 0], "intensity": [1, 1, 1]}],
            "frames": [{"index": 0, "time": 0.0, "pose": 0, "lit": "full", "lights_on": [0],
                        "images": ["a"]}]}


def test_format_round_trip_and_rejections(tmp_path):
    path = tmp_path / "capture.json"
    path.write_text(json.dumps(_minimal()))
    cap = C.read_capture(str(path))
    C.write_capture(str(tmp_path / "again.json"), cap)
    assert C.to_json(C.read_capture(str(tmp_path / "again.json"))) == C.to_json(cap)
    for change, message in (
            ({"version": 2}, "version 2 is newer"),
            ({"format": "relight/other"}, "not a relight/capture file"),
            ({"frames": [{"index": 0, "pose": 0, "lights_on": [3]}]}, "lights_on"),
            ({"frames": [{"index": 0, "pose": 0, "images": ["zz"]}]}, "unknown camera"),
            ({"frames": [{"index": 0, "pose": 0, "lit": "half"}]}, "'full' or 'group'"),
            ({"lights": [{"position": [0, "x", 0]}]}, "position"),
            ({"cameras": []}, "'cameras' is empty"),
            # a capture reads only its own files (issue 52's sweep: an eval render of
            # /etc/passwd or ../x trained first and failed when read)
            ({"hand": "/etc/hand.npz"}, "inside the capture folder"),
            ({"evaluation": {"hand": "eval/hand.npz", "envs": {"sky": "../sky.exr"},
                             "renders": []}}, "inside the capture folder"),
            ({"evaluation": {"hand": "eval/hand.npz", "envs": {"sky": "eval/sky.exr"},
                             "renders": [{"pose": 0, "env": "sky", "camera": "a",
                                          "image": "/etc/passwd"}]}},
             "inside the capture folder"),
            ({"evaluation": {"hand": "eval/hand.npz", "envs": {"sky": "eval/sky.exr"},
                             "renders": [{"pose": 0, "env": "sky", "camera": "a",
                                          "image": "eval/../../x.exr"}]}},
             "inside the capture folder"),
            # an image listed twice would be trained on twice, as a light listed twice in
            # lights_on would count twice (issue 52's sweep: it was read)
            ({"frames": [{"index": 0, "pose": 0, "lights_on": [0], "images": ["a", "a"]}]},
             "lists camera 'a' twice in images")):
        obj = dict(_minimal(), **change)
        path.write_text(json.dumps(obj))
        with pytest.raises(DataError) as info:
            C.read_capture(str(path))
        assert message in str(info.value) and str(path) in str(info.value)
