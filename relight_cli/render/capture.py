"""The synthetic light stage: a dome of cameras and LEDs, a moving hand, multiplexed lighting.

Like the captures of RelightableHands and URHand (106–150 cameras, 350–460 LEDs
on a dome around the hand), scaled down: cameras and point lights are spread
evenly on spheres (Fibonacci lattices) around the hand's motion, the hand moves
through random poses interpolated by per-joint quaternion slerp, and frames are
time-multiplexed: every ``full_every``-th frame has every light on (the
tracking frames), the others a group of ``group`` neighbouring lights (the
learning signal: near-OLAT images with enough light).

This module plans captures and renders frames (plain arrays in and out);
``relight synth-capture`` writes them in the relight/capture format.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class StageSettings:
    """The light stage and the capture schedule.

    Attributes:
        cameras: number of cameras.  lights: number of LED point lights.
        group: lights on in a grouped frame.  frames: number of frames.
        full_every: every this-many frames is fully lit (1 = all fully lit).
        res: image width = height, pixels.
        camera_radius, light_radius: dome radii (metres) around the motion's centre.
        fps: frame rate.  keyframe_every: frames between random key poses.
        seed: seeds poses, light groups (identical settings give identical captures).
        tex_res, aa: renderer texture-space map size and sub-pixel grid.
        sss: subsurface scattering on.  bounce: one-bounce interreflection.
    """

    cameras: int = 20
    lights: int = 64
    group: int = 5
    frames: int = 12
    full_every: int = 3
    res: int = 128
    camera_radius: float = 1.0
    light_radius: float = 1.2
    fps: float = 30.0
    keyframe_every: int = 10
    seed: int = 0
    tex_res: int = 256
    aa: int = 2
    sss: bool = True
    bounce: bool = False


def fibonacci_sphere(n: int, min_y: float = -1.0) -> np.ndarray:
    """[n, 3] unit vectors spread evenly over the sphere's part with y ≥ ``min_y``.

    A Fibonacci lattice in (y, longitude): equal-area bands, golden-angle turns.
    """
    i = np.arange(n) + 0.5
    y = 1 - (1 - min_y) * i / n
    r = np.sqrt(np.clip(1 - y * y, 0, None))
    phi = i * math.pi * (3 - math.sqrt(5))
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], 1)


def dome_cameras(n: int, centre, radius: float, res: int, fov_y_deg: float) -> list:
    """``n`` OpenCV cameras on a sphere around ``centre`` looking at it, named cam000….

    The cap below the wrist (y < −0.6·radius, where the arm would be) is left empty.
    """
    from relight_cli.formats.camera import Camera

    centre = np.asarray(centre, np.float64)
    dirs = fibonacci_sphere(n, min_y=-0.6)
    cams = []
    for k, d in enumerate(dirs):
        up = (0.0, 1.0, 0.0) if abs(d[1]) < 0.99 else (0.0, 0.0, 1.0)
        cams.append(Camera.look_at(centre + radius * d, centre, up=up, fov_y_deg=fov_y_deg,
                                   width=res, height=res, name=f"cam{k:03d}"))
    return cams


def dome_lights(n: int, centre, radius: float):
    """``n`` white LEDs on a sphere around ``centre`` (:class:`PointLights`), names led000….

    Each LED's intensity I = 4πr²/n makes the fully lit stage give a surface facing
    any way an irradiance of ≈ π (the lights' cosine-weighted average over the
    sphere is n·I/(4r²)), so fully lit skin has radiance ≈ its albedo.
    """
    from .shading import PointLights

    positions = np.asarray(centre, np.float64) + radius * fibonacci_sphere(n)
    intensity = np.full((n, 3), 4 * math.pi * radius ** 2 / n)
    return PointLights(positions, intensity), [f"led{k:03d}" for k in range(n)]


def light_group(positions: np.ndarray, size: int, rng) -> list:
    """A random light and its ``size − 1`` nearest neighbours (sorted indices)."""
    first = int(rng.integers(len(positions)))
    dist = np.linalg.norm(positions - positions[first], axis=1)
    return sorted(int(i) for i in np.argsort(dist, kind="stable")[:min(size, len(positions))])


def hand_motion(hand, n_frames: int, seed: int = 0, keyframe_every: int = 10):
    """A copy of ``hand`` (first hand only) moving through random poses.

    Key poses every ``keyframe_every`` frames (random within joint limits, plus a
    wrist rotation of up to ±35° about each axis) are interpolated by per-joint
    slerp (:func:`relight_cli.hand.poses.interpolate_poses`).

    Returns:
        HandData with ``n_frames`` frames.
    """
    import copy

    from scipy.spatial.transform import Rotation

    from relight_cli.hand.poses import interpolate_poses, random_poses

    out = copy.deepcopy(hand)
    out.hands = out.hands[:1]
    n_keys = max(2, int(math.ceil((n_frames - 1) / keyframe_every)) + 1)
    rng = np.random.default_rng(seed)
    keys = random_poses(n_keys, seed=seed, side=hand.side, rest_joints=hand.rest_joints)
    wrist = Rotation.from_euler("xyz", rng.uniform(-35, 35, (n_keys, 3)), degrees=True)
    keys[:, 0] = wrist.as_rotvec()
    key_frames = np.arange(n_keys) * keyframe_every
    poses, trans = interpolate_poses(key_frames, keys, np.zeros((n_keys, 3)), np.arange(n_frames))
    out.hands[0].poses = poses
    out.hands[0].translations = trans
    return out


def capture_key(settings: StageSettings, hand_digest: str) -> str:
    """Fingerprint of a capture's content: settings + the hand model's digest."""
    text = json.dumps({"settings": asdict(settings), "hand": hand_digest}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def hand_digest(hand) -> str:
    """SHA-256 (16 hex) of a hand's model and poses."""
    h = hashlib.sha256()
    for arr in (hand.coarse.vertices, hand.fine.vertices, hand.fine.faces, hand.fine.uv,
                hand.rest_joints, *[i.poses for i in hand.hands]):
        h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()[:16]


@dataclass
class Plan:
    """Everything a capture will contain, before rendering.

    Attributes:
        motion: HandData with one frame per capture frame.
        cameras: list of Camera.  lights: PointLights.  light_names: list.
        frames: list of ``formats.capture.CaptureFrame`` (images empty).
        centre: [3] the motion's centre.  key: :func:`capture_key`.
    """

    motion: object
    cameras: list
    lights: object
    light_names: list
    frames: list
    centre: np.ndarray
    key: str


def plan_capture(hand, settings: StageSettings, motion=None) -> Plan:
    """Plan a capture: the motion, the dome, and each frame's lights (deterministic).

    Args:
        hand: HandData (the model; its poses are replaced by a random motion unless
            ``motion`` is given).
        settings: :class:`StageSettings`.
        motion: optional HandData whose frames are the motion (e.g. a real sequence).
    """
    from relight_cli.formats.capture import CaptureFrame
    from relight_cli.hand.scene import posed_meshes

    s = settings
    if motion is None:
        motion = hand_motion(hand, s.frames, s.seed, s.keyframe_every)
    n = motion.n_frames
    # Frame the whole motion: bounding sphere of the posed coarse meshes.
    pts = np.concatenate([m.vertices for f in range(0, n, max(1, n // 16))
                          for m in posed_meshes(motion, f, "coarse")])
    centre = 0.5 * (pts.min(0) + pts.max(0))
    radius = float(np.linalg.norm(pts - centre, axis=1).max())
    fov = 2 * math.degrees(math.asin(min(0.99, 1.08 * radius / s.camera_radius)))
    cameras = dome_cameras(s.cameras, centre, s.camera_radius, s.res, fov)
    lights, names = dome_lights(s.lights, centre, s.light_radius)
    rng = np.random.default_rng(s.seed + 1)
    frames = []
    for f in range(n):
        full = s.full_every <= 1 or f % s.full_every == 0
        on = list(range(len(lights))) if full else light_group(lights.positions, s.group, rng)
        frames.append(CaptureFrame(f, f / s.fps, f, "full" if full else "group", on, []))
    return Plan(motion, cameras, lights, names, frames, centre,
                capture_key(s, hand_digest(motion)))


class FrameRenderer:
    """Renders capture frames: one lighting pass per frame, then every camera.

    Shadows come from the texture-space visibility maps (``direct="texel"``): traced
    once per frame for all lights, shared by every camera.

    Args:
        plan: the :class:`Plan`.
        materials: one Material per hand of the motion.
        settings: the stage settings (tex_res, aa, sss, bounce).
    """

    def __init__(self, plan: Plan, materials, settings: StageSettings):
        from relight_cli.uvraster import rasterize_uv

        self.plan = plan
        self.materials = materials
        self.settings = settings
        model = plan.motion.mesh("fine")
        raster = rasterize_uv(model.uv, model.faces_uv, settings.tex_res)
        self.rasters = [raster for _ in plan.motion.hands]      # UV layout is pose independent

    def renderer(self, pose: int, hand=None):
        from relight_cli.hand.scene import posed_meshes

        from .shading import HandRenderer, RenderSettings

        s = self.settings
        meshes = posed_meshes(hand or self.plan.motion, pose, "fine")
        return HandRenderer(meshes, self.materials,
                            RenderSettings(tex_res=s.tex_res, aa=s.aa, sss=s.sss,
                                           bounce=s.bounce, direct="texel"),
                            rasters=self.rasters)

    def frame(self, frame, cameras=None):
        """Yield (camera, RenderResult) for ``frame`` (a CaptureFrame) and ``cameras``."""
        renderer = self.renderer(frame.pose)
        lighting = renderer.light(self.plan.lights.subset(frame.lights_on))
        for cam in (self.plan.cameras if cameras is None else cameras):
            yield cam, renderer.render(cam, lighting)

    def env_views(self, hand, pose: int, env, cameras):
        """Yield (camera, RenderResult) of ``hand``'s ``pose`` under an env map."""
        renderer = self.renderer(pose, hand)
        lighting = renderer.light(env=env)
        for cam in cameras:
            yield cam, renderer.render(cam, lighting)
