"""``relight dgsm-build``: Deep Gaussian Shadow Maps of occluder Gaussians for point lights."""

from __future__ import annotations

import click

from relight_cli.clitools import (FiniteFloat, check_input, check_output, log, no_clobber_option,
                                  parse_size, preview_option, progress, quiet_option, seed_option)


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
@click.option("--half", is_flag=True, help="Store 16-bit half floats (default float32).")
@preview_option("Also write a labelled PNG: the receivers shadowed (with the occluders) and "
                "their shadow matte, seen from --preview-camera, and each light's atlas slice "
                "(min T over the bins).")
@click.option("--preview-camera", default=None, metavar="CAMERA.json",
              help="OpenCV camera of --preview (default: one framing the occluders and their "
                   "shadow, from the side and above).")
@seed_option
@no_clobber_option
@quiet_option
def command(occluders, receivers, translate, occluders_out, receivers_out, lights_spec, estimator,
            lights_out, output, size, bins, atlas, mapping,
            kappa, t_max, roi, roi_radius, cull, cull_tolerance, footprint, samples,
            allow_light_inside, half, preview, preview_camera, seed, no_clobber, quiet):
    """Tabulate the transmittance from each light through the OCCLUDER Gaussians
    (closed-form erf optical depth, T = exp(−τ)) on K radial shells over an
    octahedral atlas of directions (Mir et al., Deep Gaussian Shadow Maps).

    Each OCCLUDER and SCENE is a 3DGS PLY file, a triangle mesh (.obj .glb
    .gltf .stl .off, turned into flat surface Gaussians with their texture or
    face colours), a posed hand.npz (fit-geometry's output: its fine mesh at frame
    0, or frame=K, as flat Gaussians with the hand's albedo; --occluders-out then
    exports it as a PLY), or builtin:hand | builtin:room | builtin:sphere.  An
    OCCLUDER may carry its own placement, SOURCE:KEY=VALUE;...  with keys
    fit=SIZE (scale the opacity-weighted 1-99 % box of its centres to SIZE
    metres on its largest side and centre it at the origin), centre, scale=S,
    rotate-x|y|z=DEG, on-floor (rest that box's bottom on y = 0) and
    translate=X,Y,Z, applied in that order whatever the order written
    (frame=K only picks a hand.npz's pose).

    With several OCCLUDERs, one table per occluder is built (all sharing t_max)
    and stored besides their product: scene receivers read the product, and
    `relight relight` shadows each object by the OTHER objects' tables (each
    object's Gaussians are receivers of the others' tables here).  An object
    does not shadow itself.

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

    import numpy as np

    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.dgsm_exr import FORMAT, VERSION, write_dgsm
    from relight_cli.clitools import parse_vector
    from relight_cli.formats.gaussians_ply import FORMAT as GFORMAT
    from relight_cli.formats.gaussians_ply import VERSION as GVERSION
    from relight_cli.formats.gaussians_ply import write_gaussians
    from relight_cli.formats.gaussians_ply import concatenate
    from relight_cli.gaussians.from_mesh import load_gaussians
    from relight_cli.formats.lights_json import FORMAT as LFORMAT
    from relight_cli.formats.lights_json import VERSION as LVERSION
    from relight_cli.formats.lights_json import Lights, read_lights, write_lights
    from relight_cli.gaussians import dgsm as D
    from relight_cli.gaussians import transmittance as TR
    from relight_cli.inputs import load_placed, parse_occluder
    from relight_cli.provenance import provenance

    start = time.perf_counter()
    check_output(output, no_clobber, kind="exr")
    check_output(lights_out, no_clobber, kind="json", what="--lights-out")
    check_output(occluders_out, no_clobber, kind="ply", what="--occluders-out")
    check_output(receivers_out, no_clobber, kind="ply", what="--receivers-out")
    check_output(preview, no_clobber, kind="png", what="--preview")
    if preview_camera is not None and preview is None:
        raise UsageProblem("--preview-camera needs --preview PNG")
    offset = None if translate is None else np.array(parse_vector(translate, 3, "--translate"))
    w, h = parse_size(size, "--size", minimum=2, maximum=4096)
    if receivers is None and t_max is None:
        raise UsageProblem("give --receivers SCENE.ply (or --t-max for a receiver-free build)")
    auto_k = _parse_auto(lights_spec)
    if auto_k is not None and receivers is None:
        raise UsageProblem("--lights auto:K estimates lights from the scene: give --receivers")

    parsed = [parse_occluder(spec, "OCCLUDER") for spec in occluders]
    if receivers is not None:
        check_input(receivers)
    objects = []
    for spec, (source, placement) in zip(occluders, parsed):
        check_input(source)
        objects.append(load_placed(source, placement, spec, offset))
    occ = objects[0] if len(objects) == 1 else concatenate(objects)
    scene = None
    if receivers is not None:
        check_input(receivers)
        scene = load_gaussians(receivers)

    view = None
    if preview_camera is not None:
        from relight_cli.formats.camera import read_camera
        view = read_camera(check_input(preview_camera))
    if auto_k is None:
        check_input(lights_spec, stdin="--lights")
        lights = read_lights(lights_spec)
    else:
        lights = _estimate_lights(scene, auto_k, lights_spec, occ, estimator)
    # Logged once every input has been read: a bad input gets one line only.
    if scene is not None:
        log(f"read {receivers}: {len(scene)} receiver Gaussians", quiet)
    for spec, obj in zip(occluders, objects):
        log(f"read {spec}: {len(obj)} occluder Gaussians", quiet)
    log(f"{len(lights)} light(s)", quiet)

    if mapping != TR.canonical_mapping(mapping):
        log(f"note: --mapping {mapping} is the old name of {TR.canonical_mapping(mapping)}", quiet)
    mapping = TR.canonical_mapping(mapping)
    mix = TR.from_gaussians(occ, mapping, kappa)
    inside = _lights_inside(mix, lights.positions)
    for li, gi, m in inside:
        message = (f"light {li} at {_fmt(lights.positions[li])} lies inside occluder Gaussian "
                   f"{gi} (Mahalanobis distance {m:.2f} < 1)")
        if not allow_light_inside:
            raise DataError(message, lights_spec if auto_k is None else ", ".join(occluders),
                            hint="move the light, or pass --allow-light-inside")
        log(f"warning: {message}; its shadows are dominated by that Gaussian", quiet)

    recv_points = None
    if scene is not None:
        pts, _ = D.footprint_samples(scene.means, scene.scales, scene.rotations, footprint,
                                     samples, seed)
        recv_points = pts.reshape(-1, 3)
        if not np.isfinite(recv_points).all():
            raise DataError("receiver positions hold NaN/Inf", receivers)

    options = dict(size=(h, w), bins=bins, layout=atlas, t_max=t_max, roi=roi,
                   roi_radius=roi_radius, cull=cull, cull_tolerance=cull_tolerance,
                   intensities=lights.intensities, colors=lights.colors)
    if len(objects) == 1:
        bar = (lambda it, total: progress(it, total=total, desc="lights", quiet=quiet))
        shadow_map = D.build_dgsm(mix, lights.positions, recv_points, progress=bar, **options)
    else:
        # each object receives the others' shadows: its footprint samples join their ROIs
        group_points = [D.footprint_samples(o.means, o.scales, o.rotations, footprint, samples,
                                            seed)[0].reshape(-1, 3) for o in objects]
        bar = (lambda it, total: progress(it, total=total, desc="occluders", quiet=quiet))
        shadow_map = D.build_dgsm_groups(
            [TR.from_gaussians(o, mapping, kappa) for o in objects], lights.positions,
            recv_points, group_points, names=list(occluders), progress=bar, **options)
    for li, info in enumerate(shadow_map.roi):
        if scene is not None and roi and info["receivers"] == 0:
            log(f"warning: light {li}: no receivers in the ROI (none can be shadowed by the "
                f"occluders); its table is all ones", quiet)
        else:
            log(f"light {li}: {info['texels']} texels, bins {info['bins'][0]}..{info['bins'][1]}, "
                f"t_max {shadow_map.t_max[li]:.3f} m, min T "
                f"{float(shadow_map.transmittance[li].min()):.3f}", quiet)
    st = shadow_map.stats
    log(f"built in {shadow_map.build_seconds:.3f} s ({st['pairs_kept']} ray/Gaussian pairs kept "
        f"of {st['pairs_tested']} tested), opacity mapping {mapping} (κ = {kappa:g})", quiet)

    inputs = {"occluders": parsed[0][0]} if len(occluders) == 1 else {
        f"occluder{j}": source for j, (source, _) in enumerate(parsed)}
    if receivers is not None:
        inputs["receivers"] = receivers
    if auto_k is None:
        inputs["lights"] = lights_spec
    settings = {"size": [h, w], "bins": bins, "atlas": atlas, "mapping": mapping, "kappa": kappa,
                "t_max": t_max, "roi": roi, "roi_radius": roi_radius, "cull": cull,
                "cull_tolerance": cull_tolerance, "footprint": footprint, "samples": samples,
                "seed": seed, "lights": lights_spec, "half": half, "translate": translate,
                "estimator": estimator if auto_k is not None else None,
                "occluders": list(occluders)}
    write_dgsm(output, shadow_map, provenance(FORMAT, VERSION, inputs, settings), half=half)
    log(f"wrote {output} ({time.perf_counter() - start:.2f} s)", quiet)
    if occluders_out is not None:
        write_gaussians(occluders_out, occ, provenance(GFORMAT, GVERSION, inputs,
                                                       {"translate": translate,
                                                        "occluders": list(occluders)}))
        log(f"wrote {occluders_out}", quiet)
    if receivers_out is not None and scene is not None:
        write_gaussians(receivers_out, scene, provenance(GFORMAT, GVERSION,
                                                         {"receivers": receivers}, {}))
        log(f"wrote {receivers_out}", quiet)
    if lights_out is not None:
        write_lights(lights_out, Lights(lights.positions, lights.colors, lights.intensities,
                                        lights.names, lights.extra),
                     provenance(LFORMAT, LVERSION, inputs, settings))
        log(f"wrote {lights_out}", quiet)
    if preview is not None:
        from relight_cli.formats.image import write_png
        from relight_cli.preview import dgsm_sheet
        title = (f"dgsm-build: {len(lights)} light(s), {atlas} atlas {w}x{h}, {bins} bins, "
                 f"mapping {mapping}\noccluders: {' '.join(occluders)}"
                 + (f"\nreceivers: {receivers}" if receivers else ""))
        image, _ = dgsm_sheet(shadow_map, occ, scene, view, footprint, samples, seed, title)
        write_png(preview, image)
        log(f"wrote {preview}", quiet)


def _parse_auto(spec: str):
    from relight_cli.errors import UsageProblem
    if not spec.startswith("auto"):
        return None
    try:
        k = int(spec.split(":", 1)[1])
    except (IndexError, ValueError):
        raise UsageProblem(f"--lights auto needs a count, e.g. auto:2, got {spec!r}") from None
    if not 1 <= k <= 64:
        raise UsageProblem(f"--lights auto:K needs 1 ≤ K ≤ 64, got {k}")
    return k


def _estimate_lights(scene, k, spec, character=None, variant="paper"):
    """auto:K through relight_cli.gaussians.lights (the light-estimation module), if present."""
    import importlib

    import numpy as np

    from relight_cli.errors import UsageProblem
    from relight_cli.formats.lights_json import Lights
    try:
        module = importlib.import_module("relight_cli.gaussians.lights")
    except ImportError:
        module = None
    estimator = getattr(module, "estimate_lights", None) if module is not None else None
    if estimator is None:
        raise UsageProblem("--lights auto:K is not available in this build (no light estimator "
                           "in relight_cli.gaussians.lights); give a lights JSON file", spec)
    try:
        result = estimator(scene, k, character=character, variant=variant)   # deterministic
    except ValueError as exc:
        from relight_cli.errors import DataError
        raise DataError(f"light estimation failed: {exc}", spec) from None
    if isinstance(result, Lights):
        return result
    if hasattr(result, "positions"):
        return Lights(result.positions, getattr(result, "colors", None),
                      getattr(result, "intensities", None),
                      extra={"estimator": "relight_cli.gaussians.lights.estimate_lights",
                             "variant": variant, "count": int(k),
                             "character": "the occluders (alpha-weighted centroid)"})
    return Lights(np.asarray(result, np.float64).reshape(-1, 3))


def _lights_inside(mix, positions, threshold: float = 1.0):
    """[(light, gaussian, mahalanobis)] for lights within 1σ of an occluder Gaussian."""
    import numpy as np
    found = []
    for li, p in enumerate(np.asarray(positions, np.float64)):
        rel = (p - mix.means) / mix.scale_max[:, None]
        local = np.einsum("nji,nj->ni", mix.rotation, rel)
        m2 = (local ** 2 / mix.var).sum(axis=1)
        m2 = np.where(mix.alpha > 0, m2, np.inf)
        j = int(np.argmin(m2))
        if m2[j] < threshold ** 2:
            found.append((li, j, float(np.sqrt(m2[j]))))
    return found


def _fmt(v) -> str:
    return "(" + ", ".join(f"{float(x):.3g}" for x in v) + ")"
