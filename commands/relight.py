"""``relight relight``: relight an input under new lighting.

The first input decides the mode: a Gaussians PLY (``.ply``) is relit with an
SH probe and optionally shadowed with a DGSM (paper Sec. 3.4); a hand
(``.npz`` or ``builtin:right|left|two[:POSE]``) is rendered under an env map
and/or point lights from a camera.  Each
mode is one function below; options that belong to one mode are refused in
the other.  Hand mode ``--model physical`` is the physically based renderer of
``relight_cli.render`` (URHand's physical-only baseline).
"""

from __future__ import annotations

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
                   "exactly as bake-features --env-res [default: 32x16].")
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
def command(input, env, output, probe, dgsm, receivers, objects, receivers_out, footprint, samples,
            shadow_strength, light_weights, direct_light, shadow_matte, lobe, intensity, t_max,
            normals, camera, background, model, checkpoint, device, precision, hand_size,
            hand_lights, hand_frame, hand_frames, hand_mesh, env_res, tex_res, aa,
            no_shadows, no_specular, no_sss, sss_scale, bounce, albedo_map, roughness_map, aov,
            preview, splits, eval_samples, seed, no_clobber, quiet):
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

    from relight_cli.gaussians.placement import split_spec

    capture_only = {"--splits": splits, "--eval-samples": eval_samples}
    if _is_capture(input):
        return _relight_capture(**locals())
    given = [k for k, v in capture_only.items() if v is not None]
    if given:
        raise UsageProblem(f"{', '.join(given)} only apply to a capture (IN = CAPTURE/)")
    lower = split_spec(input)[0].lower()
    gaussian_in = (lower.endswith((".ply", ".obj", ".glb", ".gltf", ".stl", ".off"))
                   or lower in ("builtin:hand", "builtin:room", "builtin:sphere"))
    # a hand .npz given Gaussian options is the posed hand made into Gaussians (the bridge
    # from the hand half to the Gaussian half; frame=K in its placement picks the pose)
    if lower.endswith(".npz") and any(v is not None and v != () for v in
                                      (probe, dgsm, receivers, shadow_matte, objects)):
        gaussian_in = True
    if objects and not gaussian_in:
        raise UsageProblem("--object inserts Gaussian objects beside IN = AVATAR.ply (or a mesh, "
                           "builtin:hand|room|sphere); it does not apply to a hand .npz", input)
    if gaussian_in:
        hand_only = {"ENV": env, "--model": model, "--checkpoint": checkpoint or None,
                     "--device": device, "--precision": precision, "--size": hand_size,
                     "--lights": hand_lights, "--frame": hand_frame,
                     "--frames": hand_frames, "--mesh": hand_mesh,
                     "--env-res": env_res, "--tex-res": tex_res, "--aa": aa,
                     "--no-shadows": no_shadows or None, "--no-specular": no_specular or None,
                     "--no-sss": no_sss or None, "--sss-scale": sss_scale,
                     "--bounce": bounce or None, "--albedo": albedo_map,
                     "--roughness": roughness_map, "--aov": aov}
        given = [k for k, v in hand_only.items() if v is not None]
        if given:
            raise UsageProblem(f"{', '.join(given)} only apply to a hand (IN = HAND.npz)")
        return _relight_gaussians(**locals())
    if lower.endswith(".npz") or lower.startswith("builtin:"):
        return _relight_hand(**locals())
    raise UsageProblem("IN must be a Gaussians .ply (or a mesh, builtin:hand|room|sphere) or a "
                       "hand .npz (or builtin:right|left|two); cannot tell what this is", input)


def _relight_gaussians(input, output, probe, dgsm, receivers, objects, receivers_out, footprint,
                       samples,
                       shadow_strength, light_weights, direct_light, shadow_matte, lobe, intensity,
                       t_max, normals, camera, background, preview, seed, no_clobber, quiet, **_):
    import math
    import time

    import numpy as np

    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.gaussians_ply import FORMAT, VERSION, write_gaussians
    from relight_cli.gaussians.from_mesh import load_gaussians
    from relight_cli.formats.sh_probe_json import read_probe
    from relight_cli.gaussians import transfer as TF
    from relight_cli.provenance import provenance

    # ---- usage checks before any work
    if probe is None and shadow_matte is None:
        raise UsageProblem("Gaussian relighting needs --probe PROBE.json (make one with relight "
                           "sh-probe)")
    if dgsm is not None and receivers is None:
        raise UsageProblem("--dgsm shadows receivers: give --receivers SCENE.ply")
    if direct_light and dgsm is None:
        raise UsageProblem("--direct-light takes its lights from --dgsm SHADOWS.exr")
    if receivers_out is not None and receivers is None:
        raise UsageProblem("--receivers-out needs --receivers")
    if preview is not None and camera is None:
        raise UsageProblem("--preview needs --camera (a rendered view)")
    if shadow_matte is not None and (camera is None or dgsm is None):
        raise UsageProblem("--shadow-matte renders a matte: give --camera CAMERA.json and --dgsm "
                           "SHADOWS.exr (its lights)")
    bg = parse_vector(background, 3, "--background", minimum=0)
    if camera is not None and not output.lower().endswith(".exr"):
        raise UsageProblem("with --camera, -o is an EXR image (name it .exr)", output)
    if camera is None and not output.lower().endswith(".ply"):
        raise UsageProblem("-o is the relit Gaussians PLY (name it .ply), or use --camera CAM "
                           "-o IMAGE.exr", output)
    check_output(output, no_clobber)
    check_output(receivers_out, no_clobber, kind="ply", what="--receivers-out")
    check_output(preview, no_clobber, kind="png", what="--preview")
    from relight_cli.inputs import load_placed, parse_occluder

    specs = [input] + list(objects)
    parsed = [parse_occluder(spec, "IN/--object") for spec in specs]
    for path in [source for source, _ in parsed] + [dgsm, receivers]:
        if path is not None:
            check_input(path)
    for path, role in ((probe, "--probe"), (camera, "--camera")):
        if path is not None:
            check_input(path, stdin=role)

    start = time.perf_counter()
    if shadow_matte is not None:
        return _shadow_matte(shadow_matte, specs, parsed, output, dgsm, receivers, camera,
                             footprint, samples, light_weights or "intensity", background,
                             preview, seed, quiet, start)
    sh_probe = read_probe(probe)
    shadow_map = _read_dgsm(dgsm) if dgsm is not None else None
    auto = shadow_strength == "auto"
    if auto and shadow_map is not None and shadow_map.intensities is None:
        log("note: this shadow map (DGSM version 1) stores no light intensities, so "
            "--shadow-strength auto cannot weigh them against the probe: s = 1", quiet)
        auto, shadow_strength = False, 1.0
    if light_weights is None:
        light_weights = "irradiance" if auto else "intensity"
    relit_objects, object_direct = [], []
    for spec, (source, placement) in zip(specs, parsed):
        avatar = load_placed(source, placement, spec)
        log(f"read {spec}: {len(avatar)} Gaussians", quiet)
        try:
            n = TF.estimate_normals(avatar, normals)
        except ValueError as exc:  # e.g. --normals stored on a file without normals
            raise DataError(str(exc), source) from None
        direct = None       # [L, N, 3] each light's irradiance (--direct-light)
        extra = None
        if direct_light:
            direct = TF.direct_irradiance(shadow_map.intensities, shadow_map.colors,
                                          shadow_map.lights, avatar.means, n, one_sided=True)
            extra = direct.sum(axis=0) / math.pi
        object_direct.append(direct)
        relit_objects.append(TF.relight_gaussians(
            avatar, sh_probe.coefficients, q=lobe, intensity=intensity,
            t_max=math.inf if t_max is None else t_max, normals=n, extra=extra))
    log(f"probe degree {sh_probe.degree}" + (", objects lit by the shadow map's "
                                              f"{len(shadow_map.lights)} light(s) too"
                                              if direct_light else ""), quiet)

    scene = None
    if receivers is not None:
        scene = load_gaussians(receivers)   # PLY, mesh or builtin:
        log(f"read {receivers}: {len(scene)} receiver Gaussians", quiet)
    if shadow_map is not None:
        from relight_cli.gaussians.dgsm import sample_transmittance
        weights_used = _weights_mode(light_weights, shadow_map, quiet)

        def weights_for(g, normals=None):
            return TF.dgsm_light_weights(weights_used, shadow_map, g, normals)

        T = sample_transmittance(shadow_map, scene.means, scene.scales, scene.rotations,
                                 footprint=footprint, samples=samples, seed=seed)   # [L, M]
        strength = shadow_strength
        receiver_normals = None
        if auto:        # per receiver: the lights' share of its light against the probe's
            receiver_normals = TF.facing_lights(scene.means, TF.estimate_normals(scene, "axis"),
                                                shadow_map.lights)
            e_direct = TF.direct_irradiance(shadow_map.intensities, shadow_map.colors,
                                            shadow_map.lights, scene.means,
                                            receiver_normals).sum(axis=0)
            strength = TF.direct_share(e_direct, sh_probe.coefficients, receiver_normals)
            log(f"direct share of the receivers' light (auto): median "
                f"{float(np.median(strength)):.2f}, range {float(strength.min()):.2f}–"
                f"{float(strength.max()):.2f}", quiet)
        factor = TF.shadow_factor(T, weights_for(scene, receiver_normals), strength)  # [M, 3]
        scene = TF.attenuate(scene, factor)
        log(f"shadowed receivers: mean factor {factor.mean():.3f}, "
            f"{int((factor.reshape(len(factor), -1).min(axis=1) < 0.99).sum())} of {len(factor)} "
            f"darkened", quiet)
        if shadow_map.groups is not None:
            if len(shadow_map.groups) != len(relit_objects):
                raise DataError(f"the shadow map has {len(shadow_map.groups)} occluder groups "
                                f"({', '.join(shadow_map.group_names)}) but {len(relit_objects)} "
                                f"object(s) were given (IN + --object, in dgsm-build's order)",
                                dgsm)
            for j, obj in enumerate(relit_objects):
                if auto and object_direct[j] is None:
                    continue    # lit by the probe only: the lights' shadows do not reach it
                T = sample_transmittance(shadow_map.others(j), obj.means, obj.scales,
                                         obj.rotations, footprint=footprint, samples=samples,
                                         seed=seed)
                if auto:        # colour ρ(S + D): direct share D/(S + D), weights D_l (exact)
                    d = object_direct[j].sum(axis=0) / math.pi
                    probe_part = np.clip(TF.shading(sh_probe.coefficients, obj.normals, lobe),
                                         0.0, None)
                    total = probe_part + d
                    share = np.where(total > 0, d / np.where(total > 0, total, 1), 0.0)
                    factor = TF.shadow_factor(T, object_direct[j], share)
                else:
                    factor = TF.shadow_factor(T, weights_for(obj, obj.normals), shadow_strength)
                relit_objects[j] = TF.attenuate(obj, factor)
                log(f"shadowed object {j} by the others: mean factor {factor.mean():.3f}, "
                    f"{int((factor.reshape(len(factor), -1).min(axis=1) < 0.99).sum())} of "
                    f"{len(factor)} darkened", quiet)
        elif len(relit_objects) > 1:
            log("note: the shadow map has no occluder groups, so the objects do not shadow "
                "each other (build it from all objects: dgsm-build A B ...)", quiet)

    from relight_cli.formats.gaussians_ply import concatenate
    relit = relit_objects[0] if len(relit_objects) == 1 else concatenate(relit_objects)
    inputs = {"input": parsed[0][0], "probe": probe}
    for j, (source, _) in enumerate(parsed[1:]):
        inputs[f"object{j}"] = source
    if receivers:
        inputs["receivers"] = receivers
    if dgsm:
        inputs["dgsm"] = dgsm
    settings = {"lobe": lobe, "intensity": intensity, "t_max": t_max, "normals": normals,
                "footprint": footprint, "samples": samples, "seed": seed,
                "shadow_strength": shadow_strength, "direct_light": direct_light,
                "objects": specs}
    if dgsm is not None:
        # which opacity mapping made the shadow map, and how its lights were weighted
        settings.update(dgsm_mapping=shadow_map.mapping, dgsm_kappa=shadow_map.kappa,
                        light_weights=weights_used)
    if receivers_out is not None:
        write_gaussians(receivers_out, scene, provenance(FORMAT, VERSION, inputs,
                                                         dict(settings, role="receivers")))
        log(f"wrote {receivers_out}", quiet)
    if camera is None:
        write_gaussians(output, relit, provenance(FORMAT, VERSION, inputs, settings))
        log(f"wrote {output} ({time.perf_counter() - start:.2f} s)", quiet)
        return

    from relight_cli.formats.camera import read_camera
    from relight_cli.formats.exr import write_exr
    from relight_cli.gaussians.splat import render

    inputs["camera"] = camera
    view = read_camera(camera)
    everything = relit if scene is None else concatenate([scene, relit])
    image = render(everything, view, background=bg)
    channels = {"R": image.image[..., 0], "G": image.image[..., 1], "B": image.image[..., 2],
                "A": image.alpha}
    write_exr(output, channels, attributes={"relight.camera": view.to_json()},
              provenance=provenance("relight/render", 1, inputs,
                                    dict(settings, background=list(bg))), camera=view)
    log(f"wrote {output} ({view.width}x{view.height}, {len(everything)} Gaussians, "
        f"{time.perf_counter() - start:.2f} s)", quiet)
    if preview is not None:
        from relight_cli.preview import write_preview
        write_preview(preview, image.image.astype(np.float32))
        log(f"wrote {preview}", quiet)


def _weights_mode(light_weights, shadow_map, quiet):
    """--light-weights as it can run with this shadow map (version 1 maps: equal, said)."""
    from relight_cli.gaussians import transfer as TF
    mode = TF.effective_light_weights(light_weights, shadow_map.intensities)
    if mode != light_weights:
        log("note: this shadow map (DGSM version 1) stores no light intensities; the lights "
            "are weighted equally", quiet)
    return mode


def _shadow_matte(mode, specs, parsed, output, dgsm, receivers, camera_path, footprint, samples,
                  light_weights, background, preview, seed, quiet, start):
    """The receivers-only shadow matte of the paper's Sec. 4.2 (``--shadow-matte``)."""
    import time

    import numpy as np

    from relight_cli.errors import DataError
    from relight_cli.formats.camera import read_camera
    from relight_cli.formats.exr import write_exr
    from relight_cli.gaussians import dgsm as D
    from relight_cli.gaussians import shadow_matte as SM
    from relight_cli.gaussians import transfer as TF
    from relight_cli.gaussians.from_mesh import load_gaussians
    from relight_cli.gaussians.splat import render
    from relight_cli.provenance import provenance

    shadow_map = _read_dgsm(dgsm)
    scene = load_gaussians(receivers)
    camera = read_camera(camera_path)
    weights_used = _weights_mode(light_weights, shadow_map, quiet)
    weights = TF.dgsm_light_weights(weights_used, shadow_map, scene)
    if mode == "dgsm":
        V = D.sample_transmittance(shadow_map, scene.means, scene.scales, scene.rotations,
                                   footprint=footprint, samples=samples, seed=seed)   # [L, M]
    else:
        meshes = []
        for spec, (source, placement) in zip(specs, parsed):
            try:
                meshes.append(SM.load_placed_mesh(source, placement))
            except ValueError as exc:
                raise DataError(str(exc), spec) from None
        pts, n = D.footprint_samples(scene.means, scene.scales, scene.rotations, footprint,
                                     samples, seed)
        V = SM.mesh_visibility(meshes, shadow_map.lights, pts.reshape(-1, 3))
        V = V.reshape(len(shadow_map.lights), len(scene), n).mean(axis=2)
    strength = SM.shadow_strength(TF.shadow_factor(V, weights, 1.0))
    image = render(scene, camera, background=parse_vector(background, 3, "--background"),
                   colors=SM.matte_colors(strength))
    inputs = {"input": parsed[0][0], "dgsm": dgsm, "receivers": receivers, "camera": camera_path}
    for j, (source, _) in enumerate(parsed[1:]):
        inputs[f"object{j}"] = source
    settings = {"shadow_matte": mode, "footprint": footprint, "samples": samples, "seed": seed,
                "light_weights": weights_used, "dgsm_mapping": shadow_map.mapping,
                "objects": specs}
    channels = {"R": image.image[..., 0], "G": image.image[..., 1], "B": image.image[..., 2],
                "A": image.alpha}
    write_exr(output, channels, attributes={"relight.matte": f"shadow strength ({mode})",
                                            "relight.camera": camera.to_json()},
              provenance=provenance("relight/render", 1, inputs, settings), camera=camera)
    log(f"wrote {output} (shadow matte, {mode}: {int((strength > 0.1).sum())} of {len(strength)} "
        f"receivers > 0.1, {time.perf_counter() - start:.2f} s)", quiet)
    if preview is not None:
        from relight_cli.preview import write_preview
        write_preview(preview, image.image.astype(np.float32))


def _relight_hand(input, env, output, checkpoint, device, precision, probe, dgsm, receivers,
                  receivers_out, model, camera, hand_size, hand_lights, hand_frame, hand_frames, hand_mesh,
                  env_res, tex_res, aa, no_shadows, no_specular, no_sss, sss_scale, bounce,
                  albedo_map, roughness_map, aov, background, preview, seed, no_clobber, quiet,
                  **_):
    """Hand mode: hand.npz + model + env map and/or point lights + camera → EXR image(s)
    (one per frame with --frames; relight_cli.jobs.relight_hand renders them)."""
    import time

    from relight_cli.errors import DataError, UsageProblem

    # ---- usage checks before any work
    gaussian_only = {"--probe": probe, "--dgsm": dgsm, "--receivers": receivers,
                     "--receivers-out": receivers_out, "--shadow-matte": _.get("shadow_matte")}
    given = [k for k, v in gaussian_only.items() if v is not None]
    if given:
        raise UsageProblem(f"{', '.join(given)} only apply to Gaussians (IN = AVATAR.ply)")
    model = model or "physical"
    if model not in ("physical", "teacher", "student", "linear"):
        raise UsageProblem(f"--model {model!r} is not available; use physical, teacher, student "
                           f"or linear")
    if model == "physical" and (checkpoint or device is not None):
        raise UsageProblem("--checkpoint and --device belong to a learned --model (teacher, "
                           "student, linear)")
    if precision is not None and model != "student":
        raise UsageProblem("--precision sets the student's decoder: it needs --model student")
    if model in ("teacher", "student", "linear"):
        return _relight_hand_learned(**locals())
    width, height, frame, env_h, env_w = _hand_view_options(env, hand_lights, output, camera,
                                                            hand_size, hand_frame, env_res)
    _sequence_patterns(hand_frame, hand_frames, output, preview)
    tex = 256 if tex_res is None else tex_res
    if not 8 <= tex <= 4096:
        raise UsageProblem(f"--tex-res must be in [8, 4096], got {tex}")
    samples_axis = 2 if aa is None else aa
    if not 1 <= samples_axis <= 8:
        raise UsageProblem(f"--aa must be in [1, 8], got {samples_axis}")
    scale = 1.0 if sss_scale is None else sss_scale   # its range is checked by FiniteFloat
    aovs = [a.strip() for a in aov.split(",") if a.strip()] if aov else []
    if aov is not None and not aovs:
        raise UsageProblem("--aov needs at least one of normal, uv, depth")
    bad = [a for a in aovs if a not in ("normal", "uv", "depth")]
    if bad:
        raise UsageProblem(f"--aov takes normal, uv, depth; unknown: {', '.join(bad)}")
    rough_value = None
    if roughness_map is not None:
        try:
            rough_value = float(roughness_map)
        except ValueError:
            check_input(roughness_map)
        else:
            if not 0 < rough_value <= 1:
                raise UsageProblem(f"--roughness must be in (0, 1], got {roughness_map}")
    bg = parse_vector(background, 3, "--background", minimum=0)
    if hand_frames is None:
        check_output(output, no_clobber, kind="exr")
        check_output(preview, no_clobber, kind="png", what="--preview")
    for path, role in ((camera, "--camera"), (hand_lights, "--lights"), (albedo_map, None)):
        if path is not None:
            check_input(path, stdin=role)

    # ---- inputs (data errors)
    start = time.perf_counter()
    from relight_cli.inputs import load_envmap, load_hand, read_roughness_map
    from relight_cli.jobs import relight_hand as J
    from relight_cli.render import appearance as A
    from relight_cli.render.shading import PointLights, RenderSettings
    from relight_cli.provenance import provenance

    data = load_hand(input)
    frames = _frames(hand_frames, frame, data, input, output, preview, no_clobber)
    envmap = load_envmap(env) if env is not None else None
    lights = None
    if hand_lights is not None:
        from relight_cli.formats.lights_json import read_lights
        raw = read_lights(hand_lights)
        lights = PointLights(raw.positions, raw.colors * raw.intensities[:, None])
    albedo = None
    if albedo_map is not None:
        from relight_cli.formats.image import read_image
        pixels, _names = read_image(albedo_map)
        if pixels.shape[2] < 3:
            raise DataError("albedo map needs 3 colour channels", albedo_map)
        albedo = pixels[..., :3]
    rough = rough_value
    if roughness_map is not None and rough_value is None:
        rough = read_roughness_map(roughness_map)
    mesh_name = hand_mesh or "fine"
    view_of = _view_of(camera, width, height)
    try:
        materials = A.hand_materials(data, mesh_name, max(tex, 256), seed, albedo, rough)
    except ValueError as exc:
        raise DataError(str(exc), albedo_map or roughness_map) from None
    log(f"read {input}: {len(data.hands)} hand(s), "
        f"{_frames_text(frames)}; {'env ' + env if env else 'no env'}, "
        f"{0 if lights is None else len(lights)} point light(s)", quiet)

    # ---- render
    settings = RenderSettings(tex_res=tex, aa=samples_axis, shadows=not no_shadows,
                              specular=not no_specular, sss=not no_sss, sss_scale=scale,
                              env_res=(env_h, env_w), bounce=bounce)
    inputs = {"hand": input}
    if env is not None:
        inputs["env"] = env
    for role, path in (("camera", camera), ("lights", hand_lights), ("albedo", albedo_map)):
        if path is not None:
            inputs[role] = path
    if roughness_map is not None and rough_value is None:
        inputs["roughness"] = roughness_map
    from relight_cli.formats.exr import write_exr
    renders = J.physical(data, frames, view_of, materials, settings, lights, envmap, bg,
                         mesh_name, aovs, input)
    with _frame_bar(frames, hand_frames, quiet) as (step, done):
        for r in renders:
            record = provenance("relight/render", 1, inputs, {
                "model": model, "frame": r.frame, "mesh": mesh_name, "env_res": [env_h, env_w],
                "tex_res": tex, "aa": samples_axis, "shadows": not no_shadows,
                "specular": not no_specular, "sss": not no_sss, "sss_scale": scale,
                "bounce": bounce, "roughness": roughness_map, "seed": seed,
                "background": list(bg)})
            path, png = _frame_outputs(hand_frames, output, preview, r.frame)
            write_exr(path, r.channels, attributes={
                "relight.model": model, "relight.camera": r.view.to_json()}, provenance=record,
                camera=r.view)
            if png is not None:
                from relight_cli.preview import write_preview
                write_preview(png, r.rgb)
            step(r)
    _log_written(done, output, hand_frames, start, quiet)


def _relight_hand_learned(input, env, output, checkpoint, device, precision, model, camera,
                          hand_size,
                          hand_lights, hand_frame, hand_frames, hand_mesh, env_res, tex_res, aa,
                          no_shadows, no_specular, no_sss, sss_scale, bounce, albedo_map, roughness_map, aov,
                          background, preview, no_clobber, quiet, **_):
    """Hand mode with a learned model: the teacher's per-light textures summed (Eq. 2)."""
    import time

    import numpy as np

    from relight_cli.errors import DataError, UsageProblem

    # ---- usage checks before any work
    physical_only = {"--mesh": hand_mesh, "--tex-res": tex_res,
                     "--no-shadows": no_shadows or None, "--no-specular": no_specular or None,
                     "--no-sss": no_sss or None, "--sss-scale": sss_scale,
                     "--bounce": bounce or None, "--albedo": albedo_map,
                     "--roughness": roughness_map, "--aov": aov}
    given = [k for k, v in physical_only.items() if v is not None]
    if given:
        raise UsageProblem(f"{', '.join(given)} only apply to --model physical (a learned "
                           f"model has its own texture, materials and shadows)")
    if not checkpoint:
        raise UsageProblem(f"--model {model} needs --checkpoint CKPT.pt (from "
                           f"{'distill' if model == 'student' else 'train-teacher'})")
    if model == "student" and len(checkpoint) > 1:
        raise UsageProblem("--model student takes one --checkpoint (one student renders "
                           "every hand)")
    if model == "student" and hand_lights is not None:
        raise UsageProblem("the student is an env-map model: it cannot take --lights (use "
                           "--model teacher for point lights)")
    width, height, frame, env_h, env_w = _hand_view_options(env, hand_lights, output, camera,
                                                            hand_size, hand_frame, env_res)
    _sequence_patterns(hand_frame, hand_frames, output, preview)
    if aa is not None and not 1 <= aa <= 8:
        raise UsageProblem(f"--aa must be in [1, 8], got {aa}")
    bg = parse_vector(background, 3, "--background")
    if hand_frames is None:
        check_output(output, no_clobber, kind="exr")
        check_output(preview, no_clobber, kind="png", what="--preview")
    for path, role in ((camera, "--camera"), (hand_lights, "--lights")):
        if path is not None:
            check_input(path, stdin=role)
    for path in checkpoint:
        check_input(path)

    # ---- inputs (data errors)
    start = time.perf_counter()
    from relight_cli.inputs import load_envmap, load_hand
    from relight_cli.jobs import relight_hand as J
    from relight_cli.neural.train import resolve_device

    torch_device = resolve_device(device or "auto")
    data = load_hand(input)
    frames = _frames(hand_frames, frame, data, input, output, preview, no_clobber)
    if model == "student":
        from relight_cli.formats.checkpoint import read_checkpoint
        from relight_cli.neural.checkpoints import student_model
        from relight_cli.neural.geometry import uv_layout_digest
        ckpt = read_checkpoint(checkpoint[0], kind=model)
        try:
            net, config = student_model(ckpt, torch_device)
        except (ValueError, UsageProblem) as exc:
            raise DataError(getattr(exc, "message", str(exc)), checkpoint[0]) from None
        if (data.n_joints - 1) * 3 != int(ckpt["pose_dim"]):
            raise DataError(f"the hand has {data.n_joints} joints; the checkpoint's model was "
                            f"trained on {int(ckpt['pose_dim']) // 3 + 1}", input)
        layout = ckpt.get("extra", {}).get("uv_layout")
        if layout is not None and layout != uv_layout_digest(data.mesh("fine")):
            raise DataError("the hand's UV layout differs from the one the model learned its "
                            "texture on (another hand model?)", input)
    else:
        from relight_cli.hand.scene import handedness
        from relight_cli.neural import evaluate as EV
        models = _load_hand_models(checkpoint, model, torch_device)
        try:
            per_hand = EV.assign_models(models, handedness(data))
        except ValueError as exc:
            raise UsageProblem(str(exc)) from None
        try:
            EV.check_hands(per_hand, data)
        except ValueError as exc:
            raise DataError(str(exc), getattr(exc, "path", None) or input) from None
        config, ckpt = per_hand[0].config, None
        _log_mirrored(per_hand, handedness(data), quiet)
    envmap = load_envmap(env) if env is not None else None
    lights = None
    if hand_lights is not None:
        from relight_cli.formats.lights_json import read_lights
        lights = read_lights(hand_lights)
    view_of = _view_of(camera, width, height)
    samples_axis = ((config.aa or 2) if model == "teacher" else 2) if aa is None else aa
    from relight_cli.features import discretize_env
    if model == "student":
        if env_res is None:
            env_h, env_w = config.env_res            # the student's own grid
        if (env_h, env_w) != tuple(config.env_res):
            from relight_cli.envmap import EnvGrid
            raise UsageProblem(f"the student was trained on a {EnvGrid(*config.env_res)} (WxH) "
                               f"env grid; --env-res must match")
        used = J.decoder_precision(precision or "auto", torch_device)
        log(f"student decoder: {used} (--precision {precision or 'auto'})", quiet)
        renders = J.student(data, frames, view_of, net, config,
                            discretize_env(envmap, env_h, env_w), samples_axis, bg, torch_device,
                            input, used)
        inputs = {"hand": input, "checkpoint": checkpoint[0], "env": env, "camera": camera}
        settings = {"model": model, "student": config.student, "mesh": "fine",
                    "precision": used,
                    "env_res": [env_h, env_w], "tex_res": config.tex_res, "aa": samples_axis,
                    "specular": config.specular, "visibility": config.visibility,
                    "checkpoint_step": int(ckpt["step"]), "background": list(bg)}
        return _write_frames(renders, frames, hand_frames, output, preview, model, inputs,
                             settings, start, quiet, passes=False)

    # ---- render: one pass per light / direction and hand (teacher; linear: one per
    # lighting and hand), hand k by its own model, visibility against every hand
    from relight_cli.clitools import progress
    denv = discretize_env(envmap, env_h, env_w) if envmap is not None else None
    inputs = {"hand": input, "env": env, "camera": camera, "lights": hand_lights}
    inputs.update(_checkpoint_roles(checkpoint))
    settings = {"model": model, "teacher": config.model, "mesh": "fine",
                "env_res": [env_h, env_w], "tex_res": config.tex_res, "aa": samples_axis,
                "visibility": config.visibility, "falloff": config.falloff,
                "checkpoints": [{"hand": k, "checkpoint": m.name, "model": m.model_name,
                                 "sides": m.sides, "step": m.step}
                                for k, m in enumerate(per_hand)],
                "background": list(bg)}
    if hand_frames is not None:          # a sequence: a bar over its frames
        renders = J.learned(data, frames, view_of, per_hand, samples_axis, lights, denv, bg,
                            torch_device, input)
        return _write_frames(renders, frames, hand_frames, output, preview, model, inputs,
                             settings, start, quiet, passes=True)
    lit = 0 if denv is None else int(np.count_nonzero(denv.lit))
    total = (lit + (0 if lights is None else len(lights.positions))) * len(data.hands)
    with progress(total=total, desc=f"relight ({model} passes)", quiet=quiet) as bar:
        renders = J.learned(data, frames, view_of, per_hand, samples_axis, lights, denv, bg,
                            torch_device, input, progress=bar.update)
        _write_frames(renders, frames, hand_frames, output, preview, model, inputs, settings,
                      start, quiet, passes=True)


def _write_frames(renders, frames, hand_frames, output, preview, model, inputs, settings,
                  start, quiet, passes: bool) -> None:
    """Write each FrameRender of a learned model (EXR R, G, B, A with provenance recording
    its frame; the PNG preview), then the closing log line."""
    with _frame_bar(frames, hand_frames, quiet) as (step, done):
        for r in renders:
            path, png = _frame_outputs(hand_frames, output, preview, r.frame)
            _write_learned(path, png, r.rgb, r.channels["A"], model, r.view, inputs,
                           {**settings, "frame": r.frame})
            step(r)
    _log_written(done, output, hand_frames, start, quiet, passes=passes)


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


def _log_mirrored(per_hand, sides, quiet) -> None:
    """Say so when one hand's model renders a hand of the other handedness (its mirror
    image: allowed, the tangent frames mirror, but not what the model was trained on)."""
    for k, (m, side) in enumerate(zip(per_hand, sides)):
        if m.sides and side not in m.sides:
            log(f"note: hand {k} ({side}) is rendered by {m.name}, trained on the "
                f"{'/'.join(m.sides)} hand; give one --checkpoint per hand for its own model",
                quiet)


def _checkpoint_roles(paths) -> dict:
    """Provenance roles of the checkpoints: ``checkpoint``, or ``checkpoint.0``, ``.1`` …"""
    if len(paths) == 1:
        return {"checkpoint": paths[0]}
    return {f"checkpoint.{i}": p for i, p in enumerate(paths)}


def _is_capture(spec: str) -> bool:
    import os
    if spec.lower().endswith((".npz", ".ply", ".obj", ".glb", ".gltf", ".stl", ".off")):
        return False      # a file name (a folder by that name is then refused as a hand/avatar)
    return os.path.isdir(spec) or os.path.basename(spec) == "capture.json"


def _relight_capture(input, env, output, checkpoint, device, model, aa, env_res, splits,
                     eval_samples, no_clobber, quiet, **options):
    """Capture mode: a capture's frames and env renders, each hand by its own learned
    model, scored against the capture's images (relight/metrics JSON)."""
    import os
    import time

    from relight_cli.errors import DataError, UsageProblem

    # ---- usage checks before any work
    hand_or_gaussian = {"ENV": env, **{flag: options.get(name)
                                       for name, flag in _VIEW_OPTIONS.items()}}
    given = [k for k, v in hand_or_gaussian.items() if v not in (None, False, ())]
    if given:
        raise UsageProblem(f"{', '.join(given)} do not apply to a capture (IN = CAPTURE/ renders "
                           f"the capture's own cameras, lights and env maps)")
    if model not in ("teacher", "linear"):
        raise UsageProblem("a capture is scored with --model teacher or linear (and one "
                           "--checkpoint per hand)")
    if not checkpoint:
        raise UsageProblem(f"--model {model} needs --checkpoint CKPT.pt (one per hand)")
    from relight_cli.neural.evaluate import SPLITS
    names = None
    if splits is not None:
        names = [n.strip() for n in splits.split(",") if n.strip()]
        bad = [n for n in names if n not in SPLITS]
        if not names or bad:
            raise UsageProblem(f"--splits takes {', '.join(SPLITS)}"
                               + (f"; unknown: {', '.join(bad)}" if bad else ""))
    if eval_samples is not None and eval_samples < 1:
        raise UsageProblem(f"--eval-samples must be ≥ 1, got {eval_samples}")
    if aa is not None and not 1 <= aa <= 8:
        raise UsageProblem(f"--aa must be in [1, 8], got {aa}")
    from relight_cli.inputs import env_grid
    grid = env_grid(env_res or "32x16")
    from relight_cli.formats.capture import index_path
    index = index_path(input)   # names a folder without capture.json and a capture.json that is a folder
    folder = os.path.dirname(index) or "."
    for path in (index, *checkpoint):
        check_input(path)
    # after the inputs (never one of them): the scores are a relight/metrics JSON
    check_output(output, no_clobber, kind="json")

    # ---- inputs (data errors), then the scores
    start = time.perf_counter()
    from relight_cli.clitools import progress
    from relight_cli.formats.metrics_json import make_record, write_metrics
    from relight_cli.neural.evaluate import CaptureEvaluator
    from relight_cli.neural.train import resolve_device
    from relight_cli.provenance import provenance

    torch_device = resolve_device(device or "auto")
    models = _load_hand_models(checkpoint, model, torch_device)
    try:
        evaluator = CaptureEvaluator(folder, models, torch_device, aa, grid)
    except ValueError as exc:
        raise UsageProblem(str(exc)) from None
    if not evaluator.sampling["matched"]:
        log(f"note: pixels sampled {evaluator.aa}×{evaluator.aa}, but the capture's images were "
            f"made with {evaluator.sampling['capture_aa']}×{evaluator.sampling['capture_aa']} "
            f"(recorded as settings.sampling.matched = false)", quiet)
    chosen = names or evaluator.default_splits()
    available = evaluator.data.splits()
    total = sum(len(available.get(n) or []) if eval_samples is None
                else min(eval_samples, len(available.get(n) or [])) for n in chosen)
    with progress(total=total, desc="relight (capture samples)", quiet=quiet) as bar:
        scores = evaluator.evaluate(chosen, eval_samples, progress=bar.update)
    if not scores:
        raise DataError(f"the capture has no samples in {', '.join(chosen)}", index)
    inputs = {"capture": index, **_checkpoint_roles(checkpoint)}
    settings = {"model": model, "splits": chosen, "eval_samples": eval_samples,
                "env_res": list(grid), "aa": evaluator.aa, "sampling": evaluator.sampling,
                "hands": [{"hand": k, "name": evaluator.names[k], "checkpoint": m.name,
                           "model": m.model_name, "sides": m.sides, "step": m.step,
                           **({"subject": m.subject} if m.subject else {})}
                          for k, m in enumerate(evaluator.models)]}
    record = provenance("relight/metrics", 2, inputs, settings)
    write_metrics(output, make_record("validation", scores, {r: {"path": p} for r, p in
                                                              inputs.items()}, settings, record))
    summary = "; ".join(f"{n}: MSE {m['mse'] * 1e3:.3f}e-3 SSIM {m['ssim']:.3f} ({m['samples']})"
                        for n, m in scores.items())
    log(f"wrote {output} ({time.perf_counter() - start:.1f} s): {summary}", quiet)


# options of the hand and Gaussian modes (a capture brings its own views and lights)
_VIEW_OPTIONS = {"probe": "--probe", "dgsm": "--dgsm", "receivers": "--receivers",
                 "objects": "--object", "receivers_out": "--receivers-out",
                 "shadow_matte": "--shadow-matte", "camera": "--camera",
                 "hand_size": "--size", "hand_lights": "--lights",
                 "hand_frame": "--frame", "hand_frames": "--frames", "hand_mesh": "--mesh",
                 "tex_res": "--tex-res",
                 "no_shadows": "--no-shadows", "no_specular": "--no-specular",
                 "no_sss": "--no-sss", "sss_scale": "--sss-scale", "bounce": "--bounce",
                 "albedo_map": "--albedo", "roughness_map": "--roughness", "aov": "--aov",
                 "preview": "--preview", "precision": "--precision",
                 "direct_light": "--direct-light"}


def _write_learned(output, preview, rgb, mask, model, camera, inputs, settings):
    """A learned model's render (over its background: relight_cli.jobs.relight_hand): EXR
    (R, G, B, A) with provenance, and the PNG preview."""
    from relight_cli.formats.exr import write_exr
    from relight_cli.provenance import provenance
    channels = {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "A": mask}
    record = provenance("relight/render", 1, {k: v for k, v in inputs.items() if v is not None},
                        settings)
    write_exr(output, channels, attributes={"relight.model": model,
                                            "relight.camera": camera.to_json()},
              provenance=record, camera=camera)
    if preview is not None:
        from relight_cli.preview import write_preview
        write_preview(preview, rgb)


def _sequence_patterns(hand_frame, hand_frames, output, preview) -> None:
    """--frames' usage checks that need no input: not with --frame, and -o (and
    --preview) patterns that name each frame's file ({frame}, Python format syntax)."""
    from relight_cli.errors import UsageProblem
    if hand_frames is None:
        return
    if hand_frame is not None:
        raise UsageProblem("--frame renders one frame, --frames a sequence: give one of them")
    for what, pattern in (("-o", output), ("--preview", preview)):
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


def _frames(hand_frames, frame, data, source, output, preview, no_clobber) -> list:
    """The frames to render (``--frames`` or the one ``--frame``), and with --frames every
    frame's output checked as -o / --preview are (before any work)."""
    from relight_cli.errors import UsageProblem
    if hand_frames is None:
        if frame >= data.n_frames:
            raise UsageProblem(f"--frame {frame} is out of range: {source} has {data.n_frames} "
                               f"frame(s)")
        return [frame]
    from relight_cli.jobs.relight_hand import select_frames
    try:
        frames = select_frames(hand_frames, data.n_frames)
    except ValueError as exc:
        raise UsageProblem(str(exc)) from None
    for what, pattern, kind in (("-o", output, "exr"), ("--preview", preview, "png")):
        if pattern is None:
            continue
        paths = [pattern.format(frame=f) for f in frames]
        if len(set(paths)) != len(paths):
            raise UsageProblem(f"{what} pattern {pattern!r} gives two frames the same file")
        for path in paths:
            check_output(path, no_clobber, kind=kind, what=what)
    return frames


def _frame_outputs(hand_frames, output, preview, frame) -> tuple:
    """(EXR path, PNG path or None) of one frame."""
    if hand_frames is None:
        return output, preview
    return output.format(frame=frame), (None if preview is None else preview.format(frame=frame))


def _view_of(camera, width, height):
    """(frame, posed meshes) → Camera: ``camera`` read once, or each frame framed by the
    default camera of ``width`` × ``height``."""
    from relight_cli.hand.scene import preview_camera
    if camera is not None:
        from relight_cli.formats.camera import read_camera
        view = read_camera(camera)
        return lambda frame, meshes: view
    return lambda frame, meshes: preview_camera(meshes, width, height)


def _frames_text(frames) -> str:
    if len(frames) == 1:
        return f"frame {frames[0]}"
    return f"{len(frames)} frames ({frames[0]}…{frames[-1]})"


class _frame_bar:
    """A progress bar over a sequence's frames (frames/s); nothing for one frame.
    Yields (step(render), done list of the renders' FrameRender)."""

    def __init__(self, frames, hand_frames, quiet):
        self.frames, self.sequence, self.quiet = frames, hand_frames is not None, quiet
        self.done, self.bar = [], None

    def __enter__(self):
        if self.sequence:
            from relight_cli.clitools import progress
            self.bar = progress(total=len(self.frames), desc="relight (frames)", unit="frame",
                                quiet=self.quiet).__enter__()

        def step(render):
            render.rgb = None          # the pixels are written; keep the timings only
            render.channels = None
            self.done.append(render)
            if self.bar is not None:
                self.bar.update(1)
        return step, self.done

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.__exit__(*exc)
        return False


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


def _hand_view_options(env, hand_lights, output, camera, hand_size, hand_frame, env_res):
    """Hand mode's shared usage checks: (width, height, frame, env H, env W)."""
    from relight_cli.errors import UsageProblem
    if env is None and hand_lights is None:
        raise UsageProblem("give an env map ENV and/or --lights LIGHTS.json to light the hand")
    from relight_cli.clitools import check_extension
    check_extension(output, "exr")
    if camera is not None and hand_size is not None:
        raise UsageProblem("--size sets the default camera's image; the size of --camera is its own")
    width, height = 256, 256
    if hand_size is not None:
        from relight_cli.clitools import parse_size
        width, height = parse_size(hand_size, "--size", maximum=8192)
    frame = 0 if hand_frame is None else hand_frame
    if frame < 0:
        raise UsageProblem(f"--frame must be ≥ 0, got {frame}")
    from relight_cli.inputs import env_grid
    env_h, env_w = env_grid(env_res or "32x16")
    return width, height, frame, env_h, env_w


def _read_dgsm(path: str):
    """The DGSM reader of formats/dgsm_exr.py (owned by the DGSM module)."""
    from relight_cli.errors import UsageProblem
    try:
        from relight_cli.formats import dgsm_exr
    except ImportError:
        raise UsageProblem("--dgsm is not available in this build (formats/dgsm_exr.py is "
                           "missing)", path) from None
    return dgsm_exr.read_dgsm(path)
