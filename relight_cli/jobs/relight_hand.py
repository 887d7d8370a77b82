"""Relight a hand's frames: the hand modes of ``relight relight`` as engine jobs.

Each job is a generator over the selected frames of one hand recording (a
:class:`~relight_cli.hand.model.HandData`, one or two hands): what does not depend on
the pose is prepared once (materials, the discretized env map, loaded models, the UV
rasterizations of the student's features), and each frame is posed, framed, traced and
rendered exactly as a single-frame call renders it, so a sequence's pixels equal those
of one call per frame.  Each yields a :class:`FrameRender`; writing is the caller's.

    physical(...)   Lambert + GGX + SSS with embree shadows (``--model physical``)
    learned(...)    the OLAT teacher / GGX baseline or URHand's linear model, hand k by
                    its own model, visibility traced against every hand
    student(...)    RelightableHands' student: texel features under the env map, one pass

``physical_settings``, ``learned_settings`` and ``student_settings`` give the settings
each frame's provenance records (plus its ``frame``); ``check_student`` that a student
checkpoint fits the hand.  ``view_of(frame, meshes)`` gives each frame's camera (a fixed
camera, or the default camera framing that frame's posed hands).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np


@dataclass
class FrameRender:
    """One rendered frame: ``channels`` (name → [H, W] float32: R, G, B, A and AOVs for
    the physical renderer; R, G, B, A for learned models, A the coverage mask),
    ``rgb`` [H, W, 3] (over the background), the ``view`` camera, the per-stage
    ``seconds`` and the frame-specific ``settings`` the provenance records."""

    frame: int
    channels: dict
    rgb: np.ndarray
    view: object
    seconds: dict = field(default_factory=dict)
    passes: int = 0


@dataclass(frozen=True)
class PhysicalOptions:
    """The options only ``--model physical`` takes, as given (None: the default): the
    renderer's :class:`~relight_cli.render.shading.RenderSettings` fields, its materials
    (albedo, roughness: a map's path or a number) and AOVs.  A learned model has its own
    texture, materials and shadows."""

    hand_mesh: str | None = None
    tex_res: int | None = None
    no_shadows: bool = False
    no_specular: bool = False
    no_sss: bool = False
    sss_scale: float | None = None
    bounce: bool = False
    albedo_map: str | None = None
    roughness_map: str | None = None
    aov: str | None = None
    env_space: str | None = None
    env_sources: str | None = None
    ggx_shadowing: str | None = None

    def sources(self):
        """``RenderSettings.env_sources`` from ``--env-sources`` (auto, none or a count);
        ValueError naming the option."""
        text = "auto" if self.env_sources is None else str(self.env_sources).strip()
        if text in ("auto", "none"):
            return text
        try:
            count = int(text)
        except ValueError:
            count = -1
        if not 0 <= count <= 64:
            raise ValueError(f"--env-sources takes auto, none or a count in [0, 64], got {text!r}")
        return count

    def check(self, aa: int | None) -> tuple:
        """(tex_res, samples per axis, AOV names, the roughness number or None for a map);
        ValueError naming the option that is out of range."""
        tex = 256 if self.tex_res is None else self.tex_res
        if not 8 <= tex <= 4096:
            raise ValueError(f"--tex-res must be in [8, 4096], got {tex}")
        samples_axis = 2 if aa is None else aa
        if not 1 <= samples_axis <= 8:
            raise ValueError(f"--aa must be in [1, 8], got {samples_axis}")
        aovs = [v.strip() for v in self.aov.split(",") if v.strip()] if self.aov else []
        if self.aov is not None and not aovs:
            raise ValueError("--aov needs at least one of normal, uv, depth")
        bad = [v for v in aovs if v not in AOVS]
        if bad:
            raise ValueError(f"--aov takes normal, uv, depth; unknown: {', '.join(bad)}")
        rough_value = None
        if self.roughness_map is not None:
            try:
                rough_value = float(self.roughness_map)
            except ValueError:
                rough_value = None                   # a map's path
            else:
                if not 0 < rough_value <= 1:
                    raise ValueError(f"--roughness must be in (0, 1], got {self.roughness_map}")
        self.sources()
        return tex, samples_axis, aovs, rough_value

    def render_settings(self, tex_res: int, samples_axis: int, env_res):
        """The renderer's settings (``env_res``: (H, W))."""
        from relight_cli.render.shading import RenderSettings
        return RenderSettings(tex_res=tex_res, aa=samples_axis, shadows=not self.no_shadows,
                              specular=not self.no_specular, sss=not self.no_sss,
                              sss_scale=1.0 if self.sss_scale is None else self.sss_scale,
                              env_res=tuple(env_res), bounce=self.bounce,
                              env_space=self.env_space or "texels",
                              env_sources=self.sources(),
                              shadowing=self.ggx_shadowing or "smith")


#: The physical renderer's extra EXR layers.
AOVS = ("normal", "uv", "depth")


def physical(data, frames, view_of, materials, settings, lights=None, envmap=None,
             background=(0.0, 0.0, 0.0), mesh: str = "fine", aovs=(), source: str = ""):
    """``--model physical`` over ``frames``: yields a :class:`FrameRender` per frame.

    Args:
        data: HandData.  frames: frame indices.  view_of: (frame, posed meshes) → Camera.
        materials: :func:`relight_cli.render.appearance.hand_materials` (pose independent).
        settings: :class:`relight_cli.render.shading.RenderSettings`.
        lights: a ``formats.lights_json.Lights`` or None.  envmap: EnvMap or None.
        background: RGB behind the hand.  mesh: ``fine`` or ``coarse``.
        aovs: any of ``normal``, ``uv``, ``depth``.  source: the hand's name in errors.
    """
    from relight_cli.bake import pose_scene
    from relight_cli.envmap import discretize_env
    from relight_cli.render.shading import HandRenderer
    from relight_cli.uvraster import rasterize_uv

    # pose independent, so made once: the env map on the renderer's direction grid and
    # each mesh's UV rasterization (the same arrays a single-frame call makes)
    denv = None if envmap is None else discretize_env(envmap, *settings.env_res,
                                                      sources=settings.env_sources)
    rasters = None
    for frame in frames:
        meshes = pose_scene(data, frame, mesh, source)
        if rasters is None:
            rasters = [rasterize_uv(m.uv, m.faces_uv, settings.tex_res) for m in meshes]
        view = view_of(frame, meshes)
        renderer = HandRenderer(meshes, materials, settings, rasters)
        lighting = renderer.light(lights, denv)
        result = renderer.render(view, lighting, background=background)
        channels = {"R": result.image[..., 0], "G": result.image[..., 1],
                    "B": result.image[..., 2], "A": result.mask}
        if "normal" in aovs:
            channels.update({f"normal.{c}": result.normal[..., i] for i, c in enumerate("XYZ")})
        if "uv" in aovs:
            channels.update({"uv.U": result.uv[..., 0], "uv.V": result.uv[..., 1]})
        if "depth" in aovs:
            channels["depth.Z"] = result.depth
        yield FrameRender(frame, channels, result.image, view,
                          {**renderer.stats, **lighting.stats, **result.stats})


def learned(data, frames, view_of, per_hand, samples_axis: int, lights=None, denv=None,
            background=(0.0, 0.0, 0.0), device="cpu", source: str = "", progress=None):
    """``--model teacher|linear`` over ``frames``: hand k by ``per_hand[k]`` (a
    :class:`~relight_cli.neural.evaluate.HandModel`), one network pass per light or
    env direction and hand (teacher; linear: one per lighting and hand), visibility
    traced against every hand; passes composited over black, the background filling
    the uncovered sample fraction.

    Args:
        lights: a read relight/lights record (positions, colors, intensities) or None.
        denv: the env map discretized on the model's grid
            (:func:`relight_cli.envmap.discretize_env`) or None.
        progress: callable(n) per pass done (for a bar), or None.
    """
    from relight_cli.bake import pose_scene
    from relight_cli.neural import evaluate as EV
    from relight_cli.neural import teacher as T
    from relight_cli.neural.geometry import PoseTexels
    from relight_cli.render.gbuffer import render_gbuffer

    from relight_cli.uvraster import rasterize_uv

    intensity = None
    if lights is not None:
        intensity = lights.radiant_intensity()                                 # [L, 3]
    rasters = {}      # (mesh k, tex_res) → UV rasterization: pose independent, made once
    for frame in frames:
        timing = T.Timing()
        t0 = time.perf_counter()
        meshes = pose_scene(data, frame, "fine", source)
        view = view_of(frame, meshes)

        def make(n, vis):
            for k, m in enumerate(meshes):
                if (k, n) not in rasters:
                    rasters[k, n] = rasterize_uv(m.uv, m.faces_uv, n)
            return PoseTexels(meshes, n, [rasters[k, n] for k in range(len(meshes))],
                              shadows=vis)
        texels = EV.scene_texels(per_hand, make)
        gbuffer = render_gbuffer(meshes, view, samples_axis, scene=texels[0].renderer.scene)
        timing.add("geometry", time.perf_counter() - t0)
        passes = []       # (per-hand LightInputs, per-hand [L, 3] weights)
        t0 = time.perf_counter()
        if lights is not None:
            passes.append(([EV.point_inputs(m, texels[k], k, lights.positions)
                            for k, m in enumerate(per_hand)], [intensity] * len(per_hand)))
        if denv is not None:
            pairs = [EV.env_inputs(m, texels[k], k, denv) for k, m in enumerate(per_hand)]
            passes.append(([li for li, _ in pairs], [w for _, w in pairs]))
        timing.add("visibility", time.perf_counter() - t0)
        poses = np.stack([inst.poses[frame] for inst in data.hands])
        image = None
        for light_inputs, weights in passes:
            part = EV.render_scene(per_hand, texels, gbuffer, poses, light_inputs, weights,
                                   device, progress=progress, timing=timing)
            image = part if image is None else image + part
        rgb, mask = _over_background(image.cpu().numpy().astype(np.float32), gbuffer.mask,
                                     background)
        yield FrameRender(frame, _rgba(rgb, mask), rgb, view, dict(timing.seconds),
                          sum(len(w) for _, weights in passes for w in weights))


def framing(width: int, height: int, camera=None):
    """A ``view_of`` for the jobs: (frame, posed meshes) → ``camera`` when given, else the
    default camera of ``width`` × ``height`` framing that frame's posed hands from the
    front (+Z; :func:`relight_cli.hand.scene.preview_camera`)."""
    if camera is not None:
        return lambda frame, meshes: camera
    from relight_cli.hand.scene import preview_camera
    return lambda frame, meshes: preview_camera(meshes, width, height)


PRECISIONS = ("auto", "float32", "bfloat16")


def decoder_precision(precision: str, device) -> str:
    """``--precision`` as it runs: ``auto`` is bfloat16 on a CPU whose oneDNN has native
    bfloat16 kernels (AVX512-BF16 / AMX: 2.1× faster than float32 at the paper's widths
    and 54–57 dB from it, benchmarks/results/student.md), float32 elsewhere (CUDA, and
    CPUs that would only emulate bfloat16)."""
    import torch

    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if precision != "auto":
        return precision
    if str(device).startswith("cpu") and torch.backends.mkldnn.is_available() \
            and torch.ops.mkldnn._is_mkldnn_bf16_supported():
        return "bfloat16"
    return "float32"


def student(data, frames, view_of, net, config, denv, samples_axis: int,
            background=(0.0, 0.0, 0.0), device="cpu", source: str = "",
            precision: str = "float32"):
    """``--model student`` over ``frames``: bake-features' texel maps of each pose
    (visibility traced once per pose; the UV rasterizations shared by every pose) under
    ``denv`` (the env map on the student's render grid, :func:`relight_cli.neural.distill.
    render_grid`, or any other for the texel-aligned student; DRAM's light code needs its
    training grid), one forward pass, the textures
    rendered through the frame's G-buffer.

    ``precision``: the decoder's arithmetic, ``float32`` or ``bfloat16`` (autocast; the
    textures come back as float32), both with channels_last weights (the fastest float32
    layout on CPU, benchmarks/results/student.md); see :func:`decoder_precision`.
    """
    import contextlib

    import torch

    from relight_cli.bake import pose_scene
    from relight_cli.neural import distill as DI
    from relight_cli.neural.teacher import composite
    from relight_cli.render.gbuffer import render_gbuffer

    if precision not in ("float32", "bfloat16"):
        raise ValueError(f"precision must be float32 or bfloat16, got {precision!r}")
    net = net.to(memory_format=torch.channels_last)
    kind = "cuda" if str(device).startswith("cuda") else "cpu"
    autocast = (lambda: torch.autocast(kind, dtype=torch.bfloat16)) if precision == "bfloat16" \
        else contextlib.nullcontext
    DI.check_render_grid(config, (denv.height, denv.width))
    features = DI.StudentFeatures(config, cache=1, env_res=(denv.height, denv.width))
    for frame in frames:
        seconds = {}
        t0 = time.perf_counter()
        meshes = pose_scene(data, frame, "fine", source)
        view = view_of(frame, meshes)
        gbuffer = render_gbuffer(meshes, view, samples_axis)
        seconds["geometry"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        maps = None                  # DRAM reads no texel features: none are traced
        if DI.reads_texel_features(config):
            maps = features.maps(features.pose(data, frame, key=frame), denv, view.center)
        seconds["features"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        with torch.no_grad():
            with autocast():
                textures = DI.student_forward(net, config, maps, DI.hand_poses(data, frame), denv,
                                              DI.wrist_rotations(data, frame), device)
            textures = [t.float() for t in textures]
            seconds["decoder"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            image = composite(textures, gbuffer)
        seconds["composite"] = time.perf_counter() - t0
        rgb, mask = _over_background(image.cpu().numpy().astype(np.float32), gbuffer.mask,
                                     background)
        yield FrameRender(frame, _rgba(rgb, mask), rgb, view, seconds, 1)


def physical_settings(settings, mesh: str, roughness, seed: int, background) -> dict:
    """The provenance settings of :func:`physical`'s frames (each adds its ``frame``):
    the RenderSettings, the mesh, the roughness option as given, seed and background."""
    return {"model": "physical", "mesh": mesh, "env_res": list(settings.env_res),
            "tex_res": settings.tex_res, "aa": settings.aa, "shadows": settings.shadows,
            "specular": settings.specular, "sss": settings.sss, "sss_scale": settings.sss_scale,
            "bounce": settings.bounce, "roughness": roughness, "seed": seed,
            "env_space": settings.env_space, "env_sources": settings.env_sources,
            "ggx_shadowing": settings.shadowing, "background": list(background)}


def learned_settings(model: str, per_hand, env_res, samples_axis: int, background) -> dict:
    """The provenance settings of :func:`learned`'s frames (``model`` teacher or linear;
    each hand's checkpoint, model and training step)."""
    config = per_hand[0].config
    return {"model": model, "teacher": config.model, "mesh": "fine",
            "env_res": list(env_res), "tex_res": config.tex_res, "aa": samples_axis,
            "visibility": config.visibility, "falloff": config.falloff,
            "checkpoints": [{"hand": k, "checkpoint": m.name, "model": m.model_name,
                             "sides": m.sides, "step": m.step}
                            for k, m in enumerate(per_hand)],
            "background": list(background)}


def student_settings(config, step: int, precision: str, env_res, samples_axis: int,
                     background) -> dict:
    """The provenance settings of :func:`student`'s frames (``step``: the checkpoint's)."""
    return {"model": "student", "student": config.student, "mesh": "fine",
            "precision": precision, "env_res": list(env_res), "tex_res": config.tex_res,
            "aa": samples_axis, "specular": config.specular, "visibility": config.visibility,
            "checkpoint_step": int(step), "background": list(background)}


def check_student(checkpoint: dict, data) -> None:
    """ValueError unless the student ``checkpoint`` learned a hand of ``data``'s joints
    and UV layout."""
    from relight_cli.neural.geometry import uv_layout_digest
    if (data.n_joints - 1) * 3 != int(checkpoint["pose_dim"]):
        raise ValueError(f"the hand has {data.n_joints} joints; the checkpoint's model was "
                         f"trained on {int(checkpoint['pose_dim']) // 3 + 1}")
    layout = checkpoint.get("extra", {}).get("uv_layout")
    if layout is not None and layout != uv_layout_digest(data.mesh("fine")):
        raise ValueError("the hand's UV layout differs from the one the model learned its "
                         "texture on (another hand model?)")


def _over_background(rgb: np.ndarray, mask: np.ndarray, background) -> tuple:
    return rgb + np.asarray(background, np.float32)[None, None] * (1 - mask[..., None]), mask


def _rgba(rgb: np.ndarray, mask: np.ndarray) -> dict:
    return {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "A": mask}



# ----------------------------------------------------------------------------- the models
# What ``relight HAND --model NAME`` does with a learned model, per registry entry
# (relight_cli.neural.registry: ``render``): build it from read checkpoints, pick the env
# grid and samples it renders with, render the frames, name the settings provenance
# records.  The command reads the checkpoint files and writes the frames.


class ModelProblem(ValueError):
    """A checkpoint that does not fit (``path``: the checkpoint at fault, else None: the
    hand is) or, with ``usage``, a request the model cannot serve (a usage error)."""

    def __init__(self, message: str, path=None, usage: bool = False):
        super().__init__(message)
        self.path, self.usage = path, usage


class PerHandModels:
    """The teacher (OLAT or GGX) and URHand's linear model: hand k by the checkpoint
    trained on its handedness (or one checkpoint for every hand), one network pass per
    light or env direction and hand (teacher; linear: one per lighting and hand),
    visibility traced against every hand (:func:`learned`)."""

    def __init__(self, spec, checkpoints: list, names: list, data, device, log=None):
        """``checkpoints``: read checkpoint dicts of ``spec``'s kind, ``names`` their files.
        Raises :class:`ModelProblem`."""
        from relight_cli.errors import UsageProblem
        from relight_cli.hand.scene import handedness
        from relight_cli.neural import evaluate as EV
        self.spec, self.device = spec, device
        models = []
        for ckpt, name in zip(checkpoints, names):
            try:
                models.append(EV.load_hand_model(ckpt, device, name=name))
            except (ValueError, UsageProblem) as exc:
                raise ModelProblem(getattr(exc, "message", str(exc)), name) from None
        try:
            self.per_hand = EV.assign_models(models, handedness(data))
        except ValueError as exc:
            raise ModelProblem(str(exc), usage=True) from None
        try:
            EV.check_hands(self.per_hand, data)
        except ValueError as exc:
            raise ModelProblem(str(exc), getattr(exc, "path", None)) from None
        self.config = self.per_hand[0].config
        if data.mean_texture is not None and spec.subjects:
            self.per_hand = EV.with_own_subject(self.per_hand, data.mean_texture)
            if log is not None:
                log("note: the hand file carries its subject's mean texture "
                    f"({data.mean_texture.shape[-1]}²): the model renders that subject")
        for k, (m, side) in enumerate(zip(self.per_hand, handedness(data))):
            if log is not None and m.sides and side not in m.sides:
                log(f"note: hand {k} ({side}) is rendered by {m.name}, trained on the "
                    f"{'/'.join(m.sides)} hand; give one --checkpoint per hand for its own "
                    f"model")

    def env_grid(self, requested):
        """(H, W) the env map is integrated over: ``requested`` (the default grid when
        None)."""
        from relight_cli.envmap import DEFAULT_GRID
        return tuple(requested) if requested is not None else DEFAULT_GRID

    def samples_axis(self, aa: int | None) -> int:
        """Sub-pixel samples per axis: ``aa``, else the sampling the model trained with
        where its registry entry says so (the teacher's config ``aa``), else 2."""
        if aa is not None:
            return aa
        return (self.config.aa or 2) if self.spec.trained_sampling else 2

    def passes(self, data, denv, lights):
        """Network passes of one frame (a progress bar's total)."""
        lit = 0 if denv is None else int(np.count_nonzero(denv.lit))
        return (lit + (0 if lights is None else len(lights.positions))) * len(data.hands)

    def render(self, data, frames, view_of, samples_axis, lights, denv, background,
               source: str = "", progress=None):
        return learned(data, frames, view_of, self.per_hand, samples_axis, lights, denv,
                       background, self.device, source, progress)

    def settings(self, env_res, samples_axis, background) -> dict:
        return learned_settings(self.spec.name, self.per_hand, env_res, samples_axis,
                                background)


class StudentModel:
    """RelightableHands' student (or DRAM): one checkpoint for every hand, an env map
    only (:func:`student`)."""

    def __init__(self, spec, checkpoints: list, names: list, data, device, log=None):
        from relight_cli.errors import UsageProblem
        from relight_cli.neural.checkpoints import student_model
        if len(checkpoints) != 1:
            raise ModelProblem(f"--model {spec.name} takes one --checkpoint (one student "
                               f"renders every hand)", usage=True)
        self.spec, self.device, self.checkpoint = spec, device, checkpoints[0]
        try:
            self.net, self.config = student_model(self.checkpoint, device)
        except (ValueError, UsageProblem) as exc:
            raise ModelProblem(getattr(exc, "message", str(exc)), names[0]) from None
        try:
            check_student(self.checkpoint, data)
        except ValueError as exc:
            raise ModelProblem(str(exc)) from None
        self.precision = "float32"

    def env_grid(self, requested):
        """The student's own render grid (:func:`relight_cli.neural.distill.render_grid`)
        unless ``requested``; DRAM renders only on its training grid (a usage error)."""
        from relight_cli.neural import distill as DI
        grid = DI.render_grid(self.config) if requested is None else tuple(requested)
        try:
            DI.check_render_grid(self.config, grid)
        except ValueError as exc:
            raise ModelProblem(str(exc), usage=True) from None
        return grid

    def samples_axis(self, aa: int | None) -> int:
        return 2 if aa is None else aa

    def passes(self, data, denv, lights):
        """None: one decoder pass per frame (no bar over passes)."""
        return None

    def render(self, data, frames, view_of, samples_axis, lights, denv, background,
               source: str = "", progress=None):
        return student(data, frames, view_of, self.net, self.config, denv, samples_axis,
                       background, self.device, source, self.precision)

    def settings(self, env_res, samples_axis, background) -> dict:
        return student_settings(self.config, self.checkpoint["step"], self.precision,
                                env_res, samples_axis, background)



def timing_summary(done: list, output: str, sequence: bool, wall: float,
                   passes: bool = False) -> str:
    """What a run of :class:`FrameRender` s cost, for its closing log line: the single
    frame's size and stage times, or a sequence's frames/s and median time per stage."""
    if not sequence:
        r = done[0]
        return (f"{output} ({r.view.width}x{r.view.height}, "
                + (f"{r.passes} pass(es), " if passes else "") + f"{wall:.2f} s: "
                + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in r.seconds.items()) + ")")
    stages = list(dict.fromkeys(k for r in done for k in r.seconds))
    median = {k: float(np.median([r.seconds.get(k, 0.0) for r in done])) for k in stages}
    rendered = sum(sum(r.seconds.values()) for r in done)
    return (f"{len(done)} frames to {output} ({wall:.1f} s in all, "
            f"{len(done) / max(rendered, 1e-9):.2f} frames/s rendering; median per frame: "
            + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in median.items()) + ")")
