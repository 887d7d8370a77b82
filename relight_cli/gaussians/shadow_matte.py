"""The shadow protocol of the DGSM paper (Sec. 4.2): shadow mattes and the avatar-centric ROI.

* Shadow map in Gaussian space, S(p): a receivers-only pass — every scene
  Gaussian's colour is replaced by its shadow strength 1 − V̄, V̄ the
  light-weighted transmittance of :func:`relight_cli.gaussians.transfer.shadow_factor`
  (strength 1: the whole colour is direct light), and only the receivers are
  splatted (the avatar itself is not drawn), so the image accumulates only
  shadow strength.
* Pseudo ground truth, S†(p): the same object as a triangle mesh, hard shadow
  rays (embree) from each receiver centre to each light onto the same
  receivers — the paper's "white receiver" pass: V̄ from binary visibility with
  the same light weights, splatted identically.  Both passes share the
  receivers, lights, weights and camera, so they differ only in the occluder
  model (Gaussian transmittance vs mesh visibility).
* Avatar-centric ROI: the image box of the paper's receiver region
  B = {x : ‖(x − c)_xz‖∞ ≤ R, y_lo ≤ x_y ≤ y_hi} (Sec. 3.2; +Y up here), c the
  avatar's alpha-weighted centroid and [y_lo, y_hi] its robust height range
  extended down to the floor — computed from the avatar, not passed by hand.

Matte values are luminance-weighted (Rec. 709) over the per-channel factors.
"""

from __future__ import annotations

import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722])


def shadow_strength(factor: np.ndarray) -> np.ndarray:
    """[M] 1 − luminance of the per-receiver shading factor ([M] or [M, 3], from shadow_factor)."""
    f = np.asarray(factor, np.float64)
    lum = f if f.ndim == 1 else f @ LUMA
    return np.clip(1.0 - lum, 0.0, 1.0)


def mesh_visibility(meshes, lights, points, offset: float = 1e-5) -> np.ndarray:
    """[L, M] float 1 where the segment receiver → light is free of the triangle meshes.

    Args:
        meshes: list of (vertices [V, 3], faces [F, 3]) in world space, metres.
        lights: [L, 3] positions; points: [M, 3] receiver centres.
        offset: the segment starts this far (metres) towards the light (self-hits).
    """
    from relight_cli.raytrace import RayScene

    scene = RayScene(meshes)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.empty((len(lights), len(points)))
    for i, light in enumerate(np.asarray(lights, np.float64).reshape(-1, 3)):
        v = light - points
        dist = np.linalg.norm(v, axis=1)
        d = v / np.where(dist > 0, dist, 1)[:, None]
        hit = scene.occluded(points + offset * d, d, np.maximum(dist - offset, 0.0))
        out[i] = np.where(hit, 0.0, 1.0)
    return out


def matte_colors(strength: np.ndarray) -> np.ndarray:
    """[M, 3] grey colours = shadow strength, for ``splat.render(colors=...)``."""
    s = np.asarray(strength, np.float64).reshape(-1, 1)
    return np.repeat(s, 3, axis=1)


def avatar_roi(avatar, camera, radius: float = 1.0, floor: float | None = None,
               margin: int = 0) -> tuple[int, int, int, int] | None:
    """Pixel box (X, Y, W, H) of the avatar-centric region B seen by ``camera`` (module doc).

    Args:
        avatar: the avatar Gaussians (world frame).
        camera: formats.camera.Camera.
        radius: R, metres (horizontal half-size of B around the centroid).
        floor: lowest height of B (default: the avatar's 1st-percentile height
            minus 5 cm — the ground it stands on).
        margin: pixels added on each side.
    Returns:
        The box clipped to the image, or None when B lies entirely off-screen
        or behind the camera.
    """
    w = np.asarray(avatar.opacities, np.float64)
    means = np.asarray(avatar.means, np.float64)
    c = (w[:, None] * means).sum(0) / max(w.sum(), 1e-300)
    lo = float(np.percentile(means[:, 1], 1)) - 0.05 if floor is None else float(floor)
    hi = float(np.percentile(means[:, 1], 99))
    xs = (c[0] - radius, c[0] + radius)
    zs = (c[2] - radius, c[2] + radius)
    corners = np.array([[x, y, z] for x in xs for y in (lo, hi) for z in zs])
    # sample the box's faces densely enough that clipping at the near plane is honest
    t = np.linspace(0, 1, 9)
    gx, gy, gz = np.meshgrid(t, t, t, indexing="ij")
    pts = corners.min(0) + np.stack([gx, gy, gz], -1).reshape(-1, 3) * (corners.max(0) - corners.min(0))
    p = pts @ camera.R.T + camera.t
    front = p[:, 2] > 1e-6
    if not front.any():
        return None
    uv = (p[front] @ camera.K.T)
    uv = uv[:, :2] / uv[:, 2:3]
    x0, y0 = np.floor(uv.min(0)).astype(int) - margin
    x1, y1 = np.ceil(uv.max(0)).astype(int) + margin
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, camera.width), min(y1, camera.height)
    if x1 <= x0 or y1 <= y0:
        return None
    return int(x0), int(y0), int(x1 - x0), int(y1 - y0)


def load_placed_mesh(source: str, placement, gaussians_before=None):
    """(vertices [V, 3], faces [F, 3]) of a mesh IN placed exactly as its Gaussians are.

    ``source`` is a mesh file (.obj .glb .gltf .stl .off), a hand .npz (its posed fine
    meshes at the placement's frame) or builtin:hand|sphere;
    the placement's similarity is resolved on the mesh's own Gaussians (fit and
    on-floor read their robust box), so mesh and Gaussians coincide.  Raises
    ValueError for inputs that have no mesh (a 3DGS PLY, builtin:room).
    """
    from .from_mesh import MESH_SUFFIXES, load_gaussians
    from .placement import resolve

    if source == "builtin:hand":
        from relight_cli.hand.model import builtin_hand
        from relight_cli.hand.scene import posed_meshes
        pm = posed_meshes(builtin_hand(), 0, "fine")[0]
        v, f = np.asarray(pm.vertices, np.float64), np.asarray(pm.faces)
    elif source == "builtin:sphere":
        import trimesh
        s = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
        v, f = np.asarray(s.vertices, np.float64), np.asarray(s.faces)
    elif source.lower().endswith(".npz"):
        from relight_cli.formats.hand_npz import read_hand
        from relight_cli.hand.scene import posed_meshes
        hand = read_hand(source)
        frame = 0 if getattr(placement, "frame", None) is None else placement.frame
        if not 0 <= frame < hand.n_frames:
            raise ValueError(f"frame {frame} is out of range: the hand has {hand.n_frames} "
                             f"frame(s)")
        pms = posed_meshes(hand, frame, "fine")
        offsets = np.cumsum([0] + [len(pm.vertices) for pm in pms[:-1]])
        v = np.concatenate([pm.vertices for pm in pms]).astype(np.float64)
        f = np.concatenate([pm.faces + o for pm, o in zip(pms, offsets)])
    elif source.lower().endswith(MESH_SUFFIXES):
        import trimesh
        m = trimesh.load(source, force="mesh", process=False)
        v, f = np.asarray(m.vertices, np.float64), np.asarray(m.faces)
    else:
        raise ValueError("the mesh pseudo-ground truth needs a triangle mesh (.obj .glb .gltf "
                         ".stl .off or builtin:hand|sphere), not Gaussians")
    if placement is None or placement.is_identity():
        return v, f
    g = (gaussians_before if gaussians_before is not None
         else load_gaussians(source, frame=getattr(placement, "frame", None)))
    return resolve(placement, g).apply(v), f
