"""FK and LBS: vectorized numpy vs a per-vertex loop reference vs torch; normals; scenes."""

from __future__ import annotations

import numpy as np
import pytest

from relight_cli.hand import poses as P
from relight_cli.hand.model import PARENTS, builtin_hand
from relight_cli.hand.skinning import (forward_kinematics, lbs, lbs_reference, posed_joints,
                                       rodrigues, vertex_normals)


@pytest.fixture(scope="module")
def hand():
    return builtin_hand(pose=None)


def test_rest_pose_reproduces_rest_vertices_exactly(hand):
    m = hand.fine
    out = lbs(m.vertices, m.weights, hand.rest_joints, PARENTS, np.zeros((25, 3)))
    # Rotation = I exactly at θ = 0 (series branch), so only float64 round-off of
    # (v − J) + J remains: a few ulps of 0.2 m.
    assert np.abs(out - m.vertices).max() < 1e-15
    np.testing.assert_allclose(posed_joints(np.zeros((25, 3)), np.zeros(3), hand.rest_joints, PARENTS),
                               hand.rest_joints, atol=1e-16)


def test_rodrigues_matches_scipy_incl_tiny_and_pi():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    r = np.concatenate([rng.normal(size=(50, 3)), rng.normal(size=(5, 3)) * 1e-9,
                        [[np.pi, 0, 0], [0, 0, 0]]])
    np.testing.assert_allclose(rodrigues(r), Rotation.from_rotvec(r).as_matrix(), atol=1e-12)


def test_vectorized_lbs_matches_loop_reference(hand):
    rng = np.random.default_rng(2)
    m = hand.coarse
    pose = P.random_poses(1, seed=5, global_rotation=True)[0]
    t = rng.normal(size=3) * 0.1
    sel = rng.choice(len(m.vertices), 400, replace=False)
    fast = lbs(m.vertices, m.weights, hand.rest_joints, PARENTS, pose, t)[sel]
    slow = lbs_reference(m.vertices[sel], m.weights[sel], hand.rest_joints, PARENTS, pose, t)
    # Two float64 evaluations of the same sum: round-off ~1e-16 · 0.3 m · 25 terms.
    np.testing.assert_allclose(fast, slow, atol=1e-13)
    # Batched frames equal frame-by-frame.
    poses = P.random_poses(3, seed=9, global_rotation=True)
    batch = lbs(m.vertices, m.weights, hand.rest_joints, PARENTS, poses, np.zeros((3, 3)))
    for n in range(3):
        np.testing.assert_allclose(batch[n], lbs(m.vertices, m.weights, hand.rest_joints, PARENTS,
                                                 poses[n]), atol=1e-15)


def test_fk_matches_mano_formula_by_hand(hand):
    """G_j = G_parent · [R(θ_j) | J_j − J_parent], written out for one chain."""
    pose = P.named_pose("claw")
    G = forward_kinematics(pose, hand.rest_joints, PARENTS)
    J = hand.rest_joints
    R = rodrigues(pose)
    # wrist → index metacarpal → index proximal (joints 0, 5, 6)
    G0 = np.eye(4)
    G0[:3, :3], G0[:3, 3] = R[0], J[0]
    L5 = np.eye(4)
    L5[:3, :3], L5[:3, 3] = R[5], J[5] - J[0]
    L6 = np.eye(4)
    L6[:3, :3], L6[:3, 3] = R[6], J[6] - J[5]
    np.testing.assert_allclose(G[6], G0 @ L5 @ L6, atol=1e-15)


def test_torch_lbs_matches_numpy_and_has_gradients(hand):
    import torch

    from relight_cli.hand.skinning import lbs_torch

    m = hand.coarse
    poses = P.random_poses(2, seed=3, global_rotation=True)
    poses[1, 7] = 0.0                          # a zero rotation: series branch in torch too
    t = np.array([[0.01, 0.02, 0.03], [0.0, -0.1, 0.2]])
    ref = lbs(m.vertices, m.weights, hand.rest_joints, PARENTS, poses, t)
    tp = torch.tensor(poses, requires_grad=True)
    v, j = lbs_torch(torch.tensor(m.vertices), torch.tensor(m.weights),
                     torch.tensor(hand.rest_joints), PARENTS, tp, torch.tensor(t))
    np.testing.assert_allclose(v.detach().numpy(), ref, atol=1e-14)
    np.testing.assert_allclose(j.detach().numpy(), posed_joints(poses, t, hand.rest_joints, PARENTS),
                               atol=1e-14)
    # Gradients against central finite differences on a few joints (float64).
    sel = torch.arange(0, len(m.vertices), 97)

    def f(p):
        vv, _ = lbs_torch(torch.tensor(m.vertices[sel.numpy()]), torch.tensor(m.weights[sel.numpy()]),
                          torch.tensor(hand.rest_joints), PARENTS, p, None)
        return vv.pow(2).sum()

    assert torch.autograd.gradcheck(f, (torch.tensor(poses[:1], requires_grad=True),), eps=1e-6,
                                    atol=1e-6)
    # And at exactly θ = 0 the gradient is finite.
    z = torch.zeros(1, 25, 3, dtype=torch.float64, requires_grad=True)
    f(z).backward()
    assert torch.isfinite(z.grad).all()


def test_vertex_normals_unit_outward_and_never_nan(hand):
    m = hand.coarse
    n = vertex_normals(m.vertices, m.faces)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    # Outward: the fingertip pole of the middle finger points along +y.
    top = np.argmax(m.vertices[:, 1])
    assert n[top, 1] > 0.9
    # Degenerate input: a zero-area face and an isolated vertex still give finite unit normals.
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [5, 5, 5]], float)
    f = np.array([[0, 1, 2]])
    nn = vertex_normals(v, f)
    assert np.isfinite(nn).all()
    np.testing.assert_allclose(np.linalg.norm(nn, axis=1), 1.0)


def test_posed_meshes_two_hands_world_and_normals(hand):
    from relight_cli.hand.scene import posed_meshes, posed_joints_world, two_hands

    h = builtin_hand()
    pair = two_hands(h)
    meshes = posed_meshes(pair, 0, "coarse")
    assert [m.name for m in meshes] == ["right", "left"]
    r, l = meshes
    assert r.vertices.dtype == np.float64 and r.faces.dtype == np.int64
    assert r.uv.dtype == np.float64 and r.faces_uv.dtype == np.int64
    # The pair is mirror-symmetric about x = 0 and does not intersect.
    np.testing.assert_allclose(l.vertices * [-1, 1, 1], r.vertices, atol=1e-12)
    assert r.vertices[:, 0].min() > l.vertices[:, 0].max()
    np.testing.assert_allclose(np.linalg.norm(l.normals, axis=1), 1.0, atol=1e-12)
    # Mirrored hand keeps outward normals: its signed volume is positive.
    tri = l.vertices[l.faces]
    assert np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() > 0
    # World joints agree with the skinned mesh: the middle fingertip joint lies near the mesh tip.
    joints = posed_joints_world(pair, 0)
    for jw, m in zip(joints, meshes):
        assert np.linalg.norm(m.vertices - jw[14], axis=1).min() < 0.004
    with pytest.raises(IndexError):
        posed_meshes(pair, 5)


def test_root_transform_applied(hand):
    from relight_cli.hand.scene import posed_meshes

    h = builtin_hand()
    base = posed_meshes(h)[0].vertices
    root = np.eye(4)
    root[:3, :3] = rodrigues(np.array([0.0, np.pi / 2, 0.0]))
    root[:3, 3] = [1.0, 2.0, 3.0]
    h.hands[0].root = root
    moved = posed_meshes(h)[0]
    np.testing.assert_allclose(moved.vertices, base @ root[:3, :3].T + root[:3, 3], atol=1e-12)
