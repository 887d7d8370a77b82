"""A synthetic light-stage capture: ``relight synth-capture``'s plan and renders as an
engine job.

:func:`light_stage` takes a loaded hand (a :class:`~relight_cli.hand.model.HandData`,
one or two hands), the evaluation env maps and the :class:`StageSettings` and returns a
:class:`LightStage`: the plan (motion, dome of cameras and LEDs, each frame's lit LEDs,
the capture key), the held-out poses and the env maps on the stage's working grid.  Its
:meth:`LightStage.frame` and :meth:`LightStage.held_out` render the images a capture
holds, camera by camera, so a caller renders only what it still needs (a resumed
capture skips finished images).  Writing the capture folder is the caller's
(:mod:`relight_cli.formats.capture`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from functools import cached_property

import numpy as np

from relight_cli.render.capture import StageSettings

__all__ = ["LightStage", "StageRender", "StageSettings", "light_stage"]

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
