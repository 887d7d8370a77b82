"""Fitting the hand to calibrated 2D keypoints (relight_cli.hand.fit2d): triangulation
against exact points, robustness to a wild detection, bone lengths recovered."""

from __future__ import annotations

import numpy as np
import pytest

from relight_cli.formats.camera import Camera
from relight_cli.hand import fit2d


def _cameras(center, n=5, radius=0.4):
    return [Camera.look_at(center + radius * np.array([np.cos(a), 0.5, np.sin(a)]), center,
                           [0, 1, 0], 40, 200, 160) for a in np.linspace(0, 2 * np.pi, n, False)]


def _project(cam, points):
    x = points @ cam.R.T + cam.t
    return x[:, :2] / x[:, 2:] @ cam.K[:2, :2].T + cam.K[:2, 2]


def test_triangulation_is_exact_and_ignores_a_wild_view():
    X = np.array([0.01, -0.02, 0.03])
    cams = _cameras(np.zeros(3))
    P = np.stack([fit2d.projection(c) for c in cams])
    uv = np.stack([_project(c, X[None])[0] for c in cams])
    np.testing.assert_allclose(fit2d.triangulate(P, uv, np.ones(5)), X, atol=1e-9)
    uv[2] += [40.0, -25.0]                      # one detection 47 px off
    got = fit2d.triangulate(P, uv, np.ones(5))
    assert np.linalg.norm(got - X) < 2e-4       # < 0.2 mm: the wild view is down-weighted
    naive = fit2d.triangulate(P, uv, np.ones(5), iterations=1)
    assert np.linalg.norm(naive - X) > 5 * np.linalg.norm(got - X)
    assert fit2d.triangulate(P[:1], uv[:1], np.ones(1)) is None


@pytest.mark.parametrize("seed", [1, 2])
def test_fit_recovers_pose_and_bone_lengths(seed):
    from relight_cli.hand.fitting import scaled_joints
    from relight_cli.hand.model import PARENTS, builtin_hand
    from relight_cli.hand.poses import named_pose
    from relight_cli.hand.skinning import posed_joints
    template = builtin_hand()
    rng = np.random.default_rng(seed)
    scales = np.r_[1.0, rng.uniform(0.85, 1.15, 24)]   # another person: bones ±15 %
    rest = scaled_joints(template.rest_joints, PARENTS, scales)
    pose = named_pose("relaxed", "right", rest)[None]
    joints = posed_joints(pose, np.zeros((1, 3)), rest, PARENTS)[0]
    cams = _cameras(joints.mean(0), 6)
    uv = np.stack([_project(c, joints) + rng.normal(0, 0.5, (25, 2)) for c in cams])
    r = fit2d.fit_views(template, cams, uv, np.ones((6, 25)), np.zeros(6, int),
                        options=fit2d.Fit2DOptions(iterations=80))
    fitted = posed_joints(r.poses, r.translations, r.rest_joints, PARENTS)[0]
    assert np.linalg.norm(fitted - joints, axis=1).mean() < 1.5e-3
    assert r.reprojection_px.max() < 1.5

    def lengths(x):
        return np.array([np.linalg.norm(x[j] - x[PARENTS[j]]) for j in range(1, 25)])
    err = np.abs(lengths(r.rest_joints) - lengths(rest)).mean()
    assert err < 0.4 * np.abs(lengths(template.rest_joints) - lengths(rest)).mean()


def test_one_view_per_pose_is_refused():
    from relight_cli.hand.model import builtin_hand
    cams = _cameras(np.zeros(3), 2)
    with pytest.raises(ValueError, match="at least two views"):
        fit2d.fit_views(builtin_hand(), cams, np.zeros((2, 25, 2)), np.ones((2, 25)),
                        np.array([0, 1]))
