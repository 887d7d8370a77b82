"""``relight bake-features``: texel-aligned, visibility-aware shading features."""

from __future__ import annotations

import click

from relight_cli.cli.tools import (check_output, log, no_clobber_option, preview_option,
                                   quiet_option, renamed_option)
from relight_cli.sequence import FRAME_HELP, FRAMES_HELP


@click.command("bake-features",
               short_help="Bake texel-aligned diffuse/specular/visibility features (EXR).")
@click.argument("hand", metavar="HAND")
@click.argument("envs", metavar="ENV...", nargs=-1, required=True)
@click.option("-o", "--output", required=True,
              help="Output EXR. May hold {frame} (e.g. {frame:04d}) and {env} (the env map's "
                   "name); required with --frames / several env maps.")
@click.option("--frame", type=int, default=None, help=FRAME_HELP)
@click.option("--frames", "frames", default=None, metavar="all|A:B[:S]",
              help=FRAMES_HELP + " Every output needs {frame}.")
@renamed_option("--all-frames", "--frames all", takes_value=False,
                why="one frame grammar in every command")
@click.option("--mesh", type=click.Choice(["coarse", "fine"]), default="coarse", show_default=True,
              help="Receivers and occluders: the coarse proxy, or the fine mesh (ablations).")
@click.option("--env-res", default="32x16", show_default=True,
              help="Lat-long grid WxH (width first) the env map is integrated over (M = W·H "
                   "directions).")
@click.option("--res", "texture_res", default="128", show_default=True,
              help="Feature map size N (N×N) or WxH.")
@click.option("--shininess", default="16,32,64", show_default=True,
              help="Phong exponents, comma-separated (one phong<α> layer each).")
@click.option("--specular", type=click.Choice(["phong", "ggx", "both", "none"]), default="phong",
              show_default=True, help="Specular features: RelightableHands' Phong, URHand's GGX.")
@click.option("--roughness", default="0.5", show_default=True,
              help="GGX roughness: a number in (0, 1], or a UV-space EXR map (channel Y or R).")
@click.option("--ggx-shadowing", type=click.Choice(["smith", "schlick"]), default="smith",
              show_default=True,
              help="The GGX layer's shadowing term: the exact Smith G (as Mitsuba 3 and pbrt) "
                   "or URHand Eq. 15's Schlick remap k = (rho+1)^2/8.")
@click.option("--env-sources", default="auto", show_default=True, metavar="auto|none|N",
              help="Take up to N small bright sources (a sun, a lamp) out of each env map "
                   "before it is put on the --env-res grid, each kept as a distant light at "
                   "its own direction and power (auto: up to 8), as relight --model physical "
                   "does.")
@click.option("--eye", default=None, help="Viewer position x,y,z (metres, world).")
@click.option("--camera", type=str, default=None,
              help="Viewer from an OpenCV camera JSON (its centre). Default: a camera framing "
                   "the hands from the front (+Z).")
@click.option("--no-visibility", is_flag=True, help="Ablation: no shadows (h ≡ 1, no rays).")
@click.option("--per-vertex", type=str, default=None,
              help="Also write per-vertex features (.npz; may hold {frame} and {env}).")
@preview_option("Also write a labelled PNG contact sheet of the feature layers, one tile per "
                "layer with its exposure (may hold {frame}, {env}).")
@no_clobber_option
@quiet_option
def command(hand, envs, output, frame, frames, mesh, env_res, texture_res, shininess, specular,
            roughness, ggx_shadowing, env_sources, eye, camera, no_visibility, per_vertex,
            preview, no_clobber, quiet):
    """Bake shading features of the posed hand(s) in HAND (a hand.npz, or
    builtin:right|left|two[:POSE]) under each ENV (EXR/HDR env map or
    builtin:sky|studio|uniform|point) into texel-aligned EXR maps.

    Layers: diffuse (RelightableHands' d = Σ L·h·max(n·ω,0)·Δω), phong<α>
    ((α+2)/2π Σ L·h·max(r·ω,0)^α·Δω), ggx (URHand's GGX lobe, --specular),
    visibility (cosine-weighted) and mask (UV charts).  Visibility h is traced
    with embree once per pose against every hand and reused for every env map.

    \b
    Examples:
      relight bake-features hand.npz stage.exr -o feats.exr
      relight bake-features hand.npz a.exr b.exr -o 'feats_{env}.exr'
      relight bake-features hand.npz builtin:sky --frames all -o 'f_{frame:04d}.exr'
    """
    from relight_cli.cli import inputs as I
    from relight_cli.jobs import bake_features as job
    from relight_cli.sequence import select

    # ---- options (usage errors, before any work)
    options, rough_value, env_names, patterns = _options(
        envs, env_res, texture_res, shininess, specular, roughness, eye, camera, frame,
        frames, mesh, no_visibility, (output, per_vertex, preview), ggx_shadowing, env_sources)

    # ---- inputs (data errors)
    data = I.load_hand(hand)
    selected = select(frame, frames, data.n_frames, hand)
    targets = _targets(selected, env_names, patterns, no_clobber)
    if camera is not None:
        options.viewer = I.load_camera(camera).center
    env_maps = [I.load_envmap(spec) for spec in envs]
    if rough_value is None:
        options.roughness_map = I.read_roughness_map(roughness)
    baked = job.bake(data, selected, env_maps, options, names=envs, source=hand, quiet=quiet)
    log(f"read {hand}: {len(data.hands)} hand(s), {data.n_frames} frame(s); "
        f"{len(envs)} env map(s)", quiet)
    env_h, env_w = options.env_res
    for env, spec in zip(env_maps, envs):   # a file finer than the grid loses detail: say so
        if not spec.startswith("builtin:") and env.width * env.height > env_w * env_h:
            size = (f"{env.width}x{env.height}" if env.layout == "latlong"
                    else f"cube {env.width}x{env.width}x6")
            log(f"note: {spec} ({size}) is reduced to the --env-res grid {env_w}x{env_h} "
                f"(area-weighted, power kept; small bright sources kept apart per "
                f"--env-sources); a larger --env-res keeps more detail", quiet)

    # ---- the job, each frame written as it comes
    inputs = {"hand": hand} if camera is None else {"hand": hand, "camera": camera}
    charts = []
    for result in baked:
        for _, k, exr_path, npz_path, png_path in (t for t in targets if t[0] == result.frame):
            _write(result, k, envs[k], exr_path, npz_path, png_path, inputs, options, data,
                   hand, charts, quiet)
        log(f"frame {result.frame}: {result.rays_traced} rays, "
            + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in result.seconds.items()), quiet)


def _options(envs, env_res, texture_res, shininess, specular, roughness, eye, camera, frame,
             frames, mesh, no_visibility, patterns, ggx_shadowing="smith", env_sources="auto"):
    """The options' usage errors (exit 2), before any work: (BakeOptions, the scalar
    roughness or None for a map, the env maps' names, the outputs' OutputPatterns)."""
    import numpy as np

    from relight_cli import features as FE
    from relight_cli.cli import inputs as I
    from relight_cli.cli.tools import parse_size, parse_vector
    from relight_cli.errors import UsageProblem
    from relight_cli.jobs.bake_features import BakeOptions
    from relight_cli.sequence import OutputPattern, check_frame

    from relight_cli.envmap import DEFAULT_GRID
    env_h, env_w = I.env_grid(env_res) if env_res is not None else DEFAULT_GRID
    tex_w, tex_h = parse_size(texture_res, "--res", maximum=8192)
    try:
        alphas = tuple(float(a) for a in shininess.split(",") if a.strip()) if shininess else ()
        settings = FE.FeatureSettings(shininess=alphas, specular=specular,
                                      visibility=not no_visibility, shadowing=ggx_shadowing)
    except ValueError as exc:
        raise UsageProblem(f"--shininess: {exc}") from None
    if settings.specular in ("phong", "both") and not settings.phong:
        raise UsageProblem("--specular phong needs at least one --shininess exponent")
    if eye is not None and camera is not None:
        raise UsageProblem("give --eye or --camera, not both")
    check_frame(frame, frames)
    rough_value = I.roughness_value(roughness)
    if rough_value is not None:
        settings.roughness = rough_value
    eye_pos = None if eye is None else np.asarray(parse_vector(eye, 3, "--eye"))
    env_names = [_env_name(e) for e in envs]
    if len(set(env_names)) != len(env_names):
        raise UsageProblem("two env maps have the same name; {env} would not tell them apart")
    parsed = {}
    for pattern, what in zip(patterns, ("-o", "--per-vertex", "--preview")):
        parsed[what] = None if pattern is None else OutputPattern(pattern, what)
        if pattern is None:
            continue
        if len(envs) > 1 and not parsed[what].holds("env"):
            raise UsageProblem(f"several env maps need {{env}} in every output name: {pattern}")
        if frames is not None and not parsed[what].holds("frame"):
            raise UsageProblem(f"--frames needs {{frame}} in every output name: {pattern}")
    from relight_cli.jobs.relight_hand import PhysicalOptions
    try:
        sources = PhysicalOptions(env_sources=env_sources).sources()
    except ValueError as exc:
        raise UsageProblem(str(exc)) from None
    options = BakeOptions(settings, (env_h, env_w), (tex_h, tex_w), mesh, eye_pos,
                          roughness_label=roughness, env_sources=sources)
    return options, rough_value, env_names, parsed


def _targets(frames, env_names, patterns, no_clobber):
    """[(frame, env index, exr, npz or None, png or None)], every output checked."""
    from relight_cli.errors import UsageProblem
    from relight_cli.sequence import plan_outputs
    plan = plan_outputs(patterns, frames, tuple(env_names))
    targets = []
    for (fr, name), paths in plan.items():
        for what, kind in (("-o", "exr"), ("--per-vertex", "npz"), ("--preview", "png")):
            check_output(paths[what], no_clobber, kind=kind, what=what)
        targets.append((fr, env_names.index(name), paths["-o"], paths["--per-vertex"],
                        paths["--preview"]))
    per_vertex = patterns["--per-vertex"]
    if per_vertex is not None and patterns["-o"].format(0, "x") == per_vertex.format(0, "x"):
        raise UsageProblem("--per-vertex must differ from -o")
    return targets


def _write(result, k, env, exr_path, npz_path, png_path, inputs, options, data, hand, charts,
           quiet):
    """Env map ``k``'s features of one baked frame: the EXR, the per-vertex npz, the
    preview sheet (``charts``: a one-item cache of the UV charts)."""
    from relight_cli.formats.features_exr import (FORMAT, VERSION, VERTEX_FORMAT,
                                                  VERTEX_VERSION, write_features,
                                                  write_vertex_features)
    from relight_cli.provenance import provenance

    record = provenance(FORMAT, VERSION, {**inputs, "env": env}, result.settings)
    s, fr, viewer = result.settings, result.frame, result.viewer
    env_h, env_w = options.env_res
    attrs = {"relight.env": env,
             "relight.env_sha256": record["inputs"]["env"]["sha256"],
             "relight.env_res": f"{env_h}x{env_w}",
             "relight.shininess": s["shininess"] or "none",
             "relight.specular": s["specular"],
             "relight.view": s["view"],
             "relight.frame": int(fr),
             "relight.mesh": options.mesh,
             "relight.visibility": int(s["visibility"]),
             "relight.rays_traced": result.rays_traced,
             "relight.hands": ",".join(result.hands)}
    write_features(exr_path, result.maps[k], attributes=attrs, provenance=record)
    log(f"wrote {exr_path}", quiet)
    if npz_path is not None:
        vrecord = dict(record, format=VERTEX_FORMAT, version=VERTEX_VERSION)
        write_vertex_features(npz_path, result.vertex[k], vrecord)
        log(f"wrote {npz_path}", quiet)
    if png_path is not None:
        from relight_cli.formats.image import write_png
        from relight_cli.preview import feature_sheet, uv_charts
        if not charts:     # which texels are palm, back, fingers (pose independent)
            charts.append(uv_charts(getattr(data, options.mesh), data.label_names,
                                    data.joint_names, options.tex_res))
        write_png(png_path, feature_sheet(
            result.maps[k], f"bake-features {hand}, frame {fr}, env {env} "
                            f"({env_w}x{env_h} directions), view "
                            + ",".join(f"{float(x):.2f}" for x in viewer),
            charts=charts[0]))
        log(f"wrote {png_path}", quiet)


def _env_name(spec: str) -> str:
    import os
    if spec.startswith("builtin:"):
        return spec.split(":", 1)[1]
    base = os.path.basename(spec)
    return base.split(".", 1)[0] or base
