"""``relight relight``: relight an input under new lighting.

The first input decides the mode: a Gaussians PLY (``.ply``) is relit with an
SH probe and optionally shadowed with a DGSM (paper Sec. 3.4); a hand
(``.npz`` or ``builtin:right|left|two[:POSE]``) is rendered under an env map
and/or point lights from a camera; a capture folder is scored.  Each mode is
one function below (options → usage checks → inputs → one job → writers); the
options that belong to one mode are declared once (_MODE_OPTIONS) and refused
in the others.  The work is relight_cli.jobs': relight_gaussians, relight_hand
(``--model physical`` is relight_cli.render's physically based renderer,
URHand's physical-only baseline) and score_capture.
"""

from __future__ import annotations

from types import SimpleNamespace

import click

from relight_cli.clitools import (FiniteFloat, ModeGroupedCommand, ShadowStrength, SquareSize,
                                  check_input, check_output, log, no_clobber_option,
                                  parse_vector, quiet_option, renamed_option, seed_option)


@click.command("relight", cls=ModeGroupedCommand,
               short_help="Relight Gaussians with an SH probe (+ DGSM shadows), or a hand.")
@click.argument("input", metavar="IN")
@click.argument("env", metavar="[ENV]", required=False, default=None)
@click.option("-o", "--output", required=True,
              help="Relit Gaussians PLY, or with --camera an EXR image; for a hand the EXR image.")
@click.option("--probe", default=None, metavar="PROBE.json",
              help="[Gaussians] SH light probe (relight sh-probe) lighting the avatar ('-': "
                   "stdin).")
@click.option("--dgsm", default=None, metavar="SHADOWS.exr",
              help="[Gaussians] Deep Gaussian Shadow Map (relight dgsm-build) darkening --receivers.")
@click.option("--receivers", default=None, metavar="SCENE.ply",
              help="[Gaussians] Scene Gaussians: shadowed by --dgsm, and rendered with --camera.")
@click.option("--object", "objects", multiple=True, metavar="SPEC",
              help="[Gaussians] Another object inserted beside IN (repeatable): a PLY, mesh or "
                   "builtin:, with a placement SOURCE:KEY=VALUE;... as in dgsm-build. Relit "
                   "by --probe like IN; with a grouped --dgsm, IN and the objects (in this "
                   "order, matching dgsm-build's OCCLUDERs) shadow each other.")
@click.option("--receivers-out", default=None, metavar="PLY",
              help="[Gaussians] Also write the shadowed receivers as a PLY.")
@click.option("--footprint", type=click.Choice(["centre", "stencil", "mc"]), default="stencil",
              show_default=True,
              help="[Gaussians] DGSM lookup over a receiver: centre sample, 7-point stencil, or "
                   "seeded Monte Carlo (--samples) in its principal frame.  The paper's default "
                   "is mc (Sec. 3.3); stencil is ours: 7 deterministic lookups that reproduce "
                   "the Gaussian's mean and covariance exactly (no sampling noise).")
@click.option("--samples", type=click.IntRange(1, 1024), default=16, show_default=True,
              help="[Gaussians] Monte Carlo samples per receiver for --footprint mc.")
@click.option("--shadow-strength", type=ShadowStrength(), default="auto", show_default=True,
              help="[Gaussians] Direct share s of a receiver's colour: colour × ((1 − s) + "
                   "s·Σ w_l T_l / Σ w_l) per channel.  A number in [0, 1] for every receiver (1, "
                   "the paper's reading: the whole colour is direct light, a full shadow is "
                   "black), or auto: per receiver, the share of its light the DGSM's lights "
                   "deliver against the probe's irradiance, E_d / (E_d + E_probe).")
@click.option("--light-weights", type=click.Choice(["intensity", "irradiance", "equal"]),
              default=None,
              help="[Gaussians] Each light's share w_l of the direct light (paper Sec. 3.3): "
                   "intensity × colour (from the DGSM), also × |n·ω|/r² at each receiver "
                   "(irradiance), or equal (the plain mean T of older versions).  Default: "
                   "irradiance with --shadow-strength auto (so the shadow is exactly each "
                   "light's irradiance times its T), else intensity.")
@click.option("--direct-light", is_flag=True,
              help="[Gaussians] With --dgsm: the DGSM's point lights also light IN and the "
                   "objects directly, albedo × Σ I_l C_l max(n·ω_l, 0)/(π r_l²) added to the "
                   "probe's shading (ours: the paper lights avatars by the probe only), each "
                   "light's term shadowed by the other objects.")
@click.option("--shadow-matte", type=click.Choice(["dgsm", "mesh"]), default=None,
              help="[Gaussians] With --camera: the receivers-only shadow matte of the paper's "
                   "protocol (Sec. 4.2): receivers coloured by shadow strength 1 − Σw_l V_l/Σw_l, "
                   "nothing else drawn; dgsm: V = the DGSM's transmittance; mesh: V = embree "
                   "shadow rays against IN (and --object) as triangle meshes, the pseudo ground "
                   "truth.  Lights and weights come from --dgsm in both.")
@click.option("--lobe", type=FiniteFloat(0, 1e4, min_open=True), default=1.0, show_default=True,
              help="[Gaussians] Cosine lobe exponent q of the transfer (1 = Lambertian).")
@click.option("--intensity", type=FiniteFloat(0, 1e6), default=1.0, show_default=True,
              help="[Gaussians] Global intensity γ.")
@click.option("--shading-clip", "t_max", type=FiniteFloat(0, min_open=True), default=None,
              help="[Gaussians] Clip t_max of the shading factor (default: no clip; formerly "
                   "--t-max).")
@renamed_option("--t-max", "--shading-clip",
                why="--t-max is dgsm-build's radial extent in metres")
@click.option("--normals", type=click.Choice(["auto", "axis", "pca", "stored"]), default="auto",
              show_default=True,
              help="[Gaussians] Normals: shortest ellipsoid axis, local PCA of neighbours, the "
                   "file's nx ny nz; auto = stored if present, else axis. Oriented outward.")
@click.option("--camera", "camera", default=None, metavar="CAMERA.json",
              help="The OpenCV camera of the view (relight camera; formats/camera.md; '-': "
                   "stdin). Gaussians: render receivers + relit objects to -o as an EXR (R, G, "
                   "B, A) instead of writing a PLY (formerly --render). Hand: default a camera "
                   "framing the hands from the front.")
@renamed_option("--render", "--camera", why="one camera option for hands and Gaussians")
@click.option("--background", default="0,0,0", show_default=True, metavar="R,G,B",
              help="Background radiance of the rendered image.")
@click.option("--model", default=None, metavar="NAME",
              help="[hand] Appearance model: 'physical' (Lambert + GGX, shadows, SSS), "
                   "'teacher' (a train-teacher checkpoint, --checkpoint) or 'linear' (URHand's "
                   "linear model, train-teacher --model linear) [default: physical].")
@click.option("--checkpoint", multiple=True, metavar="CKPT.pt",
              help="[hand] The learned model of --model teacher, linear or student "
                   "(relight/checkpoint).  Repeat it to give each hand its own model (teacher, "
                   "linear): each hand of IN takes the checkpoint trained on its handedness, as "
                   "RelightableHands trains one teacher per hand; one checkpoint renders every "
                   "hand.")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default=None,
              help="[hand] Where a learned model runs [default: auto].")
@click.option("--precision", type=click.Choice(["auto", "float32", "bfloat16"]), default=None,
              help="[hand, --model student] The decoder's arithmetic: float32, bfloat16 "
                   "(autocast, ~2× faster on CPUs with native bfloat16, within ~55 dB of "
                   "float32), or auto: bfloat16 on such a CPU, else float32 [default: auto].")
@click.option("--size", "hand_size", default=None, metavar="WxH",
              help="[hand] Image size WxH (or N) of the default camera [default: 256x256].")
@click.option("--lights", "hand_lights", default=None, metavar="LIGHTS.json",
              help="[hand] Point lights (relight/lights JSON, '-': stdin): radiance falls as "
                   "1/r².")
@click.option("--frame", "hand_frame", type=int, default=None,
              help="[hand] Frame of HAND to render [default: 0].")
@click.option("--frames", "hand_frames", default=None, metavar="all|A:B[:S]",
              help="[hand] Render a sequence in one process: every frame of HAND (all) or "
                   "the frames A, A+S, … before B (a Python slice). -o (and --preview) is a "
                   "pattern holding {frame}, e.g. 'out/frame_{frame:04d}.exr'. The model, "
                   "materials and env map are prepared once; each frame's pixels equal its "
                   "single --frame call's (without --camera each frame is framed on its own "
                   "pose, as that call frames it).")
@click.option("--mesh", "hand_mesh", type=click.Choice(["fine", "coarse"]), default=None,
              help="[hand] Mesh rendered (and shadowing) [default: fine].")
@click.option("--env-res", "env_res", default=None, metavar="WxH",
              help="[hand] Lat-long grid WxH (width first) the env map is integrated over, "
                   "exactly as bake-features --env-res [default: 32x16; --model student: "
                   "the checkpoint's render grid, any grid for the texel-aligned student, "
                   "DRAM's training grid].")
@click.option("--tex-res", "tex_res", type=SquareSize(), default=None,
              help="[hand] Texture-space lighting/SSS map size N (N×N) [default: 256].")
@click.option("--aa", type=int, default=None,
              help="[hand] Stratified sub-pixel samples per axis (aa² per pixel) [default: 2].")
@click.option("--no-shadows", is_flag=True, help="[hand] Ablation: no shadow rays.")
@click.option("--no-specular", is_flag=True, help="[hand] Ablation: diffuse only.")
@click.option("--no-sss", is_flag=True, help="[hand] Ablation: no subsurface scattering.")
@click.option("--sss-scale", type=FiniteFloat(0, 10, min_open=True), default=None,
              help="[hand] Scale of the skin profile's widths [default: 1].")
@click.option("--bounce", is_flag=True, help="[hand] Add one bounce of interreflection.")
@click.option("--albedo", "albedo_map", default=None, metavar="IMAGE",
              help="[hand] UV albedo map (EXR/PNG, linear) instead of the procedural skin.")
@click.option("--roughness", "roughness_map", default=None, metavar="IMAGE|VALUE",
              help="[hand] GGX roughness: a UV map (EXR channel Y or R) or a number in (0, 1].")
@click.option("--aov", default=None, metavar="LIST",
              help="[hand] Extra EXR layers: comma-separated from normal, uv, depth.")
@click.option("--preview", default=None, metavar="PNG",
              help="With --camera (or for a hand): a tone-mapped PNG too.")
@click.option("--splits", default=None, metavar="LIST",
              help="[capture] Comma-separated splits scored: train, heldout, grouped (every "
                   "grouped-light frame), fully_lit, env [default: heldout (grouped for a "
                   "capture no checkpoint trained on), fully_lit, env].")
@click.option("--eval-samples", type=int, default=None, metavar="N",
              help="[capture] At most N evenly spaced samples per split [default: all].")
@seed_option
@no_clobber_option
@quiet_option
def command(**options):
    """Relight IN under new lighting.

    \b
    IN = AVATAR.ply (3DGS Gaussians; also a mesh or builtin:hand|room|sphere,
    optionally placed as SOURCE:KEY=VALUE;... like dgsm-build's OCCLUDERs):
    per-Gaussian SH radiance transfer from --probe (paper Eq. 9-10): colour =
    γ · albedo · clip(S(n), 0, t_max), t_max = --shading-clip, S the cosine-lobe
    (exponent q) weighted
    mean probe radiance around the normal n (normals per object).  --object
    inserts more objects, relit the same way.  With --dgsm and --receivers, each
    light's transmittance attenuates that light's share of a receiver's direct
    light (paper Sec. 3.3): colour × ((1 − s) + s·Σ w_l T_l / Σ w_l) per
    channel, s = --shadow-strength, w_l = the light's intensity × colour
    stored in the DGSM (--light-weights); with a
    DGSM of several OCCLUDERs, each object is also multiplied by the
    transmittance through the OTHER objects (never its own).  Writes the relit
    objects as one PLY, or with --camera an EXR view of receivers + objects.
    A HAND.npz given with --probe, --dgsm, --receivers, --object or
    --shadow-matte is its posed hand as Gaussians (fine mesh, the hand's
    albedo; frame=K in its placement picks the pose), as in dgsm-build.

    IN = HAND.npz (or builtin:right|left|two[:POSE]) with --model physical:
    render the posed hand(s) under the env map ENV (EXR/HDR or
    builtin:sky|studio|uniform|point) and/or --lights, seen by --camera.
    Lambert + GGX (F0 0.04), embree shadows, texture-space subsurface
    scattering, optional one bounce.  Writes an EXR with R, G, B, A (mask) and
    optional AOV layers.

    With --model teacher --checkpoint TEACHER.pt: RelightableHands' OLAT teacher
    (or its GGX baseline) from train-teacher.  Point lights, near or far, take
    one network pass each (their own 1/r² and visibility); an env map is the sum
    over its --env-res directions (linearity of light transport), each a
    distant light with its own ray-traced visibility; passes are batched.

    With --model linear --checkpoint LINEAR.pt: URHand's linear lighting model
    (train-teacher --model linear).  The shading features of all the lights (an
    env map's --env-res directions, point lights with 1/r²; visibility traced)
    are summed and go through the model once: it is linear in them, so no
    distillation is needed.

    Two hands, one model each (RelightableHands Sec. 5): --checkpoint right.pt
    --checkpoint left.pt; each hand takes the checkpoint trained on its
    handedness, its visibility traced against both hands.

    \b
    IN = CAPTURE/ (a relight/capture folder) with --model teacher|linear:
    render the capture's frames and its eval/ env renders, each hand by its
    own --checkpoint, and score them against the capture's images inside the
    hand masks (MSE, PSNR, SSIM, MAE; per hand too for two hands): -o is a
    relight/metrics JSON (kind validation) with one object per --splits split.

    \b
    Examples:
      relight relight avatar.ply --probe probe.json -o avatar-relit.ply
      relight relight avatar.ply --probe probe.json --dgsm shadows.exr \\
          --receivers room.ply --camera cam.json -o view.exr --preview view.png
      relight relight 'builtin:hand:translate=0,0.25,0' --object 'donut.ply:fit=0.15;on-floor' \\
          --probe probe.json --dgsm shadows.exr --receivers room.ply --camera cam.json -o view.exr
      relight relight hand.npz builtin:sky --model physical --camera cam.json -o img.exr
      relight relight hand.npz builtin:sky --model teacher --checkpoint teacher.pt -o img.exr
      relight relight hand.npz builtin:sky --model linear --checkpoint linear.pt -o img.exr
      relight relight both/ --model teacher --checkpoint right.pt --checkpoint left.pt \\
          -o both_scores.json
    """
    from relight_cli.errors import UsageProblem

    a = SimpleNamespace(**options)
    mode = _mode(a)
    _refuse_other_modes(mode, options, a.input)
    if mode == "?":
        raise UsageProblem("IN must be a Gaussians .ply (or a mesh, builtin:hand|room|sphere) or "
                           "a hand .npz (or builtin:right|left|two); cannot tell what this is",
                           a.input)
    if mode == "h":
        raise UsageProblem(f"--model {a.model!r} is not available; use physical, teacher, "
                           f"student or linear")
    {"c": _capture, "g": _gaussians, "p": _hand_physical, "l": _hand_learned,
     "s": _hand_learned}[mode](a)


# ------------------------------------------------------------------------- the modes' options

# Mode-only options, declared once: parameter → (flag, the modes that take it).  Modes:
# g Gaussians, p hand --model physical, l hand --model teacher|linear, s hand --model
# student, c capture.  Options missing here (--output, --background, --seed, ...) are
# common, and so are those whose default cannot be told from a given value (--footprint,
# --samples, --shadow-strength, --lobe, --intensity, --normals: Gaussian options that a
# hand or capture ignores).
_MODE_OPTIONS = {
    "env": ("ENV", "pls"),
    "probe": ("--probe", "g"), "dgsm": ("--dgsm", "g"), "receivers": ("--receivers", "g"),
    "objects": ("--object", "g"), "receivers_out": ("--receivers-out", "g"),
    "light_weights": ("--light-weights", "g"), "direct_light": ("--direct-light", "g"),
    "shadow_matte": ("--shadow-matte", "g"),
    "t_max": ("--shading-clip", "g"),
    "camera": ("--camera", "gpls"),
    "model": ("--model", "plsc"), "checkpoint": ("--checkpoint", "lsc"),
    "device": ("--device", "lsc"), "precision": ("--precision", "s"),
    "hand_size": ("--size", "pls"), "hand_lights": ("--lights", "pls"),
    "hand_frame": ("--frame", "pls"), "hand_frames": ("--frames", "pls"),
    "hand_mesh": ("--mesh", "p"), "env_res": ("--env-res", "plsc"),
    "tex_res": ("--tex-res", "p"), "aa": ("--aa", "plsc"),
    "no_shadows": ("--no-shadows", "p"), "no_specular": ("--no-specular", "p"),
    "no_sss": ("--no-sss", "p"), "sss_scale": ("--sss-scale", "p"), "bounce": ("--bounce", "p"),
    "albedo_map": ("--albedo", "p"), "roughness_map": ("--roughness", "p"),
    "aov": ("--aov", "p"), "preview": ("--preview", "gpls"),
    "splits": ("--splits", "c"), "eval_samples": ("--eval-samples", "c"),
}

# How a run refuses the options of other modes, in the order checked: (the run modes
# this row applies to — h: a hand whose --model is unknown, ?: an IN of no mode —,
# which refused options it names (parameter, their modes), the error; the error names
# IN where the row says "IN").
_REFUSALS = (
    ("c", lambda n, m: True, "{} do not apply to a capture (IN = CAPTURE/ renders the "
                             "capture's own cameras, lights and env maps)"),
    ("gplsh?", lambda n, m: m == "c", "{} only apply to a capture (IN = CAPTURE/)"),
    ("plsh?", lambda n, m: n == "objects",
     "--object inserts Gaussian objects beside IN = AVATAR.ply (or a mesh, "
     "builtin:hand|room|sphere); it does not apply to a hand .npz", "IN"),
    ("plsh", lambda n, m: m == "g", "{} only apply to Gaussians (IN = AVATAR.ply)"),
    ("g", lambda n, m: True, "{} only apply to a hand (IN = HAND.npz)"),
    ("p", lambda n, m: n in ("checkpoint", "device"),
     "--checkpoint and --device belong to a learned --model (teacher, student, linear)"),
    ("pl", lambda n, m: n == "precision",
     "--precision sets the student's decoder: it needs --model student"),
    ("ls", lambda n, m: True, "{} only apply to --model physical (a learned model has its "
                              "own texture, materials and shadows)"),
)

_HAND_MODELS = {"physical": "p", "teacher": "l", "linear": "l", "student": "s"}
_GAUSSIAN_FILES = (".ply", ".obj", ".glb", ".gltf", ".stl", ".off")


def _mode(a) -> str:
    """The run's mode (a letter of _MODE_OPTIONS; h: a hand of an unknown --model, ?: an
    IN that is none of them)."""
    from relight_cli.gaussians.placement import split_spec
    if _is_capture(a.input):
        return "c"
    lower = split_spec(a.input)[0].lower()
    if lower.endswith(_GAUSSIAN_FILES) or lower in ("builtin:hand", "builtin:room",
                                                    "builtin:sphere"):
        return "g"
    # a hand .npz given Gaussian options is the posed hand made into Gaussians (the bridge
    # from the hand half to the Gaussian half; frame=K in its placement picks the pose)
    if lower.endswith(".npz") and any(v is not None and v != () for v in
                                      (a.probe, a.dgsm, a.receivers, a.shadow_matte, a.objects)):
        return "g"
    if lower.endswith(".npz") or lower.startswith("builtin:"):
        return _HAND_MODELS.get(a.model or "physical", "h")
    return "?"


def _refuse_other_modes(mode: str, values: dict, source: str) -> None:
    """A usage error (exit 2) naming the given options that ``mode`` does not take."""
    from relight_cli.errors import UsageProblem
    given = [(name, flag, modes) for name, (flag, modes) in _MODE_OPTIONS.items()
             if mode not in modes and values[name] is not None and values[name] is not False
             and values[name] != ()]
    for modes, which, message, *names_in in _REFUSALS:
        named = [flag for name, flag, taken in given if which(name, taken)]
        if mode in modes and named:
            raise UsageProblem(message.format(", ".join(named)), source if names_in else None)


def _is_capture(spec: str) -> bool:
    import os
    if spec.lower().endswith((".npz",) + _GAUSSIAN_FILES):
        return False      # a file name (a folder by that name is then refused as a hand/avatar)
    return os.path.isdir(spec) or os.path.basename(spec) == "capture.json"


# ------------------------------------------------------------------------- Gaussians

def _gaussians(a) -> None:
    """Gaussian mode: IN (+ --object) relit by --probe, shadowed by --dgsm with
    --receivers, → a PLY or with --camera an EXR view (relight_cli.jobs.relight_gaussians)."""
    import time

    from relight_cli.errors import DataError
    from relight_cli.formats.sh_probe_json import read_probe
    from relight_cli.gaussians.from_mesh import load_gaussians
    from relight_cli.inputs import load_placed, parse_occluder
    from relight_cli.jobs import relight_gaussians as G

    bg = _gaussian_usage(a)
    specs = [a.input] + list(a.objects)
    parsed = [parse_occluder(spec, "IN/--object") for spec in specs]
    for path in [source for source, _ in parsed] + [a.dgsm, a.receivers]:
        if path is not None:
            check_input(path)
    for path, role in ((a.probe, "--probe"), (a.camera, "--camera")):
        if path is not None:
            check_input(path, stdin=role)
    start = time.perf_counter()
    if a.shadow_matte is not None:
        return _shadow_matte(a, specs, parsed, bg, start)
    probe = read_probe(a.probe)
    shadow_map = _read_dgsm(a.dgsm) if a.dgsm is not None else None
    objects = []
    for spec, (source, placement) in zip(specs, parsed):
        objects.append(load_placed(source, placement, spec))
        log(f"read {spec}: {len(objects[-1])} Gaussians", a.quiet)
    scene = None
    if a.receivers is not None:
        scene = load_gaussians(a.receivers)   # PLY, mesh or builtin:
        log(f"read {a.receivers}: {len(scene)} receiver Gaussians", a.quiet)
    if shadow_map is not None and shadow_map.groups is not None \
            and len(shadow_map.groups) != len(objects):
        raise DataError(f"the shadow map has {len(shadow_map.groups)} occluder groups "
                        f"({', '.join(shadow_map.group_names)}) but {len(objects)} "
                        f"object(s) were given (IN + --object, in dgsm-build's order)", a.dgsm)
    view = _read_view(a.camera)
    relit = G.relight(objects, probe, _gaussian_options(a), shadow_map, scene, view, bg,
                      names=[source for source, _ in parsed], log=lambda m: log(m, a.quiet))
    settings = dict(relit.settings, objects=specs)
    inputs = _gaussian_inputs(a, parsed, camera=False)
    if a.receivers_out is not None:
        _write_ply(a.receivers_out, relit.receivers, inputs, dict(settings, role="receivers"))
        log(f"wrote {a.receivers_out}", a.quiet)
    if view is None:
        _write_ply(a.output, relit.objects, inputs, settings)
        log(f"wrote {a.output} ({time.perf_counter() - start:.2f} s)", a.quiet)
        return
    _write_view(a, relit.channels, relit.rgb, view, _gaussian_inputs(a, parsed, camera=True),
                dict(settings, background=list(bg)), {})
    log(f"wrote {a.output} ({view.width}x{view.height}, {relit.rendered} Gaussians, "
        f"{time.perf_counter() - start:.2f} s)", a.quiet)
    if a.preview is not None:
        log(f"wrote {a.preview}", a.quiet)


def _gaussian_usage(a) -> tuple:
    """The Gaussian mode's usage checks (before any work): the background."""
    from relight_cli.errors import UsageProblem
    if a.probe is None and a.shadow_matte is None:
        raise UsageProblem("Gaussian relighting needs --probe PROBE.json (make one with relight "
                           "sh-probe)")
    for wrong, message in (
            (a.dgsm is not None and a.receivers is None,
             "--dgsm shadows receivers: give --receivers SCENE.ply"),
            (a.direct_light and a.dgsm is None,
             "--direct-light takes its lights from --dgsm SHADOWS.exr"),
            (a.receivers_out is not None and a.receivers is None,
             "--receivers-out needs --receivers"),
            (a.preview is not None and a.camera is None,
             "--preview needs --camera (a rendered view)"),
            (a.shadow_matte is not None and (a.camera is None or a.dgsm is None),
             "--shadow-matte renders a matte: give --camera CAMERA.json and --dgsm "
             "SHADOWS.exr (its lights)")):
        if wrong:
            raise UsageProblem(message)
    bg = parse_vector(a.background, 3, "--background", minimum=0)
    if a.camera is not None and not a.output.lower().endswith(".exr"):
        raise UsageProblem("with --camera, -o is an EXR image (name it .exr)", a.output)
    if a.camera is None and not a.output.lower().endswith(".ply"):
        raise UsageProblem("-o is the relit Gaussians PLY (name it .ply), or use --camera CAM "
                           "-o IMAGE.exr", a.output)
    check_output(a.output, a.no_clobber)
    check_output(a.receivers_out, a.no_clobber, kind="ply", what="--receivers-out")
    check_output(a.preview, a.no_clobber, kind="png", what="--preview")
    return bg


def _gaussian_options(a):
    from relight_cli.jobs.relight_gaussians import GaussianOptions
    return GaussianOptions(lobe=a.lobe, intensity=a.intensity, t_max=a.t_max, normals=a.normals,
                           footprint=a.footprint, samples=a.samples, seed=a.seed,
                           shadow_strength=a.shadow_strength, light_weights=a.light_weights,
                           direct_light=a.direct_light)


def _gaussian_inputs(a, parsed, camera: bool) -> dict:
    """The provenance roles of the Gaussian mode's input files."""
    inputs = {"input": parsed[0][0]}
    if a.shadow_matte is None:
        inputs["probe"] = a.probe
    inputs.update({f"object{j}": source for j, (source, _) in enumerate(parsed[1:])})
    inputs.update({role: path for role, path in (("receivers", a.receivers), ("dgsm", a.dgsm))
                   if path})
    if camera:
        inputs["camera"] = a.camera
    return inputs


def _shadow_matte(a, specs, parsed, bg, start) -> None:
    """The receivers-only shadow matte of the paper's Sec. 4.2 (``--shadow-matte``)."""
    import time

    from relight_cli.errors import DataError
    from relight_cli.gaussians.from_mesh import load_gaussians
    from relight_cli.jobs import relight_gaussians as G

    shadow_map = _read_dgsm(a.dgsm)
    scene = load_gaussians(a.receivers)
    view = _read_view(a.camera)
    meshes = None
    if a.shadow_matte == "mesh":
        from relight_cli.gaussians import shadow_matte as SM
        meshes = []
        for spec, (source, placement) in zip(specs, parsed):
            try:
                meshes.append(SM.load_placed_mesh(source, placement))
            except ValueError as exc:
                raise DataError(str(exc), spec) from None
    options = _gaussian_options(a)
    options.light_weights = a.light_weights or "intensity"
    matte = G.shadow_matte(a.shadow_matte, scene, shadow_map, view, options, meshes, bg,
                           log=lambda m: log(m, a.quiet))
    _write_view(a, matte.channels, matte.rgb, view, _gaussian_inputs(a, parsed, camera=True),
                dict(matte.settings, objects=specs),
                {"relight.matte": f"shadow strength ({a.shadow_matte})"})
    log(f"wrote {a.output} (shadow matte, {a.shadow_matte}: "
        f"{int((matte.strength > 0.1).sum())} of {len(matte.strength)} receivers > 0.1, "
        f"{time.perf_counter() - start:.2f} s)", a.quiet)


def _write_ply(path, gaussians, inputs, settings) -> None:
    from relight_cli.formats.gaussians_ply import FORMAT, VERSION, write_gaussians
    from relight_cli.provenance import provenance
    write_gaussians(path, gaussians, provenance(FORMAT, VERSION, inputs, settings))


def _write_view(a, channels, rgb, view, inputs, settings, attributes) -> None:
    """A rendered Gaussian view: -o's EXR (R, G, B, A) and the --preview PNG."""
    from relight_cli.formats.exr import write_exr
    from relight_cli.provenance import provenance
    write_exr(a.output, channels, attributes={**attributes, "relight.camera": view.to_json()},
              provenance=provenance("relight/render", 1, inputs, settings), camera=view)
    if a.preview is not None:
        from relight_cli.preview import write_preview
        write_preview(a.preview, rgb)


def _read_view(path):
    """The camera of --camera (None without one)."""
    if path is None:
        return None
    from relight_cli.formats.camera import read_camera
    return read_camera(path)


def _read_dgsm(path: str):
    """The DGSM of --dgsm (formats/dgsm_exr.py)."""
    from relight_cli.formats.dgsm_exr import read_dgsm
    return read_dgsm(path)


# ------------------------------------------------------------------------- hands

def _hand_physical(a) -> None:
    """Hand mode, --model physical: the posed hand(s) under ENV and/or --lights → EXR
    image(s), one per frame with --frames (relight_cli.jobs.relight_hand.physical)."""
    import time

    from relight_cli.errors import DataError
    from relight_cli.inputs import load_envmap, load_hand, read_roughness_map
    from relight_cli.jobs import relight_hand as J
    from relight_cli.render import appearance as A
    from relight_cli.render.shading import RenderSettings

    width, height, frame, env_h, env_w = _hand_view_options(a)
    _sequence_patterns(a)
    tex, samples_axis, aovs, rough_value = _physical_usage(a)
    bg = parse_vector(a.background, 3, "--background", minimum=0)
    _check_hand_files(a, (a.albedo_map, None))

    start = time.perf_counter()
    data = load_hand(a.input)
    frames = _frames(a, frame, data)
    envmap = load_envmap(a.env) if a.env is not None else None
    lights = _point_lights(a.hand_lights)
    rough = rough_value
    if a.roughness_map is not None and rough_value is None:
        rough = read_roughness_map(a.roughness_map)
    mesh_name = a.hand_mesh or "fine"
    view_of = _view_of(a, width, height)
    try:
        materials = A.hand_materials(data, mesh_name, max(tex, 256), a.seed,
                                     _albedo(a.albedo_map), rough)
    except ValueError as exc:
        raise DataError(str(exc), a.albedo_map or a.roughness_map) from None
    log(f"read {a.input}: {len(data.hands)} hand(s), "
        f"{_frames_text(frames)}; {'env ' + a.env if a.env else 'no env'}, "
        f"{0 if lights is None else len(lights)} point light(s)", a.quiet)

    scale = 1.0 if a.sss_scale is None else a.sss_scale   # its range is checked by FiniteFloat
    settings = RenderSettings(tex_res=tex, aa=samples_axis, shadows=not a.no_shadows,
                              specular=not a.no_specular, sss=not a.no_sss, sss_scale=scale,
                              env_res=(env_h, env_w), bounce=a.bounce)
    inputs = {"hand": a.input, "env": a.env, "camera": a.camera, "lights": a.hand_lights,
              "albedo": a.albedo_map,
              "roughness": a.roughness_map if rough_value is None else None}
    record = J.physical_settings(settings, mesh_name, a.roughness_map, a.seed, bg)
    renders = J.physical(data, frames, view_of, materials, settings, lights, envmap, bg,
                         mesh_name, aovs, a.input)
    _write_frames(a, renders, frames, inputs, record, start, passes=False)


def _physical_usage(a) -> tuple:
    """--model physical's own usage checks: (tex_res, aa, AOV names, roughness value or None)."""
    from relight_cli.errors import UsageProblem
    tex = 256 if a.tex_res is None else a.tex_res
    if not 8 <= tex <= 4096:
        raise UsageProblem(f"--tex-res must be in [8, 4096], got {tex}")
    samples_axis = 2 if a.aa is None else a.aa
    if not 1 <= samples_axis <= 8:
        raise UsageProblem(f"--aa must be in [1, 8], got {samples_axis}")
    aovs = [v.strip() for v in a.aov.split(",") if v.strip()] if a.aov else []
    if a.aov is not None and not aovs:
        raise UsageProblem("--aov needs at least one of normal, uv, depth")
    bad = [v for v in aovs if v not in ("normal", "uv", "depth")]
    if bad:
        raise UsageProblem(f"--aov takes normal, uv, depth; unknown: {', '.join(bad)}")
    rough_value = None
    if a.roughness_map is not None:
        try:
            rough_value = float(a.roughness_map)
        except ValueError:
            check_input(a.roughness_map)
        else:
            if not 0 < rough_value <= 1:
                raise UsageProblem(f"--roughness must be in (0, 1], got {a.roughness_map}")
    return tex, samples_axis, aovs, rough_value


def _hand_learned(a) -> None:
    """Hand mode with a learned model: the teacher's per-light textures summed (Eq. 2),
    URHand's linear model, or the student (relight_cli.jobs.relight_hand)."""
    import time

    from relight_cli.errors import UsageProblem
    from relight_cli.inputs import load_envmap, load_hand
    from relight_cli.neural.train import resolve_device

    if not a.checkpoint:
        raise UsageProblem(f"--model {a.model} needs --checkpoint CKPT.pt (from "
                           f"{'distill' if a.model == 'student' else 'train-teacher'})")
    if a.model == "student" and len(a.checkpoint) > 1:
        raise UsageProblem("--model student takes one --checkpoint (one student renders "
                           "every hand)")
    if a.model == "student" and a.hand_lights is not None:
        raise UsageProblem("the student is an env-map model: it cannot take --lights (use "
                           "--model teacher for point lights)")
    width, height, frame, env_h, env_w = _hand_view_options(a)
    _sequence_patterns(a)
    if a.aa is not None and not 1 <= a.aa <= 8:
        raise UsageProblem(f"--aa must be in [1, 8], got {a.aa}")
    bg = parse_vector(a.background, 3, "--background")
    _check_hand_files(a, *((path, None) for path in a.checkpoint))

    start = time.perf_counter()
    device = resolve_device(a.device or "auto")
    data = load_hand(a.input)
    frames = _frames(a, frame, data)
    if a.model == "student":
        net, config, ckpt = _load_student(a, data, device)
    else:
        per_hand = _load_per_hand(a, data, device)
        config = per_hand[0].config
    envmap = load_envmap(a.env) if a.env is not None else None
    lights = None
    if a.hand_lights is not None:
        from relight_cli.formats.lights_json import read_lights
        lights = read_lights(a.hand_lights)
    view_of = _view_of(a, width, height)
    samples_axis = ((config.aa or 2) if a.model == "teacher" else 2) if a.aa is None else a.aa
    job = dict(data=data, frames=frames, view_of=view_of, samples_axis=samples_axis,
               background=bg, device=device, source=a.input)
    if a.model == "student":
        return _render_student(a, job, net, config, ckpt, envmap, env_h, env_w, start)
    _render_per_hand(a, job, per_hand, lights, envmap, env_h, env_w, start)


def _render_student(a, job, net, config, ckpt, envmap, env_h, env_w, start) -> None:
    """--model student: the texel features under the env map, one decoder pass per frame."""
    from relight_cli.errors import UsageProblem
    from relight_cli.envmap import discretize_env
    from relight_cli.jobs import relight_hand as J
    from relight_cli.neural.distill import render_grid
    if a.env_res is None:
        env_h, env_w = render_grid(config)       # the student's own render grid
    if config.student == "dram" and (env_h, env_w) != tuple(config.env_res):
        from relight_cli.envmap import EnvGrid
        raise UsageProblem(f"the DRAM student was trained on a {EnvGrid(*config.env_res)} "
                           f"(WxH) env grid, its light code's; --env-res must match")
    used = J.decoder_precision(a.precision or "auto", job["device"])
    log(f"student decoder: {used} (--precision {a.precision or 'auto'})", a.quiet)
    renders = J.student(net=net, config=config, denv=discretize_env(envmap, env_h, env_w),
                        precision=used, **job)
    inputs = {"hand": a.input, "checkpoint": a.checkpoint[0], "env": a.env, "camera": a.camera}
    settings = J.student_settings(config, ckpt["step"], used, (env_h, env_w),
                                  job["samples_axis"], job["background"])
    _write_frames(a, renders, job["frames"], inputs, settings, start, passes=False)


def _render_per_hand(a, job, per_hand, lights, envmap, env_h, env_w, start) -> None:
    """--model teacher|linear: one pass per light / direction and hand (teacher; linear:
    one per lighting and hand), hand k by its own model, visibility against every hand;
    a bar over the passes for one frame."""
    import contextlib

    import numpy as np

    from relight_cli.clitools import progress
    from relight_cli.envmap import discretize_env
    from relight_cli.jobs import relight_hand as J
    denv = discretize_env(envmap, env_h, env_w) if envmap is not None else None
    inputs = {"hand": a.input, "env": a.env, "camera": a.camera, "lights": a.hand_lights,
              **_checkpoint_roles(a.checkpoint)}
    settings = J.learned_settings(a.model, per_hand, (env_h, env_w), job["samples_axis"],
                                  job["background"])
    bar = contextlib.nullcontext()
    if a.hand_frames is None:          # one frame: a bar over its passes (a sequence: frames)
        lit = 0 if denv is None else int(np.count_nonzero(denv.lit))
        total = (lit + (0 if lights is None else len(lights.positions))) * len(job["data"].hands)
        bar = progress(total=total, desc=f"relight ({a.model} passes)", quiet=a.quiet)
    with bar as passes:
        renders = J.learned(per_hand=per_hand, lights=lights, denv=denv,
                            progress=None if passes is None else passes.update, **job)
        _write_frames(a, renders, job["frames"], inputs, settings, start, passes=True)


def _load_student(a, data, device) -> tuple:
    """(net, config, checkpoint) of --model student; DataError for a checkpoint that does
    not load or does not fit the hand."""
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.checkpoint import read_checkpoint
    from relight_cli.jobs import relight_hand as J
    from relight_cli.neural.checkpoints import student_model
    ckpt = read_checkpoint(a.checkpoint[0], kind="student")
    try:
        net, config = student_model(ckpt, device)
    except (ValueError, UsageProblem) as exc:
        raise DataError(getattr(exc, "message", str(exc)), a.checkpoint[0]) from None
    try:
        J.check_student(ckpt, data)
    except ValueError as exc:
        raise DataError(str(exc), a.input) from None
    return net, config, ckpt


def _load_per_hand(a, data, device) -> list:
    """The HandModel of each hand (--model teacher|linear): each hand takes the checkpoint
    trained on its handedness; a note when one renders its mirror image."""
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.hand.scene import handedness
    from relight_cli.neural import evaluate as EV
    models = _load_hand_models(a.checkpoint, a.model, device)
    try:
        per_hand = EV.assign_models(models, handedness(data))
    except ValueError as exc:
        raise UsageProblem(str(exc)) from None
    try:
        EV.check_hands(per_hand, data)
    except ValueError as exc:
        raise DataError(str(exc), getattr(exc, "path", None) or a.input) from None
    for k, (m, side) in enumerate(zip(per_hand, handedness(data))):
        if m.sides and side not in m.sides:
            log(f"note: hand {k} ({side}) is rendered by {m.name}, trained on the "
                f"{'/'.join(m.sides)} hand; give one --checkpoint per hand for its own model",
                a.quiet)
    return per_hand


def _load_hand_models(paths, kind: str, device) -> list:
    """One HandModel per checkpoint path (of ``kind``: teacher or linear); DataError
    naming the file for one that does not load or build."""
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.checkpoint import read_checkpoint
    from relight_cli.neural.evaluate import load_hand_model
    models = []
    for path in paths:
        ckpt = read_checkpoint(path, kind=kind)
        try:
            models.append(load_hand_model(ckpt, device, name=path))
        except (ValueError, UsageProblem) as exc:
            raise DataError(getattr(exc, "message", str(exc)), path) from None
    return models


def _checkpoint_roles(paths) -> dict:
    """Provenance roles of the checkpoints: ``checkpoint``, or ``checkpoint.0``, ``.1`` …"""
    if len(paths) == 1:
        return {"checkpoint": paths[0]}
    return {f"checkpoint.{i}": p for i, p in enumerate(paths)}


def _hand_view_options(a) -> tuple:
    """Hand mode's shared usage checks: (width, height, frame, env H, env W)."""
    from relight_cli.clitools import check_extension, parse_size
    from relight_cli.errors import UsageProblem
    from relight_cli.inputs import env_grid
    if a.env is None and a.hand_lights is None:
        raise UsageProblem("give an env map ENV and/or --lights LIGHTS.json to light the hand")
    check_extension(a.output, "exr")
    if a.camera is not None and a.hand_size is not None:
        raise UsageProblem("--size sets the default camera's image; the size of --camera is its own")
    width, height = 256, 256
    if a.hand_size is not None:
        width, height = parse_size(a.hand_size, "--size", maximum=8192)
    frame = 0 if a.hand_frame is None else a.hand_frame
    if frame < 0:
        raise UsageProblem(f"--frame must be ≥ 0, got {frame}")
    env_h, env_w = env_grid(a.env_res or "32x16")
    return width, height, frame, env_h, env_w


def _check_hand_files(a, *more) -> None:
    """-o and --preview (one frame; a sequence's are checked by _frames), then the input
    files: --camera, --lights and ``more`` (path, stdin role)."""
    if a.hand_frames is None:
        check_output(a.output, a.no_clobber, kind="exr")
        check_output(a.preview, a.no_clobber, kind="png", what="--preview")
    for path, role in ((a.camera, "--camera"), (a.hand_lights, "--lights"), *more):
        if path is not None:
            check_input(path, stdin=role)


def _point_lights(path):
    """--lights as the physical renderer's PointLights (radiance colour × intensity)."""
    if path is None:
        return None
    from relight_cli.formats.lights_json import read_lights
    from relight_cli.render.shading import PointLights
    raw = read_lights(path)
    return PointLights(raw.positions, raw.colors * raw.intensities[:, None])


def _albedo(path):
    """--albedo's [H, W, 3] UV albedo (None without one)."""
    if path is None:
        return None
    from relight_cli.errors import DataError
    from relight_cli.formats.image import read_image
    pixels, _names = read_image(path)
    if pixels.shape[2] < 3:
        raise DataError("albedo map needs 3 colour channels", path)
    return pixels[..., :3]


def _sequence_patterns(a) -> None:
    """--frames' usage checks that need no input: not with --frame, and -o (and
    --preview) patterns that name each frame's file ({frame}, Python format syntax)."""
    from relight_cli.errors import UsageProblem
    if a.hand_frames is None:
        return
    if a.hand_frame is not None:
        raise UsageProblem("--frame renders one frame, --frames a sequence: give one of them")
    for what, pattern in (("-o", a.output), ("--preview", a.preview)):
        if pattern is None:
            continue
        if pattern == "-":
            raise UsageProblem(f"{what} of a sequence is a file pattern, not stdout")
        if "{frame" not in pattern:
            raise UsageProblem(f"with --frames, {what} must hold {{frame}} (e.g. "
                               f"'out/frame_{{frame:04d}}.exr'): one file per frame", pattern)
        try:
            first, second = pattern.format(frame=0), pattern.format(frame=1)
        except (KeyError, IndexError, ValueError) as exc:
            raise UsageProblem(f"{what} pattern {pattern!r} does not format with frame=N "
                               f"({exc})") from None
        if first == second:
            raise UsageProblem(f"{what} pattern {pattern!r} gives every frame the same file")


def _frames(a, frame, data) -> list:
    """The frames to render (``--frames`` or the one ``--frame``), and with --frames every
    frame's output checked as -o / --preview are (before any work)."""
    from relight_cli.errors import UsageProblem
    from relight_cli.jobs.relight_hand import select_frames
    if a.hand_frames is None:
        if frame >= data.n_frames:
            raise UsageProblem(f"--frame {frame} is out of range: {a.input} has {data.n_frames} "
                               f"frame(s)")
        return [frame]
    try:
        frames = select_frames(a.hand_frames, data.n_frames)
    except ValueError as exc:
        raise UsageProblem(str(exc)) from None
    for what, pattern, kind in (("-o", a.output, "exr"), ("--preview", a.preview, "png")):
        if pattern is None:
            continue
        paths = [pattern.format(frame=f) for f in frames]
        if len(set(paths)) != len(paths):
            raise UsageProblem(f"{what} pattern {pattern!r} gives two frames the same file")
        for path in paths:
            check_output(path, a.no_clobber, kind=kind, what=what)
    return frames


def _frame_outputs(a, frame) -> tuple:
    """(EXR path, PNG path or None) of one frame."""
    if a.hand_frames is None:
        return a.output, a.preview
    return (a.output.format(frame=frame),
            None if a.preview is None else a.preview.format(frame=frame))


def _view_of(a, width, height):
    """(frame, posed meshes) → Camera: --camera read once, or each frame framed by the
    default camera of ``width`` × ``height``."""
    from relight_cli.jobs.relight_hand import framing
    return framing(width, height, _read_view(a.camera))


def _frames_text(frames) -> str:
    if len(frames) == 1:
        return f"frame {frames[0]}"
    return f"{len(frames)} frames ({frames[0]}…{frames[-1]})"


def _write_frames(a, renders, frames, inputs, settings, start, passes: bool) -> None:
    """Write each FrameRender (EXR: its channels, provenance recording its frame; the PNG
    preview; a bar over a sequence's frames), then the closing log line.  ``inputs``'
    None roles are left out."""
    import contextlib

    from relight_cli.clitools import progress
    from relight_cli.formats.exr import write_exr
    from relight_cli.provenance import provenance
    inputs = {role: path for role, path in inputs.items() if path is not None}
    done, bar = [], contextlib.nullcontext()
    if a.hand_frames is not None:
        bar = progress(total=len(frames), desc="relight (frames)", unit="frame", quiet=a.quiet)
    with bar as frames_bar:
        for r in renders:
            path, png = _frame_outputs(a, r.frame)
            record = provenance("relight/render", 1, inputs, {**settings, "frame": r.frame})
            write_exr(path, r.channels, attributes={
                "relight.model": settings["model"], "relight.camera": r.view.to_json()},
                provenance=record, camera=r.view)
            if png is not None:
                from relight_cli.preview import write_preview
                write_preview(png, r.rgb)
            r.rgb = r.channels = None          # the pixels are written; keep the timings
            done.append(r)
            if frames_bar is not None:
                frames_bar.update(1)
    _log_written(done, a.output, a.hand_frames, start, a.quiet, passes=passes)


def _log_written(done, output, hand_frames, start, quiet, passes: bool = False) -> None:
    """The closing log line: the single frame's stage times, or a sequence's frames/s and
    median time per stage."""
    import time

    import numpy as np
    wall = time.perf_counter() - start
    if hand_frames is None:
        r = done[0]
        log(f"wrote {output} ({r.view.width}x{r.view.height}, "
            + (f"{r.passes} pass(es), " if passes else "") + f"{wall:.2f} s: "
            + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in r.seconds.items()) + ")", quiet)
        return
    stages = list(dict.fromkeys(k for r in done for k in r.seconds))
    median = {k: float(np.median([r.seconds.get(k, 0.0) for r in done])) for k in stages}
    rendered = sum(sum(r.seconds.values()) for r in done)
    log(f"wrote {len(done)} frames to {output} ({wall:.1f} s in all, "
        f"{len(done) / max(rendered, 1e-9):.2f} frames/s rendering; median per frame: "
        + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in median.items()) + ")", quiet)


# ------------------------------------------------------------------------- capture

def _capture(a) -> None:
    """Capture mode: a capture's frames and env renders, each hand by its own learned
    model, scored against the capture's images (relight/metrics JSON;
    relight_cli.jobs.score_capture)."""
    import os
    import time

    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.capture import index_path
    from relight_cli.inputs import env_grid
    from relight_cli.neural.evaluate import SPLITS

    if a.model not in ("teacher", "linear"):
        raise UsageProblem("a capture is scored with --model teacher or linear (and one "
                           "--checkpoint per hand)")
    if not a.checkpoint:
        raise UsageProblem(f"--model {a.model} needs --checkpoint CKPT.pt (one per hand)")
    names = None
    if a.splits is not None:
        names = [n.strip() for n in a.splits.split(",") if n.strip()]
        bad = [n for n in names if n not in SPLITS]
        if not names or bad:
            raise UsageProblem(f"--splits takes {', '.join(SPLITS)}"
                               + (f"; unknown: {', '.join(bad)}" if bad else ""))
    if a.eval_samples is not None and a.eval_samples < 1:
        raise UsageProblem(f"--eval-samples must be ≥ 1, got {a.eval_samples}")
    if a.aa is not None and not 1 <= a.aa <= 8:
        raise UsageProblem(f"--aa must be in [1, 8], got {a.aa}")
    grid = env_grid(a.env_res or "32x16")
    index = index_path(a.input)   # names a folder without capture.json and a capture.json that is a folder
    for path in (index, *a.checkpoint):
        check_input(path)
    # after the inputs (never one of them): the scores are a relight/metrics JSON
    check_output(a.output, a.no_clobber, kind="json")

    start = time.perf_counter()
    from relight_cli.formats.metrics_json import make_record, write_metrics
    from relight_cli.jobs.score_capture import CaptureOptions, score_capture
    from relight_cli.neural.train import resolve_device
    from relight_cli.provenance import provenance

    device = resolve_device(a.device or "auto")
    models = _load_hand_models(a.checkpoint, a.model, device)
    options = CaptureOptions(names, a.eval_samples, a.aa, grid, a.model)
    try:
        result = score_capture(os.path.dirname(index) or ".", models, options, device,
                               log=lambda m: log(m, a.quiet), quiet=a.quiet)
    except ValueError as exc:
        raise UsageProblem(str(exc)) from None
    if not result.scores:
        raise DataError(f"the capture has no samples in {', '.join(result.settings['splits'])}",
                        index)
    inputs = {"capture": index, **_checkpoint_roles(a.checkpoint)}
    record = provenance("relight/metrics", 2, inputs, result.settings)
    write_metrics(a.output, make_record("validation", result.scores,
                                        {r: {"path": p} for r, p in inputs.items()},
                                        result.settings, record))
    summary = "; ".join(f"{n}: MSE {m['mse'] * 1e3:.3f}e-3 SSIM {m['ssim']:.3f} ({m['samples']})"
                        for n, m in result.scores.items())
    log(f"wrote {a.output} ({time.perf_counter() - start:.1f} s): {summary}", a.quiet)
