"""``relight relight HAND.npz [ENV]``: render posed hands under an env map and/or lights.

The hand mode of ``relight relight`` (commands/relight.py dispatches on IN).  ``--model
physical`` is :mod:`relight_cli.render`'s physically based renderer (URHand's physical
baseline; its options are :class:`PhysicalRun`'s); every other ``--model`` is a learned
model of the registry (:mod:`relight_cli.neural.registry`), rendered by the job its entry
names.  One frame (``--frame``) or a sequence in one process (``--frames``, outputs
``{frame}`` patterns: :mod:`relight_cli.sequence`).  The work is
:mod:`relight_cli.jobs.relight_hand`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import click

from relight_cli.cli.tools import (FiniteFloat, SquareSize, check_input, log,
                                   no_clobber_option, parse_vector, preview_exposure_option,
                                   quiet_option, refuse_given, seed_option)
from relight_cli.cli.renders import frames_text, select_frames, view_of, write_renders
from relight_cli.provenance import numbered_roles
from relight_cli.sequence import FRAME_HELP, FRAMES_HELP
from relight_cli.commands import _hand_view as hand_view

#: What the dispatcher says IN is in this mode.
DESCRIPTION = "a hand (IN = HAND.npz)"


def accepts(spec: str, given: set) -> bool:
    """Whether IN ``spec`` is a hand: a hand.npz or ``builtin:right|left|two[:POSE]``."""
    lower = spec.lower()
    return lower.endswith(".npz") or lower.startswith("builtin:")


@dataclass(frozen=True)
class LearnedRun:
    """The options every learned model takes (the registry's entries)."""

    checkpoint: tuple
    device: str | None


@dataclass(frozen=True)
class Run:
    """This mode's options as given (the click parameters, one field each)."""

    input: str
    env: str | None
    output: str
    model: str | None
    camera: str | None
    background: str
    preview: str | None
    preview_exposure: float | None
    hand_size: str | None
    hand_lights: str | None
    hand_frame: int | None
    hand_frames: str | None
    env_res: str | None
    aa: int | None
    precision: str | None
    physical: object            # relight_cli.jobs.relight_hand.PhysicalOptions
    learned: LearnedRun
    seed: int
    no_clobber: bool
    quiet: bool


def _model_help() -> str:
    """--model's help: every name first (the registry's learned models after 'physical'),
    then what each is and which command trains it."""
    from relight_cli.neural.registry import MODELS
    names = [f"'{name}'" for name in ("physical", *MODELS)]
    return ("Appearance model: " + ", ".join(names[:-1]) + " or " + names[-1]
            + " [default: physical].  physical: Lambert + GGX, shadows, SSS; the learned "
            "ones need --checkpoint: " + "; ".join(f"{name}: {spec.title}, from {spec.trainer}"
                                                  for name, spec in MODELS.items()) + ".")


@click.command("relight", short_help="Render posed hands under an env map and/or lights.")
@click.argument("input", metavar="HAND")
@click.argument("env", metavar="[ENV]", required=False, default=None)
@click.option("-o", "--output", required=True,
              help="The EXR image (with --frames a pattern holding {frame}).")
@click.option("--model", default=None, metavar="NAME", help=_model_help())
@click.option("--checkpoint", multiple=True, metavar="CKPT.pt",
              help="The learned model of --model (relight/checkpoint).  Repeat it to give "
                   "each hand its own model (teacher, linear): each hand of HAND takes the "
                   "checkpoint trained on its handedness, as RelightableHands trains one "
                   "teacher per hand; one checkpoint renders every hand.")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default=None,
              help="Where a learned model runs [default: auto].")
@click.option("--precision", type=click.Choice(["auto", "float32", "bfloat16"]), default=None,
              help="--model student: the decoder's arithmetic, float32, bfloat16 (autocast, "
                   "~2× faster on CPUs with native bfloat16, within ~55 dB of float32), or "
                   "auto: bfloat16 on such a CPU, else float32 [default: auto].")
@click.option("--camera", "camera", default=None, metavar="CAMERA.json",
              help="The OpenCV camera of the view (relight camera; formats/camera.md; '-': "
                   "stdin) [default: a camera framing the hands from the front].")
@click.option("--size", "hand_size", default=None, metavar="WxH",
              help="Image size WxH (or N) of the default camera [default: 256x256].")
@click.option("--lights", "hand_lights", default=None, metavar="LIGHTS.json",
              help="Point lights (relight/lights JSON, '-': stdin): radiance falls as 1/r².")
@click.option("--frame", "hand_frame", type=int, default=None, help=FRAME_HELP)
@click.option("--frames", "hand_frames", default=None, metavar="all|A:B[:S]",
              help=FRAMES_HELP + " -o (and --preview) is a pattern holding {frame}, e.g. "
                   "'out/frame_{frame:04d}.exr'. The model, materials and env map are "
                   "prepared once; each frame's pixels equal its single --frame call's "
                   "(without --camera each frame is framed on its own pose, as that call "
                   "frames it).")
@click.option("--env-res", "env_res", default=None, metavar="WxH",
              help="Lat-long grid WxH (width first) the env map is integrated over, exactly "
                   "as bake-features --env-res [default: 32x16; --model student: the "
                   "checkpoint's render grid, any grid for the texel-aligned student, DRAM's "
                   "training grid].")
@click.option("--aa", type=int, default=None,
              help="Stratified sub-pixel samples per axis (aa² per pixel) [default: 2; a "
                   "teacher: the sampling it trained with].")
@click.option("--mesh", "hand_mesh", type=click.Choice(["fine", "coarse"]), default=None,
              help="--model physical: mesh rendered (and shadowing) [default: fine].")
@click.option("--tex-res", "tex_res", type=SquareSize(), default=None,
              help="--model physical: texture-space lighting/SSS map size N (N×N) "
                   "[default: 256].")
@click.option("--no-shadows", is_flag=True, help="--model physical, ablation: no shadow rays.")
@click.option("--no-specular", is_flag=True, help="--model physical, ablation: diffuse only.")
@click.option("--no-sss", is_flag=True,
              help="--model physical, ablation: no subsurface scattering.")
@click.option("--sss-scale", type=FiniteFloat(0, 10, min_open=True), default=None,
              help="--model physical: scale of the skin profile's widths [default: 1].")
@click.option("--bounce", is_flag=True,
              help="--model physical: add one bounce of interreflection.")
@click.option("--albedo", "albedo_map", default=None, metavar="IMAGE",
              help="--model physical: UV albedo map (EXR/PNG, linear) instead of the "
                   "procedural skin.")
@click.option("--roughness", "roughness_map", default=None, metavar="IMAGE|VALUE",
              help="--model physical: GGX roughness, a UV map (EXR channel Y or R) or a "
                   "number in (0, 1].")
@click.option("--aov", default=None, metavar="LIST",
              help="--model physical: extra EXR layers, comma-separated from normal, uv, "
                   "depth.")
@click.option("--env-space", type=click.Choice(["texels", "vertices"]), default=None,
              help="--model physical: where env-map light transport is integrated: at the "
                   "texel centres (shadows and highlights as sharp as the --tex-res map) or "
                   "at mesh vertices, interpolated (faster; contact shadows come out jagged "
                   "and highlights smeared) [default: texels].")
@click.option("--env-sources", default=None, metavar="auto|none|N",
              help="--model physical: take up to N small bright sources (a sun, a lamp) out "
                   "of the env map before it is put on the --env-res grid, each kept as a "
                   "distant light at its own direction and power (auto: up to 8) "
                   "[default: auto].")
@click.option("--ggx-shadowing", type=click.Choice(["smith", "schlick"]), default=None,
              help="--model physical: the GGX lobe's shadowing term, the exact Smith G "
                   "(as Mitsuba 3 and pbrt) or URHand Eq. 15's Schlick remap "
                   "k = (rho+1)^2/8 [default: smith].")
@click.option("--background", default="0,0,0", show_default=True, metavar="R,G,B",
              help="Background radiance of the image.")
@click.option("--preview", default=None, metavar="PNG",
              help="A tone-mapped PNG too (with --frames a pattern holding {frame}).")
@preview_exposure_option
@seed_option
@no_clobber_option
@quiet_option
@click.pass_context
def command(ctx, **options):
    """Render the posed hand(s) of HAND (a hand.npz, or builtin:right|left|two[:POSE])
    under the env map ENV (EXR/HDR or builtin:sky|studio|uniform|point) and/or
    --lights, seen by --camera.

    --model physical: Lambert + GGX (F0 0.04), embree shadows, texture-space
    subsurface scattering, optional one bounce.  Writes an EXR with R, G, B, A
    (mask) and optional AOV layers.

    --model teacher --checkpoint TEACHER.pt: RelightableHands' OLAT teacher (or
    its GGX baseline) from train-teacher.  Point lights, near or far, take one
    network pass each (their own 1/r² and visibility); an env map is the sum
    over its --env-res directions (linearity of light transport), each a distant
    light with its own ray-traced visibility; passes are batched.

    --model linear --checkpoint LINEAR.pt: URHand's linear lighting model
    (train-teacher --model linear).  The shading features of all the lights (an
    env map's --env-res directions, point lights with 1/r²; visibility traced)
    are summed and go through the model once: it is linear in them, so no
    distillation is needed.

    --model student --checkpoint STUDENT.pt: RelightableHands' student (or
    DRAM) from distill: bake-features' texel maps under the env map, one pass.

    Two hands, one model each (RelightableHands Sec. 5): --checkpoint right.pt
    --checkpoint left.pt; each hand takes the checkpoint trained on its
    handedness, its visibility traced against both hands.

    \b
    Examples:
      relight relight hand.npz builtin:sky --model physical --camera cam.json -o img.exr
      relight relight hand.npz builtin:sky --model teacher --checkpoint teacher.pt -o img.exr
      relight relight hand.npz builtin:sky --model linear --checkpoint linear.pt -o img.exr
      relight relight hand.npz builtin:sky --frames 0:100:10 -o 'out/f_{frame:03d}.exr'
    """
    from relight_cli.jobs.relight_hand import PhysicalOptions
    physical = PhysicalOptions(**{f.name: options.pop(f.name) for f in fields(PhysicalOptions)})
    learned = LearnedRun(**{f.name: options.pop(f.name) for f in fields(LearnedRun)})
    a = Run(physical=physical, learned=learned, **options)
    model = _model_of(ctx, a)
    if model is None:
        return _hand_physical(a)
    _hand_learned(a, model)


def _model_of(ctx, a):
    """The registry entry of --model (None: physical); a usage error for an unknown model,
    and for options the chosen model does not take (each model's own options:
    PhysicalOptions for physical, LearnedRun for every learned model, an entry's
    ``hand_options``)."""
    from relight_cli.errors import UsageProblem
    from relight_cli.jobs.relight_hand import PhysicalOptions
    from relight_cli.neural import registry
    name = a.model or "physical"
    if name != "physical" and name not in registry.MODELS:
        raise UsageProblem(f"--model {a.model!r} is not available; use physical, "
                           f"{', '.join(registry.MODELS)}")
    spec = registry.MODELS.get(name)
    if spec is None:
        refuse_given(ctx, [f.name for f in fields(LearnedRun)],
                     "{} belong to a learned --model (" + ", ".join(registry.MODELS) + ")")
    else:
        refuse_given(ctx, [f.name for f in fields(PhysicalOptions)],
                     "{} only apply to --model physical (a learned model has its own "
                     "texture, materials and shadows)")
    for other in registry.MODELS.values():
        mine = () if spec is None else spec.hand_options
        refuse_given(ctx, [n for n in other.hand_options if n not in mine],
                     "{} only apply to --model " + other.name)
    return spec


# ------------------------------------------------------------------------- physical

def _hand_physical(a) -> None:
    """--model physical: the posed hand(s) under ENV and/or --lights → EXR image(s), one
    per frame with --frames (relight_cli.jobs.relight_hand.physical)."""
    import time

    from relight_cli.cli.inputs import (load_albedo, load_envmap, load_hand, load_point_lights,
                                        read_roughness_map)
    from relight_cli.errors import DataError
    from relight_cli.jobs import relight_hand as J
    from relight_cli.render import appearance as A

    p = a.physical
    width, height, env_h, env_w, outputs = hand_view.view_options(a)
    tex, samples_axis, aovs, rough_value = _physical_usage(a)
    bg = parse_vector(a.background, 3, "--background", minimum=0)
    hand_view.check_files(a, outputs, (p.albedo_map, None))

    start = time.perf_counter()
    data = load_hand(a.input)
    frames = select_frames(outputs, a.hand_frame, a.hand_frames, data.n_frames, a.input,
                           a.no_clobber)
    envmap = load_envmap(a.env) if a.env is not None else None
    lights = load_point_lights(a.hand_lights)
    rough = rough_value
    if p.roughness_map is not None and rough_value is None:
        rough = read_roughness_map(p.roughness_map)
    mesh_name = p.hand_mesh or "fine"
    framing = view_of(a.camera, width, height)
    try:
        materials = A.hand_materials(data, mesh_name, max(tex, 256), a.seed,
                                     load_albedo(p.albedo_map), rough)
    except ValueError as exc:
        raise DataError(str(exc), p.albedo_map or p.roughness_map) from None
    log(f"read {a.input}: {len(data.hands)} hand(s), "
        f"{frames_text(frames)}; {'env ' + a.env if a.env else 'no env'}, "
        f"{0 if lights is None else len(lights)} point light(s)", a.quiet)

    settings = p.render_settings(tex, samples_axis, (env_h, env_w))
    inputs = {"hand": a.input, "env": a.env, "camera": a.camera, "lights": a.hand_lights,
              "albedo": p.albedo_map,
              "roughness": p.roughness_map if rough_value is None else None}
    record = J.physical_settings(settings, mesh_name, p.roughness_map, a.seed, bg)
    renders = J.physical(data, frames, framing, materials, settings,
                         lights, envmap, bg, mesh_name, aovs, a.input)
    write_renders(outputs, renders, len(frames), inputs, record, start, a.output, a.quiet,
                  exposure=a.preview_exposure)


def _physical_usage(a) -> tuple:
    """--model physical's own usage checks: (tex_res, aa, AOV names, roughness value or
    None); a roughness map's file must exist."""
    from relight_cli.errors import UsageProblem
    try:
        tex, samples_axis, aovs, rough_value = a.physical.check(a.aa)
    except ValueError as exc:
        raise UsageProblem(str(exc)) from None
    if a.physical.roughness_map is not None and rough_value is None:
        check_input(a.physical.roughness_map)
    return tex, samples_axis, aovs, rough_value


# ------------------------------------------------------------------------- learned models

def _hand_learned(a, spec) -> None:
    """A learned model of the registry: its job (``spec.render``) builds it from the
    checkpoints, picks its env grid and sampling, and renders the frames."""
    import contextlib
    import time

    from relight_cli.cli.inputs import load_envmap, load_hand
    from relight_cli.cli.tools import progress
    from relight_cli.envmap import discretize_env
    from relight_cli.errors import UsageProblem
    from relight_cli.jobs.relight_hand import decoder_precision
    from relight_cli.neural.registry import names
    from relight_cli.neural.train import resolve_device

    paths = a.learned.checkpoint
    if not paths:
        raise UsageProblem(f"--model {spec.name} needs --checkpoint CKPT.pt (from "
                           f"{spec.trainer})")
    if not spec.one_per_hand and len(paths) > 1:
        raise UsageProblem(f"--model {spec.name} takes one --checkpoint (one model renders "
                           f"every hand)")
    if not spec.point_lights and a.hand_lights is not None:
        raise UsageProblem(f"--model {spec.name} is an env-map model: it cannot take --lights "
                           f"(use " + " or ".join(f"--model {n}" for n in names(point_lights=True))
                           + " for point lights)")
    width, height, env_h, env_w, outputs = hand_view.view_options(a)
    if a.aa is not None and not 1 <= a.aa <= 8:
        raise UsageProblem(f"--aa must be in [1, 8], got {a.aa}")
    bg = parse_vector(a.background, 3, "--background")
    hand_view.check_files(a, outputs, *((path, None) for path in paths))

    start = time.perf_counter()
    device = resolve_device(a.learned.device or "auto")
    data = load_hand(a.input)
    frames = select_frames(outputs, a.hand_frame, a.hand_frames, data.n_frames, a.input,
                           a.no_clobber)
    model = _load_model(a, spec, paths, data, device)
    envmap = load_envmap(a.env) if a.env is not None else None
    lights = None
    if a.hand_lights is not None:
        from relight_cli.formats.lights_json import read_lights
        lights = read_lights(a.hand_lights)
    framing = view_of(a.camera, width, height)
    env_res = _model_call(a, model.env_grid, None if a.env_res is None else (env_h, env_w))
    if hasattr(model, "precision"):       # a decoder that runs in float32 or bfloat16
        model.precision = decoder_precision(a.precision or "auto", device)
        log(f"student decoder: {model.precision} (--precision {a.precision or 'auto'})",
            a.quiet)
    samples_axis = model.samples_axis(a.aa)
    denv = discretize_env(envmap, *env_res) if envmap is not None else None
    inputs = {"hand": a.input, "env": a.env, "camera": a.camera, "lights": a.hand_lights,
              **numbered_roles("checkpoint", paths)}
    settings = model.settings(env_res, samples_axis, bg)
    passes = model.passes(data, denv, lights)      # None: one pass per frame
    bar = contextlib.nullcontext()
    if a.hand_frames is None and passes is not None:   # a sequence's bar counts frames
        bar = progress(total=passes, desc=f"relight ({spec.name} passes)", quiet=a.quiet)
    with bar as passes_bar:
        renders = model.render(data, frames, framing, samples_axis, lights,
                               denv, bg, a.input,
                               progress=None if passes_bar is None else passes_bar.update)
        write_renders(outputs, renders, len(frames), inputs, settings, start, a.output, a.quiet,
                      passes=passes is not None, exposure=a.preview_exposure)


def _load_model(a, spec, paths, data, device):
    """The job of ``spec`` built from the read checkpoints (DataError naming the file at
    fault, the checkpoint or the hand; UsageProblem for a request it cannot serve)."""
    from relight_cli.neural.checkpoints import read_checkpoint
    checkpoints = [read_checkpoint(path, kind=spec.kind) for path in paths]
    job = spec.load_attr("render")
    return _model_call(a, job, spec, checkpoints, list(paths), data, device,
                       lambda m: log(m, a.quiet))


def _model_call(a, function, *args):
    """``function(*args)`` with a job's ModelProblem turned into the CLI's error."""
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.jobs.relight_hand import ModelProblem
    try:
        return function(*args)
    except ModelProblem as exc:
        if exc.usage:
            raise UsageProblem(str(exc)) from None
        raise DataError(str(exc), exc.path or a.input) from None
