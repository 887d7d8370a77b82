"""Named hand poses, joint limits, seeded random poses and slerp interpolation.

Poses are written as anatomical angles per joint — (flexion, abduction,
twist) in radians about each joint's rest-frame axes — and converted to the
axis-angle vectors θ_j that skinning uses.  The axes come from the rest
skeleton, so the same angles pose the procedural hand, a glTF template or the
left hand (mirror image) alike:

    twist axis   s · d           d: rest bone direction (joint → child)
    abduction    s · n⊥          n: palm normal (thumb: its own palmar direction), ⊥ to d
    flexion      d × n⊥          positive flexion curls the bone towards the palm
    s = +1 for a right hand, −1 for a left hand (axes are pseudo-vectors)

R_j = R(abduction) · R(flexion) · R(twist), θ_j = log(R_j).  Joint 0 (wrist)
is the global rotation; its angles are not limited.
"""

from __future__ import annotations

import functools

import numpy as np

from .skeleton import FINGERS, JOINT_NAMES, N_JOINTS, PARENTS, rest_skeleton, unit

POSE_NAMES = ("open", "relaxed", "fist", "point", "pinch", "ok", "spread", "claw")

# (lo, hi) radians for (flexion, abduction, twist) per joint kind.
_LIMITS = {
    "thumb-metacarpal": ((-0.40, 0.90), (-0.50, 0.60), (-0.40, 0.40)),
    "thumb-phalanx-proximal": ((-0.20, 1.00), (-0.15, 0.15), (-0.15, 0.15)),
    "thumb-phalanx-distal": ((-0.30, 1.40), (-0.05, 0.05), (-0.05, 0.05)),
    "metacarpal": ((-0.05, 0.05), (-0.03, 0.03), (-0.03, 0.03)),
    "metacarpal-ring": ((-0.05, 0.20), (-0.05, 0.05), (-0.05, 0.05)),
    "metacarpal-pinky": ((-0.05, 0.30), (-0.08, 0.08), (-0.08, 0.08)),
    "phalanx-proximal": ((-0.35, 1.60), (-0.35, 0.35), (-0.15, 0.15)),
    "phalanx-intermediate": ((-0.05, 1.90), (-0.05, 0.05), (-0.05, 0.05)),
    "phalanx-distal": ((-0.10, 1.40), (-0.05, 0.05), (-0.05, 0.05)),
    "tip": ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0)),
}


def _limit_key(name: str) -> str:
    if name.startswith("thumb-") and not name.endswith("tip"):
        return name
    if name.endswith("metacarpal"):
        if name.startswith("ring"):
            return "metacarpal-ring"
        if name.startswith("pinky"):
            return "metacarpal-pinky"
        return "metacarpal"
    for key in ("phalanx-proximal", "phalanx-intermediate", "phalanx-distal", "tip"):
        if name.endswith(key):
            return key
    raise KeyError(name)


def joint_limits() -> np.ndarray:
    """[J, 3, 2] (lo, hi) of (flexion, abduction, twist), radians; the wrist gets ±π."""
    out = np.zeros((N_JOINTS, 3, 2))
    out[0] = [[-np.pi, np.pi]] * 3
    for j, name in enumerate(JOINT_NAMES[1:], start=1):
        out[j] = np.array(_LIMITS[_limit_key(name)])
    return out


def joint_axes(rest_joints: np.ndarray, side: str = "right", parents=PARENTS) -> np.ndarray:
    """[J, 3, 3] rows (flexion axis, abduction axis, twist axis) per joint in the rest frame.

    Needs the WebXR joint order (index/pinky MCPs locate the palm).  Leaves
    (tips) reuse their parent's axes; the wrist uses the middle metacarpal's.
    """
    J = np.asarray(rest_joints, np.float64)
    s = 1.0 if side == "right" else -1.0
    wrist = J[0]
    index_mcp, pinky_mcp = J[6], J[21]
    n = s * unit(np.cross(index_mcp - wrist, pinky_mcp - wrist))       # palm normal
    to_pinky = unit(pinky_mcp - index_mcp)
    n_thumb = unit(0.65 * n + 0.75 * to_pinky)
    children = {}
    for j in range(1, len(J)):
        children.setdefault(int(parents[j]), j)
    axes = np.zeros((len(J), 3, 3))
    for j in range(len(J)):
        child = children.get(j)
        if child is None:
            axes[j] = axes[int(parents[j])]
            continue
        if j == 0:
            child = 11  # wrist → middle MCP direction
            d = unit(J[child] - J[0])
        else:
            d = unit(J[child] - J[j])
        normal = n_thumb if JOINT_NAMES[j].startswith("thumb") else n
        n_perp = unit(normal - (normal @ d) * d)
        axes[j] = [np.cross(d, n_perp), s * n_perp, s * d]
    return axes


def pose_from_angles(angles: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Anatomical angles [..., J, 3] (flexion, abduction, twist) → axis-angle [..., J, 3]."""
    from scipy.spatial.transform import Rotation

    angles = np.asarray(angles, np.float64)
    shape = angles.shape
    a = angles.reshape(-1, shape[-2], 3)
    out = np.zeros_like(a)
    for j in range(shape[-2]):
        flex = Rotation.from_rotvec(a[:, j, 0:1] * axes[j, 0])
        abd = Rotation.from_rotvec(a[:, j, 1:2] * axes[j, 1])
        twist = Rotation.from_rotvec(a[:, j, 2:3] * axes[j, 2])
        out[:, j] = (abd * flex * twist).as_rotvec()
    return out.reshape(shape)


def angles_from_pose(poses: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Approximate inverse of :func:`pose_from_angles`: θ_j projected on the joint axes.

    Exact for a rotation about one axis; used for limits and priors.
    """
    return np.einsum("jab,...jb->...ja", axes, np.asarray(poses, np.float64))


def _angles_table(name: str) -> np.ndarray:
    """[J, 3] anatomical angles of a named pose (right hand)."""
    A = np.zeros((N_JOINTS, 3))
    idx = {n: j for j, n in enumerate(JOINT_NAMES)}

    def finger(f, mcp, pip, dip, abd=0.0, cmc=0.0):
        A[idx[f"{f}-finger-metacarpal"], 0] = cmc
        A[idx[f"{f}-finger-phalanx-proximal"]] = [mcp, abd, 0.0]
        A[idx[f"{f}-finger-phalanx-intermediate"], 0] = pip
        A[idx[f"{f}-finger-phalanx-distal"], 0] = dip

    def thumb(cmc_flex, cmc_abd, cmc_twist, mcp, ip):
        A[idx["thumb-metacarpal"]] = [cmc_flex, cmc_abd, cmc_twist]
        A[idx["thumb-phalanx-proximal"], 0] = mcp
        A[idx["thumb-phalanx-distal"], 0] = ip

    relaxed = {"index": (0.25, 0.35, 0.15), "middle": (0.30, 0.42, 0.18),
               "ring": (0.35, 0.48, 0.20), "pinky": (0.42, 0.52, 0.22)}
    fist = (1.50, 1.80, 0.85)
    if name == "open":
        pass
    elif name == "relaxed":
        for f, (m, p, d) in relaxed.items():
            finger(f, m, p, d)
        thumb(0.15, 0.0, 0.0, 0.15, 0.2)
    elif name == "fist":
        for f in FINGERS:
            finger(f, *fist, cmc={"ring": 0.12, "pinky": 0.22}.get(f, 0.0))
        # Solved so the thumb tip rests 14 mm from the middle finger's middle
        # phalanx and its IP joint 16 mm from the index's: wrapped over the fingers.
        thumb(-0.09, 0.39, -0.12, 0.80, 0.56)
    elif name == "point":
        finger("index", 0.0, 0.05, 0.0)
        for f in FINGERS[1:]:
            finger(f, *fist, cmc={"ring": 0.12, "pinky": 0.22}.get(f, 0.0))
        thumb(-0.09, 0.39, -0.12, 0.80, 0.56)  # as in "fist"
    elif name == "pinch":
        finger("index", 0.70, 0.80, 0.35)
        for f in FINGERS[1:]:
            finger(f, *relaxed[f])
        # Thumb angles solved so the thumb and index tip joints are 11 mm apart (pads touch).
        thumb(0.31, 0.14, 0.16, 0.12, 0.19)
    elif name == "ok":
        finger("index", 0.75, 0.95, 0.40)
        finger("middle", 0.10, 0.10, 0.05, abd=0.05)
        finger("ring", 0.12, 0.12, 0.05, abd=0.15)
        finger("pinky", 0.15, 0.12, 0.05, abd=0.28)
        thumb(0.35, 0.08, 0.17, 0.20, 0.26)  # solved like "pinch"
    elif name == "spread":
        finger("index", 0.0, 0.0, 0.0, abd=-0.28)
        finger("middle", 0.0, 0.0, 0.0, abd=-0.05)
        finger("ring", 0.0, 0.0, 0.0, abd=0.18)
        finger("pinky", 0.0, 0.0, 0.0, abd=0.34)
        thumb(-0.20, -0.45, 0.0, 0.0, 0.0)
    elif name == "claw":
        for f in FINGERS:
            finger(f, -0.15, 1.35, 1.00)
        thumb(0.30, -0.10, 0.10, 0.30, 0.90)
    else:
        raise KeyError(name)
    return A


@functools.lru_cache(maxsize=None)
def _named_right(name: str) -> np.ndarray:
    return pose_from_angles(_angles_table(name), joint_axes(rest_skeleton(), "right"))


def named_pose(name: str, side: str = "right", rest_joints: np.ndarray | None = None) -> np.ndarray:
    """[J, 3] axis-angle of a named pose (one of POSE_NAMES).

    Args:
        name: pose name.
        side: "right" or "left" (the left pose mirrors the right one).
        rest_joints: [J, 3] rest skeleton of a template (WebXR order); None = built-in hand.
    """
    if name not in POSE_NAMES:
        raise KeyError(f"unknown pose {name!r}; choose one of {', '.join(POSE_NAMES)}")
    if rest_joints is not None:
        return pose_from_angles(_angles_table(name), joint_axes(rest_joints, side))
    from .skinning import mirror_pose
    pose = _named_right(name).copy()
    return pose if side == "right" else mirror_pose(pose)


def random_poses(n: int, seed: int = 0, side: str = "right", rest_joints=None,
                 global_rotation: bool = False) -> np.ndarray:
    """[n, J, 3] plausible random poses within the joint limits (seeded).

    Each finger draws a curl in [0, 1] that couples its MCP, PIP and DIP
    flexion (DIP ≈ ⅔ PIP, as tendons couple them), plus independent jitter;
    abduction and twist are uniform in the inner 60% of their limits.
    ``global_rotation`` adds a uniformly random wrist rotation.
    """
    rng = np.random.default_rng(seed)
    rest = rest_skeleton() if rest_joints is None else np.asarray(rest_joints)
    if rest_joints is None and side == "left":
        rest = rest * [-1, 1, 1]
    axes = joint_axes(rest, side)
    lim = joint_limits()
    lo, hi = lim[..., 0], lim[..., 1]
    A = np.zeros((n, N_JOINTS, 3))
    idx = {nm: j for j, nm in enumerate(JOINT_NAMES)}
    for f in FINGERS:
        curl = rng.uniform(0, 1, n)
        for k, b in enumerate(("phalanx-proximal", "phalanx-intermediate", "phalanx-distal")):
            j = idx[f"{f}-finger-{b}"]
            c = np.clip(curl + rng.normal(0, 0.12, n), 0, 1)
            A[:, j, 0] = lo[j, 0] + c * (hi[j, 0] - lo[j, 0])
        j_pip, j_dip = idx[f"{f}-finger-phalanx-intermediate"], idx[f"{f}-finger-phalanx-distal"]
        A[:, j_dip, 0] = np.clip(0.67 * A[:, j_pip, 0] + rng.normal(0, 0.08, n), lo[j_dip, 0], hi[j_dip, 0])
        j_cmc = idx[f"{f}-finger-metacarpal"]
        A[:, j_cmc, 0] = lo[j_cmc, 0] + curl * (hi[j_cmc, 0] - lo[j_cmc, 0])
    for j in range(1, N_JOINTS):
        mid = 0.5 * (lo[j] + hi[j])
        half = 0.3 * (hi[j] - lo[j])
        A[:, j, 1] = mid[1] + rng.uniform(-1, 1, n) * half[1]
        A[:, j, 2] = mid[2] + rng.uniform(-1, 1, n) * half[2]
        if JOINT_NAMES[j].startswith("thumb") and not JOINT_NAMES[j].endswith("tip"):
            A[:, j, 0] = rng.uniform(lo[j, 0], hi[j, 0], n) * 0.8 + 0.1 * (lo[j, 0] + hi[j, 0])
    A[:, 0] = 0.0
    poses = pose_from_angles(A, axes)
    if global_rotation:
        from scipy.spatial.transform import Rotation
        poses[:, 0] = Rotation.random(n, random_state=rng.integers(2**31)).as_rotvec()
    return poses


# ----------------------------------------------------------------------------- slerp

def _to_quat(rotvec):
    """Axis-angle [..., 3] → unit quaternions [..., 4] (w, x, y, z)."""
    r = np.asarray(rotvec, np.float64)
    theta = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * theta
    k = np.where(theta > 1e-12, np.sin(half) / np.where(theta > 1e-12, theta, 1), 0.5 - theta**2 / 48)
    return np.concatenate([np.cos(half), k * r], -1)


def _to_rotvec(q):
    q = np.asarray(q, np.float64)
    q = np.where(q[..., :1] < 0, -q, q)                                 # w ≥ 0: angle ≤ π
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2 * np.arctan2(s, q[..., :1])
    k = np.where(s > 1e-12, angle / np.where(s > 1e-12, s, 1), 2.0)
    return k * v


def slerp(pose0: np.ndarray, pose1: np.ndarray, alpha) -> np.ndarray:
    """Per-joint quaternion slerp between axis-angle poses [..., J, 3] (shortest arc).

    ``alpha`` is a scalar or broadcastable array in [0, 1]; 0 gives pose0, 1 pose1.
    """
    q0, q1 = _to_quat(pose0), _to_quat(pose1)
    dot = np.sum(q0 * q1, -1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    alpha = np.asarray(alpha, np.float64)[..., None]
    omega = np.arccos(np.clip(dot, -1, 1))
    so = np.sin(omega)
    linear = so < 1e-9
    w0 = np.where(linear, 1 - alpha, np.sin((1 - alpha) * omega) / np.where(linear, 1, so))
    w1 = np.where(linear, alpha, np.sin(alpha * omega) / np.where(linear, 1, so))
    q = w0 * q0 + w1 * q1
    return _to_rotvec(q / np.linalg.norm(q, axis=-1, keepdims=True))


def interpolate_poses(key_frames, key_poses, key_translations, frames):
    """Fill frames between keyframes: slerp rotations, lerp translations.

    Args:
        key_frames: [K] increasing frame numbers; key_poses [K, J, 3]; key_translations [K, 3].
        frames: [N] frame numbers to produce (outside the key range: clamped to the ends).
    Returns:
        (poses [N, J, 3], translations [N, 3]).
    """
    kf = np.asarray(key_frames, np.float64)
    frames = np.asarray(frames, np.float64)
    kp = np.asarray(key_poses, np.float64)
    kt = np.asarray(key_translations, np.float64)
    hi = np.clip(np.searchsorted(kf, frames, side="right"), 1, len(kf) - 1) if len(kf) > 1 else None
    if hi is None:
        return np.repeat(kp, len(frames), 0), np.repeat(kt, len(frames), 0)
    lo = hi - 1
    alpha = np.clip((frames - kf[lo]) / (kf[hi] - kf[lo]), 0, 1)
    poses = slerp(kp[lo], kp[hi], alpha[:, None])
    trans = (1 - alpha[:, None]) * kt[lo] + alpha[:, None] * kt[hi]
    return poses, trans
