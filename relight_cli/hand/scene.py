"""Posed hands in world space: what renderers, bakers and ray tracers consume."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .skinning import lbs, vertex_normals


@dataclass
class PosedMesh:
    """One hand of a scene, skinned and placed in the world.

    Attributes:
        vertices: [V, 3] float64 world metres (LBS-posed, root transform applied).
        faces: [F, 3] int64 (counter-clockwise from outside).
        uv: [T, 2] float64 in [0, 1]²; faces_uv: [F, 3] int64 into ``uv``.
        normals: [V, 3] float64 unit area-weighted vertex normals (never NaN).
        name: "right" / "left" (the HandInstance name).
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    faces_uv: np.ndarray
    normals: np.ndarray
    name: str


def model_for(hand, mirror: bool, mesh: str = "coarse"):
    """(rest vertices [V, 3], faces, faces_uv, rest joints [J, 3]) of the (mirrored) model."""
    m = hand.mesh(mesh)
    if not mirror:
        return m.vertices, m.faces, m.faces_uv, hand.rest_joints
    from .model import mirror_mesh
    v, f, fuv = mirror_mesh(m.vertices, m.faces, m.faces_uv)
    rest = np.asarray(hand.rest_joints, np.float64) * [-1.0, 1.0, 1.0]
    return v, f, fuv, rest


def posed_meshes(hand, frame: int = 0, mesh: str = "coarse") -> list[PosedMesh]:
    """Every hand of ``hand`` (HandData) at ``frame``, skinned, in world space.

    Args:
        hand: HandData.
        frame: frame index in [0, N).
        mesh: "coarse" (the proxy) or "fine".
    """
    if not 0 <= frame < hand.n_frames:
        raise IndexError(f"frame {frame} out of range [0, {hand.n_frames})")
    m = hand.mesh(mesh)
    out = []
    for inst in hand.hands:
        v, f, fuv, rest = model_for(hand, inst.mirror, mesh)
        posed = lbs(v, m.weights, rest, hand.parents, inst.poses[frame], inst.translations[frame])
        root = np.asarray(inst.root, np.float64)
        world = posed @ root[:3, :3].T + root[:3, 3]
        out.append(PosedMesh(world, np.asarray(f, np.int64), np.asarray(m.uv, np.float64),
                             np.asarray(fuv, np.int64), vertex_normals(world, f), inst.name))
    return out


def posed_joints_world(hand, frame: int = 0) -> list[np.ndarray]:
    """[J, 3] world joint positions of every hand at ``frame``."""
    from .skinning import posed_joints
    out = []
    for inst in hand.hands:
        rest = np.asarray(hand.rest_joints, np.float64)
        if inst.mirror:
            rest = rest * [-1.0, 1.0, 1.0]
        j = posed_joints(inst.poses[frame], inst.translations[frame], rest, hand.parents)
        root = np.asarray(inst.root, np.float64)
        out.append(j @ root[:3, :3].T + root[:3, 3])
    return out


def handedness(hand, inst=None):
    """"right" or "left": the handedness of one HandInstance of ``hand`` (the stored
    model's side, the other one for a mirrored instance); without ``inst``, the list over
    every hand of the scene."""
    if inst is None:
        return [handedness(hand, i) for i in hand.hands]
    side = hand.side if hand.side in ("right", "left") else "right"
    return side if not inst.mirror else ("left" if side == "right" else "right")


def two_hands(hand, separation: float = 0.20):
    """A copy of a one-hand HandData with the mirrored hand added beside it.

    The second hand mirrors the first one's poses and sits ``separation``
    metres away along x (towards the side its thumb does not point to), so
    the pair faces +Z like two hands held up side by side.
    """
    import copy

    from relight_cli.formats.hand_npz import HandInstance

    from .skinning import mirror_pose

    out = copy.deepcopy(hand)
    first = out.hands[0]
    other_side = "left" if hand.side == "right" else "right"
    root = np.eye(4)
    # The right model's thumb points to +x: put the left hand at −x, and vice versa.
    root[0, 3] = -separation / 2 if hand.side == "right" else separation / 2
    first.root = np.eye(4)
    first.root[0, 3] = -root[0, 3]
    out.hands.append(HandInstance(other_side, True, root, mirror_pose(first.poses),
                                  first.translations * [-1.0, 1.0, 1.0]))
    return out


def parse_builtin_hand(spec: str) -> tuple[str, str]:
    """``builtin:right|left|two[:POSE]`` → (which, pose), pose ``relaxed`` when not given;
    ValueError naming the choices for any other spec (the CLI's usage error)."""
    from .poses import POSE_NAMES
    parts = spec.split(":")[1:]
    which = parts[0] if parts else "right"
    pose = parts[1] if len(parts) > 1 else "relaxed"
    if which not in ("right", "left", "two") or len(parts) > 2 or pose not in POSE_NAMES:
        raise ValueError(f"unknown built-in hand {spec!r}; use builtin:right|left|two"
                         f"[:POSE] with POSE one of {', '.join(POSE_NAMES)}")
    return which, pose


def builtin_hands(spec: str):
    """The HandData a ``builtin:right|left|two[:POSE]`` spec names (:func:`parse_builtin_hand`;
    ``two``: the right hand and its mirror image, :func:`two_hands`)."""
    from .model import builtin_hand
    which, pose = parse_builtin_hand(spec)
    if which == "two":
        return two_hands(builtin_hand("right", pose))
    return builtin_hand(which, pose)


def preview_camera(meshes: list[PosedMesh], width: int = 256, height: int = 256,
                   direction=(0.25, 0.35, 1.0), fov_y_deg: float = 30.0):
    """An OpenCV Camera framing all ``meshes`` from ``direction`` (world, towards the camera)."""
    from relight_cli.formats.camera import Camera

    pts = np.concatenate([m.vertices for m in meshes])
    centre = 0.5 * (pts.min(0) + pts.max(0))
    radius = float(np.linalg.norm(pts - centre, axis=1).max())
    d = np.asarray(direction, np.float64)
    d /= np.linalg.norm(d)
    distance = radius / np.sin(np.radians(fov_y_deg) / 2) * 1.05
    return Camera.look_at(centre + distance * d, centre, fov_y_deg=fov_y_deg,
                          width=width, height=height)


def render_preview(meshes: list[PosedMesh], camera, albedo=(0.80, 0.55, 0.45),
                   background=(0.02, 0.02, 0.025)) -> np.ndarray:
    """[H, W, 3] float32 linear image: embree primary rays, Lambert shading with a headlight.

    Shading uses the interpolated vertex normal at the hit (flipped to face
    the camera); radiance = albedo · max(0, n·(−ray)) (a unit light at the eye).
    """
    from relight_cli.raytrace import RayScene

    H, W = camera.height, camera.width
    ys, xs = np.mgrid[0:H, 0:W]
    pix = np.stack([xs.ravel(), ys.ravel(), np.ones(H * W)], 1)   # pixel centres (camera.md)
    d_cam = pix @ np.linalg.inv(camera.K).T
    d_world = d_cam @ camera.R                                  # Rᵀ·d for each row
    d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
    origins = np.broadcast_to(camera.center, d_world.shape)
    scene = RayScene([(m.vertices, m.faces) for m in meshes])
    hits = scene.intersect(origins, d_world)
    image = np.tile(np.asarray(background, np.float32), (H * W, 1))
    ok = hits.hit
    if ok.any():
        normals = np.concatenate([m.normals for m in meshes])
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
        faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets)])
        tri = faces[hits.face[ok]]                               # [K, 3]
        n = np.einsum("kc,kcd->kd", hits.barycentric[ok].astype(np.float64), normals[tri])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        cosine = np.abs(np.einsum("kd,kd->k", n, d_world[ok]))
        image[ok] = (np.asarray(albedo)[None] * cosine[:, None]).astype(np.float32)
    return image.reshape(H, W, 3)
