"""Import of skinned glTF 2.0 / GLB hands (read with pygltflib) as templates.

The skinned mesh becomes the coarse proxy (vertices welded across UV seams,
v flipped to our bottom-up convention) and its midpoint subdivision the fine
mesh; the skin's joints are mapped by name onto the 25 WebXR joints; the
bind pose (inverse of each inverse bind matrix) gives the rest joints.

glTF skins give each joint a full bind orientation B_j, while our MANO-style
rest frame has identity orientations.  Both describe the same skinning: a
glTF pose with joint world matrices W_j skins a vertex with W_j·IBM_j, and our
global rotation of joint j is the rotation part of W_j·B_j⁻¹
(:func:`poses_from_world_matrices`).
"""

from __future__ import annotations

import os
import re

import numpy as np

from relight_cli.errors import DataError

from .model import JOINT_NAMES, N_JOINTS, PARENTS

_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16,
              5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def _load(path: str):
    import pygltflib

    if not os.path.exists(path):
        raise DataError("no such file", path)
    try:
        gltf = pygltflib.GLTF2().load(path)
    except Exception as exc:  # pygltflib raises assorted errors on damaged files
        raise DataError(f"not a readable glTF/GLB file: {type(exc).__name__}: {exc}", path) from None
    if gltf is None:
        raise DataError("not a readable glTF/GLB file", path)
    return gltf


def _buffer_bytes(gltf, index: int, path: str) -> bytes:
    buf = gltf.buffers[index]
    if buf.uri is None:
        blob = gltf.binary_blob()
        if blob is None:
            raise DataError("GLB has no binary chunk", path)
        return blob
    if buf.uri.startswith("data:"):
        import base64
        return base64.b64decode(buf.uri.split(",", 1)[1])
    target = os.path.join(os.path.dirname(path), buf.uri)
    if not os.path.exists(target):
        raise DataError(f"external buffer {buf.uri!r} not found", path)
    with open(target, "rb") as f:
        return f.read()


def _accessor(gltf, index: int, path: str) -> np.ndarray:
    """Accessor ``index`` as an array [count, width] (normalized integers scaled to [0, 1])."""
    a = gltf.accessors[index]
    dtype = np.dtype(_COMPONENT[a.componentType])
    width = _WIDTH[a.type]
    if a.bufferView is None:
        return np.zeros((a.count, width), dtype)
    view = gltf.bufferViews[a.bufferView]
    data = _buffer_bytes(gltf, view.buffer, path)
    start = (view.byteOffset or 0) + (a.byteOffset or 0)
    item = dtype.itemsize * width
    stride = view.byteStride or item
    if start + stride * (a.count - 1) + item > len(data):
        raise DataError(f"accessor {index} runs past the end of its buffer", path)
    # Interleaved views (byteStride > element size) read as a strided array.
    out = np.ndarray((a.count, width), dtype, buffer=data, offset=start,
                     strides=(stride, dtype.itemsize)).copy()
    if a.normalized and dtype.kind in "iu":
        out = out.astype(np.float64) / np.iinfo(dtype).max
    return out


def _node_world_matrices(gltf) -> np.ndarray:
    """[nodes, 4, 4] world matrices of every node in the scene graph (rest/node pose)."""
    from scipy.spatial.transform import Rotation

    n = len(gltf.nodes)
    local = np.zeros((n, 4, 4))
    for i, node in enumerate(gltf.nodes):
        if node.matrix is not None and len(node.matrix) == 16:
            local[i] = np.asarray(node.matrix, np.float64).reshape(4, 4).T
            continue
        m = np.eye(4)
        if node.rotation is not None:
            m[:3, :3] = Rotation.from_quat(node.rotation).as_matrix()   # glTF: x, y, z, w
        if node.scale is not None:
            m[:3, :3] = m[:3, :3] @ np.diag(node.scale)
        if node.translation is not None:
            m[:3, 3] = node.translation
        local[i] = m
    parent = np.full(n, -1)
    for i, node in enumerate(gltf.nodes):
        for c in node.children or []:
            parent[c] = i
    world = np.zeros_like(local)
    done = np.zeros(n, bool)

    def resolve(i):
        if done[i]:
            return world[i]
        world[i] = local[i] if parent[i] < 0 else resolve(parent[i]) @ local[i]
        done[i] = True
        return world[i]

    for i in range(n):
        resolve(i)
    return world


def canonical_joint_name(name: str) -> str | None:
    """Map a skin joint name onto a WebXR name (accepts prefixes like 'b_l_' and '_' for '-')."""
    key = re.sub(r"[_\s.]+", "-", name.strip().lower())
    for candidate in sorted(JOINT_NAMES, key=len, reverse=True):
        if key == candidate or key.endswith("-" + candidate) or key.endswith(candidate):
            return candidate
    return None


def _guess_side(gltf, path: str) -> str:
    names = " ".join((n.name or "").lower() for n in gltf.nodes) + " " + os.path.basename(path).lower()
    if "left" in names or re.search(r"(^|[^a-z])l_", names):
        return "left"
    return "right"


def import_gltf(path: str, side: str | None = None):
    """A skinned glTF/GLB hand as a one-frame HandData in its bind pose.

    Args:
        path: .glb or .gltf file with one skinned mesh (TEXCOORD_0, JOINTS_0, WEIGHTS_0).
        side: "right"/"left"; None guesses from node and file names.
    Raises:
        DataError: no skinned mesh, missing attributes, joints that do not map to
            the 25 WebXR joints, UVs outside [0, 1].
    """
    from relight_cli.formats.hand_npz import HandData, HandInstance, HandMesh

    gltf = _load(path)
    skinned = [n for n in gltf.nodes if n.mesh is not None and n.skin is not None]
    if not skinned:
        raise DataError("no skinned mesh (a node with both mesh and skin)", path)
    node = skinned[0]
    skin = gltf.skins[node.skin]
    joint_nodes = list(skin.joints)
    mapping = [canonical_joint_name(gltf.nodes[j].name or "") for j in joint_nodes]
    missing = sorted(set(JOINT_NAMES) - {m for m in mapping if m})
    if missing:
        raise DataError(f"skin lacks WebXR joints: {', '.join(missing[:5])}"
                        f"{' …' if len(missing) > 5 else ''}", path)
    ours = np.array([JOINT_NAMES.index(m) if m else -1 for m in mapping])   # skin idx → ours
    if skin.inverseBindMatrices is None:
        ibm_skin = np.linalg.inv(_node_world_matrices(gltf)[joint_nodes])
    else:
        ibm_skin = _accessor(gltf, skin.inverseBindMatrices, path).astype(np.float64)
        ibm_skin = ibm_skin.reshape(-1, 4, 4).transpose(0, 2, 1)         # column-major
    ibm = np.zeros((N_JOINTS, 4, 4))
    for k, j in enumerate(ours):
        if j >= 0:
            ibm[j] = ibm_skin[k]

    positions, uvs, weights, faces = [], [], [], []
    offset = 0
    for prim in gltf.meshes[node.mesh].primitives:
        if prim.mode not in (None, 4):
            continue  # only triangle lists
        att = prim.attributes
        for need in ("POSITION", "TEXCOORD_0", "JOINTS_0", "WEIGHTS_0"):
            if getattr(att, need) is None:
                raise DataError(f"skinned primitive lacks {need}", path)
        pos = _accessor(gltf, att.POSITION, path).astype(np.float64)
        uv = _accessor(gltf, att.TEXCOORD_0, path).astype(np.float64)
        jidx = _accessor(gltf, att.JOINTS_0, path).astype(np.int64)
        wts = _accessor(gltf, att.WEIGHTS_0, path).astype(np.float64)
        if jidx.size and jidx.max() >= len(joint_nodes):
            raise DataError("JOINTS_0 indexes past the skin's joints", path)
        dense = np.zeros((len(pos), N_JOINTS))
        for c in range(jidx.shape[1]):
            target = ours[jidx[:, c]]
            ok = target >= 0
            np.add.at(dense, (np.nonzero(ok)[0], target[ok]), wts[ok, c])
        if prim.indices is None:
            tri = np.arange(len(pos)).reshape(-1, 3)
        else:
            tri = _accessor(gltf, prim.indices, path).astype(np.int64).reshape(-1, 3)
        positions.append(pos)
        uvs.append(uv)
        weights.append(dense)
        faces.append(tri + offset)
        offset += len(pos)
    if not positions:
        raise DataError("skinned mesh has no triangle primitives", path)
    pos = np.concatenate(positions)
    uv = np.concatenate(uvs)
    uv[:, 1] = 1.0 - uv[:, 1]                                            # glTF v is top-down
    if uv.min() < -1e-6 or uv.max() > 1 + 1e-6:
        raise DataError("TEXCOORD_0 leaves [0, 1]² (tiled UVs are not supported)", path)
    uv = np.clip(uv, 0.0, 1.0)
    W = np.concatenate(weights)
    sums = W.sum(1, keepdims=True)
    if (sums <= 0).any():
        raise DataError(f"{int((sums <= 0).sum())} vertices have zero skin weight", path)
    W /= sums
    faces_uv = np.concatenate(faces)
    if faces_uv.max() >= len(pos):
        raise DataError("indices run past the vertex count", path)
    # Weld vertices split only for UV seams (same position): one position per
    # surface point keeps normals smooth and the surface closed for ray tracing.
    key = np.round(pos / 1e-7).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    vertices = pos[first]
    vweights = np.zeros((len(first), N_JOINTS))
    np.add.at(vweights, inverse, W)
    vweights /= np.bincount(inverse, minlength=len(first))[:, None]
    faces = inverse[faces_uv]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    faces, faces_uv = faces[keep], faces_uv[keep]

    bind = np.linalg.inv(ibm)                                            # joint bind world matrices
    rest_joints = bind[:, :3, 3].copy()
    coarse = HandMesh(vertices, faces, uv, faces_uv, vweights, None)
    fine = HandMesh(*subdivide(vertices, faces, uv, faces_uv, vweights), None)
    side = side or _guess_side(gltf, path)
    inst = HandInstance(side, False, np.eye(4), np.zeros((1, N_JOINTS, 3)), np.zeros((1, 3)))
    return HandData(joint_names=list(JOINT_NAMES), parents=PARENTS.copy(), rest_joints=rest_joints,
                    coarse=coarse, fine=fine, side=side, hands=[inst], label_names=[],
                    bone_scales=np.ones(N_JOINTS), inverse_bind_matrices=ibm)


def subdivide(vertices, faces, uv, faces_uv, weights):
    """One level of UV-preserving midpoint subdivision (each triangle → 4).

    New vertices sit at edge midpoints in 3D, in UV and in weight space, so the
    fine mesh maps the same UV chart onto the same (piecewise-flat) surface.
    Returns (vertices, faces, uv, faces_uv, weights) of the fine mesh.
    """
    def split(points, tris):
        edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), 1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        inv = inv.ravel()
        n_f = len(tris)
        mid = len(points) + inv.reshape(3, n_f).T                         # [F, 3]: ab, bc, ca
        a, b, c = tris.T
        ab, bc, ca = mid.T
        new_tris = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
                                   np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)])
        return uniq, new_tris

    edges_v, fine_faces = split(vertices, faces)
    v = np.concatenate([vertices, 0.5 * (vertices[edges_v[:, 0]] + vertices[edges_v[:, 1]])])
    w = np.concatenate([weights, 0.5 * (weights[edges_v[:, 0]] + weights[edges_v[:, 1]])])
    edges_t, fine_faces_uv = split(uv, faces_uv)
    t = np.concatenate([uv, 0.5 * (uv[edges_t[:, 0]] + uv[edges_t[:, 1]])])
    return v, fine_faces.astype(np.int64), t, fine_faces_uv.astype(np.int64), w


def poses_from_world_matrices(world: np.ndarray, ibm: np.ndarray, parents=PARENTS):
    """Our (poses [J, 3], translation [3]) for glTF joint world matrices ``world`` [J, 4, 4].

    Our global rotation of joint j is rot(W_j · IBM_j); local θ_j = log(R_p(j)ᵀ R_j);
    t = translation(W_0 · IBM_0 · [J_0; 1]) − J_0.  Exact when the glTF pose is
    rigid per bone (as any pose of a joint hierarchy is).
    """
    from scipy.spatial.transform import Rotation

    skin = world @ ibm                                                   # [J, 4, 4]
    Rg = skin[:, :3, :3]
    poses = np.zeros((len(world), 3))
    for j in range(len(world)):
        p = parents[j]
        local = Rg[j] if p < 0 else Rg[p].T @ Rg[j]
        poses[j] = Rotation.from_matrix(local).as_rotvec()
    J0 = np.linalg.inv(ibm[0])[:3, 3]
    t = (skin[0] @ np.append(J0, 1.0))[:3] - J0
    return poses, t


def skin_gltf_reference(vertices, weights, world, ibm) -> np.ndarray:
    """glTF's own skinning, Σ_j w_j · W_j · IBM_j · [v; 1], for tests ([V, 3])."""
    skin = world @ ibm                                                   # [J, 4, 4]
    hom = np.concatenate([vertices, np.ones((len(vertices), 1))], 1)
    per_joint = np.einsum("jab,vb->vja", skin, hom)[..., :3]            # [V, J, 3]
    return np.einsum("vj,vja->va", weights, per_joint)
