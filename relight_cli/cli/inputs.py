"""Inputs the commands share: an env map, a hand, a roughness map, a camera, placed
Gaussians, an env-map grid; fit-geometry's template, poses, keypoints (relight/keypoints
or Leap), frame range and scans.

Each loader takes what a user types (a path, ``builtin:NAME``, ``SOURCE[:PLACEMENT]``)
and returns the engine's object, with the toolkit's one-line errors (a bad spec is a
UsageProblem, exit 2; a bad file a DataError naming it).  Heavy modules are imported
when a loader is called (the commands import this module inside their callbacks).
"""

from __future__ import annotations


def env_grid(text: str, what: str = "--env-res"):
    """A ``WxH`` lat-long grid option → :class:`relight_cli.envmap.EnvGrid` ((height,
    width) to the engine); usage errors as :func:`relight_cli.cli.tools.parse_env_res`."""
    from relight_cli.cli.tools import parse_env_res
    from relight_cli.envmap import EnvGrid
    return EnvGrid.from_wh(*parse_env_res(text, what))


def load_envmap(spec: str, nonfinite: str = "error", negative: str = "error"):
    """An EnvMap from a file path or a ``builtin:NAME`` (see relight_cli.builtin_envs);
    ``negative``: ``error`` refuses negative radiance, ``keep`` leaves it to the caller."""
    if spec.startswith("builtin:"):
        from relight_cli.builtin_envs import builtin_envmap
        return builtin_envmap(spec)
    from relight_cli.cli.tools import check_input
    from relight_cli.formats.envmap import read_envmap
    check_input(spec)
    return read_envmap(spec, nonfinite=nonfinite, negative=negative)


def load_hand(spec: str):
    """HandData from a hand.npz or builtin:right|left|two[:POSE]."""
    from relight_cli.errors import UsageProblem
    if spec.startswith("builtin:"):
        from relight_cli.hand.scene import builtin_hands, parse_builtin_hand
        try:
            parse_builtin_hand(spec)
        except ValueError as exc:
            raise UsageProblem(str(exc)) from None
        return builtin_hands(spec)
    from relight_cli.cli.tools import check_input
    from relight_cli.formats.hand_npz import read_hand
    check_input(spec)
    return read_hand(spec)


def read_roughness_map(path: str):
    """[H, W] float64 roughness in (0, 1] from an EXR's Y or R channel (UV space)."""
    import numpy as np

    from relight_cli.errors import DataError
    from relight_cli.formats.exr import read_exr
    image = read_exr(path)
    name = next((c for c in ("Y", "R", "roughness.Y") if c in image.channels), None)
    if name is None:
        raise DataError("roughness map needs a Y or R channel", path)
    values = image.channels[name].astype(np.float64)
    if not np.isfinite(values).all() or values.min() <= 0 or values.max() > 1:
        raise DataError("roughness map values must be finite and in (0, 1]", path)
    return values


def parse_occluder(spec: str, what: str):
    """``SOURCE[:PLACEMENT]`` → (source, Placement); a bad spec is a usage error (exit 2)."""
    from relight_cli.errors import UsageProblem
    from relight_cli.gaussians.placement import USAGE, parse_spec
    try:
        return parse_spec(spec)
    except ValueError as exc:
        raise UsageProblem(f"bad {what} placement: {exc}; expected {USAGE}", spec) from None


def load_placed(source: str, placement, spec: str, offset=None, colour_space: str = "auto"):
    """Load Gaussians (PLY, mesh or builtin:) and apply the placement, then ``offset`` [3].
    ``colour_space``: the space a PLY's colours are stored in (load_gaussians)."""
    import numpy as np

    from relight_cli.errors import DataError
    from relight_cli.gaussians.from_mesh import load_gaussians
    from relight_cli.gaussians.placement import place

    if getattr(placement, "path", None) is not None:
        from relight_cli.errors import UsageProblem
        raise UsageProblem("path=FILE.json moves an object over a clip: give it to relight "
                           "relight --frames or dgsm-build --frames", spec)
    g = load_gaussians(source, frame=getattr(placement, "frame", None),
                       colour_space=colour_space)
    if len(g) == 0:
        raise DataError("no Gaussians", source)
    try:
        g = place(g, placement)
    except ValueError as exc:
        raise DataError(f"cannot place it: {exc}", spec) from None
    if offset is not None:
        g.means = g.means + np.asarray(offset, np.float64)
    # Beyond ~1000 km the float32 PLY/EXR outputs lose the millimetres (or overflow).
    reach = max(float(np.abs(g.means).max()), float(np.abs(g.scales).max()))
    if not reach <= 1e6:
        raise DataError(f"placed Gaussians reach {reach:.3g} m from the origin (more than "
                        f"1e6 m); check the placement's scale and translate", spec)
    return g


def roughness_value(text: str, what: str = "--roughness"):
    """A roughness option: a number in (0, 1] → float; anything else is a UV-space EXR
    map's path, checked to exist now and read by :func:`read_roughness_map` → None."""
    from relight_cli.cli.tools import check_input
    from relight_cli.errors import UsageProblem
    try:
        value = float(text)
    except ValueError:
        check_input(text)
        return None
    if not 0 < value <= 1:
        raise UsageProblem(f"{what} must be in (0, 1], got {text}")
    return value


def load_camera(spec: str, what: str = "--camera"):
    """The (first) camera of an OpenCV camera JSON file (``-`` reads stdin)."""
    from relight_cli.cli.tools import check_input
    from relight_cli.formats.camera import read_camera
    check_input(spec, stdin=what)
    return read_camera(spec)


# ---------------------------------------------------------------- fitting targets


def load_template(spec: str):
    """A fitting template (HandData, one hand, one rest frame): ``builtin:right|left``, a
    skinned glTF/GLB hand, or a hand.npz (its first hand, poses zeroed)."""
    from relight_cli.cli.tools import check_input
    from relight_cli.errors import DataError, UsageProblem

    if spec.startswith("builtin:"):
        side = spec.split(":", 1)[1]
        if side not in ("right", "left"):
            raise UsageProblem(f"unknown built-in template {spec!r}; use builtin:right or "
                               "builtin:left")
        from relight_cli.hand.model import builtin_hand
        return builtin_hand(side, pose=None)
    check_input(spec)
    lower = spec.lower()
    if lower.endswith((".glb", ".gltf")):
        from relight_cli.formats.hand_npz import validate
        from relight_cli.hand.gltf import import_gltf
        hand = import_gltf(spec)
        validate(hand, spec)   # degenerate geometry is refused now, naming the glTF
        return hand
    if lower.endswith(".npz"):
        import numpy as np

        from relight_cli.formats.hand_npz import read_hand
        hand = read_hand(spec)
        hand.hands = hand.hands[:1]
        hand.hands[0].poses = np.zeros((1,) + hand.hands[0].poses.shape[1:])
        hand.hands[0].translations = np.zeros((1, 3))
        return hand
    raise DataError("unknown template type (expected builtin:right|left, .glb/.gltf or .npz)",
                    spec)


def load_poses(spec: str, frames: int, seed: int, template):
    """``--pose`` for ``template``: a named pose, ``random`` (``frames`` seeded random
    poses) or a JSON file (``{"names": [...]}``, or poses [N, J, 3] axis-angle with
    optional translations [N, 3]) → (poses [N, J, 3], translations [N, 3])."""
    import numpy as np

    from relight_cli.cli.tools import check_input
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.hand import poses as P

    J = template.n_joints
    rest = template.rest_joints
    if spec == "random":
        p = P.random_poses(frames, seed=seed, side=template.side, rest_joints=rest)
        return p, np.zeros((frames, 3))
    if spec in P.POSE_NAMES:
        return P.named_pose(spec, template.side, rest)[None], np.zeros((1, 3))
    if not spec.endswith(".json"):
        raise UsageProblem(f"--pose must be one of {', '.join(P.POSE_NAMES)}, 'random' or a "
                           f".json file, got {spec!r}")
    from relight_cli.formats._common import read_json
    check_input(spec)
    obj = read_json(spec)
    if isinstance(obj, dict) and "names" in obj:
        try:
            p = np.stack([P.named_pose(n, template.side, rest) for n in obj["names"]])
        except (KeyError, TypeError) as exc:
            raise DataError(f"bad pose name: {exc}", spec) from None
        if len(p) == 0:
            raise DataError("'names' is empty", spec)
        return p, np.zeros((len(p), 3))
    poses_list = obj.get("poses") if isinstance(obj, dict) else obj
    try:
        p = np.asarray(poses_list, np.float64)
        t = (np.asarray(obj["translations"], np.float64)
             if isinstance(obj, dict) and "translations" in obj else np.zeros((len(p), 3)))
    except (TypeError, ValueError):
        raise DataError("'poses' must be an N × J × 3 array of numbers", spec) from None
    if p.ndim == 2:
        p = p[None]
    if p.ndim != 3 or p.shape[1:] != (J, 3) or len(p) == 0:
        raise DataError(f"'poses' must have shape (N, {J}, 3) axis-angle, got {p.shape}", spec)
    if t.shape != (len(p), 3):
        raise DataError(f"'translations' must have shape ({len(p)}, 3), got {t.shape}", spec)
    if not (np.isfinite(p).all() and np.isfinite(t).all()):
        raise DataError("poses or translations hold NaN/Inf", spec)
    return p, t


def leap_hand(text: str | None):
    """``--hand`` of a Leap recording: None (automatic), ``left``, ``right`` or a Leap hand
    id (int); anything else is a usage error."""
    from relight_cli.errors import UsageProblem
    from relight_cli.formats.leap import parse_hand_choice
    try:
        return parse_hand_choice(text)
    except ValueError as exc:
        raise UsageProblem(str(exc)) from None


def load_keypoints(spec: str, template, reader: str = "auto", hand=None, frames=None,
                   side_follows: bool = False):
    """3D keypoints of ``spec`` (relight/keypoints JSON/.npy, or a Leap recording) in
    ``template``'s joint order (a :class:`relight_cli.formats.keypoints.Keypoints`),
    checked against the template's handedness and cut to the ``frames`` slice of frame
    numbers (``--frames``: :func:`relight_cli.sequence.parse_frames`).  ``reader``: auto|keypoints|leap; ``hand``: the Leap
    hand (:func:`leap_hand`); ``side_follows``: a tracked hand of the other side than
    ``template``'s is returned (the caller takes the matching template) instead of
    refused."""
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.keypoints import read_keypoints

    kp = read_keypoints(spec, template.n_joints, reader, hand)
    if hand is not None and kp.source is None:
        raise UsageProblem("--hand applies to Leap recordings only")
    side = template.side
    if kp.side is not None and kp.side != side and not side_follows:
        raise DataError(f"the tracked hand is a {kp.side} hand but the template is a {side} "
                        f"hand; use --template builtin:{kp.side}", spec)
    if frames is not None:
        f = kp.frames
        start, step = frames.start or 0, frames.step or 1
        keep = (f >= start) & ((f - start) % step == 0)
        if frames.stop is not None:
            keep &= f < frames.stop
        if not keep.any():
            raise DataError(f"no keypoint frames in --frames {start}:"
                            f"{'' if frames.stop is None else frames.stop}:{step} (the file has "
                            f"frames {f[0]}…{f[-1]})", spec)
        kp.positions, kp.confidence, kp.frames = \
            kp.positions[keep], kp.confidence[keep], kp.frames[keep]
    return kp


def scan_paths(spec: str, what: str = "--scans") -> list:
    """A scan spec (one path, or a glob pattern such as ``scan_*.ply``) → the existing
    files in sorted order (a pattern matching nothing is a usage error)."""
    import glob

    from relight_cli.cli.tools import check_input
    from relight_cli.errors import UsageProblem
    paths = sorted(glob.glob(spec)) if any(c in spec for c in "*?[") else [spec]
    if not paths:
        raise UsageProblem(f"{what} {spec!r} matches no files")
    for p in paths:
        check_input(p)
    return paths


def load_scans(paths: list, seed: int = 0) -> list:
    """Points [P, 3] of each scan (PLY/OBJ/STL): 5000 seeded samples on a mesh's surface
    (scan i's seed drawn i-th from ``default_rng(seed)``), a point cloud's vertices."""
    import numpy as np
    rng = np.random.default_rng(seed)
    return [_read_scan(p, rng) for p in paths]


def _read_scan(path: str, rng):
    import numpy as np
    import trimesh

    from relight_cli.errors import DataError

    try:
        geom = trimesh.load(path, force=None, process=False)
    except Exception as exc:  # trimesh raises many types for damaged files
        raise DataError(f"unreadable scan: {type(exc).__name__}: {exc}", path) from None
    if isinstance(geom, trimesh.Scene):
        geom = geom.dump(concatenate=True) if geom.geometry else None
    if geom is None:
        raise DataError("scan is empty", path)
    if isinstance(geom, trimesh.Trimesh) and len(geom.faces):
        if geom.area <= 0:
            raise DataError("scan mesh has zero area", path)
        pts, _ = trimesh.sample.sample_surface(geom, 5000, seed=int(rng.integers(2**31)))
    else:
        pts = np.asarray(getattr(geom, "vertices", np.zeros((0, 3))))
    pts = np.asarray(pts, np.float64)
    if len(pts) < 10:
        raise DataError(f"scan has only {len(pts)} points", path)
    if not np.isfinite(pts).all():
        raise DataError("scan holds NaN/Inf coordinates", path)
    return pts


def load_capture(folder: str, config, cache_poses: int | None = None):
    """A capture folder (``relight/capture``, e.g. from ``synth-capture``) as the
    :class:`~relight_cli.neural.data.CaptureData` a learned model of ``config`` trains on
    and is scored with: its texel size, pixel sampling, visibility, falloff and held-out
    split (``cache_poses``: posed geometry kept in memory, default the config's)."""
    from relight_cli.neural.data import CaptureData
    return CaptureData(folder, config.tex_res, config.aa, config.visibility, config.falloff,
                       config.holdout, config.cache_poses if cache_poses is None else cache_poses)


def load_point_lights(path):
    """--lights as read (a ``formats.lights_json.Lights``, which the renderers shade with
    as is: radiant intensity colour × intensity), or None without --lights."""
    if path is None:
        return None
    from relight_cli.formats.lights_json import read_lights
    return read_lights(path)


def load_albedo(path):
    """--albedo's [H, W, 3] UV albedo (None without one)."""
    if path is None:
        return None
    from relight_cli.errors import DataError
    from relight_cli.formats.image import read_image
    pixels, _names = read_image(path)
    if pixels.shape[2] < 3:
        raise DataError("albedo map needs 3 colour channels", path)
    return pixels[..., :3]


def parse_auto_lights(spec: str):
    """``--lights auto:K`` → K (1 ≤ K ≤ 64), None for a lights file; a usage error for
    ``auto`` without a count or one out of range."""
    from relight_cli.errors import UsageProblem
    if not spec.startswith("auto"):
        return None
    try:
        k = int(spec.split(":", 1)[1])
    except (IndexError, ValueError):
        raise UsageProblem(f"--lights auto needs a count, e.g. auto:2, got {spec!r}") from None
    if not 1 <= k <= 64:
        raise UsageProblem(f"--lights auto:K needs 1 ≤ K ≤ 64, got {k}")
    return k
