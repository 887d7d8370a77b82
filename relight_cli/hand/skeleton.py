"""The 25-joint WebXR/OpenXR hand skeleton and the procedural hand's proportions.

Joint names (``relight_cli.formats.joints``, the table every format shares), the
parent of each joint, the built-in right hand's bone layout (metres, model space,
+Y up, palm facing +Z) and its rest skeleton.  ``relight_cli.hand.model`` builds
the hand's surface on these and ``relight_cli.hand.poses`` its named poses; both
import them from here (model re-exports them), so neither imports the other's
module for them.
"""

from __future__ import annotations

import numpy as np

from relight_cli.formats.joints import FINGERS, JOINT_NAMES, N_JOINTS  # noqa: F401

PARENTS = np.array([-1, 0, 1, 2, 3, 0, 5, 6, 7, 8, 0, 10, 11, 12, 13,
                    0, 15, 16, 17, 18, 0, 20, 21, 22, 23], np.int64)

# Finger geometry (right hand): CMC (metacarpal joint), MCP, splay direction,
# phalanx lengths (proximal, intermediate, distal-to-tip), radii at MCP, PIP, DIP, tip.
FINGER_SPECS = {
    "index":  dict(cmc=(0.013, 0.022, 0.0), mcp=(0.025, 0.090, 0.0), dir=(0.09, 1.0, 0.0),
                   lengths=(0.040, 0.024, 0.020), radii=(0.0097, 0.0088, 0.0078, 0.0069)),
    "middle": dict(cmc=(0.003, 0.024, 0.0), mcp=(0.006, 0.095, 0.0), dir=(0.02, 1.0, 0.0),
                   lengths=(0.044, 0.027, 0.021), radii=(0.0099, 0.0090, 0.0080, 0.0071)),
    "ring":   dict(cmc=(-0.007, 0.023, 0.0), mcp=(-0.013, 0.090, 0.0), dir=(-0.06, 1.0, 0.0),
                   lengths=(0.041, 0.026, 0.020), radii=(0.0093, 0.0085, 0.0076, 0.0067)),
    "pinky":  dict(cmc=(-0.016, 0.020, 0.0), mcp=(-0.031, 0.079, 0.0), dir=(-0.16, 1.0, 0.0),
                   lengths=(0.032, 0.020, 0.018), radii=(0.0083, 0.0075, 0.0068, 0.0061)),
}
THUMB_CMC = np.array([0.019, 0.017, 0.006])
THUMB_META_DIR = np.array([0.52, 0.78, 0.34])
THUMB_PHAL_DIR = np.array([0.40, 0.87, 0.30])
THUMB_LENGTHS = (0.046, 0.034, 0.029)
THUMB_RADII = (0.0125, 0.0112, 0.0102, 0.0090)   # CMC (thenar), MCP, IP, tip


def unit(v):
    """``v`` scaled to unit length along its last axis."""
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def rest_skeleton() -> np.ndarray:
    """[25, 3] rest joint positions of the right hand, metres."""
    J = np.zeros((N_JOINTS, 3))
    d0, d1 = unit(THUMB_META_DIR), unit(THUMB_PHAL_DIR)
    J[1] = THUMB_CMC
    J[2] = J[1] + THUMB_LENGTHS[0] * d0
    J[3] = J[2] + THUMB_LENGTHS[1] * d1
    J[4] = J[3] + THUMB_LENGTHS[2] * d1
    for k, f in enumerate(FINGERS):
        spec = FINGER_SPECS[f]
        base = 5 + 5 * k
        d = unit(spec["dir"])
        J[base] = spec["cmc"]
        J[base + 1] = spec["mcp"]
        for i, length in enumerate(spec["lengths"]):
            J[base + 2 + i] = J[base + 1 + i] + length * d
    return J
