"""``relight bake-features``: texel-aligned, visibility-aware shading features."""

from __future__ import annotations

import click

from relight_cli.clitools import (check_output, log, no_clobber_option, preview_option,
                                  quiet_option, renamed_option)


@click.command("bake-features",
               short_help="Bake texel-aligned diffuse/specular/visibility features (EXR).")
@click.argument("hand", metavar="HAND")
@click.argument("envs", metavar="ENV...", nargs=-1, required=True)
@click.option("-o", "--output", required=True,
              help="Output EXR. May hold {frame} (e.g. {frame:04d}) and {env} (the env map's "
                   "name); required with --all-frames / several env maps.")
@click.option("--frame", type=int, default=None, help="Frame to bake [default: 0].")
@click.option("--all-frames", "frames_all", is_flag=True,
              help="Bake every frame (the output needs {frame}; formerly --frames all).")
@renamed_option("--frames", "--all-frames", why="--frames is a count in other commands")
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
def command(hand, envs, output, frame, frames_all, mesh, env_res, texture_res, shininess, specular,
            roughness, eye, camera, no_visibility, per_vertex, preview, no_clobber, quiet):
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
      relight bake-features hand.npz builtin:sky --all-frames -o 'f_{frame:04d}.exr'
    """
    import time

    import numpy as np

    from relight_cli import features as F
    from relight_cli.clitools import check_input, parse_vector, progress
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.features_exr import (FORMAT, VERSION, VERTEX_FORMAT,
                                                  VERTEX_VERSION, write_features,
                                                  write_vertex_features)
    from relight_cli.provenance import provenance

    from relight_cli.inputs import load_envmap, load_hand, read_roughness_map

    # ---- options (usage errors, before any work)
    from relight_cli.inputs import env_grid
    env_h, env_w = env_grid(env_res)
    from relight_cli.clitools import parse_size
    tex_w, tex_h = parse_size(texture_res, "--res", maximum=8192)
    try:
        alphas = tuple(float(a) for a in shininess.split(",") if a.strip()) if shininess else ()
        settings = F.FeatureSettings(shininess=alphas, specular=specular,
                                     visibility=not no_visibility)
    except ValueError as exc:
        raise UsageProblem(f"--shininess: {exc}") from None
    if settings.specular in ("phong", "both") and not settings.phong:
        raise UsageProblem("--specular phong needs at least one --shininess exponent")
    if eye is not None and camera is not None:
        raise UsageProblem("give --eye or --camera, not both")
    if frame is not None and frames_all:
        raise UsageProblem("give --frame N or --all-frames, not both")
    if frame is not None and frame < 0:
        raise UsageProblem(f"--frame must be ≥ 0, got {frame}")
    rough_value = None
    try:
        rough_value = float(roughness)
    except ValueError:
        check_input(roughness)
    if rough_value is not None and not (0 < rough_value <= 1):
        raise UsageProblem(f"--roughness must be in (0, 1], got {roughness}")
    if rough_value is not None:
        settings.roughness = rough_value
    eye_pos = None if eye is None else np.asarray(parse_vector(eye, 3, "--eye"))
    env_names = [_env_name(e) for e in envs]
    if len(set(env_names)) != len(env_names):
        raise UsageProblem("two env maps have the same name; {env} would not tell them apart")
    for pattern in filter(None, (output, per_vertex, preview)):
        if len(envs) > 1 and "{env" not in pattern:
            raise UsageProblem(f"several env maps need {{env}} in every output name: {pattern}")
        _check_pattern(pattern)

    # ---- inputs (data errors)
    data = load_hand(hand)
    n_frames = data.n_frames
    if frames_all:
        frames = list(range(n_frames))
    else:
        frames = [frame or 0]
        if frames[0] >= n_frames:
            raise UsageProblem(f"--frame {frames[0]} is out of range: {hand} has {n_frames} "
                               f"frame(s)")
    for pattern in filter(None, (output, per_vertex, preview)):
        if len(frames) > 1 and "{frame" not in pattern:
            raise UsageProblem(f"--all-frames needs {{frame}} in every output name: {pattern}")
    targets = []  # (frame, env index, exr, npz, png)
    for fr in frames:
        for k, name in enumerate(env_names):
            paths = [None if p is None else p.format(frame=fr, env=name)
                     for p in (output, per_vertex, preview)]
            for p, kind, what in zip(paths, ("exr", "npz", "png"),
                                     ("-o", "--per-vertex", "--preview")):
                check_output(p, no_clobber, kind=kind, what=what)
            targets.append((fr, k, *paths))
    if per_vertex is not None and output.format(frame=0, env="x") == per_vertex.format(
            frame=0, env="x"):
        raise UsageProblem("--per-vertex must differ from -o")
    cam = None
    if camera is not None:
        from relight_cli.formats.camera import read_camera
        check_input(camera, stdin="--camera")
        cam = read_camera(camera)
    env_maps = []
    for spec in envs:
        env_maps.append(load_envmap(spec))
    rough_map = None if rough_value is not None else read_roughness_map(roughness)
    t0 = time.perf_counter()
    discrete = [F.discretize_env(e, env_h, env_w) for e in env_maps]
    env_seconds = time.perf_counter() - t0
    for d, spec in zip(discrete, envs):
        # Every layer is at most ~1e3 × the map's power Σ L Δω (the sharpest Phong/GGX
        # lobes): beyond float32's range the stored features would be Inf.
        power = float((d.radiance * d.solid_angle[:, None]).sum(axis=0).max())
        if not power * 1e3 < float(np.finfo(np.float32).max):
            raise DataError(f"env map is too bright (power {power:.3g}): its features would "
                            f"overflow float32", spec)
    log(f"read {hand}: {len(data.hands)} hand(s), {n_frames} frame(s); "
        f"{len(envs)} env map(s)", quiet)
    for env, spec in zip(env_maps, envs):   # a file finer than the grid loses detail: say so
        if not spec.startswith("builtin:") and env.width * env.height > env_w * env_h:
            size = (f"{env.width}x{env.height}" if env.layout == "latlong"
                    else f"cube {env.width}x{env.width}x6")
            log(f"note: {spec} ({size}) is reduced to the --env-res grid {env_w}x{env_h} "
                f"(area-weighted, power kept); a larger --env-res keeps more detail", quiet)

    from relight_cli.bake import PoseFeatures

    inputs = {"hand": hand}
    if camera is not None:
        inputs["camera"] = camera
    rasters = {}
    charts = None
    for fr in progress(frames, desc="frames", quiet=quiet or len(frames) == 1):
        pose = PoseFeatures(data, fr, settings, (env_h, env_w), (tex_h, tex_w), mesh, rasters,
                            source=hand)
        posed = pose.posed
        if eye_pos is not None:
            viewer = eye_pos
        elif cam is not None:
            viewer = cam.center
        else:
            viewer = pose.default_viewer()
        rough = None
        if rough_map is not None:
            rough = np.concatenate([_sample_uv_map(rough_map, pm) for pm in posed])
        results, texel = pose.bake(discrete, viewer, roughness=rough)
        baker = pose.baker
        maps_per_env = [pose.layers(per_mesh) for per_mesh in texel]
        for layers, spec in zip(maps_per_env, envs):
            overflow = [n for n, value in layers.items() if not np.isfinite(value).all()]
            if overflow:  # e.g. radiance near float32's limit: the sums overflow
                raise DataError(f"features overflow float32 in layer(s) {', '.join(overflow)} "
                                f"(env map radiance too large)", spec)
        seconds = {"env": env_seconds, **pose.stats}
        for fr_t, k, exr_path, npz_path, png_path in (t for t in targets if t[0] == fr):
            record = provenance(FORMAT, VERSION, {**inputs, "env": envs[k]}, {
                "frame": fr, "mesh": mesh, "env_res": [env_h, env_w],
                "res": [tex_w, tex_h], "shininess": list(settings.phong),
                "specular": specular, "roughness": roughness, "visibility": not no_visibility,
                "view": [float(x) for x in viewer]})
            attrs = {"relight.env": envs[k],
                     "relight.env_sha256": record["inputs"]["env"]["sha256"],
                     "relight.env_res": f"{env_h}x{env_w}",
                     "relight.shininess": list(settings.phong) or "none",
                     "relight.specular": specular,
                     "relight.view": [float(x) for x in viewer],
                     "relight.frame": int(fr),
                     "relight.mesh": mesh,
                     "relight.visibility": int(not no_visibility),
                     "relight.rays_traced": int(baker.stats.rays_traced),
                     "relight.hands": ",".join(pm.name for pm in posed)}
            write_features(exr_path, maps_per_env[k], attributes=attrs, provenance=record)
            log(f"wrote {exr_path}", quiet)
            if npz_path is not None:
                arrays = {}
                for pm, feats in zip(posed, results[k]):
                    prefix = "" if len(posed) == 1 else pm.name + "."
                    arrays[prefix + "vertices"] = pm.vertices
                    arrays[prefix + "faces"] = pm.faces
                    arrays[prefix + "normals"] = pm.normals
                    for name, value in feats.items():
                        arrays[prefix + name] = value
                vrecord = dict(record, format=VERTEX_FORMAT, version=VERTEX_VERSION)
                write_vertex_features(npz_path, arrays, vrecord)
                log(f"wrote {npz_path}", quiet)
            if png_path is not None:
                from relight_cli.formats.image import write_png
                from relight_cli.preview import feature_sheet, uv_charts
                if charts is None:     # which texels are palm, back, fingers (pose independent)
                    charts = uv_charts(getattr(data, mesh), data.label_names, data.joint_names,
                                       (tex_h, tex_w))
                write_png(png_path, feature_sheet(
                    maps_per_env[k], f"bake-features {hand}, frame {fr}, env {envs[k]} "
                                     f"({env_w}x{env_h} directions), view "
                                     + ",".join(f"{float(x):.2f}" for x in viewer),
                    charts=charts))
                log(f"wrote {png_path}", quiet)
        log(f"frame {fr}: {baker.stats.rays_traced} rays, "
            + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in seconds.items()), quiet)


def _check_pattern(pattern: str) -> None:
    """Output names may hold {frame} and {env} fields (with a format spec such as
    {frame:04d}) and nothing else: no attribute or index access, no conversions."""
    import string

    from relight_cli.errors import UsageProblem
    bad = None
    try:
        for _, field, spec, conversion in string.Formatter().parse(pattern):
            if field is None:
                continue
            if field not in ("frame", "env") or conversion is not None or "{" in (spec or ""):
                bad = "{" + field + ("!" + conversion if conversion else "") + "}"
                break
        else:
            pattern.format(frame=0, env="x")
    except (KeyError, IndexError, ValueError) as exc:
        bad = f"({type(exc).__name__}: {exc})"
    if bad is not None:
        raise UsageProblem(f"output name {pattern!r} may only use {{frame}} and {{env}} "
                           f"fields, found {bad}")


def _env_name(spec: str) -> str:
    import os
    if spec.startswith("builtin:"):
        return spec.split(":", 1)[1]
    base = os.path.basename(spec)
    return base.split(".", 1)[0] or base


def _sample_uv_map(image, pm):
    """[V] bilinear samples of a UV-space map at each vertex's (first) UV."""
    import numpy as np
    h, w = image.shape
    uv_of_vertex = np.zeros((len(pm.vertices), 2))
    uv_of_vertex[pm.faces.ravel()] = pm.uv[pm.faces_uv.ravel()]
    x = np.clip(uv_of_vertex[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1 - uv_of_vertex[:, 1]) * h - 0.5, 0, h - 1)   # v = 0 at the bottom row
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    return ((image[y0, x0] * (1 - fx) + image[y0, x1] * fx) * (1 - fy)
            + (image[y1, x0] * (1 - fx) + image[y1, x1] * fx) * fy)
