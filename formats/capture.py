"""Light-stage captures: ``capture.json`` + per-frame EXR images (spec: ``formats/capture.md``).

A capture folder holds ``capture.json`` (format ``relight/capture``), the
ground-truth ``hand.npz`` (model + per-frame poses), the images
``images/{frame:06d}/{camera}.exr`` (R, G, B linear radiance, A = hand mask)
and optionally held-out evaluation renders under env maps.

This module reads, validates and writes those files; it does not render.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field

import numpy as np

from relight_cli.errors import DataError

FORMAT = "relight/capture"
VERSION = 1
IMAGE_FORMAT = "relight/capture-image"
IMAGE_VERSION = 1
INDEX = "capture.json"


@dataclass
class CaptureFrame:
    """One time step of the capture.

    Attributes:
        index: frame number (images live in ``images/{index:06d}/``).
        time: seconds since the start.
        pose: index of the pose in the capture's hand.npz frames.
        lit: "full" (every light on) or "group" (a few neighbouring lights).
        lights_on: indices of the lights that are on.
        images: names of the cameras whose image of this frame exists.
    """

    index: int
    time: float
    pose: int
    lit: str
    lights_on: list
    images: list = field(default_factory=list)


@dataclass
class Capture:
    """A light-stage capture.

    Attributes:
        cameras: list of ``relight_cli.formats.camera.Camera`` with unique names.
        light_positions: [L, 3] float64 metres, world.
        light_intensity: [L, 3] float64 linear RGB radiant intensity (irradiance I/r²).
        light_names: L names.
        frames: list of :class:`CaptureFrame`.
        hand: path of the hand.npz relative to the folder.
        fps: frame rate (frames per second).
        evaluation: held-out renders: {"hand": path, "envs": {name: path},
            "renders": [{"pose", "env", "camera", "image"}]} or None.
        key: fingerprint of what was rendered (settings + inputs); images carry it too,
            so a resumed run trusts only images of the same capture.
        complete: every planned image exists.
        settings: generator settings (free-form JSON object).
        provenance: provenance record.
    """

    cameras: list
    light_positions: np.ndarray
    light_intensity: np.ndarray
    light_names: list
    frames: list
    hand: str = "hand.npz"
    fps: float = 30.0
    evaluation: dict | None = None
    key: str = ""
    complete: bool = False
    settings: dict = field(default_factory=dict)
    provenance: dict | None = None

    def camera(self, name: str):
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise KeyError(name)


def image_path(frame: int, camera: str) -> str:
    """Path of a capture image relative to the capture folder."""
    return os.path.join("images", f"{int(frame):06d}", f"{camera}.exr")


def to_json(capture: Capture) -> dict:
    out = {
        "format": FORMAT, "version": VERSION,
        "hand": capture.hand, "fps": float(capture.fps), "key": capture.key,
        "complete": bool(capture.complete),
        "cameras": [c.to_json() for c in capture.cameras],
        "lights": [{"name": n, "position": [float(v) for v in p],
                    "intensity": [float(v) for v in i]}
                   for n, p, i in zip(capture.light_names, capture.light_positions,
                                      capture.light_intensity)],
        "frames": [{"index": f.index, "time": float(f.time), "pose": f.pose, "lit": f.lit,
                    "lights_on": [int(i) for i in f.lights_on], "images": list(f.images)}
                   for f in capture.frames],
    }
    if capture.evaluation is not None:
        out["evaluation"] = capture.evaluation
    if capture.settings:
        out["settings"] = capture.settings
    if capture.provenance is not None:
        out["provenance"] = capture.provenance
    return out


def write_capture(path: str, capture: Capture) -> None:
    """Write ``capture.json`` atomically (rounding-free floats)."""
    from relight_cli.fileio import write_text_atomic
    validate(capture, path)
    write_text_atomic(path, json.dumps(to_json(capture), indent=1, allow_nan=False) + "\n")


def _int(value, what, path, lo=0, hi=None):
    if not isinstance(value, int) or isinstance(value, bool) or value < lo or (
            hi is not None and value >= hi):
        rng = f"[{lo}, {hi})" if hi is not None else f"≥ {lo}"
        raise DataError(f"{what} must be an integer in {rng}, got {value!r}", path)
    return value


def _finite_list(value, n, what, path):
    if (not isinstance(value, list) or len(value) != n
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
            or not all(math.isfinite(v) for v in value)):
        raise DataError(f"{what} must be a list of {n} finite numbers", path)
    return [float(v) for v in value]


def _string(value, what, path, empty=False):
    if not isinstance(value, str) or (not empty and not value):
        raise DataError(f"{what} must be a{'' if empty else ' non-empty'} string, got "
                        f"{value!r}"[:200], path)
    return value


#: The sizes and counts a ``settings`` object may record (inclusive bounds; the limits
#: of ``synth-capture``'s options): a stage rebuilt from them (the learned models'
#: ceiling) allocates by them, so a value beyond is refused before any work
#: (formats/capture.md).  ``eval_env_res`` is [H, W].
SETTINGS_LIMITS = {"res": (1, 4096), "tex_res": (1, 4096), "aa": (1, 8),
                   "cameras": (1, 1000), "lights": (1, 10_000), "group": (1, 10_000),
                   "frames": (1, 100_000), "full_every": (1, 100_000),
                   "keyframe_every": (1, 100_000),
                   # seeds as synth-capture's --seed and --skin-seed take them (numpy's)
                   "seed": (0, 2**32 - 1), "skin_seed": (0, 2**32 - 1)}
EVAL_ENV_RES_LIMITS = ((1, 4096), (1, 8192))
#: The other settings the stage is rebuilt from, each in synth-capture's domain: on/off
#: switches, the dome's radii (metres) and clock, and the choices of its options.
SETTINGS_FLAGS = ("sss", "bounce")
SETTINGS_POSITIVE = ("camera_radius", "light_radius", "fps")
SETTINGS_CHOICES = {"eval_env_space": ("texels", "vertices"),
                    "ggx_shadowing": ("smith", "schlick")}


def _settings(settings, path):
    """Check what ``settings`` records that the stage is rebuilt from: the sizes and counts
    (:data:`SETTINGS_LIMITS`), the switches, radii and choices (a string where a number
    belongs is one line naming the file, not an internal error of the stage); any other
    field is free form."""
    from ._common import MAX_POSITION
    for key, (lo, hi) in SETTINGS_LIMITS.items():
        if key in settings:
            _int(settings[key], f"settings.{key}", path, lo, hi + 1)
    for key in SETTINGS_FLAGS:
        if key in settings and not isinstance(settings[key], bool):
            raise DataError(f"settings.{key} must be true or false, got "
                            f"{settings[key]!r}"[:200], path)
    for key in SETTINGS_POSITIVE:
        value = settings.get(key, 1.0)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                math.isfinite(value) and 0 < value <= MAX_POSITION):
            raise DataError(f"settings.{key} must be a number in (0, {MAX_POSITION:g}], got "
                            f"{value!r}"[:200], path)
    for key, choices in SETTINGS_CHOICES.items():
        if key in settings and settings[key] not in choices:
            raise DataError(f"settings.{key} must be {' or '.join(choices)}, got "
                            f"{settings[key]!r}"[:200], path)
    if "eval_env_res" in settings:
        value = settings["eval_env_res"]
        if (not isinstance(value, list) or len(value) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi
                           for v, (lo, hi) in zip(value, EVAL_ENV_RES_LIMITS))):
            (hlo, hhi), (wlo, whi) = EVAL_ENV_RES_LIMITS
            raise DataError(f"settings.eval_env_res must be [H, W], integers with H in "
                            f"[{hlo}, {hhi}] and W in [{wlo}, {whi}], got {value!r}"[:200], path)


def _inside(value, what, path):
    """A file the capture names: a relative path inside the capture folder (no absolute
    path, no ``..`` leaving it), so a capture reads only its own files."""
    norm = os.path.normpath(value)
    if os.path.isabs(value) or norm == ".." or norm.startswith(".." + os.sep):
        raise DataError(f"{what} must be a path inside the capture folder, got {value!r}"[:200],
                        path)
    return value


def _evaluation(ev, camera_names, path):
    """The checked ``evaluation`` object: ``hand`` (a path), ``envs`` (name → path) and
    ``renders`` (each a pose ≥ 0, one of the envs, one of the cameras and an image path)."""
    if not isinstance(ev, dict):
        raise DataError("'evaluation' must be an object with hand, envs and renders", path)
    for key in ("hand", "envs", "renders"):
        if key not in ev:
            raise DataError(f"'evaluation' lacks '{key}'", path)
    _inside(_string(ev["hand"], "evaluation.hand", path), "evaluation.hand", path)
    envs = ev["envs"]
    if not isinstance(envs, dict):
        raise DataError("evaluation.envs must be an object (env name → env map path)", path)
    for name, file in envs.items():
        _inside(_string(file, f"evaluation.envs[{name!r}]", path), f"evaluation.envs[{name!r}]",
                path)
    if not isinstance(ev["renders"], list):
        raise DataError("evaluation.renders must be a list", path)
    for i, r in enumerate(ev["renders"]):
        what = f"evaluation.renders[{i}]"
        if not isinstance(r, dict):
            raise DataError(f"{what} must be an object with pose, env, camera and image", path)
        _int(r.get("pose"), f"{what}.pose", path)
        if r.get("env") not in envs:
            raise DataError(f"{what}.env must name one of evaluation.envs, got "
                            f"{r.get('env')!r}"[:200], path)
        if r.get("camera") not in camera_names:
            raise DataError(f"{what}.camera must name one of the cameras, got "
                            f"{r.get('camera')!r}"[:200], path)
        _inside(_string(r.get("image"), f"{what}.image", path), f"{what}.image", path)
    return ev


def capture_from_json(obj, path: str = "") -> Capture:
    """A :class:`Capture` from parsed ``capture.json``, every field checked against
    formats/capture.md (one-line DataErrors naming ``path``)."""
    from relight_cli.formats.camera import camera_from_json

    if not isinstance(obj, dict):
        raise DataError("expected a JSON object", path)
    if obj.get("format") != FORMAT:
        raise DataError(f"not a {FORMAT} file (format is {obj.get('format')!r})", path)
    version = obj.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise DataError("missing or invalid 'version'", path)
    if version > VERSION:
        raise DataError(f"{FORMAT} version {version} is newer than this relight understands "
                        f"(≤ {VERSION})", path, hint="upgrade relight")
    for key in ("cameras", "lights", "frames"):
        if not isinstance(obj.get(key), list):
            raise DataError(f"'{key}' must be a list", path)
    if "hand" not in obj:
        raise DataError("'hand' is missing (the path of the capture's hand.npz)", path)
    hand = _inside(_string(obj["hand"], "'hand' (the path of the capture's hand.npz)", path),
                   "'hand'", path)
    fps = obj.get("fps", 30.0)
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not (
            math.isfinite(fps) and fps > 0):
        raise DataError(f"'fps' must be a positive number, got {fps!r}"[:200], path)
    key = _string(obj.get("key", ""), "'key'", path, empty=True)
    complete = obj.get("complete", False)
    if not isinstance(complete, bool):
        raise DataError(f"'complete' must be true or false, got {complete!r}"[:200], path)
    settings = obj.get("settings", {})
    if not isinstance(settings, dict):
        raise DataError("'settings' must be an object", path)
    _settings(settings, path)
    provenance = obj.get("provenance")
    if provenance is not None and not isinstance(provenance, dict):
        raise DataError("'provenance' must be an object", path)
    if not obj["cameras"]:
        raise DataError("'cameras' is empty", path)
    cameras = [camera_from_json(c, path, i) for i, c in enumerate(obj["cameras"])]
    lights = obj["lights"]
    from .lights_json import MAX_LIGHTS
    if len(lights) > MAX_LIGHTS:
        raise DataError(f"{len(lights):,} lights; a capture holds at most {MAX_LIGHTS:,}", path)
    positions, intensity, names = [], [], []
    for i, item in enumerate(lights):
        if not isinstance(item, dict) or "position" not in item:
            raise DataError(f"lights[{i}] must be an object with a position", path)
        positions.append(_finite_list(item["position"], 3, f"lights[{i}].position", path))
        inten = _finite_list(item.get("intensity", [1.0, 1.0, 1.0]), 3,
                             f"lights[{i}].intensity", path)
        if min(inten) < 0:
            raise DataError(f"lights[{i}].intensity must be non-negative", path)
        from ._common import MAX_POSITION, MAX_VALUE, bounded
        bounded(positions[-1], f"lights[{i}].position", path, MAX_POSITION)
        bounded(inten, f"lights[{i}].intensity", path, MAX_VALUE)
        intensity.append(inten)
        names.append(_string(item.get("name", f"light{i:03d}"), f"lights[{i}].name", path))
    n_lights = len(lights)
    frames = []
    for i, item in enumerate(obj["frames"]):
        if not isinstance(item, dict):
            raise DataError(f"frames[{i}] must be an object", path)
        index = _int(item.get("index"), f"frames[{i}].index", path)
        t = item.get("time", index / fps)
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t):
            raise DataError(f"frames[{i}].time must be a finite number", path)
        pose = _int(item.get("pose"), f"frames[{i}].pose", path)
        lit = item.get("lit", "group")
        if lit not in ("full", "group"):
            raise DataError(f"frames[{i}].lit must be 'full' or 'group', got {lit!r}", path)
        on = item.get("lights_on", [])
        if not isinstance(on, list):
            raise DataError(f"frames[{i}].lights_on must be a list", path)
        on = [_int(v, f"frames[{i}].lights_on", path, 0, n_lights) for v in on]
        images = item.get("images", [])
        if not isinstance(images, list) or not all(isinstance(s, str) for s in images):
            raise DataError(f"frames[{i}].images must be a list of camera names", path)
        frames.append(CaptureFrame(index, float(t), pose, lit, on, images))
    evaluation = obj.get("evaluation")
    if evaluation is not None:
        evaluation = _evaluation(evaluation, {c.name for c in cameras}, path)
    cap = Capture(cameras, np.array(positions, np.float64).reshape(-1, 3),
                  np.array(intensity, np.float64).reshape(-1, 3), names, frames,
                  hand=hand, fps=float(fps), evaluation=evaluation, key=key,
                  complete=complete, settings=settings, provenance=provenance)
    validate(cap, path)
    return cap


def validate(capture: Capture, path: str = "") -> None:
    names = [c.name for c in capture.cameras]
    if any(not n for n in names):
        raise DataError("every camera needs a name (images are named after it)", path)
    if len(set(names)) != len(names):
        raise DataError("camera names must be unique", path)
    bad = [n for n in names if "/" in n or "\\" in n or n in (".", "..")]
    if bad:
        raise DataError(f"camera name {bad[0]!r} cannot be a file name", path)
    indices = [f.index for f in capture.frames]
    if len(set(indices)) != len(indices):
        raise DataError("frame indices must be unique", path)
    for f in capture.frames:
        unknown = [n for n in f.images if n not in names]
        if unknown:
            raise DataError(f"frame {f.index} lists images of unknown camera {unknown[0]!r}", path)
        if len(set(f.images)) != len(f.images):   # one image, trained on and scored twice
            twice = next(n for i, n in enumerate(f.images) if n in f.images[:i])
            raise DataError(f"frame {f.index} lists camera {twice!r} twice in images", path)
    n_lights = len(capture.light_positions)
    for f in capture.frames:
        # every frame is lit: a frame with no light on has nothing to learn from (and no
        # lights to sum over); a light listed twice would count twice
        if not f.lights_on:
            raise DataError(f"frame {f.index} has no light on (its lights_on is empty or "
                            f"missing)", path)
        seen = set()
        for i in f.lights_on:
            if not 0 <= int(i) < n_lights:
                raise DataError(f"frame {f.index} turns on light {i}, but the capture has "
                                f"{n_lights} light(s)", path)
            if i in seen:
                raise DataError(f"frame {f.index} lists light {i} twice in lights_on", path)
            seen.add(i)


def index_path(path: str) -> str:
    """The ``capture.json`` of a capture given as its folder or as the index itself.

    Raises DataError naming the path: a folder without ``capture.json``, and a
    ``capture.json`` that is a folder (not a file) — whichever of the two was given.
    """
    if os.path.isdir(path):
        inner = os.path.join(path, INDEX)
        if os.path.isdir(inner):
            raise DataError(f"{INDEX} is a folder, not a file", inner)
        if os.path.lexists(inner):
            return inner
        if os.path.basename(os.path.normpath(path)) == INDEX:
            raise DataError("is a folder, not a file (a capture's index is a JSON file)", path)
        raise DataError(f"not a capture folder (no {INDEX})", path)
    return path


def read_capture(path: str) -> Capture:
    """Read ``capture.json`` (or a folder holding it).  Raises DataError naming the file."""
    path = index_path(path)
    from ._common import read_json
    obj = read_json(path)
    return capture_from_json(obj, path)


# ---------------------------------------------------------------- images


def immediate_writes():
    """Writes inside this block land at once, even inside a command's all-or-nothing
    output transaction: a resumable capture must keep every finished frame when a
    later one fails or the run is interrupted."""
    from relight_cli.fileio import outside_transaction
    return outside_transaction()


def hand_channel(hand: int) -> str:
    """EXR channel of hand ``hand``'s coverage (hand.npz order) in a scene of two or more."""
    return f"hand{int(hand)}.A"


def write_image(path: str, rgb: np.ndarray, mask: np.ndarray, key: str,
                attributes: dict | None = None, provenance: dict | None = None,
                camera=None, hand_masks=None) -> None:
    """Write one capture image: R, G, B (linear radiance, half floats), A (mask) and, for a
    scene of several hands, each hand's coverage (``hand_masks``: [H, W] per hand); with
    ``camera``, also OpenEXR's worldToCamera and worldToNDC (formats/exr.py)."""
    from relight_cli.formats.exr import write_exr
    channels = {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "A": mask}
    for k, coverage in enumerate(hand_masks or []):
        channels[hand_channel(k)] = coverage
    attrs = {"relight.capture_key": key, **(attributes or {})}
    record = dict(provenance or {}, format=IMAGE_FORMAT, version=IMAGE_VERSION)
    write_exr(path, channels, attributes=attrs, half=True, provenance=record, camera=camera)


def read_image(path: str, camera=None) -> tuple[np.ndarray, np.ndarray]:
    """([H, W, 3] float32 radiance, [H, W] float32 mask) of a capture image.

    Raises DataError for a damaged file, a newer version of the format, missing
    channels, non-finite pixels, or a size different from ``camera``'s.  Images of
    other tools (a converted real capture) may carry no relight header.
    """
    return read_image_hands(path, camera, 0)[:2]


def read_image_hands(path: str, camera=None, n_hands: int = 0):
    """(radiance [H, W, 3], mask [H, W], per-hand coverage [n_hands, H, W] or None) of a
    capture image, float32; the coverage is None when the image has no per-hand channels
    (one-hand captures, converted real captures) or ``n_hands`` < 2.

    Raises DataError as :func:`read_image`, and for a partial set of per-hand channels.
    """
    from relight_cli.formats.exr import FORMAT_KEY, VERSION_KEY, read_exr

    from ._common import check_format_version
    image = read_exr(path)
    if FORMAT_KEY in image.attributes or VERSION_KEY in image.attributes:
        check_format_version(image.attributes.get(FORMAT_KEY), image.attributes.get(VERSION_KEY),
                             IMAGE_FORMAT, IMAGE_VERSION, path)
    missing = [c for c in "RGBA" if c not in image.channels]
    if missing:
        raise DataError(f"capture image lacks channel(s) {', '.join(missing)}", path)
    rgb = np.stack([image.channels[c] for c in "RGB"], -1)
    mask = image.channels["A"]
    if camera is not None and rgb.shape[:2] != (camera.height, camera.width):
        raise DataError(f"image is {rgb.shape[1]}x{rgb.shape[0]}, camera {camera.name!r} is "
                        f"{camera.width}x{camera.height}", path)
    if not (np.isfinite(rgb).all() and np.isfinite(mask).all()):
        raise DataError("capture image holds NaN/Inf pixels", path)
    hands = None
    names = [hand_channel(k) for k in range(n_hands)] if n_hands >= 2 else []
    present = [n for n in names if n in image.channels]
    if present:
        if len(present) != len(names):
            absent = next(n for n in names if n not in image.channels)
            raise DataError(f"capture image has per-hand channels but lacks {absent}", path)
        hands = np.stack([image.channels[n] for n in names]).astype(np.float32)
        if not np.isfinite(hands).all():
            raise DataError("capture image holds NaN/Inf per-hand coverage", path)
    return rgb, mask, hands


def image_is_valid(path: str, camera, key: str) -> bool:
    """True when ``path`` is a complete, readable image of this capture (``key``) and size."""
    from relight_cli.formats.exr import read_exr
    if not os.path.isfile(path):
        return False
    try:
        image = read_exr(path)
        if image.attributes.get("relight.capture_key") != key:
            return False
        read_image(path, camera)
    except DataError:
        return False
    return True
