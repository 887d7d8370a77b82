"""``relight dgsm-build``: Deep Gaussian Shadow Maps of occluder Gaussians for point lights.

The build is :func:`relight_cli.jobs.dgsm_build.build`; this module loads the inputs and
writes the outputs."""

from __future__ import annotations

import click

from relight_cli.cli.tools import (FiniteFloat, ShadowStrength, check_input, check_output,
                                   colour_space_option, log, no_clobber_option, parse_size,
                                   preview_option, quiet_option, seed_option)


@click.command("dgsm-build", short_help="Build Deep Gaussian Shadow Maps (occluders → lights).")
@click.argument("occluders", metavar="OCCLUDER...", nargs=-1, required=True)
@click.option("--receivers", default=None, metavar="SCENE",
              help="Scene Gaussians that receive shadows: they drive the ROI and t_max.")
@click.option("--translate", default=None, metavar="X,Y,Z",
              help="Move every occluder by this offset (metres), after its own placement.")
@click.option("--occluders-out", default=None, metavar="FILE.ply",
              help="Also write the occluder Gaussians used, all occluders in one PLY (after "
                   "placement and --translate; handy for builtin: and mesh inputs).")
@click.option("--receivers-out", default=None, metavar="FILE.ply",
              help="Also write the receiver Gaussians used.")
@click.option("--lights", "lights_spec", required=True, metavar="LIGHTS.json|auto:K",
              help="Point lights (relight/lights JSON, '-': stdin), or auto:K to estimate "
                   "K lights from the receivers' scene.")
@click.option("--estimator", type=click.Choice(["paper", "v1"]), default="paper",
              show_default=True,
              help="Light estimator of --lights auto:K (paper Sec. 3.1: ROI and viewpoints at "
                   "the occluders' centroid, soft-clipped cues, mean-neighbourhood peakness, "
                   "colour toward the character, intensity = base score; v1: the earlier variant).")
@click.option("--lights-out", default=None, metavar="FILE.json",
              help="Also write the lights used (e.g. the auto:K estimate; '-': stdout).")
@click.option("-o", "--output", required=True, help="Output EXR (relight/dgsm).")
@click.option("--size", default="128", show_default=True,
              help="Octahedral atlas WxH (width first) or N for NxN (a cube atlas gets faces "
                   "with as many texels).")
@click.option("--bins", type=click.IntRange(1, 999), default=64, show_default=True,
              help="Radial bins K per texel.")
@click.option("--atlas", type=click.Choice(["octahedral", "cube"]), default="octahedral",
              show_default=True, help="Direction atlas (cube for the ablation).")
@click.option("--mapping", type=click.Choice(["avg", "simple", "mass", "diag", "peak", "eq5"]),
              default="avg", show_default=True,
              help="Opacity→absorption β (paper Sec. 3.2, Table 4): avg = Eq. 5, κτ·√(tr A/3)/√(2π); "
                   "simple = κτ; mass = κτ/((2π)^1.5·√det Σ); diag = κτ/((2π)^1.5·s_x s_y s_z) "
                   "(equal to mass); peak = direction-dependent, every ray through a centre sees "
                   "τ (this toolkit's; eq5 is its old name).")
@click.option("--kappa", type=FiniteFloat(0, min_open=True), default=1.0, show_default=True,
              help="Absorption scale κ (> 0).")
@click.option("--t-max", type=FiniteFloat(0, min_open=True), default=None,
              help="Radial extent (metres) for every light; default from the receivers.")
@click.option("--roi/--no-roi", default=True, show_default=True,
              help="Compute only texels and bins that receivers read.")
@click.option("--roi-radius", type=FiniteFloat(0, min_open=True), default=None,
              help="Also cap the ROI at this distance (metres) from the occluders' centroid.")
@click.option("--cull/--no-cull", default=True, show_default=True,
              help="Light-space occluder culling (tiles, texels, kσ ellipse, radial).")
@click.option("--cull-tolerance",
              type=FiniteFloat(0, 1, min_open=True, max_open=True), default=1e-7, show_default=True,
              help="Largest optical depth a culled Gaussian may have contributed.")
@click.option("--footprint", type=click.Choice(["centre", "stencil", "mc"]), default="stencil",
              show_default=True,
              help="Receiver footprint that later lookups use (widens the ROI to cover it); "
                   "the paper's default is mc, see relight --footprint.")
@click.option("--samples", type=click.IntRange(1, 1024), default=16, show_default=True,
              help="Monte Carlo samples for --footprint mc.")
@click.option("--allow-light-inside", is_flag=True,
              help="Build even if a light lies inside an occluder Gaussian (1σ).")
@click.option("--radial", type=click.Choice(["full", "roi"]), default="full", show_default=True,
              help="Where the --bins radial bins lie: full = the paper's shells from the light "
                   "to t_max; roi = ours, over the receivers' distances only (the same bins "
                   "spent where they are read: finer shadows, e.g. a hand's own with "
                   "--self-shadow).")
@click.option("--self-shadow", is_flag=True,
              help="Also cover each occluder's own self-shadow lookups (relight relight "
                   "--self-shadow: its Gaussians shadowed by the occluder itself, each "
                   "looked up 3σ + one radial bin towards the light).")
@click.option("--half", is_flag=True, help="Store 16-bit half floats (default float32).")
@preview_option("Also write a labelled PNG: the receivers shadowed as relight relight "
                "shadows them (with the occluders; its label says the shadow strength) and "
                "their shadow matte, seen from --preview-camera, and each light's atlas slice "
                "(min T over the bins).")
@click.option("--preview-camera", default=None, metavar="CAMERA.json",
              help="OpenCV camera of --preview (default: one framing the occluders and their "
                   "shadow, from the side and above).")
@click.option("--preview-probe", default=None, metavar="PROBE.json",
              help="The scene's SH probe (relight sh-probe), as relight relight --probe "
                   "gets it: the --preview then shows the shadow relight's default "
                   "--shadow-strength auto delivers (each receiver's direct share of its "
                   "light, lighter than a full shadow).")
@click.option("--preview-shadow-strength", type=ShadowStrength(), default=None,
              help="The relight --shadow-strength the --preview shows: a number in [0, 1] "
                   "or auto (needs --preview-probe) [default: auto with --preview-probe, "
                   "else 1, the paper's full shadow].")
@click.option("--frame", "frame", type=click.IntRange(0), default=None, metavar="K",
              help="One frame of moving OCCLUDERs (a hand.npz's motion, a '{frame}' PLY "
                   "pattern or a relight/gaussian-sequence index) [default: the first].")
@click.option("--frames", "frames", default=None, metavar="all|A:B[:S]",
              help="One DGSM per frame, in one process: every frame (all) or the frames A, "
                   "A+S, … before B (a Python slice). Receivers read and lights read or "
                   "estimated once; -o, --occluders-out and --preview are patterns holding "
                   "{frame}; relight relight --dgsm PATTERN reads them back.")
@colour_space_option
@seed_option
@no_clobber_option
@quiet_option
def command(occluders, receivers, translate, occluders_out, receivers_out, lights_spec, estimator,
            lights_out, output, size, bins, atlas, mapping,
            kappa, t_max, roi, roi_radius, cull, cull_tolerance, footprint, samples,
            allow_light_inside, radial, self_shadow, half, preview, preview_camera,
            preview_probe, preview_shadow_strength, frame,
            frames, colour_space, seed, no_clobber, quiet):
    """Tabulate the transmittance from each light through the OCCLUDER Gaussians
    (closed-form erf optical depth, T = exp(−τ)) on K radial shells over an
    octahedral atlas of directions (Mir et al., Deep Gaussian Shadow Maps).

    Each OCCLUDER and SCENE is a 3DGS PLY file, a triangle mesh (.obj .glb
    .gltf .stl .off, turned into flat surface Gaussians with their texture or
    face colours), a posed hand.npz (fit-geometry's output: its fine mesh at frame
    0, or frame=K, as flat Gaussians with the hand's albedo; --occluders-out then
    exports it as a PLY), or builtin:hand | builtin:room | builtin:sphere.  An
    OCCLUDER may carry its own placement, SOURCE:KEY=VALUE;...  with keys
    crop=X0,Y0,Z0,X1,Y1,Z1 (keep the Gaussians whose centres lie in this box,
    in the source's own frame and units), min-opacity=A (drop opacities below
    A), max-scale=S (drop Gaussians whose largest std dev exceeds S, the
    source's units: needle floaters), fit=SIZE (scale the opacity-weighted
    1-99 % box of the kept centres to SIZE metres on its largest side and
    centre it at the origin), centre, scale=S, rotate-x|y|z=DEG, on-floor
    (rest that box's bottom on y = 0) and translate=X,Y,Z, applied in that
    order whatever the order written (frame=K only picks a hand.npz's pose).
    A scene capture becomes an object by a crop and a prune, e.g.
    'desk.ply:crop=-0.2,-0.3,0.4,0.1,0.05,0.8;min-opacity=0.3;fit=0.3'.

    With several OCCLUDERs, one table per occluder is built (all sharing t_max)
    and stored besides their product: scene receivers read the product, and
    `relight relight` shadows each object by the OTHER objects' tables (each
    object's Gaussians are receivers of the others' tables here).  An object
    does not shadow itself.

    --preview draws the receivers shadowed as relight relight will, at the
    shadow strength its label gives: relight's default --shadow-strength auto
    takes away only each receiver's direct share of its light, which needs
    the scene's probe (--preview-probe); without one the preview shows the
    full shadow (strength 1), darker than relight's default delivers.

    Only what the receivers need is computed: receivers that can be shadowed at
    all mark the atlas texels and radial bins that lookups will read (everything
    else is T = 1), and occluders are culled in light space.  The EXR layout is
    documented in formats/dgsm_exr.md; `relight relight --dgsm` reads it.

    \b
    Examples:
      relight dgsm-build avatar.ply --receivers room.ply --lights lights.json -o shadows.exr
      relight dgsm-build hand.ply --receivers floor.ply --lights lights.json \\
          --atlas cube --mapping mass -o shadows-cube.exr
      relight dgsm-build builtin:hand --translate 0,0.3,0 --receivers builtin:room \\
          --lights lights.json -o shadows.exr --occluders-out hand.ply --receivers-out room.ply \\
          --preview shadows.png
      relight dgsm-build 'builtin:hand:translate=0,0.25,0' \\
          'donut.ply:fit=0.15;rotate-y=30;on-floor;translate=-0.1,0,-0.05' \\
          --receivers builtin:room --lights lights.json -o shadows.exr
    """
    import time

    from relight_cli.errors import UsageProblem
    from relight_cli.jobs.dgsm_build import build

    start = time.perf_counter()
    if frame is not None or frames is not None or any(_moves(spec) for spec in occluders):
        from relight_cli.commands._dgsm_frames import build_frames
        options, offset = _options(preview, preview_camera, translate, receivers, size, bins,
                                   atlas, mapping, kappa, t_max, roi, roi_radius, cull,
                                   cull_tolerance, footprint, samples, seed, allow_light_inside,
                                   estimator)
        options.self_shadow, options.radial = self_shadow, radial
        _preview_shadow(options, preview, preview_probe, preview_shadow_strength)
        if _parse_auto(lights_spec) is not None and receivers is None:
            raise UsageProblem("--lights auto:K estimates lights from the scene: give "
                               "--receivers")
        return build_frames(dict(locals()), options, offset)
    check_output(output, no_clobber, kind="exr")
    check_output(lights_out, no_clobber, kind="json", what="--lights-out")
    check_output(occluders_out, no_clobber, kind="ply", what="--occluders-out")
    check_output(receivers_out, no_clobber, kind="ply", what="--receivers-out")
    check_output(preview, no_clobber, kind="png", what="--preview")
    options, offset = _options(preview, preview_camera, translate, receivers, size, bins, atlas,
                               mapping, kappa, t_max, roi, roi_radius, cull, cull_tolerance,
                               footprint, samples, seed, allow_light_inside, estimator)
    options.self_shadow, options.radial = self_shadow, radial
    _preview_shadow(options, preview, preview_probe, preview_shadow_strength)
    auto_k = _parse_auto(lights_spec)
    if auto_k is not None and receivers is None:
        raise UsageProblem("--lights auto:K estimates lights from the scene: give --receivers")

    parsed, objects, scene, view, lights = _load(occluders, receivers, offset, lights_spec,
                                                 auto_k, preview_camera, colour_space)
    options.camera = view
    result = build(objects, lights if auto_k is None else auto_k, options, scene,
                   names=occluders, receivers_name=receivers, lights_name=lights_spec,
                   log=lambda message: log(message, quiet), quiet=quiet)

    inputs = {"occluders": parsed[0][0]} if len(occluders) == 1 else {
        f"occluder{j}": source for j, (source, _) in enumerate(parsed)}
    if receivers is not None:
        inputs["receivers"] = receivers
    if auto_k is None:
        inputs["lights"] = lights_spec
    settings = {**result.settings, "lights": lights_spec, "half": half, "translate": translate,
                "estimator": estimator if auto_k is not None else None,
                "occluders": list(occluders), "colour_space": colour_space}
    _write(result, scene, inputs, settings, output, half, occluders_out, receivers_out,
           lights_out, preview, quiet, start)


def _options(preview, preview_camera, translate, receivers, size, bins, atlas, mapping, kappa,
             t_max, roi, roi_radius, cull, cull_tolerance, footprint, samples, seed,
             allow_light_inside, estimator):
    """The build options' usage errors (exit 2), before any work: (the job's DgsmOptions,
    camera None until read; the --translate offset or None)."""
    from relight_cli.cli.tools import parse_vector
    from relight_cli.errors import UsageProblem
    from relight_cli.jobs.dgsm_build import DgsmOptions

    if preview_camera is not None and preview is None:
        raise UsageProblem("--preview-camera needs --preview PNG")
    offset = None if translate is None else parse_vector(translate, 3, "--translate")
    w, h = parse_size(size, "--size", minimum=2, maximum=4096)
    if receivers is None and t_max is None:
        raise UsageProblem("give --receivers SCENE.ply (or --t-max for a receiver-free build)")
    options = DgsmOptions(size=(h, w), bins=bins, atlas=atlas, mapping=mapping, kappa=kappa,
                          t_max=t_max, roi=roi, roi_radius=roi_radius, cull=cull,
                          cull_tolerance=cull_tolerance, footprint=footprint, samples=samples,
                          seed=seed, allow_light_inside=allow_light_inside, estimator=estimator,
                          preview=preview is not None)
    return options, offset


def _preview_shadow(options, preview, probe_path, strength) -> None:
    """The --preview's shadow strength and probe into ``options`` (usage errors first; the
    probe is read now, as relight relight --probe reads it)."""
    from relight_cli.errors import UsageProblem
    for name, value in (("--preview-probe", probe_path),
                        ("--preview-shadow-strength", strength)):
        if value is not None and preview is None:
            raise UsageProblem(f"{name} needs --preview PNG")
    if strength == "auto" and probe_path is None:
        raise UsageProblem("--preview-shadow-strength auto weighs the lights against the "
                           "scene's probe: give --preview-probe PROBE.json")
    options.preview_strength = strength
    if probe_path is not None:
        from relight_cli.formats.sh_probe_json import read_probe
        check_input(probe_path, stdin="--preview-probe")
        options.preview_probe = read_probe(probe_path)


def _load(occluders, receivers, offset, lights_spec, auto_k, preview_camera, colour_space="auto"):
    """(parsed OCCLUDER specs, placed occluder objects, receiver Gaussians or None, the
    preview camera or None, the read lights or None for auto:K), in the order whose first
    bad input is reported."""
    import numpy as np

    from relight_cli.formats.lights_json import read_lights
    from relight_cli.gaussians.from_mesh import load_gaussians
    from relight_cli.cli.inputs import load_placed, parse_occluder

    offset = None if offset is None else np.array(offset)
    parsed = [parse_occluder(spec, "OCCLUDER") for spec in occluders]
    if receivers is not None:
        check_input(receivers)
    objects = []
    for spec, (source, placement) in zip(occluders, parsed):
        check_input(source)
        objects.append(load_placed(source, placement, spec, offset, colour_space=colour_space))
    scene = None
    if receivers is not None:
        check_input(receivers)
        scene = load_gaussians(receivers, colour_space=colour_space)
    view = None
    if preview_camera is not None:
        from relight_cli.formats.camera import read_camera
        view = read_camera(check_input(preview_camera))
    lights = None
    if auto_k is None:
        check_input(lights_spec, stdin="--lights")
        lights = read_lights(lights_spec)
    return parsed, objects, scene, view, lights


def _write(result, scene, inputs, settings, output, half, occluders_out, receivers_out,
           lights_out, preview, quiet, start):
    """Every output of the build, each with its provenance."""
    import time

    from relight_cli.formats.dgsm_exr import FORMAT, VERSION, write_dgsm
    from relight_cli.formats.gaussians_ply import FORMAT as GFORMAT
    from relight_cli.formats.gaussians_ply import VERSION as GVERSION
    from relight_cli.formats.gaussians_ply import write_gaussians
    from relight_cli.formats.lights_json import FORMAT as LFORMAT
    from relight_cli.formats.lights_json import VERSION as LVERSION
    from relight_cli.formats.lights_json import Lights, write_lights
    from relight_cli.provenance import provenance

    write_dgsm(output, result.shadow_map, provenance(FORMAT, VERSION, inputs, settings), half=half)
    log(f"wrote {output} ({time.perf_counter() - start:.2f} s)", quiet)
    if occluders_out is not None:
        write_gaussians(occluders_out, result.occluders, provenance(
            GFORMAT, GVERSION, inputs, {"translate": settings["translate"],
                                        "occluders": settings["occluders"],
                                        "colour_space": settings["colour_space"]}))
        log(f"wrote {occluders_out}", quiet)
    if receivers_out is not None and scene is not None:
        write_gaussians(receivers_out, scene, provenance(GFORMAT, GVERSION,
                                                         {"receivers": inputs["receivers"]},
                                                         {"colour_space":
                                                          settings["colour_space"]}))
        log(f"wrote {receivers_out}", quiet)
    if lights_out is not None:
        lights = result.lights
        write_lights(lights_out, Lights(lights.positions, lights.colors, lights.intensities,
                                        lights.names, lights.extra),
                     provenance(LFORMAT, LVERSION, inputs, settings))
        log(f"wrote {lights_out}", quiet)
    if preview is not None:
        from relight_cli.formats.image import write_png
        write_png(preview, result.preview)
        log(f"wrote {preview}", quiet)


def _moves(spec: str) -> bool:
    """Whether an OCCLUDER names per-frame files (a '{frame}' pattern or a sequence
    index): such a run builds per frame (commands/_dgsm_frames.py)."""
    from relight_cli.gaussians.placement import split_spec
    from relight_cli.gaussians.sequence import is_pattern
    source, placement = split_spec(spec)
    return (is_pattern(source) or source.lower().endswith(".json")
            or "path=" in (placement or ""))


def _parse_auto(spec: str):
    """``auto:K`` → K (relight_cli.cli.inputs.parse_auto_lights)."""
    from relight_cli.cli.inputs import parse_auto_lights
    return parse_auto_lights(spec)
