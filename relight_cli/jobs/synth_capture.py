"""A synthetic light-stage capture: ``relight synth-capture``'s plan and renders as an
engine job.

:func:`light_stage` takes a loaded hand (a :class:`~relight_cli.hand.model.HandData`,
one or two hands), the evaluation env maps and the :class:`StageSettings` and returns a
:class:`LightStage`: the plan (motion, dome of cameras and LEDs, each frame's lit LEDs,
the capture key), the held-out poses and the env maps on the stage's working grid.  Its
:meth:`LightStage.frame` and :meth:`LightStage.held_out` render the images a capture
holds, camera by camera, so a caller renders only what it still needs (a resumed
capture skips finished images).

:func:`write_capture_folder` renders and writes the capture folder
(:mod:`relight_cli.formats.capture`): the one job that writes, because a capture is
resumable only when each image lands on disk as soon as it is rendered.  ``relight
synth-capture`` and the studies (``benchmarks/study_hands.py``) call it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from functools import cached_property

import numpy as np

from relight_cli.render.capture import StageSettings

__all__ = ["LightStage", "StageRender", "StageSettings", "env_name", "light_stage",
           "make_capture", "write_capture_folder"]

#: Offset of the held-out poses' seed from the capture's (a motion of its own).
EVAL_SEED_OFFSET = 7919


@dataclass
class StageRender:
    """One rendered image: ``image`` [H, W, 3] float32 linear RGB over black, ``mask``
    [H, W] coverage, ``hand_masks`` (each hand's [H, W] coverage; None for one hand)."""

    camera: object
    image: np.ndarray
    mask: np.ndarray
    hand_masks: list | None = None


class LightStage:
    """A planned capture (see :func:`light_stage`).

    Attributes:
        settings: the StageSettings (``frames``: the motion's).  plan: the
            :class:`relight_cli.render.capture.Plan` (motion, cameras, lights, frames, key).
        eval_hand: HandData of the held-out poses, or None.  eval_poses: their number.
        envs: the evaluation EnvMaps resampled to ``settings.eval_env_res`` (what the
            ground truth integrates and a capture stores in eval/envs/).
        n_hands: hands in the scene.  record: the stage settings a capture records
            (StageSettings' fields; with two hands their placement, ``two_hands``).
    """

    def __init__(self, settings, plan, eval_hand, eval_poses: int, envs, placed: bool):
        self.settings, self.plan, self.eval_hand, self.envs = settings, plan, eval_hand, envs
        self.eval_poses = eval_poses if eval_hand is not None else 0
        self.n_hands = len(plan.motion.hands)
        self._placed = placed

    @property
    def key(self) -> str:
        return self.plan.key

    @cached_property
    def record(self) -> dict:
        from relight_cli.render.capture import two_hand_record
        stage = asdict(self.settings)
        if self.n_hands == 2:
            stage["two_hands"] = two_hand_record(self.plan.motion, self.eval_hand,
                                                 placed=self._placed)
        return stage

    @cached_property
    def renderer(self):
        """The :class:`~relight_cli.render.capture.FrameRenderer` (the skin's materials
        and the UV rasterization, made at the first render)."""
        from relight_cli.render.appearance import hand_materials
        from relight_cli.render.capture import FrameRenderer
        s = self.settings
        materials = hand_materials(self.plan.motion, "fine", max(s.tex_res, 256), s.skin_seed)
        return FrameRenderer(self.plan, materials, s)

    def frame(self, frame, cameras=None):
        """Yield a :class:`StageRender` of capture frame ``frame`` (a ``plan.frames``
        item, its LEDs on) per camera of ``cameras`` (default: every camera)."""
        for cam, result in self.renderer.frame(frame, cameras):
            yield self._render(cam, result)

    def held_out(self, pose: int, env: int, cameras):
        """Yield a :class:`StageRender` of held-out pose ``pose`` under ``envs[env]`` per
        camera of ``cameras``."""
        for cam, result in self.renderer.env_views(self.eval_hand, pose, self.envs[env],
                                                   cameras):
            yield self._render(cam, result)

    def _render(self, cam, result) -> StageRender:
        from relight_cli.render.capture import hand_coverage
        return StageRender(cam, result.image, result.mask, hand_coverage(result, self.n_hands))


def light_stage(data, envs, settings: StageSettings, motion: str = "random",
                eval_poses: int = 0) -> LightStage:
    """Plan a light-stage capture of ``data``.

    Args:
        data: HandData (one or two hands).
        envs: EnvMaps of the held-out renders (any layout and size: each is resampled
            once, power preserving, to ``settings.eval_env_res``).
        settings: :class:`StageSettings`; with ``motion="file"`` its ``frames`` is
            replaced by ``data``'s own frame count.
        motion: ``random`` (slerp between seeded random key poses; two hands placed to
            interact) or ``file`` (``data``'s own frames).
        eval_poses: held-out poses (a random motion of the scene's hands, seeded by
            ``settings.seed`` + :data:`EVAL_SEED_OFFSET`); 0 for none.
    """
    from relight_cli.render.capture import hand_motion, plan_capture, stage_envmap

    if motion not in ("random", "file"):
        raise ValueError(f"motion must be random or file, got {motion!r}")
    if motion == "file":
        settings = replace(settings, frames=data.n_frames)
    envs = [stage_envmap(env, settings.eval_env_res) for env in envs]
    plan = plan_capture(data, settings, motion=data if motion == "file" else None)
    eval_hand = (hand_motion(data, eval_poses, settings.seed + EVAL_SEED_OFFSET,
                             keyframe_every=1) if eval_poses else None)
    return LightStage(settings, plan, eval_hand, eval_poses, envs, placed=motion == "random")


def make_capture(output: str, hand: str = "builtin:right", *, motion: str = "random",
                 eval_poses: int = 2, eval_envs=("builtin:sky", "builtin:studio"),
                 eval_cameras: int = 4, quiet: bool = True, **settings):
    """``relight synth-capture HAND -o OUTPUT`` from Python (its defaults; byte-identical
    folders): the hand and env maps loaded from their specs, :func:`light_stage`, then
    :func:`write_capture_folder`.  ``settings``: :class:`StageSettings` fields (``lights``
    is the command's ``--leds``, ``res`` its ``--size``).  → (Capture, rendered, skipped).
    ``hand`` is ``builtin:right|left|two[:POSE]`` or a hand.npz, each env map
    ``builtin:NAME`` or a file, read by the engine and the formats (the command's own
    loaders, :mod:`relight_cli.cli.inputs`, live in the CLI).  The command's usage
    checks are not repeated here (ValueError/TypeError from the engine instead)."""
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.formats.envmap import read_envmap
    from relight_cli.formats.hand_npz import read_hand
    from relight_cli.hand.scene import builtin_hands
    envs = list(eval_envs) if eval_poses else []
    loaded = builtin_hands(hand) if hand.startswith("builtin:") else read_hand(hand)
    stage = light_stage(loaded, [builtin_envmap(spec) if spec.startswith("builtin:")
                                 else read_envmap(spec) for spec in envs],
                        StageSettings(**settings), motion, eval_poses)
    return write_capture_folder(output, stage, hand, envs, eval_cameras, quiet)


def env_name(spec: str) -> str:
    """The name an evaluation env map has in a capture (``eval/envs/NAME.exr``): the file's
    stem, or a built-in's name."""
    import os
    return os.path.basename(spec.split(":", 1)[1] if spec.startswith("builtin:") else spec) \
        .split(".", 1)[0]


def write_capture_folder(output: str, stage: LightStage, hand: str, env_specs: list,
                         eval_cameras: int, quiet: bool = True):
    """Render ``stage`` into the capture folder ``output`` (formats/capture.md), resuming:
    images already there and valid for the stage's key are kept.  → (Capture index,
    images rendered, images skipped).

    Args:
        output: the folder (made if missing; a folder this call makes is removed again
            when it fails before anything is in it).
        stage: from :func:`light_stage` (its ``envs`` are ``env_specs``' maps).
        hand: the HAND spec the capture records as its input (provenance).
        env_specs: the evaluation env map specs (their names: :func:`env_name`).
        eval_cameras: cameras (the dome's first N) of the evaluation renders.
        quiet: no progress lines on stderr.
    """
    import os
    from dataclasses import asdict

    from relight_cli.formats import capture as C
    from relight_cli.provenance import provenance

    inputs = {"hand": hand}
    env_names = [env_name(spec) for spec in env_specs]
    capture = _index(stage, env_names, eval_cameras,
                     provenance(C.FORMAT, C.VERSION, inputs, asdict(stage.settings)))
    # A folder this call makes is removed again when it fails before anything is in it (a
    # full disk, a folder where no file can be created); one the caller gave, and anything
    # written (kept for a resume), stay.
    made = not os.path.lexists(output)
    try:
        rendered, skipped = _write(output, capture, stage, inputs, env_names, env_specs,
                                   eval_cameras, quiet)
    except BaseException:
        if made:
            _remove_empty_tree(output)
        raise
    return capture, rendered, skipped


def _index(stage, env_names, eval_cameras, record):
    """The capture's index (capture.json, ``complete`` false until every file is written)."""
    from relight_cli.formats import capture as C
    plan = stage.plan
    evaluation = None
    if stage.eval_hand is not None:
        evaluation = {"hand": "eval/hand.npz",
                      "envs": {n: f"eval/envs/{n}.exr" for n in env_names},
                      "renders": [{"pose": p, "env": n, "camera": c.name,
                                   "image": f"eval/{p:03d}/{n}/{c.name}.exr"}
                                  for p in range(stage.eval_poses) for n in env_names
                                  for c in plan.cameras[:eval_cameras]]}
    return C.Capture(plan.cameras, plan.lights.positions, plan.lights.radiant_intensity(),
                     plan.light_names, plan.frames, "hand.npz", stage.settings.fps, evaluation,
                     plan.key, False, stage.record, record)


def _remove_empty_tree(folder: str) -> None:
    """Remove ``folder`` if it holds nothing but empty folders (never a file)."""
    import os
    for root, dirs, files in os.walk(folder, topdown=False):
        if files:
            return
        try:
            os.rmdir(root)
        except OSError:
            return


def _write(output, capture, stage, inputs, env_names, env_specs, eval_cameras, quiet):
    """Write the capture (resumable: finished files land at once); (rendered, skipped)."""
    import os

    from relight_cli.progress import progress
    from relight_cli.formats import capture as C
    from relight_cli.formats.hand_npz import write_hand
    from relight_cli.provenance import provenance

    plan = stage.plan
    index_path = os.path.join(output, C.INDEX)
    rendered = skipped = 0
    with C.immediate_writes():
        os.makedirs(output, exist_ok=True)
        # the index first (complete: false): a run stopped after it resumes, whatever
        # else it wrote
        C.write_capture(index_path, capture)
        write_hand(os.path.join(output, "hand.npz"), plan.motion,
                   provenance("relight/hand", 1, inputs, {"role": "capture ground truth",
                                                          "key": plan.key}))
        for frame in progress(plan.frames, desc="frames", quiet=quiet):
            folder = os.path.join(output, "images", f"{frame.index:06d}")
            todo = [c for c in plan.cameras
                    if not C.image_is_valid(os.path.join(output, C.image_path(frame.index, c.name)),
                                            c, plan.key)]
            skipped += len(plan.cameras) - len(todo)
            if todo:
                os.makedirs(folder, exist_ok=True)
                for r in stage.frame(frame, todo):
                    C.write_image(os.path.join(output, C.image_path(frame.index, r.camera.name)),
                                  r.image, r.mask, plan.key,
                                  {"relight.frame": frame.index, "relight.camera": r.camera.name,
                                   "relight.lit": frame.lit},
                                  provenance("relight/capture-image", 1, inputs,
                                             {"frame": frame.index, "camera": r.camera.name}),
                                  camera=r.camera, hand_masks=r.hand_masks)
                    rendered += 1
            frame.images = [c.name for c in plan.cameras]
        if capture.evaluation is not None:
            held = _write_held_out(output, stage, inputs, env_names, env_specs,
                                   eval_cameras, quiet)
            rendered, skipped = rendered + held[0], skipped + held[1]
        capture.complete = True
        C.write_capture(index_path, capture)
    return rendered, skipped


def _write_held_out(output, stage, inputs, env_names, env_specs, eval_cameras, quiet) -> int:
    """The held-out poses, env maps and renders under eval/ (resumable); (images
    rendered, images already there)."""
    import os

    from relight_cli.progress import progress
    from relight_cli.formats import capture as C
    from relight_cli.formats.envmap import write_envmap
    from relight_cli.formats.hand_npz import write_hand
    from relight_cli.provenance import provenance

    plan, rendered, skipped = stage.plan, 0, 0
    os.makedirs(os.path.join(output, "eval", "envs"), exist_ok=True)
    write_hand(os.path.join(output, "eval", "hand.npz"), stage.eval_hand,
               provenance("relight/hand", 1, inputs, {"role": "held-out poses",
                                                      "key": plan.key}))
    for name, spec, env in zip(env_names, env_specs, stage.envs):
        write_envmap(os.path.join(output, "eval", "envs", f"{name}.exr"), env,
                     provenance("relight/envmap", 1, {"env": spec}, {}))
    for pose in progress(range(stage.eval_poses), desc="held-out", quiet=quiet):
        for k, name in enumerate(env_names):
            folder = os.path.join(output, "eval", f"{pose:03d}", name)
            wanted = plan.cameras[:eval_cameras]
            cams = [c for c in wanted if not C.image_is_valid(
                os.path.join(folder, f"{c.name}.exr"), c, plan.key)]
            skipped += len(wanted) - len(cams)
            if not cams:
                continue
            os.makedirs(folder, exist_ok=True)
            for r in stage.held_out(pose, k, cams):
                C.write_image(os.path.join(folder, f"{r.camera.name}.exr"),
                              r.image, r.mask, plan.key,
                              {"relight.pose": pose, "relight.env": name,
                               "relight.camera": r.camera.name},
                              provenance("relight/capture-image", 1, inputs,
                                         {"pose": pose, "env": name, "camera": r.camera.name}),
                              camera=r.camera, hand_masks=r.hand_masks)
                rendered += 1
    return rendered, skipped
