"""Leap Motion recordings (LeapJS playback JSON) as hand keypoints (spec: ``formats/leap.md``).

A recording is a JSON object ``{"metadata": {...}, "frames": [frame, ...]}``
(or a bare list of frames), each frame a LeapJS tracking frame with
``hands[]`` and ``pointables[]``.  One tracked hand becomes
:class:`~relight_cli.formats.keypoints.Keypoints` on the 25 WebXR joints:
millimetres → metres, Leap's axes kept (right-handed, +Y up, +Z towards the
user, as the toolkit's world), joints Leap does not measure left MISSING
(position NaN, confidence 0), never invented.  Files are read through
``keypoints.read_keypoints`` (``reader="leap"``, or ``"auto"`` detection).
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from relight_cli.errors import DataError

from ._common import is_int, is_number
from .joints import JOINT_NAMES, N_JOINTS, Keypoints

FORMAT = "leap"
FINGER_NAMES = ("thumb", "index", "middle", "ring", "pinky")
MM_TO_M = 1e-3

# Leap field of a pointable (finger type 0 thumb … 4 pinky) → WebXR joint index
# (joints.JOINT_NAMES).  The thumb has no row for
# carpPosition: Leap models the thumb with a zero-length metacarpal, so its
# carpPosition equals its mcpPosition, which is the thumb's carpometacarpal
# joint (the base of the anatomical metacarpal = WebXR thumb-metacarpal).
# tipPosition (the centre of the fingertip sphere) rather than btipPosition
# (the end of the distal bone, a few mm short of it): WebXR's tip joint is at
# the fingertip, and every recording has tipPosition.
POINTABLE_JOINTS: dict[int, dict[str, int]] = {
    0: {"mcpPosition": 1, "pipPosition": 2, "dipPosition": 3, "tipPosition": 4},
    **{f: {"carpPosition": 5 * f, "mcpPosition": 5 * f + 1, "pipPosition": 5 * f + 2,
           "dipPosition": 5 * f + 3, "tipPosition": 5 * f + 4} for f in range(1, 5)},
}
# Hand field → joint: the wrist (the arm bone's distal end) in protocols that send it.
HAND_JOINTS = {"wrist": 0}


def looks_like_leap(obj) -> bool:
    """True for a LeapJS recording: ``{"frames": [...]}`` whose frames are Leap
    tracking frames (objects with ``hands`` or ``pointables``) or whose
    metadata names LeapJS, or a bare list of such frames."""
    frames = obj.get("frames") if isinstance(obj, dict) else obj
    if isinstance(obj, dict):
        meta = obj.get("metadata")
        if isinstance(meta, dict) and "leap" in str(meta.get("generatedBy", "")).lower():
            return True
    if not isinstance(frames, list) or not frames:
        return False
    first = frames[0]
    return isinstance(first, dict) and ("hands" in first or "pointables" in first)


def parse_hand_choice(text: str | None):
    """``--hand`` for one hand: None (automatic), ``"left"``, ``"right"`` or an integer Leap
    hand id.  (``both``, fit-geometry's two-hand fit, reads each side in turn.)"""
    if text is None:
        return None
    if text in ("left", "right"):
        return text
    if text.isdigit():
        return int(text)
    raise ValueError(f"--hand must be left, right, both or a Leap hand id (an integer), "
                     f"got {text!r}")


def _vector(value, what: str, path: str) -> np.ndarray:
    if not (isinstance(value, list) and len(value) == 3 and all(is_number(v) for v in value)):
        raise DataError(f"{what} must be 3 numbers, got {value!r}"[:200], path)
    return np.asarray(value, np.float64)


def _frames_of(obj, path: str) -> list:
    frames = obj.get("frames") if isinstance(obj, dict) else obj
    if not isinstance(frames, list):
        raise DataError("not a Leap Motion recording: expected an object with a 'frames' list",
                        path)
    if not frames:
        raise DataError("the Leap recording holds no frames", path)
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise DataError(f"Leap frame {i} is not a JSON object (packed LeapJS recordings "
                            "are not supported: save them unpacked)", path)
    return frames


def _hands_of(frame, i: int, path: str) -> list[dict]:
    hands = frame.get("hands", [])
    if not isinstance(hands, list):
        raise DataError(f"Leap frame {i}: 'hands' must be a list", path)
    for h in hands:
        if not isinstance(h, dict) or not is_int(h.get("id")) \
                or h.get("type") not in ("left", "right"):
            raise DataError(f"Leap frame {i}: each hand needs an integer 'id' and a 'type' "
                            f"left or right, got {h!r}"[:200], path)
    return hands


def select_hand(frames: list, choice, path: str) -> tuple[list[dict | None], str, list[int]]:
    """The tracked hand of each frame (None where absent), its type and its Leap ids.

    ``choice``: None picks the hand type present in most frames (ties: the one
    seen first in the file -- frame order, then the order of the frame's ``hands``
    list -- never set or hash order, so the pick is the same from run to run); ``"left"``/``"right"`` that type; an int that Leap hand id.  In
    a frame with several hands of the chosen type, the one whose id is seen in
    most frames wins.
    """
    per_frame = [_hands_of(f, i, path) for i, f in enumerate(frames)]
    type_frames: Counter = Counter()
    id_frames: Counter = Counter()
    for hands in per_frame:
        # dict.fromkeys, not a set: keys keep the file's order, and Counter.most_common
        # breaks ties by that insertion order (a set's order changes with PYTHONHASHSEED)
        type_frames.update(dict.fromkeys(h["type"] for h in hands).keys())
        id_frames.update(dict.fromkeys(h["id"] for h in hands).keys())
    if not type_frames:
        raise DataError(f"no hands in any of the recording's {len(frames)} frames", path)
    seen = ", ".join(f"{t} in {n} frame(s)" for t, n in type_frames.items())
    if isinstance(choice, int):
        picked = [next((h for h in hands if h["id"] == choice), None) for hands in per_frame]
        if not any(picked):
            ids = ", ".join(str(k) for k in sorted(id_frames))
            raise DataError(f"no hand with id {choice} in the recording (hand ids: {ids})", path)
        types = Counter(h["type"] for h in picked if h is not None)
        return picked, types.most_common(1)[0][0], [choice]
    side = choice if choice is not None else type_frames.most_common(1)[0][0]
    if side not in type_frames:
        raise DataError(f"no {side} hand in the recording (it has: {seen})", path)
    picked = []
    for hands in per_frame:
        mine = [h for h in hands if h["type"] == side]
        picked.append(max(mine, key=lambda h: id_frames[h["id"]]) if mine else None)
    ids = sorted({h["id"] for h in picked if h is not None})
    return picked, side, ids


def leap_keypoints(obj, path: str, hand=None) -> Keypoints:
    """One tracked hand of a parsed Leap recording as Keypoints on the 25 WebXR joints.

    Frames where the hand is absent, or present without any measured joint, are
    left out (``frames`` holds the recording's frame indices, 0-based, of the frames
    kept); a recording with no frame measuring a joint of the hand is a DataError.  Positions are
    metres in Leap's axes (right-handed, +Y up, +Z towards the user);
    ``positions`` is NaN and ``confidence`` 0 where Leap gives no joint.

    Args:
        obj: the parsed JSON (object with ``frames``, or a list of frames).
        path: the file name, for errors.
        hand: None, ``"left"``, ``"right"`` or an int hand id (see select_hand).
    """
    frames = _frames_of(obj, path)
    picked, side, ids = select_hand(frames, hand, path)
    keep = [i for i, h in enumerate(picked) if h is not None]
    positions = np.full((len(keep), N_JOINTS, 3), np.nan)
    confidence = np.zeros((len(keep), N_JOINTS))
    for row, i in enumerate(keep):
        frame, h = frames[i], picked[i]
        for key, j in HAND_JOINTS.items():
            if key in h:
                positions[row, j] = _vector(h[key], f"Leap frame {i}, hand {h['id']}: '{key}'",
                                            path)
                confidence[row, j] = 1.0
        pointables = frame.get("pointables", [])
        if not isinstance(pointables, list):
            raise DataError(f"Leap frame {i}: 'pointables' must be a list", path)
        seen: set[int] = set()
        for p in pointables:
            if not isinstance(p, dict):
                raise DataError(f"Leap frame {i}: a pointable is not a JSON object", path)
            if p.get("handId") != h["id"] or p.get("tool", False) is True:
                continue
            finger = p.get("type")
            if not is_int(finger) or finger not in POINTABLE_JOINTS:
                raise DataError(f"Leap frame {i}, hand {h['id']}: pointable 'type' must be a "
                                f"finger 0 (thumb) … 4 (pinky), got {finger!r}"[:200], path)
            if finger in seen:
                raise DataError(f"Leap frame {i}, hand {h['id']}: two {FINGER_NAMES[finger]} "
                                "pointables", path)
            seen.add(finger)
            for key, j in POINTABLE_JOINTS[finger].items():
                if key in p:
                    positions[row, j] = _vector(
                        p[key], f"Leap frame {i}, {FINGER_NAMES[finger]} '{key}'", path)
                    confidence[row, j] = 1.0
    # A frame whose hand measures no joint (no pointables of it, only tools, no position
    # fields) tells nothing about the hand: it is a missing frame, as one without the hand.
    measured = confidence.any(axis=1)
    if not measured.any():
        raise DataError(f"no frame of the recording measures any joint of the {side} hand "
                        f"(id {', '.join(map(str, ids))}): it is in {len(keep)} of "
                        f"{len(frames)} frame(s), but with no joint position (no pointables "
                        f"of it, only tools, or no position fields)", path)
    keep = [i for i, ok in zip(keep, measured) if ok]
    positions, confidence = positions[measured] * MM_TO_M, confidence[measured]
    source = {"format": FORMAT, "hand": side, "hand_ids": ids, "recorded_frames": len(frames),
              "frames_without_hand": len(frames) - len(keep),
              "never_observed_joints": [JOINT_NAMES[j] for j in range(N_JOINTS)
                                        if not confidence[:, j].any()]}
    return Keypoints(positions, confidence, np.asarray(keep, np.int64), list(JOINT_NAMES),
                     side=side, source=source)
