"""Forward kinematics and linear blend skinning (MANO/SMPL convention).

With local axis-angle rotations θ_j (in the rest frame, whose joint
orientations are the identity), rest joints J_j and parents p(j):

    G_0 = [R(θ_0) | J_0]
    G_j = G_p(j) · [R(θ_j) | J_j − J_p(j)]
    posed joint j   = translation(G_j) + t
    skinned vertex  = Σ_j w_j · G_j · [v − J_j; 1] + t

Three implementations: :func:`lbs` (numpy, vectorized, the fast path),
:func:`lbs_torch` (differentiable, batched over frames) and
:func:`lbs_reference` (a per-vertex loop over explicit 4×4 matrices built
with scipy's rotations; the slow twin for tests).
"""

from __future__ import annotations

import numpy as np


def rodrigues(rotvec: np.ndarray) -> np.ndarray:
    """Axis-angle [..., 3] (radians) → rotation matrices [..., 3, 3] (float64).

    Uses the series of sin θ/θ and (1 − cos θ)/θ² near θ = 0 so the rest pose is exact.
    """
    r = np.asarray(rotvec, np.float64)
    theta2 = np.sum(r * r, axis=-1)[..., None, None]                    # [..., 1, 1]
    theta = np.sqrt(theta2)
    small = theta2 < 1e-12
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)         # sin θ / θ
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    zero = np.zeros_like(x)
    K = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(r.shape[:-1] + (3, 3))
    return np.eye(3) + a * K + b * (K @ K)


def forward_kinematics(poses: np.ndarray, rest_joints: np.ndarray, parents) -> np.ndarray:
    """World transforms G_j of every joint.

    Args:
        poses: [..., J, 3] axis-angle, radians.
        rest_joints: [J, 3] metres.
        parents: [J] parent indices (−1 root), each parent before its child.
    Returns:
        [..., J, 4, 4] float64 transforms (without the global translation t).
    """
    poses = np.asarray(poses, np.float64)
    rest = np.asarray(rest_joints, np.float64)
    R = rodrigues(poses)                                                 # [..., J, 3, 3]
    J = rest.shape[0]
    G = np.zeros(poses.shape[:-1] + (4, 4))
    G[..., 3, 3] = 1.0
    for j in range(J):
        p = parents[j]
        offset = rest[j] if p < 0 else rest[j] - rest[p]
        if p < 0:
            G[..., j, :3, :3] = R[..., j, :, :]
            G[..., j, :3, 3] = offset
        else:
            Gp = G[..., p, :, :]
            G[..., j, :3, :3] = Gp[..., :3, :3] @ R[..., j, :, :]
            G[..., j, :3, 3] = (Gp[..., :3, :3] @ offset) + Gp[..., :3, 3]
    return G


def posed_joints(poses, translations, rest_joints, parents) -> np.ndarray:
    """[..., J, 3] posed joint positions (metres): translation(G_j) + t."""
    G = forward_kinematics(poses, rest_joints, parents)
    return G[..., :3, 3] + np.asarray(translations, np.float64)[..., None, :]


def skinning_matrices(poses, rest_joints, parents) -> np.ndarray:
    """[..., J, 3, 4] A_j = G_j · [I | −J_j]: maps a rest vertex to its pose under joint j."""
    G = forward_kinematics(poses, rest_joints, parents)
    rest = np.asarray(rest_joints, np.float64)
    A = G[..., :3, :].copy()
    A[..., :3, 3] -= np.einsum("...jab,jb->...ja", G[..., :3, :3], rest)
    return A


def lbs(vertices, weights, rest_joints, parents, poses, translations=None) -> np.ndarray:
    """Linear blend skinning, vectorized (the fast path).

    Args:
        vertices: [V, 3] rest vertices, metres.
        weights: [V, J] skinning weights (rows sum to 1).
        rest_joints: [J, 3]; parents: [J].
        poses: [J, 3] or [N, J, 3] axis-angle; translations: [3] or [N, 3] (None = 0).
    Returns:
        [V, 3] or [N, V, 3] float64 posed vertices, metres.
    """
    poses = np.asarray(poses, np.float64)
    single = poses.ndim == 2
    if single:
        poses = poses[None]
    N, J = poses.shape[:2]
    t = np.zeros((N, 3)) if translations is None else np.asarray(translations, np.float64).reshape(N, 3)
    A = skinning_matrices(poses, rest_joints, parents).reshape(N, J, 12)  # [N, J, 12]
    W = np.asarray(weights, np.float64)
    v = np.asarray(vertices, np.float64)
    blended = np.matmul(W[None], A).reshape(N, -1, 3, 4)                # [N, V, 3, 4]
    # Σ_b M_ab·v_b + M_a3 as broadcast multiply-adds: faster than a batched einsum.
    out = (blended[..., :3] * v[None, :, None, :]).sum(-1) + blended[..., 3] + t[:, None, :]
    return out[0] if single else out


def lbs_reference(vertices, weights, rest_joints, parents, poses, translations=None) -> np.ndarray:
    """Slow twin of :func:`lbs` for one frame: explicit 4×4 chain, one vertex at a time.

    Rotations come from scipy (independent of :func:`rodrigues`).  Tests only.
    """
    from scipy.spatial.transform import Rotation

    poses = np.asarray(poses, np.float64)
    rest = np.asarray(rest_joints, np.float64)
    t = np.zeros(3) if translations is None else np.asarray(translations, np.float64)
    J = len(rest)
    world = []
    for j in range(J):
        local = np.eye(4)
        local[:3, :3] = Rotation.from_rotvec(poses[j]).as_matrix()
        local[:3, 3] = rest[j] if parents[j] < 0 else rest[j] - rest[parents[j]]
        world.append(local if parents[j] < 0 else world[parents[j]] @ local)
    out = np.zeros((len(vertices), 3))
    for i, v in enumerate(np.asarray(vertices, np.float64)):
        acc = np.zeros(3)
        for j in range(J):
            w = weights[i][j]
            if w == 0:
                continue
            acc += w * (world[j] @ np.append(v - rest[j], 1.0))[:3]
        out[i] = acc + t
    return out


# ----------------------------------------------------------------------------- torch

def rodrigues_torch(rotvec):
    """Axis-angle [..., 3] → [..., 3, 3], differentiable at θ = 0 (series branch)."""
    import torch

    theta2 = (rotvec * rotvec).sum(-1, keepdim=True)[..., None]         # [..., 1, 1]
    small = theta2 < 1e-8
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    x, y, z = rotvec.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(rotvec.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return eye + a * K + b * (K @ K)


def joint_levels(parents) -> list[np.ndarray]:
    """Joints grouped by depth in the tree (root first), so FK runs one batch per level."""
    parents = np.asarray(parents)
    depth = np.zeros(len(parents), np.int64)
    for j in range(1, len(parents)):
        depth[j] = depth[parents[j]] + 1
    return [np.nonzero(depth == d)[0] for d in range(depth.max() + 1)]


def forward_kinematics_torch(poses, rest_joints, parents):
    """Torch twin of :func:`forward_kinematics`, one batched step per tree level.

    Args:
        poses: [N, J, 3]; rest_joints: [J, 3] or [N, J, 3] tensors (may require grad).
    Returns:
        (rotations [N, J, 3, 3], joint positions [N, J, 3]) without translation t.
    """
    import torch

    R = rodrigues_torch(poses)
    N, J = poses.shape[:2]
    rest = rest_joints.expand(N, J, 3) if rest_joints.dim() == 2 else rest_joints
    parents = np.asarray(parents)
    levels = joint_levels(parents)
    rot_parts, pos_parts = [R[:, levels[0]]], [rest[:, levels[0]]]
    rot_of = {int(j): (0, k) for k, j in enumerate(levels[0])}
    for li, level in enumerate(levels[1:], start=1):
        par = parents[level]
        # Gather parents' global transforms from the level tensors they live in.
        pr = torch.stack([rot_parts[rot_of[int(p)][0]][:, rot_of[int(p)][1]] for p in par], 1)
        pp = torch.stack([pos_parts[rot_of[int(p)][0]][:, rot_of[int(p)][1]] for p in par], 1)
        offset = rest[:, level] - rest[:, par]                           # [N, L, 3]
        rot_parts.append(pr @ R[:, level])
        pos_parts.append(pp + (pr @ offset[..., None])[..., 0])
        for k, j in enumerate(level):
            rot_of[int(j)] = (li, k)
    order = np.concatenate(levels)
    inverse = np.argsort(order)
    rots = torch.cat(rot_parts, 1)[:, inverse]
    pos = torch.cat(pos_parts, 1)[:, inverse]
    return rots, pos


def lbs_torch(vertices, weights, rest_joints, parents, poses, translations=None):
    """Differentiable LBS batched over frames.

    Args:
        vertices: [V, 3] or [N, V, 3] rest vertices; weights: [V, J];
        rest_joints: [J, 3] or [N, J, 3]; poses: [N, J, 3]; translations: [N, 3] or None.
    Returns:
        (posed vertices [N, V, 3], posed joints [N, J, 3]).
    """
    rots, pos = forward_kinematics_torch(poses, rest_joints, parents)   # [N,J,3,3], [N,J,3]
    N, J = poses.shape[:2]
    rest = rest_joints.expand(N, J, 3) if rest_joints.dim() == 2 else rest_joints
    trans = pos - (rots @ rest[..., None])[..., 0]                       # [N, J, 3]
    A = torch_cat_affine(rots, trans).reshape(N, J, 12)
    blended = (weights @ A).reshape(N, -1, 3, 4)                        # [N, V, 3, 4]
    v = vertices if vertices.dim() == 3 else vertices.expand(N, *vertices.shape)
    out = (blended[..., :3] @ v[..., None])[..., 0] + blended[..., 3]
    if translations is not None:
        out = out + translations[:, None, :]
        pos = pos + translations[:, None, :]
    return out, pos


def torch_cat_affine(rots, trans):
    import torch
    return torch.cat([rots, trans[..., None]], dim=-1)                   # [..., 3, 4]


# ----------------------------------------------------------------------------- geometry

def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[V, 3] unit area-weighted vertex normals; never NaN.

    A vertex whose adjacent faces cancel (or that has none) gets the direction
    from the mesh centroid, and (0, 0, 1) if that is zero too.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])      # [F, 3], 2·area·n
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    length = np.linalg.norm(n, axis=1)
    bad = ~(length > 1e-20)
    if bad.any():
        fallback = v[bad] - v.mean(0)
        fl = np.linalg.norm(fallback, axis=1)
        fallback = np.where(fl[:, None] > 1e-20, fallback, [0.0, 0.0, 1.0])
        n[bad] = fallback
        length = np.linalg.norm(n, axis=1)
    return n / length[:, None]


def mirror_pose(poses: np.ndarray) -> np.ndarray:
    """Axis-angle poses [..., J, 3] of the mirror image across x = 0: (x, y, z) → (x, −y, −z).

    With M = diag(−1, 1, 1), the mirrored rotation is M R M, whose axis-angle is
    −M r (rotation axes are pseudo-vectors).
    """
    p = np.array(poses, np.float64, copy=True)
    p[..., 1:] *= -1.0
    return p
