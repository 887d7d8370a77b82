"""G-buffers: what an OpenCV camera sees of posed meshes, by embree primary rays.

Every pixel is covered by S = ``aa``² stratified sub-pixel samples (an aa×aa grid
of sub-cells, sample at each sub-cell's centre, or jittered inside it with a
seeded generator).  For every sample the closest hit gives the hand (mesh) id,
the face, barycentrics, and from them the UV, world position, shading normal
and camera depth.  Shading works per sample; :meth:`GBuffer.resolve` averages
the samples of a pixel (box filter), which is the antialiasing.

Camera convention (formats/camera.md): x_cam = R·x_world + t, pixel = K·x_cam/z,
x right, y down, z forward; as in OpenCV the centre of pixel (col, row) is at
(col, row), so the pixel covers [col − ½, col + ½) × [row − ½, row + ½).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class GBuffer:
    """Per-sample surface attributes of one camera view.

    P = height · width · spp samples, pixel-major (sample s of pixel (row, col)
    is index (row·width + col)·spp + s).

    Attributes:
        width, height: image size in pixels.  spp: samples per pixel.
        hand: [P] int64 mesh index hit (−1: background).
        face: [P] int64 face index within that mesh (−1: background).
        barycentric: [P, 3] float64 weights of the face's corners (0 for background).
        uv: [P, 2] float64 texture coordinates (v = 0 at the bottom row).
        position: [P, 3] float64 world metres (0 for background).
        normal: [P, 3] float64 unit shading normal, world (interpolated vertex normals).
        depth: [P] float64 camera-space z, metres (inf for background).
        view: [P, 3] float64 unit direction from the surface towards the camera centre.
        eye: [3] float64 camera centre, world.
        layouts: per mesh its :class:`~relight_cli.uvraster.UVLayout` (None: unknown, and
            texture lookups are plain bilinear).
    """

    width: int
    height: int
    spp: int
    hand: np.ndarray
    face: np.ndarray
    barycentric: np.ndarray
    uv: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    depth: np.ndarray
    view: np.ndarray
    eye: np.ndarray
    layouts: list | None = None
    _taps: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def hit(self) -> np.ndarray:
        """[P] bool: the sample sees a hand."""
        return self.hand >= 0

    @property
    def mask(self) -> np.ndarray:
        """[H, W] float32 coverage: fraction of a pixel's samples that see a hand."""
        return self.hit.reshape(self.height, self.width, self.spp).mean(-1).astype(np.float32)

    def coverage(self, hand: int) -> np.ndarray:
        """[H, W] float32: fraction of a pixel's samples that see hand ``hand`` (the
        per-hand masks sum to :attr:`mask`)."""
        return ((self.hand == hand).reshape(self.height, self.width, self.spp).mean(-1)
                .astype(np.float32))

    def taps(self, hand: int, height: int, width: int):
        """``(samples, rows, cols, weights)``: the samples [S] that see hand ``hand`` and
        the four texels and weights [S, 4] each reads of that hand's H×W UV map — the
        seam-aware bilinear lookup (:func:`relight_cli.uvraster.seam_taps`: taps outside
        the sample's UV chart dropped), plain bilinear without :attr:`layouts`.  Cached
        per (hand, size): a G-buffer reused across training steps computes them once."""
        from relight_cli.uvraster import bilinear_taps
        key = (int(hand), int(height), int(width))
        if key not in self._taps:
            samples = np.nonzero(self.hand == hand)[0]
            uv = self.uv[samples]
            if self.layouts is not None and hand < len(self.layouts) and \
                    self.layouts[hand] is not None:
                taps = self.layouts[hand].taps(uv, self.face[samples], height, width)
            else:
                taps = bilinear_taps(uv, height, width)
            self._taps[key] = (samples, *taps)
        return self._taps[key]

    def lookup(self, image: np.ndarray, hand: int) -> np.ndarray:
        """Hand ``hand``'s UV map ``image`` [N, N(, C)] read at its samples (:meth:`taps`):
        [S(, C)] float64, in the order of ``np.nonzero(self.hand == hand)``."""
        from relight_cli.uvraster import gather_taps
        image = np.asarray(image)
        _, rows, cols, weights = self.taps(hand, image.shape[0], image.shape[1])
        return gather_taps(image, (rows, cols, weights))

    def resolve(self, values: np.ndarray, background=0.0) -> np.ndarray:
        """Box-filter per-sample values [P, C] (or [P]) to pixels [H, W, C] (or [H, W]).

        Background samples take ``background`` (scalar or [C]).
        """
        values = np.asarray(values)
        squeeze = values.ndim == 1
        v = values.reshape(len(values), -1).astype(np.float64)
        v = np.where(self.hit[:, None], v, np.broadcast_to(np.asarray(background, np.float64),
                                                             (1, v.shape[1])))
        out = v.reshape(self.height, self.width, self.spp, -1).mean(2)
        return out[..., 0] if squeeze else out

    def average_hits(self, values: np.ndarray) -> np.ndarray:
        """Mean over the samples that hit (AOVs such as normal, UV, depth); 0 where none do."""
        values = np.asarray(values, np.float64)
        squeeze = values.ndim == 1
        v = values.reshape(len(values), -1) * self.hit[:, None]
        count = self.hit.reshape(self.height, self.width, self.spp).sum(-1)[..., None]
        total = v.reshape(self.height, self.width, self.spp, -1).sum(2)
        out = np.divide(total, count, out=np.zeros_like(total), where=count > 0)
        return out[..., 0] if squeeze else out


def sample_offsets(aa: int, jitter: bool = False, seed: int = 0,
                   n_pixels: int = 1) -> np.ndarray:
    """Sub-pixel sample positions in [0, 1)², [n_pixels, aa², 2] (x, y).

    Stratified: the pixel is split into aa×aa equal cells with one sample per
    cell, at its centre (deterministic) or uniformly inside it (``jitter``, seeded).
    """
    if aa < 1:
        raise ValueError(f"aa must be ≥ 1, got {aa}")
    cells = (np.stack(np.meshgrid(np.arange(aa), np.arange(aa), indexing="xy"), -1)
             .reshape(-1, 2).astype(np.float64))                       # [S, 2] (x, y)
    if not jitter:
        return np.broadcast_to((cells + 0.5) / aa, (n_pixels, aa * aa, 2))
    rng = np.random.default_rng(seed)
    return (cells[None] + rng.random((n_pixels, aa * aa, 2))) / aa


def camera_rays(camera, aa: int = 2, jitter: bool = False, seed: int = 0):
    """World rays of every sample: (origins [P, 3], unit directions [P, 3]), pixel-major."""
    H, W = camera.height, camera.width
    offsets = sample_offsets(aa, jitter, seed, H * W)                      # [HW, S, 2]
    ys, xs = np.mgrid[0:H, 0:W]
    px = xs.reshape(-1, 1) + (offsets[..., 0] - 0.5)    # [HW, S]; pixel centres at integers
    py = ys.reshape(-1, 1) + (offsets[..., 1] - 0.5)
    K = np.asarray(camera.K, np.float64)
    R = np.asarray(camera.R, np.float64)
    # Camera-space direction (x, y, 1) = K⁻¹·(px, py, 1), then world = Rᵀ·d.  Written as
    # column arithmetic: a BLAS call on [P, 3] × [3, 3] is slower than this (and
    # oversubscribes threads on a shared machine).
    y_cam = (py.ravel() - K[1, 2]) / K[1, 1]
    x_cam = (px.ravel() - K[0, 2] - K[0, 1] * y_cam) / K[0, 0]
    d_world = x_cam[:, None] * R[0] + y_cam[:, None] * R[1] + R[2]
    d_world /= np.sqrt(np.sum(d_world * d_world, axis=1, keepdims=True))
    origins = np.broadcast_to(np.asarray(camera.center, np.float64), d_world.shape)
    return origins, d_world


def render_gbuffer(meshes, camera, aa: int = 2, jitter: bool = False, seed: int = 0,
                   scene=None) -> GBuffer:
    """The G-buffer of ``meshes`` seen by ``camera``.

    Args:
        meshes: posed meshes (``relight_cli.hand.scene.PosedMesh``: vertices, faces, uv,
            faces_uv, normals), world space.
        camera: ``relight_cli.formats.camera.Camera`` (OpenCV).
        aa: sub-pixel grid size (spp = aa²).
        jitter: jitter samples inside their cells (seeded by ``seed``).
        scene: a prebuilt :class:`relight_cli.raytrace.RayScene` of the same meshes.
    """
    from relight_cli.raytrace import RayScene

    if scene is None:
        scene = RayScene([(m.vertices, m.faces) for m in meshes])
    origins, dirs = camera_rays(camera, aa, jitter, seed)
    hits = scene.intersect(origins, dirs)
    n = len(dirs)
    hand = np.where(hits.hit, hits.mesh, -1)
    offsets = np.asarray(scene.face_offsets, np.int64)
    face = np.where(hits.hit, hits.face - offsets[np.maximum(hand, 0)], -1)
    bary = np.zeros((n, 3))
    uv = np.zeros((n, 2))
    position = np.zeros((n, 3))
    normal = np.zeros((n, 3))
    for k, mesh in enumerate(meshes):
        sel = hand == k
        if not sel.any():
            continue
        f = face[sel]
        b = hits.barycentric[sel].astype(np.float64)
        b /= b.sum(1, keepdims=True)
        bary[sel] = b
        corners = np.asarray(mesh.faces, np.int64)[f]                       # [K, 3]
        position[sel] = _blend(b, np.asarray(mesh.vertices, np.float64), corners)
        nrm = _blend(b, np.asarray(mesh.normals, np.float64), corners)
        normal[sel] = nrm / np.maximum(np.sqrt(np.sum(nrm * nrm, axis=1, keepdims=True)), 1e-12)
        uv_corners = np.asarray(mesh.faces_uv, np.int64)[f]
        uv[sel] = _blend(b, np.asarray(mesh.uv, np.float64), uv_corners)
    eye = np.asarray(camera.center, np.float64)
    view = eye[None] - position
    view /= np.maximum(np.sqrt(np.sum(view * view, axis=1, keepdims=True)), 1e-12)
    view[hand < 0] = 0
    z = position @ np.asarray(camera.R, np.float64)[2] + float(np.asarray(camera.t)[2])
    depth = np.where(hand >= 0, z, np.inf)
    from relight_cli.uvraster import UVLayout
    layouts = [UVLayout.of(m.uv, m.faces_uv) for m in meshes]
    return GBuffer(camera.width, camera.height, aa * aa, hand, face, bary, uv, position,
                   normal, depth, view, eye, layouts)


def _blend(weights: np.ndarray, values: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """[K, C] Σ_c weights[k, c] · values[corners[k, c]] (three fused multiply-adds, no einsum)."""
    return (weights[:, 0:1] * values[corners[:, 0]] + weights[:, 1:2] * values[corners[:, 1]]
            + weights[:, 2:3] * values[corners[:, 2]])
