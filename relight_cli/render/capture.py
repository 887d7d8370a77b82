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
        skin_seed: seeds the procedural skin (the subject: keep it across the right, left
            and two-hand captures of one study, while ``seed`` changes their motion).
        eval_env_res: (H, W) lat-long grid over which the ground-truth env renders
            integrate their env maps (the learned models use their own, 32×16 by default).
        eval_env_space: where the ground-truth env renders integrate env transport
            (``RenderSettings.env_space``): ``texels``, the texel centres where the stage's
            LEDs are shaded (irradiance and visibility per texel), so an env render is the
            stage's own transport summed over the env map's directions as distant lights —
            the superposition a real stage obeys (RelightableHands Eq. 2), which every
            model trained on LED frames relies on; or ``vertices`` (bake-features'
            receivers, interpolated to texels), what captures made before this setting
            used (their records have no ``eval_env_space``): there shadows and highlights
            under an env map are interpolated between mesh vertices while the LEDs' are
            not: one direction of an env map renders up to 105 % (relative MSE; median
            0.61 %) away from a far LED in the same direction on a converged capture's
            held-out pose, against at most 0.01 % with ``texels``
            (benchmarks/results/converged/env_truth/).
        ggx_shadowing: the GGX lobe's G (``RenderSettings.shadowing``): ``smith``, the exact
            Smith term a standard renderer (Mitsuba 3) uses, or ``schlick``, URHand Eq. 15's
            remap, which every capture made before this setting used (their records have
            no ``ggx_shadowing``).  The lobe is then evaluated in texture space for the
            LEDs as for env maps (texel visibility and lobe, so superposition is exact).
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
    skin_seed: int = 0
    eval_env_res: tuple = (32, 64)
    eval_env_space: str = "texels"
    ggx_shadowing: str = "smith"


#: settings added after the first captures, and the value a capture.json without them
#: was made with (:func:`stage_settings`; :func:`capture_key` leaves them out at that
#: value, so an older capture keeps its key)
LEGACY_SETTINGS = {"eval_env_space": "vertices", "ggx_shadowing": "schlick"}


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
    """``n`` white LEDs on a sphere around ``centre`` (a ``formats.lights_json.Lights`` of RGB
    radiant intensity I, :meth:`~relight_cli.formats.lights_json.Lights.from_radiant_intensity`),
    names led000….

    Each LED's intensity I = 4πr²/n makes the fully lit stage give a surface facing
    any way an irradiance of ≈ π (the lights' cosine-weighted average over the
    sphere is n·I/(4r²)), so fully lit skin has radiance ≈ its albedo.
    """
    from relight_cli.formats.lights_json import Lights

    positions = np.asarray(centre, np.float64) + radius * fibonacci_sphere(n)
    intensity = np.full((n, 3), 4 * math.pi * radius ** 2 / n)
    return Lights.from_radiant_intensity(positions, intensity), [f"led{k:03d}" for k in range(n)]


def light_group(positions: np.ndarray, size: int, rng) -> list:
    """A random light and its ``size − 1`` nearest neighbours (sorted indices)."""
    first = int(rng.integers(len(positions)))
    dist = np.linalg.norm(positions - positions[first], axis=1)
    return sorted(int(i) for i in np.argsort(dist, kind="stable")[:min(size, len(positions))])


# Two interacting hands (RelightableHands evaluates right, left and both hands): the second
# hand faces the first one's palm from a direction within TWO_HAND_CONE_DEG of its palm
# normal (+Z of the model), turned by up to ±TWO_HAND_TILT_DEG about each axis from the
# facing pose, and slides in along that direction until the closest pair of fine-mesh
# vertices is TWO_HAND_GAP metres apart (a random gap per key pose, interpolated).  Sliding
# in from outside never passes through the other hand, and the resulting surface distance
# stays above TWO_HAND_MARGIN (tests/render/test_capture.py measures it exactly).
TWO_HAND_GAP = (0.006, 0.025)
TWO_HAND_MARGIN = 0.005
TWO_HAND_CONE_DEG = 50.0
TWO_HAND_TILT_DEG = 35.0
_GAP_TOLERANCE = 2e-4          # metres: sphere tracing stops this close to the target gap


def instance_rest(hand, inst) -> np.ndarray:
    """[J, 3] rest joints of one hand instance (mirrored across x = 0 for a mirrored one)."""
    rest = np.asarray(hand.rest_joints, np.float64)
    return rest * [-1.0, 1.0, 1.0] if inst.mirror else rest


def _random_track(hand, inst, n_frames: int, keyframe_every: int, seed, wrist_rng):
    """(poses [N, J, 3], key frames, key wrist rotations) of one hand: random key poses
    within joint limits plus a wrist rotation of up to ±35° about each axis, slerped."""
    from scipy.spatial.transform import Rotation

    from relight_cli.hand.poses import interpolate_poses, random_poses
    from relight_cli.hand.scene import handedness

    n_keys = max(2, int(math.ceil((n_frames - 1) / keyframe_every)) + 1)
    keys = random_poses(n_keys, seed=seed, side=handedness(hand, inst),
                        rest_joints=instance_rest(hand, inst))
    wrist = Rotation.from_euler("xyz", wrist_rng.uniform(-35, 35, (n_keys, 3)), degrees=True)
    keys[:, 0] = wrist.as_rotvec()
    key_frames = np.arange(n_keys) * keyframe_every
    poses, _ = interpolate_poses(key_frames, keys, np.zeros((n_keys, 3)), np.arange(n_frames))
    return poses, key_frames


def hand_motion(hand, n_frames: int, seed: int = 0, keyframe_every: int = 10):
    """A copy of ``hand`` moving through random poses: its first hand alone, or, when the
    scene has two hands, both hands interacting (:func:`place_second_hand`).

    Key poses every ``keyframe_every`` frames (random within joint limits, plus a
    wrist rotation of up to ±35° about each axis) are interpolated by per-joint
    slerp (:func:`relight_cli.hand.poses.interpolate_poses`).  Each hand of a pair draws
    its own poses from its own stream of ``seed``, which a one-hand motion of the same
    seed does not share: a two-hand capture's poses are new to teachers trained on
    one-hand captures.

    Returns:
        HandData with ``n_frames`` frames and one or two hands (two: roots identity, the
        second hand's placement in its wrist rotation and translations).
    """
    import copy

    out = copy.deepcopy(hand)
    out.hands = out.hands[:2]
    if len(out.hands) == 1:
        inst = out.hands[0]
        inst.poses, _ = _random_track(hand, inst, n_frames, keyframe_every, seed,
                                      np.random.default_rng(seed))
        inst.translations = np.zeros((n_frames, 3))
        return out
    key_frames = None
    for k, inst in enumerate(out.hands):
        inst.poses, key_frames = _random_track(hand, inst, n_frames, keyframe_every, [seed, k],
                                               np.random.default_rng([seed, k, 1]))
        inst.translations = np.zeros((n_frames, 3))
        inst.root = np.eye(4)
    place_second_hand(out, key_frames, np.random.default_rng([seed, 2]))
    return out


def place_second_hand(hand, key_frames, rng) -> np.ndarray:
    """Place hand 1 of ``hand`` (in place) facing hand 0's palm, close but apart.

    Per key frame: a direction d within :data:`TWO_HAND_CONE_DEG` of hand 0's palm normal,
    an orientation turned 180° about +Y (facing hand 0) then by up to
    ±:data:`TWO_HAND_TILT_DEG` about each axis, and a target gap g in
    :data:`TWO_HAND_GAP`; all three are interpolated between key frames and expressed in
    hand 0's wrist frame, so the pair moves with hand 0's wrist.  Per frame, hand 1 starts
    far out along d and slides towards hand 0 by sphere tracing on the closest
    vertex–vertex distance δ(s) (1-Lipschitz in the slide s, so each step s ← s − (δ − g)
    keeps δ ≥ g): it stops at the first contact with the gap, never inside hand 0.
    Hands are roots-identity instances; only hand 1's wrist rotation and translation are
    written.

    Returns:
        [N] float64 closest vertex–vertex distance per frame (metres, ≥ g).
    """
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation, Slerp

    from relight_cli.hand.scene import posed_meshes

    first, second = hand.hands[0], hand.hands[1]
    n_frames = first.poses.shape[0]
    key_frames = np.asarray(key_frames, np.float64)
    n_keys = len(key_frames)
    cone = math.radians(TWO_HAND_CONE_DEG)
    cos_t = rng.uniform(math.cos(cone), 1.0, n_keys)                 # uniform over the cap
    phi = rng.uniform(0, 2 * math.pi, n_keys)
    sin_t = np.sqrt(1 - cos_t ** 2)
    dirs = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], 1)
    tilt = Rotation.from_euler("xyz", rng.uniform(-TWO_HAND_TILT_DEG, TWO_HAND_TILT_DEG,
                                                  (n_keys, 3)), degrees=True)
    relative = Rotation.from_euler("y", 180, degrees=True) * tilt
    gaps = rng.uniform(*TWO_HAND_GAP, n_keys)
    t = np.clip(np.arange(n_frames, dtype=np.float64), key_frames[0], key_frames[-1])
    rel = Slerp(key_frames, relative)(t)
    d = np.stack([np.interp(t, key_frames, dirs[:, c]) for c in range(3)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    gap = np.interp(t, key_frames, gaps)
    wrist0 = Rotation.from_rotvec(first.poses[:, 0])
    second.poses[:, 0] = (wrist0 * rel).as_rotvec()
    second.translations[:] = 0.0
    closest = np.zeros(n_frames)
    for f in range(n_frames):
        m0, m1 = posed_meshes(hand, f, "fine")[:2]
        c0, c1 = m0.vertices.mean(0), m1.vertices.mean(0)
        w = wrist0[f].apply(d[f])
        tree = cKDTree(m0.vertices)
        s = (np.linalg.norm(m0.vertices - c0, axis=1).max()
             + np.linalg.norm(m1.vertices - c1, axis=1).max() + gap[f] + 0.01)
        bound = np.inf
        for _ in range(500):
            # the previous closest pair is at most ``bound`` apart now (Lipschitz), so
            # the bounded query still finds the minimum, and far points cost nothing
            near = tree.query(m1.vertices + (c0 + s * w - c1), k=1,
                              distance_upper_bound=bound)[0]
            delta = float(near.min())
            step = delta - gap[f]
            if step < _GAP_TOLERANCE:
                break
            s -= step
            bound = delta + step + 1e-9
        second.translations[f] = c0 + s * w - c1
        closest[f] = delta
    return closest


def hand_distance(hand, frame: int) -> float:
    """Closest distance (metres) between a vertex of hand 0's fine mesh and one of hand 1's
    at ``frame`` (within ~0.2 mm of the surfaces' distance for the built-in hand)."""
    from scipy.spatial import cKDTree

    from relight_cli.hand.scene import posed_meshes
    m0, m1 = posed_meshes(hand, frame, "fine")[:2]
    return float(cKDTree(m0.vertices).query(m1.vertices, k=1)[0].min())


def two_hand_record(motion, eval_hand=None, placed: bool = True) -> dict:
    """What capture.json's ``settings.two_hands`` says about a two-hand scene: the
    placement rule (``placed``: made by :func:`place_second_hand`) and the closest
    vertex distance over the capture's frames and the held-out poses, millimetres."""
    out = {}
    if placed:
        out.update({"gap_mm": [1000 * g for g in TWO_HAND_GAP],
                    "margin_mm": 1000 * TWO_HAND_MARGIN, "cone_deg": TWO_HAND_CONE_DEG,
                    "tilt_deg": TWO_HAND_TILT_DEG})
    out["closest_mm"] = round(1000 * min(hand_distance(motion, f)
                                         for f in range(motion.n_frames)), 3)
    if eval_hand is not None:
        out["eval_closest_mm"] = round(1000 * min(hand_distance(eval_hand, f)
                                                  for f in range(eval_hand.n_frames)), 3)
    return out


def capture_key(settings: StageSettings, hand_digest: str) -> str:
    """Fingerprint of a capture's content: settings + the hand model's digest."""
    record = {k: v for k, v in asdict(settings).items()
              if k not in LEGACY_SETTINGS or v != LEGACY_SETTINGS[k]}
    text = json.dumps({"settings": record, "hand": hand_digest}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def hand_digest(hand) -> str:
    """SHA-256 (16 hex) of a hand's model and motion (poses, translations, roots, mirroring
    of every hand)."""
    h = hashlib.sha256()
    for arr in (hand.coarse.vertices, hand.fine.vertices, hand.fine.faces, hand.fine.uv,
                hand.rest_joints):
        h.update(np.ascontiguousarray(arr).tobytes())
    for inst in hand.hands:
        for arr in (inst.poses, inst.translations, inst.root, np.asarray([inst.mirror])):
            h.update(np.ascontiguousarray(np.asarray(arr, np.float64)).tobytes())
    return h.hexdigest()[:16]


@dataclass
class Plan:
    """Everything a capture will contain, before rendering.

    Attributes:
        motion: HandData with one frame per capture frame.
        cameras: list of Camera.  lights: ``formats.lights_json.Lights``.  light_names: list.
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


def stage_envmap(env, env_res):
    """``env`` (an EnvMap, any layout and size) resampled once to the stage's working
    lat-long grid ``env_res`` (H, W): exact and power preserving
    (:func:`relight_cli.envmap.resample`), so a 1k HDR costs its resampling once and the
    ground truth, the stored eval/envs/ map and the models' own discretization of that
    map all hold the same light."""
    from relight_cli import envmap as E
    h, w = (int(v) for v in env_res)
    if env.layout == "latlong" and (env.height, env.width) == (h, w):
        return env
    return E.resample(env, "latlong", h, w)


def hand_coverage(result, n_hands: int) -> list | None:
    """Per-hand [H, W] coverage of a render (:class:`~relight_cli.render.shading.RenderResult`),
    or None for a one-hand scene."""
    if n_hands < 2:
        return None
    return [result.gbuffer.coverage(k) for k in range(n_hands)]


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
                                           bounce=s.bounce, direct="texel",
                                           env_res=tuple(s.eval_env_res),
                                           env_space=s.eval_env_space,
                                           shadowing=s.ggx_shadowing),
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


def stage_settings(settings: dict) -> StageSettings | None:
    """The :class:`StageSettings` a capture.json ``settings`` object records (as
    ``synth-capture`` writes it), or None when it does not record every field (a
    converted real capture, or an older generator): only then can the stage be rebuilt.
    A setting added later (:data:`LEGACY_SETTINGS`) that the record lacks takes the value
    the older generator used."""
    from dataclasses import fields
    names = [f.name for f in fields(StageSettings)]
    if not isinstance(settings, dict):
        return None
    settings = {**LEGACY_SETTINGS, **settings}
    if not all(n in settings for n in names):
        return None
    values = {n: settings[n] for n in names}
    if values["eval_env_space"] not in ("texels", "vertices"):
        return None
    if values["ggx_shadowing"] not in ("smith", "schlick"):
        return None
    values["eval_env_res"] = tuple(values["eval_env_res"])
    try:
        return StageSettings(**values)
    except TypeError:
        return None


class StageShader:
    """The synthetic stage's own shader, rebuilt from a capture, evaluated anywhere.

    :meth:`texel_radiance` evaluates exactly what ``synth-capture`` evaluated at its
    pixel samples (texture-space irradiance with SSS at the stage's ``tex_res``, the
    procedural skin's albedo and roughness, the GGX lobe with texel-map visibility), but
    at the texel centres of another N×N map: the *perfect texture* of a learned model of
    that resolution — the best any texture-space model can do through the same
    compositing and pixel sampling (DESIGN.md, "How a learned model is judged").

    Args:
        hand: the capture's HandData (its hand.npz: model and motion).
        settings: the capture's :class:`StageSettings` (:func:`stage_settings`).
        lights: the stage's LEDs, a :class:`~relight_cli.formats.lights_json.Lights`.
    """

    def __init__(self, hand, settings: StageSettings, lights):
        from relight_cli.render.appearance import hand_materials
        from relight_cli.uvraster import rasterize_uv

        self.settings = settings
        self.lights = lights
        self.materials = hand_materials(hand, "fine", max(settings.tex_res, 256),
                                        settings.skin_seed)
        model = hand.mesh("fine")
        self.rasters = [rasterize_uv(model.uv, model.faces_uv, settings.tex_res)] * len(hand.hands)

    def renderer(self, meshes):
        """A stage renderer of posed fine ``meshes`` (as :meth:`FrameRenderer.renderer`)."""
        from .shading import HandRenderer, RenderSettings
        s = self.settings
        return HandRenderer(meshes, self.materials,
                            RenderSettings(tex_res=s.tex_res, aa=s.aa, sss=s.sss, bounce=s.bounce,
                                           direct="texel", env_res=tuple(s.eval_env_res),
                                           env_space=s.eval_env_space,
                                           shadowing=s.ggx_shadowing),
                            rasters=self.rasters)

    def texel_radiance(self, renderer, lighting, surfaces, eye) -> list:
        """Per hand [K_k, 3] float64 stage radiance at the texel centres of ``surfaces``
        (:class:`~relight_cli.render.shading.TexelSurface` of each hand, any N, same pose
        as ``renderer``; or any object with ``points``, ``normals``, ``uv`` and ``faces``,
        the texels' triangles) seen from ``eye`` [3], under ``lighting`` (``renderer.light``)."""
        from .gbuffer import GBuffer
        points = [np.asarray(s.points, np.float64) for s in surfaces]
        normals = [np.asarray(s.normals, np.float64) for s in surfaces]
        hand = np.concatenate([np.full(len(p), k, np.int64) for k, p in enumerate(points)])
        position = np.concatenate(points)
        normal = np.concatenate(normals)
        view = np.asarray(eye, np.float64)[None] - position
        view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-300)
        P = len(hand)
        from relight_cli.uvraster import UVLayout
        # each texel centre's triangle (a TexelSurface's raster, or a slice's ``faces``):
        # the seam-aware lookups read its own chart
        face = np.concatenate([np.asarray(s.faces if hasattr(s, "faces") else
                                          s.raster.face[s.inside], np.int64) for s in surfaces])
        layouts = [UVLayout.of(m.uv, m.faces_uv) for m in renderer.meshes]
        gb = GBuffer(width=P, height=1, spp=1, hand=hand, face=face,
                     barycentric=np.zeros((P, 3)),
                     uv=np.concatenate([np.asarray(s.uv, np.float64) for s in surfaces]),
                     position=position, normal=normal, depth=np.ones(P), view=view,
                     eye=np.asarray(eye, np.float64), layouts=layouts)
        radiance = renderer.render(None, lighting, gbuffer=gb).samples
        out, start = [], 0
        for p in points:
            out.append(radiance[start:start + len(p)])
            start += len(p)
        return out
