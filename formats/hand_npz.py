"""Articulated hands: ``hand.npz`` (spec: ``formats/hand_npz.md``).

One skinned hand model (joints, coarse proxy and fine mesh sharing one UV map,
LBS weights) plus the per-frame poses of every hand in the scene (one or two;
a second hand uses the mirrored model and its own root transform).

This module only reads, validates and writes plain arrays; posing lives in
``relight_cli.hand.skinning`` and ``relight_cli.hand.scene``.
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass, field

import numpy as np

from relight_cli.errors import DataError

FORMAT = "relight/hand"
VERSION = 1

# Weight rows must sum to 1; float32 round-off in other tools' exports is ~1e-6.
_WEIGHT_SUM_TOL = 1e-4
# UVs must lie in [0, 1]²; allow float32 round-off at the border.
_UV_TOL = 1e-6
# Plausibility of a hand in metres: coordinates within 1 km of the origin (beyond,
# float64 products overflow or lose the millimetres), a mesh at least 1 mm across,
# and at most half of its faces of zero area (a collapsed mesh casts no shadows).
_MAX_COORD = 1000.0
_MIN_EXTENT = 1e-3
_ZERO_AREA = 1e-14  # m², far below any real triangle (a 0.1 µm² sliver)


@dataclass
class HandMesh:
    """One tessellation of the hand in the rest pose (model space).

    Attributes:
        vertices: [V, 3] float64, metres, rest pose, model space.
        faces: [F, 3] int64 indices into ``vertices`` (counter-clockwise seen from outside).
        uv: [T, 2] float64 in [0, 1]², v = 0 at the bottom image row.
        faces_uv: [F, 3] int64 indices into ``uv`` (a vertex on a UV seam has several UVs).
        weights: [V, J] float64 LBS weights, rows ≥ 0 summing to 1.
        labels: [V] uint8 region label (index into HandData.label_names), or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    faces_uv: np.ndarray
    weights: np.ndarray
    labels: np.ndarray | None = None


@dataclass
class HandInstance:
    """One hand in the scene.

    Attributes:
        name: "right" or "left" (or any label).
        mirror: True if this hand uses the model mirrored across its x = 0 plane
            (x → −x, face winding flipped), e.g. a left hand from a right model.
        root: [4, 4] float64 rigid world-from-hand transform applied after skinning.
        poses: [N, J, 3] float64 local axis-angle rotations (radians) per frame,
            in the (possibly mirrored) model's rest frame; joint 0 is the wrist/global rotation.
        translations: [N, 3] float64 metres per frame (model space, before ``root``).
    """

    name: str
    mirror: bool
    root: np.ndarray
    poses: np.ndarray
    translations: np.ndarray


@dataclass
class HandData:
    """A skinned hand model and the poses of each hand in the scene.

    Attributes:
        joint_names: J names (the 25-joint WebXR set for built-in and glTF hands).
        parents: [J] int64 parent index, −1 for the root (joint 0); parents[j] < j.
        rest_joints: [J, 3] float64 metres, rest pose, model space.
        coarse: the proxy mesh (≈3k vertices) used for visibility and features.
        fine: the dense mesh (a UV-preserving subdivision of ``coarse``).
        side: handedness of the stored model, "right" or "left".
        hands: one HandInstance per hand in the scene (≥ 1, same frame count N).
        label_names: names of the region labels of ``HandMesh.labels``.
        bone_scales: [J] float64 personalization already baked into rest_joints/vertices
            (scale of the offset joint − parent; 1 for the root), for information.
        inverse_bind_matrices: [J, 4, 4] float64 from an imported glTF skin, or None.
        mean_texture: [3, N, N] float32 the subject's mean texture T̄ in sr⁻¹ (URHand
            Sec. 4: what ``relight --model linear`` conditions on; ``relight
            personalize`` writes it), in the fine mesh's UV layout, or None.
    """

    joint_names: list[str]
    parents: np.ndarray
    rest_joints: np.ndarray
    coarse: HandMesh
    fine: HandMesh
    side: str = "right"
    hands: list[HandInstance] = field(default_factory=list)
    label_names: list[str] = field(default_factory=list)
    bone_scales: np.ndarray | None = None
    inverse_bind_matrices: np.ndarray | None = None
    mean_texture: np.ndarray | None = None

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_frames(self) -> int:
        return int(self.hands[0].poses.shape[0]) if self.hands else 0

    @property
    def poses(self) -> np.ndarray:
        """[N, J, 3] poses of the first hand."""
        return self.hands[0].poses

    @poses.setter
    def poses(self, value):
        self.hands[0].poses = np.asarray(value, np.float64)

    @property
    def translations(self) -> np.ndarray:
        """[N, 3] translations of the first hand."""
        return self.hands[0].translations

    @translations.setter
    def translations(self, value):
        self.hands[0].translations = np.asarray(value, np.float64)

    def mesh(self, which: str) -> HandMesh:
        if which not in ("coarse", "fine"):
            raise ValueError(f"mesh must be 'coarse' or 'fine', got {which!r}")
        return self.coarse if which == "coarse" else self.fine


# ----------------------------------------------------------------------------- writing

def to_arrays(hand: HandData, provenance: dict | None = None) -> dict[str, np.ndarray]:
    """The npz key → array mapping of ``hand`` (validated first)."""
    validate(hand, "<in memory>")
    out: dict[str, np.ndarray] = {
        "format": np.array(FORMAT),
        "version": np.array(VERSION, np.int64),
        "provenance": np.array(json.dumps(provenance or {}, sort_keys=True)),
        "joint_names": np.array(list(hand.joint_names), dtype=str),
        "parents": np.asarray(hand.parents, np.int64),
        "rest_joints": np.asarray(hand.rest_joints, np.float64),
        "side": np.array(hand.side),
        "bone_scales": (np.ones(hand.n_joints) if hand.bone_scales is None
                        else np.asarray(hand.bone_scales, np.float64)),
    }
    for prefix, m in (("coarse_", hand.coarse), ("fine_", hand.fine)):
        out[prefix + "vertices"] = np.asarray(m.vertices, np.float64)
        out[prefix + "faces"] = np.asarray(m.faces, np.int64)
        out[prefix + "uv"] = np.asarray(m.uv, np.float64)
        out[prefix + "faces_uv"] = np.asarray(m.faces_uv, np.int64)
        out[prefix + "weights"] = np.asarray(m.weights, np.float64)
        if m.labels is not None:
            out[prefix + "labels"] = np.asarray(m.labels, np.uint8)
    if hand.label_names:
        out["label_names"] = np.array(list(hand.label_names), dtype=str)
    h0 = hand.hands[0]
    out["poses"] = np.asarray(h0.poses, np.float64)
    out["translations"] = np.asarray(h0.translations, np.float64)
    out["hand_names"] = np.array([h.name for h in hand.hands], dtype=str)
    out["hand_mirror"] = np.array([bool(h.mirror) for h in hand.hands], bool)
    out["hand_roots"] = np.stack([np.asarray(h.root, np.float64) for h in hand.hands])
    if len(hand.hands) > 1:
        out["other_poses"] = np.stack([np.asarray(h.poses, np.float64) for h in hand.hands[1:]])
        out["other_translations"] = np.stack([np.asarray(h.translations, np.float64)
                                              for h in hand.hands[1:]])
    if hand.inverse_bind_matrices is not None:
        out["inverse_bind_matrices"] = np.asarray(hand.inverse_bind_matrices, np.float64)
    if hand.mean_texture is not None:
        out["mean_texture"] = np.asarray(hand.mean_texture, np.float32)
    return out


def write_hand(path: str, hand: HandData, provenance: dict | None = None) -> None:
    """Validate ``hand`` and write it to ``path`` atomically (compressed npz, no pickles)."""
    from relight_cli.fileio import atomic_path

    from ._common import save_npz

    arrays = to_arrays(hand, provenance)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            save_npz(f, arrays)


# ----------------------------------------------------------------------------- reading

def read_hand(path: str) -> HandData:
    """Read and validate a ``hand.npz``; any problem raises DataError naming the file."""
    if not os.path.exists(path):
        raise DataError("no such file", path)
    if os.path.isdir(path):
        raise DataError("is a directory, expected a hand .npz", path)
    try:
        with open(path, "rb") as f:
            blob = f.read()
        if not blob.startswith(b"PK"):
            raise DataError("not a readable npz file (no zip header)", path)
        with np.load(io.BytesIO(blob), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except DataError:
        raise
    except ValueError as exc:
        raise DataError(f"npz holds pickled objects, which are never loaded: {exc}", path) from None
    except (OSError, EOFError) as exc:
        raise DataError(f"not a readable npz file: {exc}", path) from None
    except Exception as exc:  # zipfile.BadZipFile and friends
        raise DataError(f"not a readable npz file: {type(exc).__name__}: {exc}", path) from None
    return from_arrays(arrays, path)


def read_provenance(path: str) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return json.loads(str(z["provenance"])) if "provenance" in z.files else {}


def _get(arrays, key, path, required=True):
    if key not in arrays:
        if required:
            raise DataError(f"missing array '{key}'", path)
        return None
    return arrays[key]


def _float(arrays, key, path, shape, required=True):
    a = _get(arrays, key, path, required)
    if a is None:
        return None
    if a.dtype.kind not in "fiu":
        raise DataError(f"'{key}' must be numeric, got dtype {a.dtype}", path)
    if len(a.shape) != len(shape) or any(s is not None and s != t for s, t in zip(shape, a.shape)):
        want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
        raise DataError(f"'{key}' has shape {a.shape}, expected {want}", path)
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise DataError(f"'{key}' holds NaN or Inf", path)
    return a


def _bounded(a, key, path):
    """``a`` (metres) if every coordinate lies within _MAX_COORD of the origin."""
    if a is not None and a.size and np.abs(a).max() > _MAX_COORD:
        raise DataError(f"'{key}' has coordinates beyond {_MAX_COORD:g} m (largest "
                        f"{np.abs(a).max():.3g}); a hand is metres across, in metres", path)
    return a


def _check_geometry(vertices, faces, prefix, path):
    """Refuse meshes that read but would give plausible-looking wrong results:
    absurd coordinates, all vertices collapsed, (mostly) zero-area faces."""
    _bounded(vertices, prefix + "vertices", path)
    extent = float((vertices.max(0) - vertices.min(0)).max())
    if extent < _MIN_EXTENT:
        raise DataError(f"'{prefix}vertices' span only {extent:.3g} m (collapsed mesh; a hand "
                        f"is about 0.2 m)", path)
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    degenerate = int((area <= _ZERO_AREA).sum())
    if degenerate * 2 > len(faces):
        raise DataError(f"{degenerate} of {len(faces)} '{prefix}faces' have zero area "
                        f"(degenerate mesh)", path)


def _index(arrays, key, path, n_rows, limit, what):
    a = _get(arrays, key, path)
    if a.dtype.kind not in "iu":
        raise DataError(f"'{key}' must be an integer array, got dtype {a.dtype}", path)
    if a.ndim != 2 or a.shape[1] != 3 or (n_rows is not None and a.shape[0] != n_rows):
        want = f"({n_rows if n_rows is not None else '?'}, 3)"
        raise DataError(f"'{key}' has shape {a.shape}, expected {want}", path)
    if a.size and (a.min() < 0 or a.max() >= limit):
        raise DataError(f"'{key}' indexes {what} out of range [0, {limit})", path)
    return a.astype(np.int64)


def _strings(arrays, key, path, required=True):
    a = _get(arrays, key, path, required)
    if a is None:
        return None
    if a.dtype.kind != "U":
        raise DataError(f"'{key}' must be a string array, got dtype {a.dtype}", path)
    return a


def from_arrays(arrays: dict, path: str = "<in memory>") -> HandData:
    """Build a validated HandData from the npz key → array mapping."""
    fmt = _strings(arrays, "format", path)
    if fmt.shape != () or str(fmt) != FORMAT:
        raise DataError(f"not a {FORMAT} file (format is {fmt!r})", path)
    version = _get(arrays, "version", path)
    if version.shape != () or version.dtype.kind not in "iu":
        raise DataError("'version' must be an integer scalar", path)
    if int(version) != VERSION:
        raise DataError(f"unsupported {FORMAT} version {int(version)} (this tool reads "
                        f"version {VERSION}); upgrade relight", path)
    names = _strings(arrays, "joint_names", path)
    if names.ndim != 1 or len(names) < 1:
        raise DataError(f"'joint_names' must be a non-empty 1-D array, got shape {names.shape}", path)
    J = len(names)
    parents = _get(arrays, "parents", path)
    if parents.dtype.kind not in "iu" or parents.shape != (J,):
        raise DataError(f"'parents' must be ({J},) integers, got {parents.shape} {parents.dtype}", path)
    parents = parents.astype(np.int64)
    if parents[0] != -1:
        raise DataError("'parents[0]' must be -1 (joint 0 is the root)", path)
    bad = [j for j in range(1, J) if not 0 <= parents[j] < j]
    if bad:
        raise DataError(f"'parents' must list each joint after its parent; joint {bad[0]} "
                        f"has parent {parents[bad[0]]}", path)
    rest = _bounded(_float(arrays, "rest_joints", path, (J, 3)), "rest_joints", path)
    side = _strings(arrays, "side", path, required=False)
    side = "right" if side is None else str(side)
    if side not in ("right", "left"):
        raise DataError(f"'side' must be 'right' or 'left', got {side!r}", path)
    label_names = _strings(arrays, "label_names", path, required=False)
    label_names = [] if label_names is None else [str(s) for s in label_names]
    meshes = {}
    for prefix in ("coarse_", "fine_"):
        v = _float(arrays, prefix + "vertices", path, (None, 3))
        if len(v) < 4:
            raise DataError(f"'{prefix}vertices' has {len(v)} vertices; a mesh needs at least 4",
                            path)
        uv = _float(arrays, prefix + "uv", path, (None, 2))
        if uv.size and (uv.min() < -_UV_TOL or uv.max() > 1 + _UV_TOL):
            raise DataError(f"'{prefix}uv' has coordinates outside [0, 1]", path)
        faces = _index(arrays, prefix + "faces", path, None, len(v), "vertices")
        if len(faces) == 0:
            raise DataError(f"'{prefix}faces' is empty", path)
        _check_geometry(v, faces, prefix, path)
        faces_uv = _index(arrays, prefix + "faces_uv", path, len(faces), len(uv), "uv")
        w = _float(arrays, prefix + "weights", path, (len(v), J))
        if w.min() < 0:
            raise DataError(f"'{prefix}weights' has negative entries", path)
        sums = w.sum(1)
        worst = int(np.argmax(np.abs(sums - 1)))
        if abs(sums[worst] - 1) > _WEIGHT_SUM_TOL:
            raise DataError(f"'{prefix}weights' row {worst} sums to {sums[worst]:.6g}, not 1", path)
        labels = arrays.get(prefix + "labels")
        if labels is not None:
            if labels.dtype.kind not in "iu" or labels.shape != (len(v),):
                raise DataError(f"'{prefix}labels' must be ({len(v)},) integers", path)
            if labels.size and labels.max() >= max(1, len(label_names)):
                raise DataError(f"'{prefix}labels' exceeds the {len(label_names)} label_names", path)
            labels = labels.astype(np.uint8)
        meshes[prefix] = HandMesh(v, faces, uv, faces_uv, w, labels)
    poses = _float(arrays, "poses", path, (None, J, 3))
    N = len(poses)
    if N < 1:
        raise DataError("'poses' holds no frames", path)
    trans = _bounded(_float(arrays, "translations", path, (N, 3)), "translations", path)
    hand_names = _strings(arrays, "hand_names", path, required=False)
    H = 1 if hand_names is None else len(hand_names)
    if hand_names is not None and (hand_names.ndim != 1 or H < 1):
        raise DataError("'hand_names' must be a non-empty 1-D string array", path)
    if hand_names is None:
        hand_names = np.array([side])
    mirror = arrays.get("hand_mirror", np.zeros(H, bool))
    if mirror.dtype != bool or mirror.shape != (H,):
        raise DataError(f"'hand_mirror' must be ({H},) bool", path)
    roots = _float(arrays, "hand_roots", path, (H, 4, 4), required=False)
    if roots is None:
        roots = np.broadcast_to(np.eye(4), (H, 4, 4)).copy()
    for h in range(H):
        R = roots[h, :3, :3]
        if (np.abs(roots[h, 3] - [0, 0, 0, 1]).max() > 1e-9
                or np.abs(R @ R.T - np.eye(3)).max() > 1e-5 or abs(np.linalg.det(R) - 1) > 1e-5):
            raise DataError(f"'hand_roots[{h}]' is not a rigid transform (rotation + translation)",
                            path)
    hands = [HandInstance(str(hand_names[0]), bool(mirror[0]), roots[0], poses, trans)]
    if H > 1:
        other_p = _float(arrays, "other_poses", path, (H - 1, N, J, 3))
        other_t = _bounded(_float(arrays, "other_translations", path, (H - 1, N, 3)),
                           "other_translations", path)
        for h in range(1, H):
            hands.append(HandInstance(str(hand_names[h]), bool(mirror[h]), roots[h],
                                      other_p[h - 1], other_t[h - 1]))
    scales = _float(arrays, "bone_scales", path, (J,), required=False)
    if scales is not None and scales.min() <= 0:
        raise DataError("'bone_scales' must be positive", path)
    ibm = _float(arrays, "inverse_bind_matrices", path, (J, 4, 4), required=False)
    return HandData(joint_names=[str(s) for s in names], parents=parents, rest_joints=rest,
                    coarse=meshes["coarse_"], fine=meshes["fine_"], side=side, hands=hands,
                    label_names=label_names, bone_scales=scales, inverse_bind_matrices=ibm,
                    mean_texture=_mean_texture(arrays, path))


#: Side of a stored mean texture: a power of two from 4 to 4096 texels.
MEAN_TEXTURE_SIZES = tuple(2**k for k in range(2, 13))


def _mean_texture(arrays, path):
    """The optional ``mean_texture`` [3, N, N] (float32, finite, ≥ 0, N a power of two in
    4 … 4096), or None."""
    t = _float(arrays, "mean_texture", path, (3, None, None), required=False)
    if t is None:
        return None
    if t.shape[1] != t.shape[2] or t.shape[1] not in MEAN_TEXTURE_SIZES:
        raise DataError(f"'mean_texture' must be (3, N, N) with N a power of two in 4 … 4096, "
                        f"got {t.shape}", path)
    if t.min() < 0 or t.max() > 1e6:
        raise DataError(f"'mean_texture' values must lie in [0, 1e6] sr⁻¹ (found "
                        f"{t.min():.3g} … {t.max():.3g})", path)
    return t.astype(np.float32)


def validate(hand: HandData, path: str = "<in memory>") -> None:
    """Raise DataError if ``hand`` would not survive a write/read round trip."""
    if not hand.hands:
        raise DataError("a hand file needs at least one hand instance", path)
    arrays = {
        "format": np.array(FORMAT), "version": np.array(VERSION, np.int64),
        "joint_names": np.array(list(hand.joint_names), dtype=str),
        "parents": np.asarray(hand.parents), "rest_joints": np.asarray(hand.rest_joints),
        "side": np.array(hand.side),
        "poses": np.asarray(hand.hands[0].poses), "translations": np.asarray(hand.hands[0].translations),
        "hand_names": np.array([h.name for h in hand.hands], dtype=str),
        "hand_mirror": np.array([bool(h.mirror) for h in hand.hands], bool),
        "hand_roots": np.stack([np.asarray(h.root, np.float64) for h in hand.hands]),
    }
    if len({np.shape(h.poses)[0] for h in hand.hands}) > 1:
        raise DataError("all hands must have the same number of frames", path)
    if len(hand.hands) > 1:
        try:
            arrays["other_poses"] = np.stack([np.asarray(h.poses) for h in hand.hands[1:]])
            arrays["other_translations"] = np.stack([np.asarray(h.translations)
                                                     for h in hand.hands[1:]])
        except ValueError:
            raise DataError("all hands must have the same number of frames", path) from None
    if hand.label_names:
        arrays["label_names"] = np.array(list(hand.label_names), dtype=str)
    for prefix, m in (("coarse_", hand.coarse), ("fine_", hand.fine)):
        arrays[prefix + "vertices"] = np.asarray(m.vertices)
        arrays[prefix + "faces"] = np.asarray(m.faces)
        arrays[prefix + "uv"] = np.asarray(m.uv)
        arrays[prefix + "faces_uv"] = np.asarray(m.faces_uv)
        arrays[prefix + "weights"] = np.asarray(m.weights)
        if m.labels is not None:
            arrays[prefix + "labels"] = np.asarray(m.labels)
    if hand.bone_scales is not None:
        arrays["bone_scales"] = np.asarray(hand.bone_scales)
    if hand.inverse_bind_matrices is not None:
        arrays["inverse_bind_matrices"] = np.asarray(hand.inverse_bind_matrices)
    if hand.mean_texture is not None:
        arrays["mean_texture"] = np.asarray(hand.mean_texture)
    from_arrays(arrays, path)
