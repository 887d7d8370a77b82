"""The procedural hand: geometry, UV atlas, weights, labels, mirror, poses."""

from __future__ import annotations

import numpy as np
import pytest

from relight_cli.hand import poses as P
from relight_cli.hand.model import JOINT_NAMES, LABEL_NAMES, PARENTS, builtin_hand, rest_skeleton
from relight_cli.hand.skinning import lbs, mirror_pose, posed_joints


@pytest.fixture(scope="module")
def right():
    return builtin_hand("right")


def _uv_jacobian_stats(mesh):
    tri = mesh.vertices[mesh.faces]
    uv = mesh.uv[mesh.faces_uv]
    e = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], 2)          # [F, 3, 2]
    u = np.stack([uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]], 2)              # [F, 2, 2]
    jac = e @ np.linalg.inv(u)                                               # d(xyz)/d(uv)
    s = np.linalg.svd(jac, compute_uv=False)
    area3 = 0.5 * np.linalg.norm(np.cross(e[..., 0], e[..., 1]), axis=1)
    area2 = 0.5 * np.abs(u[:, 0, 0] * u[:, 1, 1] - u[:, 0, 1] * u[:, 1, 0])
    return s[:, 0] / s[:, 1], area3, area2


def test_skeleton_names_and_size(right):
    assert right.joint_names == list(JOINT_NAMES)
    assert len(JOINT_NAMES) == 25 and JOINT_NAMES[0] == "wrist"
    assert JOINT_NAMES[4] == "thumb-tip" and JOINT_NAMES[24] == "pinky-finger-tip"
    for j in range(1, 25):
        assert PARENTS[j] < j
        # Names chain: every non-metacarpal joint's parent is the same finger.
        if not JOINT_NAMES[j].endswith("metacarpal"):
            assert JOINT_NAMES[PARENTS[j]].split("-")[0] == JOINT_NAMES[j].split("-")[0]
    J = right.rest_joints
    # A real adult hand: wrist to middle fingertip 0.18–0.19 m.
    assert 0.18 <= np.linalg.norm(J[14] - J[0]) <= 0.19
    # Right hand: thumb towards +x, fingers towards +y.
    assert J[4, 0] > J[24, 0] and J[14, 1] > 0.15


def test_mesh_counts_closed_and_sized(right):
    import trimesh

    c, f = right.coarse, right.fine
    assert 2500 <= len(c.vertices) <= 3500
    assert len(f.vertices) >= 4 * len(c.vertices)
    for m in (c, f):
        tm = trimesh.Trimesh(m.vertices, m.faces, process=False)
        assert tm.is_watertight and tm.is_winding_consistent
        assert tm.volume > 0  # outward winding
        ext = m.vertices.max(0) - m.vertices.min(0)
        assert 0.18 < ext[1] < 0.24 and 0.06 < ext[0] < 0.14
        np.testing.assert_allclose(m.weights.sum(1), 1.0, atol=1e-12)
        assert m.weights.min() >= 0
        assert m.uv.min() >= 0 and m.uv.max() <= 1
        # Tip joints carry no weight: nothing would observe their rotation.
        assert np.all(m.weights[:, [4, 9, 14, 19, 24]] == 0)


def test_fine_refines_coarse_with_same_uv_map(right):
    """Every coarse vertex is a fine vertex with the same UV (one parameterization)."""
    from scipy.spatial import cKDTree

    c, f = right.coarse, right.fine
    # UV of each coarse vertex (first UV corner that uses it) vs the fine vertex at that spot.
    def vertex_uv(m):
        uv = np.zeros((len(m.vertices), 2))
        uv[m.faces.ravel()] = m.uv[m.faces_uv.ravel()]
        return uv
    dist, idx = cKDTree(f.vertices).query(c.vertices)
    # The fine mesh's palmar creases (Gaussian grooves ≤ 0.4 mm deep) move a few
    # vertices; all the others coincide exactly.
    assert (dist < 1e-12).mean() > 0.9
    assert dist.max() <= 0.0004 + 1e-12
    # Seam vertices have several UVs; compare away from seams (u strictly inside a chart).
    cu, fu = vertex_uv(c), vertex_uv(f)
    same = np.linalg.norm(cu - fu[idx], axis=1) < 1e-12
    assert same.mean() > 0.9


def test_uv_atlas_no_overlap_low_stretch(right):
    from relight_cli.uvraster import rasterize_uv

    for m in (right.coarse, right.fine):
        for resolution in (128, 256):              # later stages bake at 128² and up
            raster = rasterize_uv(m.uv, m.faces_uv, resolution)
            assert raster.overlap_fraction() == 0.0
            assert raster.inside.mean() > 0.5      # the atlas uses over half of [0, 1]²
            # Every texel inside the charts maps to a face with barycentrics summing to 1.
            np.testing.assert_allclose(raster.barycentric[raster.inside].sum(1), 1.0, atol=1e-9)
        aniso, area3, area2 = _uv_jacobian_stats(m)
        # ≥ 90% of the surface (by area) maps with anisotropy < 2 (conformal-ish),
        # measured 95%; poles of the capped tubes account for the rest.
        assert (area3 * (aniso < 2)).sum() / area3.sum() > 0.9
        ratio = (area2 / area3) / (area2.sum() / area3.sum())
        assert np.percentile(ratio, 5) > 0.5 and np.percentile(ratio, 95) < 2.5


def test_labels_cover_regions(right):
    for m in (right.coarse, right.fine):
        counts = np.bincount(m.labels, minlength=len(LABEL_NAMES))
        assert np.all(counts > 0), dict(zip(LABEL_NAMES, counts))
        nail = m.vertices[m.labels == LABEL_NAMES.index("nail")]
        # Nails are on the back (−z) of the hand, at the fingertips.
        assert np.median(nail[:, 2]) < 0


def test_left_is_mirror_of_right(right):
    left = builtin_hand("left")
    np.testing.assert_allclose(left.coarse.vertices * [-1, 1, 1], right.coarse.vertices)
    np.testing.assert_allclose(left.rest_joints * [-1, 1, 1], right.rest_joints)
    # Posing the mirrored model with the mirrored pose mirrors the posed mesh.
    pose = P.named_pose("pinch")
    a = lbs(right.coarse.vertices, right.coarse.weights, right.rest_joints, PARENTS, pose)
    b = lbs(left.coarse.vertices, left.coarse.weights, left.rest_joints, PARENTS,
            mirror_pose(pose))
    np.testing.assert_allclose(b * [-1, 1, 1], a, atol=1e-12)
    np.testing.assert_allclose(P.named_pose("pinch", "left"), mirror_pose(pose))


def test_named_poses_and_limits():
    rest = rest_skeleton()
    axes = P.joint_axes(rest, "right")
    lim = P.joint_limits()
    tips = {}
    for name in P.POSE_NAMES:
        pose = P.named_pose(name)
        assert pose.shape == (25, 3) and np.isfinite(pose).all()
        angles = P._angles_table(name)
        assert np.all(angles[1:] >= lim[1:, :, 0] - 1e-9) and np.all(angles[1:] <= lim[1:, :, 1] + 1e-9)
        tips[name] = posed_joints(pose, np.zeros(3), rest, PARENTS)
    # Fist: every fingertip is closer to the wrist than in the open hand.
    for tip in (9, 14, 19, 24):
        assert np.linalg.norm(tips["fist"][tip]) < 0.7 * np.linalg.norm(tips["open"][tip])
    # Pinch/ok: thumb and index tips nearly touch (tip joints ~11 mm apart).
    for name in ("pinch", "ok"):
        assert np.linalg.norm(tips[name][4] - tips[name][9]) < 0.015
    # Flexion curls towards the palm (+z for the built-in hand).
    assert tips["fist"][14, 2] > 0.02
    # Pure flexion round-trips through angles_from_pose.
    a = np.zeros((25, 3))
    a[7, 0] = 1.2
    np.testing.assert_allclose(P.angles_from_pose(P.pose_from_angles(a, axes), axes)[7], [1.2, 0, 0],
                               atol=1e-12)


def test_random_poses_seeded_within_limits():
    a = P.random_poses(50, seed=7)
    b = P.random_poses(50, seed=7)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, P.random_poses(50, seed=8))
    axes = P.joint_axes(rest_skeleton(), "right")
    lim = P.joint_limits()
    ang = P.angles_from_pose(a, axes)
    # The projection approximates the composed angles: allow 0.08 rad slack.
    assert np.all(ang[:, 1:] >= lim[None, 1:, :, 0] - 0.08)
    assert np.all(ang[:, 1:] <= lim[None, 1:, :, 1] + 0.08)


def test_slerp_matches_scipy_and_interpolates():
    from scipy.spatial.transform import Rotation, Slerp

    rng = np.random.default_rng(0)
    p0 = Rotation.random(25, random_state=1).as_rotvec()
    p1 = Rotation.random(25, random_state=2).as_rotvec()
    np.testing.assert_allclose(P.slerp(p0, p1, 0.0), p0, atol=1e-12)
    for alpha in (0.25, 0.5, 0.9):
        ours = Rotation.from_rotvec(P.slerp(p0, p1, alpha)).as_matrix()
        for j in range(25):
            ref = Slerp([0, 1], Rotation.from_rotvec([p0[j], p1[j]]))(alpha).as_matrix()
            np.testing.assert_allclose(ours[j], ref, atol=1e-9)
    # Keyframe interpolation hits the keys and lerps translations.
    keys = np.stack([p0, p1])
    trans = rng.normal(size=(2, 3))
    poses, t = P.interpolate_poses([0, 4], keys, trans, np.arange(5))
    np.testing.assert_allclose(Rotation.from_rotvec(poses[4]).as_matrix(),
                               Rotation.from_rotvec(p1).as_matrix(), atol=1e-9)
    np.testing.assert_allclose(t[2], trans.mean(0))


def test_builtin_is_fast_and_cached():
    # Generation is vectorized; a second call reuses the cached arrays and hands out copies.
    a = builtin_hand()
    a.coarse.vertices[:] = 0
    b = builtin_hand()
    assert np.abs(b.coarse.vertices).max() > 0.05
