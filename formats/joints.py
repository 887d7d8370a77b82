"""The hand joints the formats share: the 25 WebXR joint names and :class:`Keypoints`.

``JOINT_NAMES`` is the WebXR/OpenXR hand skeleton's joint order (wrist, thumb
metacarpal … tip, then index … pinky, metacarpal … tip), the order of every joint
axis in keypoints, Leap recordings and the procedural hand
(``relight_cli.hand.model`` re-exports it).  :class:`Keypoints` is what the
keypoint readers return (``keypoints.py``, ``leap.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FINGERS = ("index", "middle", "ring", "pinky")

JOINT_NAMES: tuple[str, ...] = (
    "wrist",
    "thumb-metacarpal", "thumb-phalanx-proximal", "thumb-phalanx-distal", "thumb-tip",
    *[f"{f}-finger-{b}" for f in FINGERS
      for b in ("metacarpal", "phalanx-proximal", "phalanx-intermediate", "phalanx-distal", "tip")],
)
N_JOINTS = 25


@dataclass
class Keypoints:
    """Attributes:
        positions: [N, J, 3] float64 metres, world.
        confidence: [N, J] float64 in [0, 1]; 0 marks a missing joint.
        frames: [N] int64 frame numbers (strictly increasing; default 0..N−1).
        joint_names: J names if the file gave them, else None.
        side: "left"/"right" when the file says which hand it tracks (Leap), else None.
        source: what the reader found, for the fit report (e.g. the Leap hand), else None.
    """

    positions: np.ndarray
    confidence: np.ndarray
    frames: np.ndarray
    joint_names: list[str] | None = None
    side: str | None = None
    source: dict | None = None
