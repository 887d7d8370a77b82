"""2D hand keypoints per image, from any detector (spec: ``formats/keypoints2d.md``).

What ``relight personalize`` fits a hand to: per view (one image, one camera) the
pixel position and confidence of each joint, in one of two skeletons — the 25 WebXR
joints relight's hands use, or the 21 joints of MediaPipe / OpenPose hand detectors,
mapped onto the WebXR ones (the four finger metacarpal joints, which those detectors
do not give, become missing).  Views sharing a ``pose`` id share one hand pose (a
hand held still while the phone moves); NaN or Inf is an error, never a missing joint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relight_cli.errors import DataError

from .joints import N_JOINTS

FORMAT = "relight/keypoints-2d"
VERSION = 1

#: Each MediaPipe / OpenPose hand joint (index) → the WebXR joint at the same place
#: (formats/joints.py): wrist; thumb CMC, MCP, IP, tip → thumb metacarpal … tip; for
#: each finger f = 1…4 its MCP, PIP, DIP, tip → WebXR 5f+1 … 5f+4 (phalanx-proximal
#: … tip).  WebXR's finger metacarpal joints (5f, at the wrist end of the metacarpal
#: bone) have no detector counterpart.
MEDIAPIPE_TO_WEBXR = np.array([0, 1, 2, 3, 4] + [5 * f + b for f in range(1, 5)
                                                 for b in range(1, 5)], np.int64)
SKELETONS = {"webxr-25": 25, "mediapipe-21": 21}
MAX_VIEWS = 10_000


@dataclass
class Keypoints2D:
    """Attributes:
        images: [V] the image file name each view names (matched to the images given).
        uv: [V, 25, 2] float64 pixel positions (camera.md: pixel centres at integers).
        confidence: [V, 25] float64 in [0, 1]; 0 marks a missing joint.
        pose: [V] int64 pose group of each view (views of one group share a pose).
        skeleton: the file's skeleton (``webxr-25`` or ``mediapipe-21``).
        side: ``left``/``right`` when the file says which hand, else None.
    """

    images: list
    uv: np.ndarray
    confidence: np.ndarray
    pose: np.ndarray
    skeleton: str
    side: str | None = None


def read_keypoints2d(path: str) -> Keypoints2D:
    """Read and validate a ``relight/keypoints-2d`` JSON file (DataError naming it)."""
    from ._common import read_json
    return keypoints2d_from_json(read_json(path), path)


def keypoints2d_from_json(obj, path: str = "") -> Keypoints2D:
    from ._common import check_format_version, is_int, number_array
    if not isinstance(obj, dict):
        raise DataError(f"expected a {FORMAT} JSON object with 'views'", path)
    check_format_version(obj.get("format"), obj.get("version"), FORMAT, VERSION, path)
    skeleton = obj.get("skeleton", "webxr-25")
    if skeleton not in SKELETONS:
        raise DataError(f"unknown skeleton {skeleton!r}; use {' or '.join(SKELETONS)}", path)
    side = obj.get("hand")
    if side is not None and side not in ("left", "right"):
        raise DataError(f"'hand' must be 'left' or 'right', got {side!r}", path)
    views = obj.get("views")
    if not isinstance(views, list) or not views:
        raise DataError("'views' must be a non-empty list", path)
    if len(views) > MAX_VIEWS:
        raise DataError(f"{len(views)} views; at most {MAX_VIEWS}", path)
    n = SKELETONS[skeleton]
    images, uv, conf, pose = [], [], [], []
    for i, view in enumerate(views):
        where = f"view {i}"
        if not isinstance(view, dict) or "image" not in view or "keypoints" not in view:
            raise DataError(f"{where}: expected an object with 'image' and 'keypoints'", path)
        if not isinstance(view["image"], str) or not view["image"]:
            raise DataError(f"{where}: 'image' must be a file name", path)
        a = number_array(view["keypoints"], f"{where}: 'keypoints'", path)
        if a.ndim != 2 or a.shape[1] not in (2, 3):
            raise DataError(f"{where}: 'keypoints' must be {n} rows of [u, v] or "
                            f"[u, v, confidence], got shape {a.shape}", path)
        if a.shape[0] != n:
            raise DataError(f"{where}: {a.shape[0]} keypoints; the {skeleton} skeleton has {n}",
                            path)
        if not np.isfinite(a).all():
            j = int(np.argwhere(~np.isfinite(a))[0][0])
            raise DataError(f"{where}: keypoint {j} is NaN/Inf; mark a missing joint with "
                            f"confidence 0 instead", path)
        c = a[:, 2] if a.shape[1] == 3 else np.ones(n)
        if c.min() < 0 or c.max() > 1:
            raise DataError(f"{where}: confidences must lie in [0, 1]", path)
        if np.abs(a[:, :2]).max() > 1e7:
            raise DataError(f"{where}: keypoint coordinates beyond ±1e7 pixels", path)
        group = view.get("pose", 0)
        if not is_int(group) or not 0 <= group < MAX_VIEWS:
            raise DataError(f"{where}: 'pose' must be an integer in [0, {MAX_VIEWS})", path)
        full_uv = np.zeros((N_JOINTS, 2))
        full_c = np.zeros(N_JOINTS)
        index = MEDIAPIPE_TO_WEBXR if skeleton == "mediapipe-21" else np.arange(N_JOINTS)
        full_uv[index] = a[:, :2]
        full_c[index] = c
        images.append(view["image"])
        uv.append(full_uv)
        conf.append(full_c)
        pose.append(int(group))
    if len(set(images)) != len(images):
        raise DataError("two views name the same image", path)
    conf = np.asarray(conf)
    if not (conf > 0).any():
        raise DataError("no view measures any joint (every confidence is 0): nothing to fit",
                        path)
    return Keypoints2D(images, np.asarray(uv), conf, np.asarray(pose, np.int64), skeleton, side)


def dumps_keypoints2d(kp: Keypoints2D, provenance: dict | None = None) -> str:
    """The JSON text of ``kp`` in its skeleton (``mediapipe-21``: the 21 detector joints)."""
    import json
    rows = []
    index = MEDIAPIPE_TO_WEBXR if kp.skeleton == "mediapipe-21" else np.arange(N_JOINTS)
    for i, name in enumerate(kp.images):
        points = [[float(u), float(v), float(c)]
                  for (u, v), c in zip(kp.uv[i][index], kp.confidence[i][index])]
        rows.append({"image": name, "pose": int(kp.pose[i]), "keypoints": points})
    obj = {"format": FORMAT, "version": VERSION, "skeleton": kp.skeleton}
    if kp.side is not None:
        obj["hand"] = kp.side
    head = ",\n".join(f"  {json.dumps(k)}: {json.dumps(v)}" for k, v in obj.items())
    blocks = []
    for row in rows:
        points = ",\n".join("      " + json.dumps(p, allow_nan=False) for p in row["keypoints"])
        blocks.append(f'    {{"image": {json.dumps(row["image"])}, "pose": {row["pose"]}, '
                      f'"keypoints": [\n{points}]}}')
    text = "{\n" + head + ',\n  "views": [\n' + ",\n".join(blocks) + "\n  ]"
    if provenance is not None:
        prov = json.dumps(provenance, indent=2, sort_keys=True, allow_nan=False)
        text += ',\n  "provenance": ' + prov.replace("\n", "\n  ")
    return text + "\n}\n"


def write_keypoints2d(path: str, kp: Keypoints2D, provenance: dict | None = None) -> None:
    from relight_cli.fileio import write_text_atomic
    write_text_atomic(path, dumps_keypoints2d(kp, provenance))
