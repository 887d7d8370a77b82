"""Fitting the hand to synthetic keypoints and scans made from known poses.

Targets come from the built-in hand with known poses, bone scales and
translations, so errors are measured against the truth (not the noisy input).
"""

from __future__ import annotations

import numpy as np
import pytest

from relight_cli.hand import poses as P
from relight_cli.hand.fitting import (FitOptions, displacement_basis, fit, personalize_mesh,
                                      synthetic_truth)
from relight_cli.hand.model import PARENTS, builtin_hand
from relight_cli.hand.skinning import lbs, posed_joints


@pytest.fixture(scope="module")
def template():
    return builtin_hand(pose=None)


def _truth(template, n, seed):
    return synthetic_truth(template, n, seed)


def _vertices(template, poses, trans, scales, rest, offsets=None):
    m = template.coarse
    v = personalize_mesh(m.vertices, m.weights, template.rest_joints, PARENTS, scales, offsets)
    return lbs(v, m.weights, rest, PARENTS, poses, trans)


def test_displacement_basis_moves_bones_with_their_joints(template):
    m = template.coarse
    B = displacement_basis(m.vertices, m.weights, template.rest_joints, PARENTS)
    np.testing.assert_allclose(B.sum(1), 1.0, atol=1e-12)  # a rigid shift moves everything
    # Scale 1 everywhere leaves the mesh unchanged; a longer middle finger moves its tip.
    same = personalize_mesh(m.vertices, m.weights, template.rest_joints, PARENTS, np.ones(25))
    np.testing.assert_array_equal(same, m.vertices)
    s = np.ones(25)
    s[12:15] = 1.2
    longer = personalize_mesh(m.vertices, m.weights, template.rest_joints, PARENTS, s)
    tip = np.argmax(m.vertices[:, 1])
    grow = (s[12:15] - 1) @ np.linalg.norm(np.diff(template.rest_joints[11:15], axis=0), axis=1)
    assert abs((longer[tip, 1] - m.vertices[tip, 1]) - grow) < 0.003


def test_fit_keypoints_noise_outliers_hard_poses(template):
    n = 32
    poses, trans, scales, rest, joints = _truth(template, n, seed=11)
    rng = np.random.default_rng(5)
    kp = joints + rng.normal(0, 0.002, joints.shape)           # 2 mm Gaussian noise
    outliers = rng.random(joints.shape[:2]) < 0.10             # 10% gross outliers
    kp[outliers] += rng.normal(0, 0.05, (outliers.sum(), 3))
    result = fit(template, kp, None, options=FitOptions(iterations=300))
    fitted = posed_joints(result.poses, result.translations, result.rest_joints, PARENTS)
    mpjpe = np.linalg.norm(fitted - joints, axis=-1).mean() * 1000
    # Issue target: MPJPE ≤ 5 mm (measured ≈ 2.6 mm: the 2 mm noise floor).
    assert mpjpe <= 5.0, mpjpe
    # Hard frames individually (fist, claw, at-limit poses): ≤ 5 mm each.
    per_frame = np.linalg.norm(fitted - joints, axis=-1).mean(1) * 1000
    assert per_frame[:4].max() <= 5.0, per_frame[:4]
    true_v = _vertices(template, poses, trans, scales, rest)
    fit_v = _vertices(template, result.poses, result.translations, result.bone_scales,
                      result.rest_joints)
    vertex_err = np.linalg.norm(fit_v - true_v, axis=-1) * 1000
    # Issue target: median vertex error ≤ 3 mm (measured ≈ 2.1 mm).
    assert np.median(vertex_err) <= 3.0, np.median(vertex_err)
    scale_err = np.abs(result.bone_scales[1:] / scales[1:] - 1)
    # Bone lengths from 2 mm noisy endpoints over 32 frames have a noise floor of
    # σ ≈ 2.8 mm / (L·√32) ≈ 2.5% for the 20 mm distal bones, so the per-bone 3%
    # target holds for the typical bone here and for every bone without noise
    # (next test) or with ~200 frames (benchmarks/bench_hand.py).
    assert np.median(scale_err) <= 0.015, np.median(scale_err)
    assert scale_err.max() <= 0.06, scale_err.max()
    # The report's residuals are against the noisy keypoints, all observed.
    assert result.joint_error_mm.shape == (n,) and np.isfinite(result.joint_error_mm).all()


def test_fit_outliers_only_bone_scales_within_3_percent(template):
    n = 16
    poses, trans, scales, rest, joints = _truth(template, n, seed=3)
    rng = np.random.default_rng(8)
    kp = joints.copy()
    outliers = rng.random(joints.shape[:2]) < 0.10
    kp[outliers] += rng.normal(0, 0.05, (outliers.sum(), 3))
    result = fit(template, kp, None, options=FitOptions(iterations=300))
    scale_err = np.abs(result.bone_scales[1:] / scales[1:] - 1)
    assert scale_err.max() <= 0.03, scale_err.max()       # measured ≤ 0.3%
    fitted = posed_joints(result.poses, result.translations, result.rest_joints, PARENTS)
    assert np.linalg.norm(fitted - joints, axis=-1).mean() * 1000 <= 2.0


def test_fit_missing_fingers_and_joints(template):
    n = 8
    poses, trans, scales, rest, joints = _truth(template, n, seed=21)
    conf = np.ones((n, 25))
    conf[:, 15:20] = 0.0                     # the ring finger is never seen
    conf[2:5, 1:5] = 0.0                     # the thumb is hidden in three frames
    kp = joints.copy()
    kp[conf == 0] = 123.0                    # garbage where missing: must be ignored
    result = fit(template, kp, conf, options=FitOptions(iterations=200, fit_bone_scales=False))
    fitted = posed_joints(result.poses, result.translations, rest * 0 + template.rest_joints, PARENTS)
    seen = conf > 0
    # Observed joints: only the (unfitted) bone scales (±5%) separate fit and truth.
    err = np.linalg.norm(fitted - joints, axis=-1)[seen] * 1000
    assert np.mean(err) <= 5.0, np.mean(err)
    # Unseen fingers stay inside the joint limits (the prior), not wild.
    axes = P.joint_axes(template.rest_joints, "right")
    ang = P.angles_from_pose(result.poses, axes)
    lim = P.joint_limits()
    assert np.all(ang[:, 15:20] >= lim[15:20, :, 0] - 0.1)
    assert np.all(ang[:, 15:20] <= lim[15:20, :, 1] + 0.1)
    assert np.isfinite(result.joint_error_mm).all()


def test_fit_scans_point_to_plane_and_offsets(template):
    """Scans of a hand with a personal surface bump: offsets recover it."""
    import trimesh

    n = 1
    poses, trans, scales, rest, joints = _truth(template, n, seed=31)
    poses[:, 1:] = P.named_pose("relaxed")[1:]
    joints = posed_joints(poses, trans, rest, PARENTS)
    m = template.coarse
    from relight_cli.hand.skinning import vertex_normals
    normals = vertex_normals(m.vertices, m.faces)
    # A 2 mm smooth swelling of the back of the palm (personal shape the template lacks).
    bump = 0.002 * np.exp(-((m.vertices[:, 1] - 0.05) / 0.02) ** 2) * (m.vertices[:, 2] < 0)
    offsets_true = bump[:, None] * normals
    true_v = _vertices(template, poses, trans, scales, rest, offsets_true)
    rng = np.random.default_rng(2)
    scans = []
    for k in range(n):
        pts, _ = trimesh.sample.sample_surface(trimesh.Trimesh(true_v[k], m.faces, process=False),
                                               4000, seed=k)
        scans.append(np.asarray(pts) + rng.normal(0, 0.0003, (len(pts), 3)))
    conf = np.ones((n, 25))
    conf[:, ::2] = 0                          # half the keypoints missing: the scans must help
    plain = fit(template, joints, conf, scans, FitOptions(iterations=120))
    with_offsets = fit(template, joints, conf, scans, FitOptions(iterations=120, fit_offsets=True))
    # Scan noise is 0.3 mm per axis (mean |point-to-plane| ≈ 0.24 mm); the 2 mm bump
    # the template lacks adds ≈ 0.15 mm on average.  Measured: 0.41 → 0.30 mm.
    assert plain.scan_mm.mean() < 0.6, plain.scan_mm
    assert with_offsets.scan_mm.mean() < plain.scan_mm.mean() - 0.05
    assert with_offsets.offsets is not None and np.isfinite(with_offsets.offsets).all()
    # The recovered offsets swell the bump outward (measured 1.5 of its ≥ 1 mm core).
    on_bump = bump > 0.001
    assert (with_offsets.offsets[on_bump] * normals[on_bump]).sum(1).mean() > 0.0007
    fitted = posed_joints(with_offsets.poses, with_offsets.translations, with_offsets.rest_joints,
                          PARENTS)
    assert np.linalg.norm(fitted - joints, axis=-1).mean() * 1000 <= 5.0


def test_temporal_smoothness_reduces_jitter(template):
    """A still hand seen with noise: the smoothness term steadies the fitted joints."""
    n = 6
    pose = P.named_pose("relaxed")
    joints = posed_joints(np.repeat(pose[None], n, 0), np.zeros((n, 3)), template.rest_joints,
                          PARENTS)
    kp = joints + np.random.default_rng(3).normal(0, 0.003, joints.shape)
    jitter = {}
    for w in (0.0, 5.0):
        r = fit(template, kp, None, options=FitOptions(iterations=150, fit_bone_scales=False,
                                                       w_smooth=w))
        fj = posed_joints(r.poses, r.translations, template.rest_joints, PARENTS)
        jitter[w] = np.linalg.norm(np.diff(fj, axis=0), axis=-1).mean()
    # Independent fits jitter by about the noise (≈ 3 mm); smoothing must cut that clearly.
    assert jitter[5.0] < 0.7 * jitter[0.0], jitter


def test_fit_scan_only_any_orientation(template):
    """Without keypoints, a rigid PCA + ICP start finds the hand in any orientation."""
    import trimesh

    from scipy.spatial.transform import Rotation

    pose = P.named_pose("point")
    pose[0] = Rotation.from_euler("xyz", [100, -40, 150], degrees=True).as_rotvec()
    m = template.coarse
    v = lbs(m.vertices, m.weights, template.rest_joints, PARENTS, pose, [0.3, -0.1, 0.5])
    pts, _ = trimesh.sample.sample_surface(trimesh.Trimesh(v, m.faces, process=False), 3000, seed=0)
    result = fit(template, None, None, [np.asarray(pts)],
                 FitOptions(iterations=120, fit_bone_scales=False))
    assert result.scan_mm[0] < 1.0, result.scan_mm
    fitted = posed_joints(result.poses, result.translations, template.rest_joints, PARENTS)
    truth = posed_joints(pose, [0.3, -0.1, 0.5], template.rest_joints, PARENTS)
    assert np.linalg.norm(fitted - truth, axis=-1).mean() * 1000 < 6.0
