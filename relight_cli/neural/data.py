"""A relight/capture folder (formats/capture.md) as teacher training samples.

A sample is one (frame, camera) image: the frame's lights (grouped frames: the group,
fully lit frames: every LED), the pose's texel G-buffer
(:class:`~relight_cli.neural.geometry.PoseTexels`, fine mesh) with per-light local
light directions, falloff and visibility against every hand of the scene, the
camera's local view directions, the camera's G-buffer (where each pixel sample
lands in UV), and the captured image and mask.

Splits (:meth:`CaptureData.splits`):
    train      grouped-light frames of the training poses;
    heldout    grouped-light frames of held-out poses: the last ``holdout`` fraction of
               the grouped frames in time (a held-out motion segment, as RelightableHands
               excludes segments);
    grouped    every grouped-light frame (train + heldout): a capture no model trained on,
               e.g. the two-hand sequences RelightableHands uses only for evaluation;
    fully_lit  fully lit frames: novel illumination (every LED at once, never trained on);
    env        the capture's ``eval/`` renders: held-out poses under env maps, ground truth
               the papers never had (only synthetic stages have it).

Texel G-buffers and visibility are traced once per pose and kept in an LRU cache
(``cache_poses``); camera G-buffers per (pose, camera) likewise.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from relight_cli.errors import DataError


@dataclass
class Sample:
    """One training/evaluation image and everything needed to predict it.

    Attributes:
        inputs: [B, 7, N, N] float32 per (light, hand) teacher inputs (light dir, view dir,
            visibility), hand-major: hand 0's L lights, then hand 1's …
        weights: [B, 3, N, N] float32 per (light, hand) RGB weight b_i (intensity × falloff).
        hand_of: [B] int64 hand index of each row.
        poses: [H, J, 3] float64 per-hand axis-angle poses.
        gbuffer: the camera's G-buffer of the posed fine meshes.
        image: [Hi, Wi, 3] float32 target radiance (None for pure inference).
        mask: [Hi, Wi] float32 target hand mask (None for pure inference).
        frame, camera, pose: identifiers (env samples: frame = −1, ``env`` names the map).
        n_hands: H.
    """

    inputs: np.ndarray
    weights: np.ndarray
    hand_of: np.ndarray
    poses: np.ndarray
    gbuffer: object
    image: np.ndarray | None
    mask: np.ndarray | None
    frame: int
    camera: str
    pose: int
    n_hands: int
    env: str = ""


def _require_file(path: str, what: str) -> None:
    """One line naming ``path`` when it is missing or a folder (``what``: its role)."""
    if os.path.isdir(path):
        raise DataError(f"{what} is a folder, not a file", path)
    if not os.path.isfile(path):
        raise DataError(f"{what} is missing", path)


class LRU(OrderedDict):
    """A tiny LRU cache (get-or-compute)."""

    def __init__(self, size: int):
        super().__init__()
        self.size = size

    def get_or(self, key, make):
        if key in self:
            self.move_to_end(key)
            return self[key]
        value = make()
        self[key] = value
        while len(self) > self.size:
            self.popitem(last=False)
        return value


def assemble_inputs(texels, k: int, lights, view: np.ndarray, intensity: np.ndarray,
                    visibility: bool, falloff: str) -> tuple[np.ndarray, np.ndarray]:
    """Teacher inputs [L, 7, N, N] and weights [L, 3, N, N] of hand k.

    Args:
        texels: :class:`PoseTexels`.  lights: its :class:`LightInputs` for hand k.
        view: [K, 3] local view directions.  intensity: [L, 3] RGB b_i (point lights:
            radiant intensity; directional: radiance × solid angle).
        visibility: feed the traced visibility (False: a constant 1 channel, the
            RelightableHands Table 1 ablation).
        falloff: ``analytic`` (weights × 1/r²) or ``none``.
    """
    L, K = lights.visibility.shape
    vis = lights.visibility if visibility else np.ones((L, K), np.float32)
    per_texel = np.concatenate([lights.local_light, np.broadcast_to(view[None], (L, K, 3)),
                                vis[..., None]], -1)                                # [L, K, 7]
    inputs = texels.to_maps(k, per_texel.astype(np.float32))
    if falloff == "analytic":
        w = lights.falloff[..., None] * np.asarray(intensity, np.float32)[:, None, :]  # [L, K, 3]
        weights = texels.to_maps(k, w.astype(np.float32))
    else:
        n = inputs.shape[-1]
        weights = np.broadcast_to(np.asarray(intensity, np.float32)[:, :, None, None],
                                  (L, 3, n, n)).copy()
    return inputs, weights


#: The pixel sampling of a capture that does not record one (a converted real capture):
#: a sensor integrates its pixel's area, which 2×2 samples approximate.
DEFAULT_CAPTURE_AA = 2


def capture_aa(capture) -> int:
    """Samples per pixel axis the capture's images were made with (``settings.aa`` of
    capture.json, as ``synth-capture --aa`` records it), else :data:`DEFAULT_CAPTURE_AA`."""
    value = (capture.settings or {}).get("aa")
    if isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= 8:
        return value
    return DEFAULT_CAPTURE_AA


class CaptureData:
    """Lazy access to a capture's training and evaluation samples.

    Args:
        folder: the capture folder (holding capture.json).
        tex_res: teacher texture size N.
        aa: camera G-buffer samples per pixel axis; 0 (the default): the capture's own
            (:func:`capture_aa`), so a model is trained and scored through the pixel
            sampling its images were made with (one sampling rule).  A different value is
            kept but recorded in :attr:`sampling` (``matched`` False).
        visibility, falloff: see :func:`assemble_inputs`.
        holdout: fraction of grouped frames held out (the last in time).
        cache_poses: LRU size of texel G-buffers and camera G-buffers.
    """

    def __init__(self, folder: str, tex_res: int, aa: int = 0, visibility: bool = True,
                 falloff: str = "analytic", holdout: float = 0.25, cache_poses: int = 64):
        from relight_cli.formats import capture as C
        from relight_cli.formats.hand_npz import read_hand

        index = C.index_path(folder)      # a folder or its capture.json (not a folder)
        self.folder = os.path.dirname(index) or "."
        self.index_path = index
        self.capture = C.read_capture(index)
        hand_path = os.path.join(self.folder, self.capture.hand)
        _require_file(hand_path, "the capture's hand.npz")
        self.hand_path = hand_path
        self.hand = read_hand(hand_path)
        self.eval_hand = None
        ev = self.capture.evaluation
        if ev is not None:
            # every file the evaluation names must be there: a capture missing one is
            # damaged, refused before any training or scoring (never a silently dropped split)
            path = os.path.join(self.folder, ev["hand"])
            _require_file(path, "capture.json's evaluation names a held-out hand.npz that")
            self.eval_hand = read_hand(path)
            if (len(self.eval_hand.hands), self.eval_hand.n_joints) != (
                    len(self.hand.hands), self.hand.n_joints):
                raise DataError(f"the held-out hand has {len(self.eval_hand.hands)} hand(s) of "
                                f"{self.eval_hand.n_joints} joints, the capture's hand.npz "
                                f"{len(self.hand.hands)} of {self.hand.n_joints}", path)
            for name, file in ev["envs"].items():
                _require_file(os.path.join(self.folder, file),
                              f"capture.json's evaluation names an env map ({name!r}) that")
            for r in ev["renders"]:
                if r["pose"] >= self.eval_hand.n_frames:
                    raise DataError(f"evaluation render {r['image']!r} uses held-out pose "
                                    f"{r['pose']}, but the held-out hand has "
                                    f"{self.eval_hand.n_frames} pose(s)", path)
                _require_file(os.path.join(self.folder, r["image"]),
                              "capture.json's evaluation names a render that")
        self._check_handedness()
        self.tex_res = tex_res
        captured = capture_aa(self.capture)
        self.aa = int(aa) if aa else captured
        #: how pixels are sampled against how the capture's images were made
        self.sampling = {"aa": self.aa, "capture_aa": captured, "matched": self.aa == captured}
        self.visibility = visibility
        self.falloff = falloff
        self.cache_poses = cache_poses
        self._texels = LRU(cache_poses)
        self._gbuffers = LRU(4 * cache_poses)
        self._lights = LRU(4 * cache_poses)
        self._rasters = None
        self._env_maps = {}
        self._check_eval_grid()
        self._cameras = {c.name: c for c in self.capture.cameras}
        self._check_image_sizes()
        frames = self.capture.frames
        for f in frames:
            if not 0 <= f.pose < self.hand.n_frames:
                raise DataError(f"frame {f.index} uses pose {f.pose}, but the hand has "
                                f"{self.hand.n_frames} frame(s)", index)
        grouped = sorted((f for f in frames if f.lit == "group"), key=lambda f: (f.time, f.index))
        if not grouped:
            raise DataError("the capture has no grouped-light frames to learn from", index)
        if not any(f.images for f in grouped):
            raise DataError("the capture's grouped frames have no images", index)
        n_hold = int(round(holdout * len(grouped)))
        if holdout > 0 and len(grouped) >= 2:
            n_hold = min(max(n_hold, 1), len(grouped) - 1)
        else:
            n_hold = 0
        self.train_frames = grouped[:len(grouped) - n_hold]
        self.heldout_frames = grouped[len(grouped) - n_hold:]
        self.fully_lit_frames = [f for f in frames if f.lit == "full"]
        # Fully lit frames are interleaved with the grouped ones: only those before the
        # held-out segment starts may be trained on (e.g. a student's poses), so no split
        # shares a time segment with training.
        cut = (self.heldout_frames[0].time, self.heldout_frames[0].index) \
            if self.heldout_frames else None
        self.train_fully_lit_frames = [f for f in self.fully_lit_frames
                                       if cut is None or (f.time, f.index) < cut]

    def _check_image_sizes(self) -> None:
        """Each camera's size against the first image of it in the folder, and against
        every evaluation render (their EXR headers only, milliseconds each): a camera
        whose declared size its images do not have is refused naming the image before any
        training, not when the final evaluation reads it (issue 52's sweep: a distill run
        trained, then failed).  Any other image of a wrong size is still refused when read."""
        from relight_cli.formats.capture import image_path
        first = {}
        for f in self.capture.frames:
            for name in f.images:
                first.setdefault(name, image_path(f.index, name))
        checks = list(first.items())
        if self.capture.evaluation is not None:
            checks += [(r["camera"], r["image"]) for r in self.capture.evaluation["renders"]]
        for name, relative in checks:
            path = os.path.join(self.folder, relative)
            size = _exr_size(path)
            camera = self._cameras[name]
            if size is None and os.path.isfile(path):
                from relight_cli.formats.exr import read_exr
                read_exr(path)       # its reader's own line (permission denied, damaged …)
                raise DataError("not a readable EXR image (a capture image is an OpenEXR "
                                "file, formats/capture.md)", path)
            if size is not None and size != (camera.width, camera.height):
                raise DataError(f"image is {size[0]}x{size[1]}, camera {name!r} is "
                                f"{camera.width}x{camera.height}", path)

    def _check_eval_grid(self) -> None:
        """Bound ``settings.eval_env_res`` by what the folder holds: a capture stores each
        evaluation env map resampled to that lat-long grid (formats/capture.md), and the
        stage rebuilt for the ceiling integrates over it, so a grid its maps do not have
        (a capture.json declaring 8192x4096 over 32x16 maps: > 5 min and 17 GB before
        any output) is refused naming capture.json, before any work."""
        grid = (self.capture.settings or {}).get("eval_env_res")
        ev = self.capture.evaluation
        if grid is None or ev is None:
            return
        h, w = grid
        for name, file in ev["envs"].items():
            env = self.env_map(name)
            if env.layout != "latlong" or (env.height, env.width) != (h, w):
                size = (f"{env.width}x{env.height}" if env.layout == "latlong"
                        else f"a {env.layout} map")
                raise DataError(f"settings.eval_env_res is {w}x{h}, but the evaluation env "
                                f"map {file!r} stored on it is {size}", self.index_path)

    def _check_handedness(self) -> None:
        """Refuse a hand.npz of the other hand(s) than the capture was made of (DataError
        naming it).  The capture records its handedness twice: the built-in hand
        ``synth-capture`` rendered (capture.json's ``provenance.inputs.hand.path``,
        ``builtin:right``, ``builtin:left`` or ``builtin:two``) and its held-out poses'
        eval/hand.npz, rendered with the same hands; hand.npz's sides (its ``side`` and
        ``hand_mirror``, per hand) must match both where they are there."""
        from relight_cli.hand.scene import handedness
        ours = handedness(self.hand)
        recorded = []
        source = ((self.capture.provenance or {}).get("inputs") or {}).get("hand")
        path = source.get("path") if isinstance(source, dict) else None
        builtin = {"builtin:right": ["right"], "builtin:left": ["left"],
                   "builtin:two": ["right", "left"]}
        if isinstance(path, str) and path in builtin:
            recorded.append((builtin[path], f"capture.json's provenance: {path}"))
        if self.eval_hand is not None:
            recorded.append((handedness(self.eval_hand),
                             f"its held-out {self.capture.evaluation['hand']}"))
        for sides, where in recorded:
            if sides != ours:
                raise DataError(f"the capture's hand.npz is the {' and '.join(ours)} "
                                f"hand but the capture is of the {' and '.join(sides)} hand "
                                f"({where}; a hand.npz of another capture?)", self.hand_path)

    # ---------------------------------------------------------------- identity

    @property
    def key(self) -> str:
        """The capture's fingerprint (capture.json's ``key``, else its SHA-256)."""
        if self.capture.key:
            return self.capture.key
        from relight_cli.provenance import file_sha256
        return file_sha256(self.index_path)[:16]

    @property
    def n_hands(self) -> int:
        return len(self.hand.hands)

    @property
    def pose_dim(self) -> int:
        return (self.hand.n_joints - 1) * 3

    # ---------------------------------------------------------------- splits

    def items(self, frames) -> list[tuple[int, str]]:
        """(frame index, camera) pairs of ``frames`` that have images."""
        return [(f.index, cam) for f in frames for cam in f.images]

    def splits(self) -> dict[str, list]:
        out = {"train": self.items(self.train_frames), "heldout": self.items(self.heldout_frames),
               "grouped": self.items(sorted(self.train_frames + self.heldout_frames,
                                            key=lambda f: f.index)),
               "fully_lit": self.items(self.fully_lit_frames)}
        ev = self.capture.evaluation or {}
        if self.eval_hand is not None and ev.get("renders"):
            out["env"] = [("env", r) for r in ev["renders"]]
        return out

    def frame(self, index: int):
        for f in self.capture.frames:
            if f.index == index:
                return f
        raise KeyError(index)

    # ---------------------------------------------------------------- geometry

    def rasters(self):
        if self._rasters is None:
            from relight_cli.uvraster import rasterize_uv
            model = self.hand.mesh("fine")
            raster = rasterize_uv(model.uv, model.faces_uv, self.tex_res)
            self._rasters = [raster] * self.n_hands
        return self._rasters

    def meshes(self, pose: int, held_out: bool = False):
        from relight_cli.hand.scene import posed_meshes
        hand = self.eval_hand if held_out else self.hand
        meshes = posed_meshes(hand, pose, "fine")
        for m in meshes:
            if not np.isfinite(m.vertices).all():
                raise DataError(f"pose {pose}: posed vertices hold NaN/Inf", self.hand_path)
        return meshes

    def poses(self, pose: int, held_out: bool = False) -> np.ndarray:
        hand = self.eval_hand if held_out else self.hand
        return np.stack([inst.poses[pose] for inst in hand.hands])

    def texels(self, pose: int, held_out: bool = False):
        from .geometry import PoseTexels
        return self._texels.get_or((held_out, pose), lambda: PoseTexels(
            self.meshes(pose, held_out), self.tex_res, self.rasters(), shadows=self.visibility))

    def gbuffer(self, pose: int, camera, held_out: bool = False):
        from relight_cli.render.gbuffer import render_gbuffer

        def make():
            texels = self.texels(pose, held_out)
            return render_gbuffer(texels.meshes, camera, self.aa, scene=texels.renderer.scene)
        return self._gbuffers.get_or((held_out, pose, camera.name), make)

    # ---------------------------------------------------------------- samples

    def light_inputs(self, pose: int, lights_on, held_out: bool = False):
        texels = self.texels(pose, held_out)
        positions = self.capture.light_positions[np.asarray(lights_on, np.int64)]
        key = (held_out, pose, tuple(int(i) for i in lights_on))
        return self._lights.get_or(key, lambda: [
            texels.point_lights(k, positions, visibility=self.visibility)
            for k in range(texels.n_hands)])

    def sample(self, frame_index: int, camera_name: str, with_image: bool = True) -> Sample:
        """The (frame, camera) sample of a capture frame."""
        from relight_cli.formats import capture as C

        frame = self.frame(frame_index)
        camera = self._cameras[camera_name]
        texels = self.texels(frame.pose)
        lights = self.light_inputs(frame.pose, frame.lights_on)
        intensity = self.capture.light_intensity[np.asarray(frame.lights_on, np.int64)]
        inputs, weights, hand_of = [], [], []
        for k in range(texels.n_hands):
            x, w = assemble_inputs(texels, k, lights[k], texels.local_view(k, camera.center),
                                   intensity, self.visibility, self.falloff)
            inputs.append(x)
            weights.append(w)
            hand_of.append(np.full(len(x), k, np.int64))
        image = mask = None
        if with_image:
            path = os.path.join(self.folder, C.image_path(frame.index, camera.name))
            if not os.path.isfile(path):
                raise DataError(f"frame {frame.index} lists camera {camera.name!r} but its image "
                                f"is missing", path)
            image, mask = C.read_image(path, camera)
        return Sample(np.concatenate(inputs), np.concatenate(weights), np.concatenate(hand_of),
                      self.poses(frame.pose), self.gbuffer(frame.pose, camera), image, mask,
                      frame.index, camera.name, frame.pose, texels.n_hands)

    def env_target(self, render: dict):
        """(pose, env name, camera, image, mask) of one ``eval/`` render record."""
        from relight_cli.formats import capture as C
        camera = self._cameras.get(render["camera"])
        if camera is None:
            raise DataError(f"evaluation render names unknown camera {render['camera']!r}",
                            self.index_path)
        path = os.path.join(self.folder, render["image"])
        image, mask = C.read_image(path, camera)
        return int(render["pose"]), render["env"], camera, image, mask

    def env_map(self, name: str):
        """The ``eval/envs/`` map ``name`` (read once)."""
        if name not in self._env_maps:
            from relight_cli.formats.envmap import read_envmap
            ev = self.capture.evaluation or {}
            self._env_maps[name] = read_envmap(os.path.join(self.folder, ev["envs"][name]))
        return self._env_maps[name]

    def check_alignment(self, sample: Sample, threshold: float = 0.5) -> None:
        """Refuse a hand that does not match the images: IoU of the G-buffer coverage and
        the captured mask below ``threshold`` (a wrong hand.npz, pose or calibration)."""
        if sample.mask is None:
            return
        ours = sample.gbuffer.mask > 0.5
        theirs = sample.mask > 0.5
        union = np.logical_or(ours, theirs).sum()
        if union == 0:
            return
        iou = np.logical_and(ours, theirs).sum() / union
        if iou < threshold:
            raise DataError(f"the hand does not match the images: frame {sample.frame} camera "
                            f"{sample.camera!r} overlaps its mask with IoU {iou:.2f} < "
                            f"{threshold} (wrong hand.npz, poses or cameras?)", self.hand_path)

    # ---------------------------------------------------------------- mean texture

    def mean_texture(self, max_views: int = 64) -> np.ndarray:
        """T̄: [H, 3, N, N] float32 visibility-aware mean of what the cameras saw per texel.

        Over the fully lit frames (every LED on: near-uniform irradiance, so radiance ≈
        albedo · E/π), each inside texel is projected into every camera; it counts where
        the camera's ray to it reaches it first (no occluder, same hand), weighted by the
        cosine between its normal and the view.  Texels no camera saw copy their nearest
        seen texel.  Used by the GGX baseline (App. B's T̄) and, later, URHand.
        """
        from relight_cli.formats import capture as C

        from .unwrap import Accumulator, view_samples

        frames = self.fully_lit_frames or self.train_frames
        n = self.tex_res
        acc = Accumulator(self.n_hands, n)
        views = 0
        for frame in frames:
            texels = self.texels(frame.pose)
            for cam_name in frame.images:
                if views >= max_views:
                    break
                views += 1
                camera = self._cameras[cam_name]
                image, _ = C.read_image(os.path.join(self.folder, C.image_path(frame.index,
                                                                                cam_name)), camera)
                for k in range(self.n_hands):
                    acc.add(k, view_samples(texels, k, camera, image))
        out = np.zeros((self.n_hands, 3, n, n), np.float32)
        for k in range(self.n_hands):
            out[k] = np.transpose(acc.mean(k), (2, 0, 1))
        return out


def _exr_size(path: str):
    """(width, height) from an image's header, or None when it cannot be opened (its
    reader says why when it is read)."""
    import OpenImageIO as oiio

    from relight_cli.formats.image import _library_quiet
    with _library_quiet():
        inp = oiio.ImageInput.open(path)
        if inp is None:
            oiio.geterror()
            return None
        try:
            spec = inp.spec()
            return int(spec.width), int(spec.height)
        finally:
            inp.close()
