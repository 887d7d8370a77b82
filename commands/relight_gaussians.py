"""``relight relight AVATAR.ply``: Gaussians relit by an SH probe, shadowed by a DGSM.

The Gaussian mode of ``relight relight`` (commands/relight.py dispatches on IN): IN (+
``--object``) relit by per-Gaussian SH radiance transfer from ``--probe`` (paper Eq.
9-10), shadowed with ``--dgsm`` over ``--receivers`` (Sec. 3.3), written as one PLY or,
with ``--camera``, an EXR view; ``--shadow-matte`` renders the receivers-only matte of the
paper's protocol (Sec. 4.2).  The work is :mod:`relight_cli.jobs.relight_gaussians`; its
options are :class:`~relight_cli.jobs.relight_gaussians.GaussianOptions`.
"""

from __future__ import annotations

from dataclasses import dataclass

import click

from relight_cli.cli.tools import (FiniteFloat, ShadowStrength, check_input, check_output,
                                   colour_space_option, log, no_clobber_option, parse_vector,
                                   preview_exposure_option, quiet_option, renamed_option,
                                   seed_option)
from relight_cli.commands import _gaussian_parts as parts
from relight_cli.commands._clip import clip_options, gaussian_options, write_ply

#: What IN may be in this mode: a Gaussians PLY (or a '{frame}' pattern of them), a mesh,
#: a Gaussian sequence index, or a built-in Gaussian object.
FILES = (".ply", ".obj", ".glb", ".gltf", ".stl", ".off",
         ".json")   # a relight/gaussian-sequence index (formats/gaussian_sequence.md)
BUILTINS = ("builtin:hand", "builtin:room", "builtin:sphere")
#: The inputs that make a hand (IN = HAND.npz) a Gaussian scene: its posed hand as
#: Gaussians (fine mesh, the hand's albedo; frame=K in its placement picks the pose).
SCENE_OPTIONS = ("probe", "dgsm", "receivers", "shadow_matte", "objects")
#: What the dispatcher says IN is in this mode.
DESCRIPTION = "Gaussians (IN = AVATAR.ply)"


def accepts(spec: str, given: set) -> bool:
    """Whether IN ``spec`` is relit in this mode, ``given`` the options on the command
    line (parameter names): a Gaussians file or built-in object, or a hand .npz given
    one of :data:`SCENE_OPTIONS`."""
    from relight_cli.gaussians.placement import split_spec
    lower = split_spec(spec)[0].lower()
    if lower.endswith(FILES) or lower in BUILTINS:
        return True
    return lower.endswith(".npz") and bool(given & set(SCENE_OPTIONS))


@dataclass(frozen=True)
class Run:
    """This mode's options as given (the click parameters, one field each)."""

    input: str
    env: str | None
    output: str
    probe: str | None
    up: str | None
    coordinates: str | None
    dgsm: str | None
    receivers: str | None
    objects: tuple
    receivers_out: str | None
    footprint: str
    samples: int
    shadow_strength: object
    light_weights: str | None
    direct_light: bool
    self_shadow: bool
    shadow_matte: str | None
    lobe: float
    intensity: float
    t_max: float | None
    normals: str
    colour_space: str
    camera: str | None
    background: str
    preview: str | None
    preview_exposure: float | None
    frame: int | None
    frames: str | None
    lights_spec: str | None
    shadow_size: str | None
    probe_degree: int | None
    video: str | None
    seed: int
    no_clobber: bool
    quiet: bool


@click.command("relight",
               short_help="Relight Gaussians with an SH probe or env map (+ DGSM shadows).")
@click.argument("input", metavar="IN")
@click.argument("env", metavar="[ENV]", required=False)
@click.option("-o", "--output", required=True,
              help="The relit Gaussians PLY, or with --camera an EXR image.")
@click.option("--probe", default=None, metavar="PROBE.json",
              help="SH light probe (relight sh-probe) lighting the avatar ('-': "
                   "stdin); or give an env map ENV after IN instead.")
@click.option("--up", default=None, metavar="AXIS|X,Y,Z",
              help="The up axis of IN's frame (after its placement): +y, -y, +x, -x, +z, -z "
                   "or a vector X,Y,Z.  ENV/--probe (+Y up) is turned into that frame, the "
                   "Gaussians stay where they are: a COLMAP capture (+Y down) takes --up -y, "
                   "the same as placing it with rotate-x=180 and back.  [default: +y]")
@click.option("--coordinates", type=click.Choice(["source", "scene"]), default=None,
              help="The frame of the relit PLY when IN is placed (SOURCE:KEY=VALUE): source "
                   "writes the relit Gaussians back in IN's own frame (its positions bit for "
                   "bit, so it still registers with its cameras), scene where the placement "
                   "put them.  [default: source; scene with --object]")
@click.option("--dgsm", default=None, metavar="SHADOWS.exr",
              help="Deep Gaussian Shadow Map (relight dgsm-build) darkening --receivers.")
@click.option("--receivers", default=None, metavar="SCENE.ply",
              help="Scene Gaussians: shadowed by --dgsm, and rendered with --camera.")
@click.option("--object", "objects", multiple=True, metavar="SPEC",
              help="Another object inserted beside IN (repeatable): a PLY, mesh or "
                   "builtin:, with a placement SOURCE:KEY=VALUE;... as in dgsm-build. Relit "
                   "by --probe like IN; with a grouped --dgsm, IN and the objects (in this "
                   "order, matching dgsm-build's OCCLUDERs) shadow each other.")
@click.option("--receivers-out", default=None, metavar="PLY",
              help="Also write the shadowed receivers as a PLY.")
@click.option("--footprint", type=click.Choice(["centre", "stencil", "mc"]), default="stencil",
              show_default=True,
              help="DGSM lookup over a receiver: centre sample, 7-point stencil, or "
                   "seeded Monte Carlo (--samples) in its principal frame.  The paper's default "
                   "is mc (Sec. 3.3); stencil is ours: 7 deterministic lookups that reproduce "
                   "the Gaussian's mean and covariance exactly (no sampling noise).")
@click.option("--samples", type=click.IntRange(1, 1024), default=16, show_default=True,
              help="Monte Carlo samples per receiver for --footprint mc.")
@click.option("--shadow-strength", type=ShadowStrength(), default="auto", show_default=True,
              help="Direct share s of a receiver's colour: colour × ((1 − s) + "
                   "s·Σ w_l T_l / Σ w_l) per channel.  A number in [0, 1] for every receiver (1, "
                   "the paper's reading: the whole colour is direct light, a full shadow is "
                   "black), or auto: per receiver, the share of its light the DGSM's lights "
                   "deliver against the probe's irradiance, E_d / (E_d + E_probe).")
@click.option("--light-weights", type=click.Choice(["intensity", "irradiance", "equal"]),
              default=None,
              help="Each light's share w_l of the direct light (paper Sec. 3.3): "
                   "intensity × colour (from the DGSM), also × |n·ω|/r² at each receiver "
                   "(irradiance), or equal (the plain mean T of older versions).  Default: "
                   "irradiance with --shadow-strength auto (so the shadow is exactly each "
                   "light's irradiance times its T), else intensity.")
@click.option("--direct-light", is_flag=True,
              help="With --dgsm: the DGSM's point lights also light IN and the "
                   "objects directly, albedo × Σ I_l C_l max(n·ω_l, 0)/(π r_l²) added to the "
                   "probe's shading (ours: the paper lights avatars by the probe only), each "
                   "light's term shadowed by the other objects.")
@click.option("--self-shadow", is_flag=True,
              help="With --dgsm (built by dgsm-build --self-shadow) or --lights: IN and the "
                   "objects are shadowed by themselves too (fingers on the palm), each "
                   "Gaussian looked up 3σ (+ one radial bin) towards each light so it never "
                   "shadows itself (ours: the paper's avatars receive no shadow of their "
                   "own).")
@click.option("--shadow-matte", type=click.Choice(["dgsm", "mesh"]), default=None,
              help="With --camera: the receivers-only shadow matte of the paper's "
                   "protocol (Sec. 4.2): receivers coloured by shadow strength 1 − Σw_l V_l/Σw_l, "
                   "nothing else drawn; dgsm: V = the DGSM's transmittance; mesh: V = embree "
                   "shadow rays against IN (and --object) as triangle meshes, the pseudo ground "
                   "truth.  Lights and weights come from --dgsm in both.")
@click.option("--lobe", type=FiniteFloat(0, 1e4, min_open=True), default=1.0, show_default=True,
              help="Cosine lobe exponent q of the transfer (1 = Lambertian).")
@click.option("--intensity", type=FiniteFloat(0, 1e6), default=1.0, show_default=True,
              help="Global intensity γ.")
@click.option("--shading-clip", "t_max", type=FiniteFloat(0, min_open=True), default=None,
              help="Clip t_max of the shading factor (default: no clip; formerly "
                   "--t-max).")
@renamed_option("--t-max", "--shading-clip",
                why="--t-max is dgsm-build's radial extent in metres")
@click.option("--normals", type=click.Choice(["auto", "axis", "pca", "stored"]), default="auto",
              show_default=True,
              help="Normals: shortest ellipsoid axis, local PCA of neighbours, the "
                   "file's nx ny nz; auto = stored if present, else axis. Oriented outward.")
@click.option("--camera", "camera", default=None, metavar="CAMERA.json",
              help="The OpenCV camera of a view (relight camera; formats/camera.md; '-': "
                   "stdin): render the receivers and the relit objects to -o as an EXR (R, G, "
                   "B, A) instead of writing a PLY (formerly --render).")
@renamed_option("--render", "--camera", why="one camera option for hands and Gaussians")
@click.option("--background", default="0,0,0", show_default=True, metavar="R,G,B",
              help="Background radiance of the rendered view.")
@click.option("--preview", default=None, metavar="PNG",
              help="With --camera: a tone-mapped PNG of the view too (with --frames a pattern "
                   "holding {frame}).")
@preview_exposure_option
@clip_options
@colour_space_option
@seed_option
@no_clobber_option
@quiet_option
def command(**options):
    """Relight IN = AVATAR.ply (3DGS Gaussians; also a mesh or
    builtin:hand|room|sphere, optionally placed as SOURCE:KEY=VALUE;... like
    dgsm-build's OCCLUDERs): per-Gaussian SH radiance transfer from --probe,
    or from ENV's probe fitted here as relight sh-probe ENV --degree L fits it
    (L the smallest degree holding 99 % of the transfer lobe's energy: 2 for
    --lobe 1), turned into IN's frame by --up (paper Eq. 9-10): colour =
    γ · albedo · clip(S(n), 0, t_max), t_max = --shading-clip, S the
    cosine-lobe (exponent q) weighted mean probe radiance around the normal n
    (normals per object).  --object inserts more objects,
    relit the same way.  With --dgsm and --receivers, each light's
    transmittance attenuates that light's share of a receiver's direct light
    (paper Sec. 3.3): colour × ((1 − s) + s·Σ w_l T_l / Σ w_l) per channel,
    s = --shadow-strength, w_l = the light's intensity × colour stored in the
    DGSM (--light-weights); with a DGSM of several OCCLUDERs, each object is
    also multiplied by the transmittance through the OTHER objects (never its
    own).  Writes the relit objects as one PLY, or with --camera an EXR view of
    receivers + objects.  A HAND.npz given with --probe, --dgsm, --receivers,
    --object or --shadow-matte is its posed hand as Gaussians (fine mesh, the
    hand's albedo; frame=K in its placement picks the pose), as in dgsm-build.
    A placed IN's relit PLY is written back in IN's own frame
    (--coordinates).

    \b
    Examples:
      relight relight avatar.ply --probe probe.json -o avatar-relit.ply
      relight relight statue.ply sky.hdr --up -y -o statue-relit.ply
      relight relight avatar.ply --probe probe.json --dgsm shadows.exr \\
          --receivers room.ply --camera cam.json -o view.exr --preview view.png
      relight relight 'builtin:hand:translate=0,0.25,0' --object 'donut.ply:fit=0.15;on-floor' \\
          --probe probe.json --dgsm shadows.exr --receivers room.ply --camera cam.json -o view.exr
    """
    from relight_cli.cli.tools import given_options
    a, given = Run(**options), set(given_options(click.get_current_context()))
    if _is_clip(a):
        _refuse_in_clip(a)
        from relight_cli.commands._clip import clip
        return clip(a, given)
    _gaussians(a, given)


def _is_clip(a) -> bool:
    """Whether a run goes through the clip job (relight_cli.jobs.gaussian_clip): a
    sequence, a frame of one, shadow maps built in-process or per frame, probes
    refitted from the scene."""
    from relight_cli.gaussians.placement import split_spec
    from relight_cli.gaussians.sequence import is_pattern
    sources = [split_spec(spec)[0] for spec in (a.input, *a.objects)]
    walks = any("path=" in (split_spec(spec)[1] or "") for spec in (a.input, *a.objects))
    return (a.frames is not None or a.frame is not None or a.lights_spec is not None
            or a.probe == "scene" or a.video is not None or a.probe_degree is not None
            or a.shadow_size is not None or walks
            or (a.dgsm is not None and is_pattern(a.dgsm))
            or any(is_pattern(s) or s.lower().endswith(".json") for s in sources))


def _refuse_in_clip(a) -> None:
    """ENV, --up and --coordinates are for one relit PLY or view: a clip's usage error
    saying what to do instead."""
    from relight_cli.errors import UsageProblem
    if a.env is not None:
        raise UsageProblem("a clip (--frames, --frame, --lights, --probe scene, a moving IN) "
                           "reads its light from --probe: fit ENV's probe once with relight "
                           f"sh-probe {a.env} -o probe.json and give --probe probe.json")
    if a.up is not None:
        raise UsageProblem("--up turns the light for one relit PLY or view; a clip is lit in "
                           "the scene's frame: place IN upright instead (IN:rotate-x=180 for a "
                           "+Y-down capture)")
    if a.coordinates is not None:
        raise UsageProblem("--coordinates sets the frame of one relit PLY; a clip writes its "
                           "frames where the scene puts them")


def _gaussians(a, given: set = frozenset()) -> None:
    """Gaussian mode: IN (+ --object) relit by --probe, shadowed by --dgsm with
    --receivers, → a PLY or with --camera an EXR view (relight_cli.jobs.relight_gaussians)."""
    import time

    from relight_cli.errors import DataError
    from relight_cli.gaussians.from_mesh import load_gaussians
    from relight_cli.cli.inputs import load_placed, parse_occluder
    from relight_cli.jobs import relight_gaussians as G

    bg = _gaussian_usage(a, given)
    specs = [a.input] + list(a.objects)
    parsed = [parse_occluder(spec, "IN/--object") for spec in specs]
    for path in [source for source, _ in parsed] + [a.dgsm, a.receivers]:
        if path is not None:
            check_input(path)
    for path, role in ((a.probe, "--probe"), (a.camera, "--camera")):
        if path is not None:
            check_input(path, stdin=role)
    if a.env is not None and not a.env.startswith("builtin:"):
        check_input(a.env)
    start = time.perf_counter()
    if a.shadow_matte is not None:
        return parts.shadow_matte(a, specs, parsed, bg, start)
    probe, lighting = parts.lighting(a, lambda m: log(m, a.quiet))
    shadow_map = parts.read_dgsm(a.dgsm) if a.dgsm is not None else None
    if a.self_shadow:
        from relight_cli.commands._clip import check_self_shadow
        check_self_shadow(shadow_map, a.dgsm)
    placed, unplaced, similarity = parts.load_in(a, *parsed[0], specs[0])
    objects = [placed]
    log(f"read {specs[0]}: {len(placed)} Gaussians", a.quiet)
    for spec, (source, placement) in zip(specs[1:], parsed[1:]):
        objects.append(load_placed(source, placement, spec, colour_space=a.colour_space))
        log(f"read {spec}: {len(objects[-1])} Gaussians", a.quiet)
    scene = None
    if a.receivers is not None:
        scene = load_gaussians(a.receivers, colour_space=a.colour_space)   # PLY, mesh, builtin:
        log(f"read {a.receivers}: {len(scene)} receiver Gaussians", a.quiet)
    if shadow_map is not None and shadow_map.groups is not None \
            and len(shadow_map.groups) != len(objects):
        raise DataError(f"the shadow map has {len(shadow_map.groups)} occluder groups "
                        f"({', '.join(shadow_map.group_names)}) but {len(objects)} "
                        f"object(s) were given (IN + --object, in dgsm-build's order)", a.dgsm)
    view = parts.read_view(a.camera)
    relit = G.relight(objects, probe, gaussian_options(a), shadow_map, scene, view, bg,
                      names=[source for source, _ in parsed], log=lambda m: log(m, a.quiet),
                      quiet=a.quiet)
    settings = dict(relit.settings, objects=specs, colour_space=a.colour_space, **lighting)
    inputs = parts.gaussian_inputs(a, parsed, camera=False)
    if a.receivers_out is not None:
        write_ply(a.receivers_out, relit.receivers, inputs, dict(settings, role="receivers"))
        log(f"wrote {a.receivers_out}", a.quiet)
    if view is None:
        written = relit.objects
        if unplaced is not None:       # IN back in its own frame: it registers with its cameras
            written = G.in_source_frame(relit.objects, unplaced, similarity)
            settings["coordinates"] = "source"
            log("the relit Gaussians are written back in IN's own frame (--coordinates "
                "source)", a.quiet)
        write_ply(a.output, written, inputs, settings)
        log(f"wrote {a.output} ({time.perf_counter() - start:.2f} s)", a.quiet)
        return
    parts.write_view(a, relit.channels, relit.rgb, view,
                     parts.gaussian_inputs(a, parsed, camera=True),
                     dict(settings, background=list(bg)), {})
    log(f"wrote {a.output} ({view.width}x{view.height}, {relit.rendered} Gaussians, "
        f"{time.perf_counter() - start:.2f} s)", a.quiet)
    if a.preview is not None:
        log(f"wrote {a.preview}", a.quiet)


def _gaussian_usage(a, given: set = frozenset()) -> tuple:
    """The Gaussian mode's usage checks (before any work): the background.  ``given``: the
    parameter names given on the command line -- an option that cannot apply is refused
    even when it is given as its default (--shadow-strength auto)."""
    from relight_cli.errors import UsageProblem
    if a.probe is None and a.env is None and a.shadow_matte is None:
        raise UsageProblem("Gaussian relighting needs --probe PROBE.json (make one with relight "
                           "sh-probe ENV) or an env map ENV after IN (its probe is then fitted "
                           "here)")
    for wrong, message in (
            (a.env is not None and a.probe is not None,
             f"give the light once: ENV ({a.env}, its SH probe fitted here) or --probe "
             f"PROBE.json, not both"),
            (a.env is not None and a.shadow_matte is not None,
             f"ENV ({a.env}) does not apply to --shadow-matte (the matte draws the receivers' "
             "shadow from --dgsm's lights only): drop ENV"),
            (a.up is not None and a.shadow_matte is not None,
             "--up turns ENV/--probe; --shadow-matte uses neither: drop --up"),
            (a.coordinates is not None and a.camera is not None,
             "--coordinates sets the relit PLY's frame; a --camera view is rendered where the "
             "scene puts IN: drop --coordinates"),
            (a.coordinates == "source" and bool(a.objects),
             "--coordinates source writes IN back in its own frame; with --object the objects "
             "share one PLY only in the scene's frame (--coordinates scene)"),
            (a.dgsm is None and "shadow_strength" in given,
             "--shadow-strength only applies with --dgsm SHADOWS.exr (the direct light it "
             "shadows)"),
            (a.dgsm is None and "light_weights" in given,
             "--light-weights only applies with --dgsm SHADOWS.exr (its lights)"),
            (a.shadow_matte is not None and a.direct_light,
             "--direct-light does not apply to --shadow-matte (the matte draws the receivers' "
             "shadow only)"),
            (a.shadow_matte is not None and "shadow_strength" in given,
             "--shadow-strength does not apply to --shadow-matte (the matte is the full "
             "shadow strength 1 − Σw_l V_l/Σw_l)"),
            (a.dgsm is not None and a.receivers is None,
             "--dgsm shadows receivers: give --receivers SCENE.ply"),
            (a.direct_light and a.dgsm is None,
             "--direct-light takes its lights from --dgsm SHADOWS.exr"),
            (a.self_shadow and a.dgsm is None,
             "--self-shadow looks the objects up in --dgsm SHADOWS.exr (or --lights builds "
             "it)"),
            (a.self_shadow and a.shadow_matte is not None,
             "--self-shadow does not apply to --shadow-matte (the matte is the receivers')"),
            (a.receivers_out is not None and a.receivers is None,
             "--receivers-out needs --receivers"),
            (a.preview is not None and a.camera is None,
             "--preview needs --camera (a rendered view)"),
            (a.preview_exposure is not None and a.preview is None,
             "--preview-exposure sets --preview's tone mapping: give --preview PNG"),
            (a.shadow_matte is not None and (a.camera is None or a.dgsm is None),
             "--shadow-matte renders a matte: give --camera CAMERA.json and --dgsm "
             "SHADOWS.exr (its lights)")):
        if wrong:
            raise UsageProblem(message)
    if a.up is not None:
        parts.upright(a.up)
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
