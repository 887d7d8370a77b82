"""3D hand keypoints: JSON or ``.npy`` (spec: ``formats/keypoints.md``).

Keypoints are per-frame 3D joint positions (metres, world) in the template's
joint order (25 WebXR joints), with an optional confidence per joint
(0 = missing).  NaN or Inf anywhere is an error, never a missing joint.
"""

from __future__ import annotations

import json
import os

import numpy as np

from relight_cli.errors import DataError

from .joints import Keypoints   # defined there, shared with leap.py

FORMAT = "relight/keypoints"
VERSION = 1


def keypoints_from_array(a, path: str, n_joints: int = 25, frames=None,
                         joint_names=None) -> Keypoints:
    """Validate an (N, J, 3) or (N, J, 4) array (4th column = confidence)."""
    a = np.asarray(a)
    if a.dtype.kind not in "fiu":
        raise DataError(f"keypoints must be numbers, got dtype {a.dtype}", path)
    a = a.astype(np.float64)
    if a.ndim == 2 and a.shape[-1] in (3, 4):
        a = a[None]
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise DataError(f"keypoints must have shape (N, {n_joints}, 3) or (N, {n_joints}, 4), "
                        f"got {a.shape}", path)
    if a.shape[0] == 0:
        raise DataError("keypoints hold no frames", path)
    if a.shape[1] != n_joints:
        raise DataError(f"keypoints have {a.shape[1]} joints per frame; the template has "
                        f"{n_joints}", path)
    bad = ~np.isfinite(a)
    if bad.any():
        n, j, _ = np.argwhere(bad)[0]
        raise DataError(f"keypoints hold NaN/Inf (first at frame {n}, joint {j}); mark a "
                        "missing joint with confidence 0 instead", path)
    conf = a[..., 3] if a.shape[2] == 4 else np.ones(a.shape[:2])
    if conf.min() < 0 or conf.max() > 1:
        raise DataError("keypoint confidences must lie in [0, 1]", path)
    if not (conf > 0).any():
        raise DataError("no frame measures any joint (every confidence is 0): nothing to fit",
                        path)
    if frames is None:
        frames = np.arange(a.shape[0])
    frames = np.asarray(frames)
    if frames.dtype.kind not in "iu" or frames.shape != (a.shape[0],):
        raise DataError(f"'frames' must be {a.shape[0]} integers", path)
    if len(frames) > 1 and np.any(np.diff(frames) <= 0):
        raise DataError("'frames' must be strictly increasing", path)
    if joint_names is not None and len(joint_names) != n_joints:
        raise DataError(f"'joint_names' lists {len(joint_names)} joints, expected {n_joints}", path)
    return Keypoints(a[..., :3].copy(), conf.copy(), frames.astype(np.int64),
                     None if joint_names is None else [str(s) for s in joint_names])


READERS = ("auto", "keypoints", "leap")


def read_keypoints(path: str, n_joints: int = 25, reader: str = "auto", hand=None) -> Keypoints:
    """Read keypoints from ``.npy`` or ``.json``; DataError names the file and the problem.

    Args:
        reader: ``"keypoints"`` (this format), ``"leap"`` (a Leap Motion recording,
            ``formats/leap.md``) or ``"auto"``: Leap when the JSON holds Leap frames.
        hand: which Leap hand (None, ``"left"``, ``"right"`` or an int id), or which hand
            of a two-hand file's ``hands`` list (None: its only hand; ``"left"``/``"right"``).
    """
    if not os.path.exists(path):
        raise DataError("no such file", path)
    if os.path.isdir(path):
        raise DataError("is a directory, expected keypoints (.json or .npy)", path)
    if path.lower().endswith(".npy"):
        if reader == "leap":
            raise DataError("a .npy array is not a Leap Motion recording (LeapJS JSON)", path)
        try:
            a = np.load(path, allow_pickle=False, mmap_mode="r")     # the header first:
            if a.nbytes > os.path.getsize(path):                   # a declared shape that
                raise ValueError(f"its header declares {a.shape} ({a.nbytes} bytes), more "
                                 f"than the file holds")            # the file cannot hold
            a = np.array(a)
        except (ValueError, OSError, EOFError, MemoryError) as exc:
            raise DataError(f"not a readable .npy array: {exc}", path) from None
        return keypoints_from_array(a, path, n_joints)
    from ._common import read_json
    from .leap import leap_keypoints, looks_like_leap
    obj = read_json(path)
    if reader != "keypoints" and looks_like_leap(obj):
        if n_joints != 25:
            raise DataError(f"Leap recordings map onto the 25 WebXR joints; the template has "
                            f"{n_joints}", path)
        return leap_keypoints(obj, path, hand)
    if reader == "leap":
        raise DataError("not a Leap Motion recording (expected LeapJS frames with 'hands' and "
                        "'pointables')", path)
    return _keypoints_from_json(obj, path, n_joints, hand)


def _keypoints_from_json(obj, path: str, n_joints: int, hand=None) -> Keypoints:
    frames = names = None
    if isinstance(obj, dict):
        if "format" in obj and obj["format"] != FORMAT:
            raise DataError(f"not a {FORMAT} file (format is {obj['format']!r})", path)
        if "version" in obj and (obj["version"] != VERSION or isinstance(obj["version"], bool)):
            raise DataError(f"unsupported {FORMAT} version {obj['version']!r} (this tool reads "
                            f"version {VERSION})", path)
        if "hands" in obj:
            return _hand_of(obj, path, n_joints, hand)
        if "keypoints" not in obj:
            raise DataError("JSON object lacks 'keypoints' (or a 'hands' list)", path)
        frames, names = obj.get("frames"), obj.get("joint_names")
        obj = obj["keypoints"]
    return _keypoints_of(obj, frames, names, path, n_joints, "'keypoints'")


def _keypoints_of(array, frames, names, path: str, n_joints: int, what: str) -> Keypoints:
    from ._common import number_array
    a = number_array(array, f"{what} (a regular N × J × 3 or 4 array)", path)
    if frames is not None:
        try:
            frames = np.array(frames)
        except (TypeError, ValueError):
            raise DataError("'frames' must be a list of integers", path) from None
    return keypoints_from_array(a, path, n_joints, frames, names)


SIDES = ("right", "left")


def _hand_entries(obj, path: str) -> list[dict]:
    """The checked ``hands`` list of a two-hand file: 1 or 2 objects with distinct
    ``side`` right/left and ``keypoints``; a top-level ``keypoints`` is refused."""
    hands = obj["hands"]
    if "keypoints" in obj or "frames" in obj:
        raise DataError("give either 'hands' or top-level 'keypoints'/'frames', not both", path)
    if not isinstance(hands, list) or not 1 <= len(hands) <= 2:
        raise DataError("'hands' must be a list of one or two hands", path)
    sides = []
    for i, h in enumerate(hands):
        if not isinstance(h, dict) or h.get("side") not in SIDES or "keypoints" not in h:
            raise DataError(f"hands[{i}] must be an object with 'side' (right or left) and "
                            f"'keypoints'", path)
        if h["side"] in sides:
            raise DataError(f"two {h['side']} hands in 'hands'", path)
        sides.append(h["side"])
    return hands


def _hand_of(obj, path: str, n_joints: int, hand) -> Keypoints:
    """One hand of a ``hands`` file: ``hand`` right/left, or the only one (None)."""
    hands = _hand_entries(obj, path)
    sides = [h["side"] for h in hands]
    if hand is None:
        if len(hands) > 1:
            raise DataError(f"the file holds a {sides[0]} and a {sides[1]} hand: fit one "
                            "with --hand right|left, or both with --hand both", path)
        hand = sides[0]
    if hand not in sides:
        what = "a Leap hand id" if isinstance(hand, int) else f"no {hand} hand"
        raise DataError(f"{what} in a {FORMAT} file (its 'hands': {', '.join(sides)})", path)
    i = sides.index(hand)
    kp = _keypoints_of(hands[i]["keypoints"], hands[i].get("frames"), obj.get("joint_names"),
                       path, n_joints, f"hands[{i}].keypoints")
    kp.side = hand
    kp.source = {"format": FORMAT, "hand": hand, "rows": int(len(kp.frames))}
    return kp


def keypoint_sides(path: str) -> list[str] | None:
    """The sides a ``relight/keypoints`` JSON with a ``hands`` list holds (file order);
    None for any other file (one unnamed hand, ``.npy``, a Leap recording) or one that
    does not read (its reader says why)."""
    if path.lower().endswith(".npy") or not os.path.isfile(path):
        return None
    from ._common import read_json
    try:
        obj = read_json(path)
    except DataError:
        return None
    if not isinstance(obj, dict) or "hands" not in obj or obj.get("format", FORMAT) != FORMAT:
        return None
    try:
        return [h["side"] for h in _hand_entries(obj, path)]
    except DataError:
        return None


def write_keypoints(path: str, kp: Keypoints, provenance: dict | None = None) -> None:
    """Write keypoints as JSON (N × J × 4 with confidences), atomically.

    Missing joints (confidence 0) are written as 0, 0, 0 with confidence 0 —
    the format's only missing marker (JSON has no NaN) — whatever their
    coordinates were (a Leap reader leaves them NaN).
    """
    from relight_cli.fileio import write_text_atomic

    missing = kp.confidence <= 0
    positions = np.where(missing[..., None], 0.0, kp.positions)
    if not np.isfinite(positions).all():
        raise ValueError("observed keypoints (confidence > 0) must be finite")
    data = np.concatenate([positions, kp.confidence[..., None]], -1)
    obj = {"format": FORMAT, "version": VERSION, "frames": [int(f) for f in kp.frames],
           "keypoints": data.tolist()}
    if kp.joint_names is not None:
        obj["joint_names"] = list(kp.joint_names)
    if provenance:
        obj["provenance"] = provenance
    write_text_atomic(path, json.dumps(obj) + "\n")
