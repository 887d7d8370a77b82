"""glTF/GLB import: the real WebXR hands, skinning against glTF's own joint transforms."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared_path

from relight_cli.errors import DataError
from relight_cli.hand.gltf import (_accessor, _load, _node_world_matrices, import_gltf,
                                   poses_from_world_matrices, skin_gltf_reference, subdivide)
from relight_cli.hand.model import JOINT_NAMES, PARENTS
from relight_cli.hand.skinning import lbs


def _raw(path):
    """Positions, UVs, dense weights straight from the file (for comparisons)."""
    g = _load(str(path))
    node = [n for n in g.nodes if n.skin is not None][0]
    prim = g.meshes[node.mesh].primitives[0]
    return g, node, prim


@pytest.mark.parametrize("side", ["left", "right"])
def test_import_real_webxr_hand(side):
    import trimesh

    path = shared_path("hands", f"webxr-generic-hand-{side}.glb")
    hand = import_gltf(str(path))
    assert hand.side == side
    assert hand.joint_names == list(JOINT_NAMES)
    g, node, prim = _raw(path)
    pos = _accessor(g, prim.attributes.POSITION, str(path))
    uv = _accessor(g, prim.attributes.TEXCOORD_0, str(path))
    assert len(pos) == 1360
    # Vertices split only for UV seams are welded; every UV survives (v flipped).
    assert len(hand.coarse.uv) == 1360
    np.testing.assert_allclose(hand.coarse.uv[:, 1], 1.0 - uv[:, 1], atol=1e-7)
    assert len(hand.coarse.vertices) == len(np.unique(pos, axis=0))
    tm = trimesh.Trimesh(hand.coarse.vertices, hand.coarse.faces, process=False)
    assert tm.is_watertight
    # The corner positions of each face are the file's own (through faces_uv = original indices).
    np.testing.assert_allclose(hand.coarse.vertices[hand.coarse.faces],
                               pos[hand.coarse.faces_uv], atol=1e-12)
    # Bind-pose joints: wrist to middle tip is a real hand's ≈ 0.18 m.
    assert 0.15 < np.linalg.norm(hand.rest_joints[14] - hand.rest_joints[0]) < 0.21
    np.testing.assert_allclose(hand.coarse.weights.sum(1), 1.0, atol=1e-6)
    # Fine mesh: one midpoint subdivision, ~4× vertices, same UV range.
    assert len(hand.fine.faces) == 4 * len(hand.coarse.faces)
    assert len(hand.fine.vertices) >= 3.9 * len(hand.coarse.vertices)


def test_rest_pose_of_file_skins_to_itself():
    path = shared_path("hands", "webxr-generic-hand-left.glb")
    hand = import_gltf(str(path))
    g = _load(str(path))
    node = [n for n in g.nodes if n.skin is not None][0]
    names = [g.nodes[j].name for j in g.skins[node.skin].joints]
    world_nodes = _node_world_matrices(g)
    world = np.stack([world_nodes[g.skins[node.skin].joints[names.index(n)]] for n in JOINT_NAMES])
    poses, t = poses_from_world_matrices(world, hand.inverse_bind_matrices)
    # The file's node pose is its bind pose (to float32 precision): θ ≈ 0.
    assert np.abs(poses).max() < 1e-5 and np.abs(t).max() < 1e-6


def _hierarchical_world(hand, deltas, root_shift):
    """glTF-style posing: joint-local rotation deltas in each joint's *bind* frame, chained.

    This is how a glTF animation drives a hierarchy (local = T·R relative to
    the parent node), independent of our MANO-style parameterization.
    """
    from scipy.spatial.transform import Rotation

    bind = np.linalg.inv(hand.inverse_bind_matrices)
    world = np.zeros_like(bind)
    for j in range(25):
        p = PARENTS[j]
        rest_local = bind[j] if p < 0 else np.linalg.inv(bind[p]) @ bind[j]
        delta = np.eye(4)
        delta[:3, :3] = Rotation.from_rotvec(deltas[j]).as_matrix()
        local = rest_local @ delta
        if p < 0:
            shift = np.eye(4)
            shift[:3, 3] = root_shift
            world[j] = shift @ local
        else:
            world[j] = world[p] @ local
    return world


def test_our_skinning_matches_gltf_joint_transforms():
    path = shared_path("hands", "webxr-generic-hand-right.glb")
    hand = import_gltf(str(path))
    rng = np.random.default_rng(4)
    world = _hierarchical_world(hand, rng.normal(0, 0.4, (25, 3)), [0.1, -0.2, 0.05])
    ref = skin_gltf_reference(hand.coarse.vertices, hand.coarse.weights, world,
                              hand.inverse_bind_matrices)
    poses, t = poses_from_world_matrices(world, hand.inverse_bind_matrices)
    ours = lbs(hand.coarse.vertices, hand.coarse.weights, hand.rest_joints, PARENTS, poses, t)
    # Same rigid transforms in float64; the gap is that the file's float32 inverse
    # bind matrices are orthonormal only to ~1e-7, while our rotations are exactly
    # orthonormal: ~1e-7 × a few cm lever ≈ 3e-9 m.  Allow 2e-8 m (20 nm).
    np.testing.assert_allclose(ours, ref, atol=2e-8)
    assert np.abs(ours - hand.coarse.vertices).max() > 0.02  # the pose really moved it


def test_subdivide_preserves_uv_map():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.5]], float)
    f = np.array([[0, 1, 2], [1, 3, 2]])
    uv = np.array([[0, 0], [1, 0], [0, 1], [1, 1], [0.5, 0.5]])
    fuv = np.array([[0, 1, 2], [1, 3, 4]])                   # a UV seam: vertex 2 has two UVs
    w = np.eye(4)[:, :4]
    fv, ff, fuv2, ffuv, fw = subdivide(v, f, uv, fuv, w)
    assert len(ff) == 8 and len(fv) == 4 + 5                 # 5 unique edges
    # Each fine triangle's 3D corners equal the coarse affine map of its UV corners.
    for k in range(len(ff)):
        parent = k % 2                                        # faces are stacked 4 blocks of F
        A = np.c_[uv[fuv[parent]], np.ones(3)]
        for c in range(3):
            bary = np.linalg.solve(A.T, np.r_[fuv2[ffuv[k, c]], 1.0])
            np.testing.assert_allclose(bary @ v[f[parent]], fv[ff[k, c]], atol=1e-12)
            np.testing.assert_allclose(bary @ w[f[parent]], fw[ff[k, c]], atol=1e-12)


def test_bad_gltf_files(tmp_path):
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"glTF\x02\x00\x00\x00garbage")
    with pytest.raises(DataError) as exc:
        import_gltf(str(bad))
    assert str(bad) in str(exc.value)
    with pytest.raises(DataError, match="no such file"):
        import_gltf(str(tmp_path / "none.glb"))
    # A valid glTF without a skin.
    import pygltflib

    g = pygltflib.GLTF2(scenes=[pygltflib.Scene(nodes=[0])], nodes=[pygltflib.Node(name="x")])
    plain = tmp_path / "plain.gltf"
    g.save(str(plain))
    with pytest.raises(DataError, match="no skinned mesh"):
        import_gltf(str(plain))


def test_accessor_reads_interleaved_and_normalized_views():
    """byteStride > element size (interleaved attributes) and normalized integers."""
    from types import SimpleNamespace as NS

    pos = np.arange(12, dtype=np.float32).reshape(4, 3)
    weights = np.array([[255, 0, 0, 0], [128, 127, 0, 0], [0, 0, 255, 0], [1, 2, 3, 249]], np.uint8)
    # Interleave: 12 bytes of position + 4 bytes of weights per vertex (stride 16).
    blob = b"".join(p.tobytes() + w.tobytes() for p, w in zip(pos, weights))
    gltf = NS(buffers=[NS(uri=None)], binary_blob=lambda: b"\0" * 8 + blob,
              bufferViews=[NS(buffer=0, byteOffset=8, byteStride=16)],
              accessors=[NS(bufferView=0, byteOffset=0, componentType=5126, type="VEC3",
                            count=4, normalized=False),
                         NS(bufferView=0, byteOffset=12, componentType=5121, type="VEC4",
                            count=4, normalized=True)])
    np.testing.assert_array_equal(_accessor(gltf, 0, "x"), pos)
    np.testing.assert_allclose(_accessor(gltf, 1, "x"), weights / 255.0)
    # A view running past its buffer is a data error, not a crash.
    gltf.accessors[0].count = 5
    with pytest.raises(DataError, match="past the end"):
        _accessor(gltf, 0, "x")
