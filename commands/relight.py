"""``relight relight``: relight an input under new lighting.

The first input decides the mode: a Gaussians PLY (``.ply``) is relit with an
SH probe and optionally shadowed with a DGSM (paper Sec. 3.4); a hand
(``.npz``) will be relit by the neural hand models (not available yet).  Each
mode is one function below; options that belong to one mode are refused in
the other.
"""

from __future__ import annotations

import click

from relight_cli.clitools import (check_input, check_output, log, no_clobber_option, parse_vector,
                                  quiet_option, seed_option)


@click.command("relight", short_help="Relight Gaussians with an SH probe (+ DGSM shadows), or a hand.")
@click.argument("input", metavar="IN")
@click.option("-o", "--output", required=True,
              help="Relit Gaussians PLY, or with --render an EXR image.")
@click.option("--probe", default=None, metavar="PROBE.json",
              help="[Gaussians] SH light probe (relight sh-probe) lighting the avatar.")
@click.option("--dgsm", default=None, metavar="SHADOWS.exr",
              help="[Gaussians] Deep Gaussian Shadow Map (relight dgsm-build) darkening --receivers.")
@click.option("--receivers", default=None, metavar="SCENE.ply",
              help="[Gaussians] Scene Gaussians: shadowed by --dgsm, and rendered with --render.")
@click.option("--receivers-out", default=None, metavar="PLY",
              help="[Gaussians] Also write the shadowed receivers as a PLY.")
@click.option("--footprint", type=click.Choice(["centre", "stencil", "mc"]), default="stencil",
              show_default=True,
              help="[Gaussians] DGSM lookup over a receiver: centre sample, 7-point stencil, or "
                   "seeded Monte Carlo (--samples) in its principal frame.")
@click.option("--samples", type=click.IntRange(1, 1024), default=16, show_default=True,
              help="Monte Carlo samples per receiver for --footprint mc.")
@click.option("--shadow-strength", type=click.FloatRange(0, 1), default=1.0, show_default=True,
              help="[Gaussians] Receiver colour × (1 − s·(1 − T)); 1 multiplies by T.")
@click.option("--lobe", type=float, default=1.0, show_default=True,
              help="[Gaussians] Cosine lobe exponent q of the transfer (1 = Lambertian).")
@click.option("--intensity", type=float, default=1.0, show_default=True,
              help="[Gaussians] Global intensity γ.")
@click.option("--t-max", "t_max", type=float, default=None,
              help="[Gaussians] Clip of the shading factor (default: no clip).")
@click.option("--normals", type=click.Choice(["auto", "axis", "pca", "stored"]), default="auto",
              show_default=True,
              help="[Gaussians] Normals: shortest ellipsoid axis, local PCA of neighbours, the "
                   "file's nx ny nz; auto = stored if present, else axis. Oriented outward.")
@click.option("--render", "render_camera", default=None, metavar="CAMERA.json",
              help="Render a view (receivers + relit avatar) to -o as an EXR (R, G, B, A).")
@click.option("--background", default="0,0,0", show_default=True, metavar="R,G,B",
              help="Background radiance of --render.")
@click.option("--preview", default=None, metavar="PNG", help="With --render: a tone-mapped PNG too.")
@seed_option
@no_clobber_option
@quiet_option
def command(input, output, probe, dgsm, receivers, receivers_out, footprint, samples,
            shadow_strength, lobe, intensity, t_max, normals, render_camera, background, preview,
            seed, no_clobber, quiet):
    """Relight IN under new lighting.

    \b
    IN = AVATAR.ply (3DGS Gaussians): per-Gaussian SH radiance transfer from
    --probe (paper Eq. 9-10): colour = γ · albedo · clip(S(n), 0, t_max), S the
    cosine-lobe (exponent q) weighted mean probe radiance around the normal n.
    With --dgsm and --receivers, the receivers' colours are multiplied by the
    shadow-map transmittance.  Writes the relit avatar PLY, or with --render
    an EXR view of receivers + avatar.

    IN = HAND.npz: the neural hand relighting (not available yet).

    \b
    Examples:
      relight relight avatar.ply --probe probe.json -o avatar-relit.ply
      relight relight avatar.ply --probe probe.json --dgsm shadows.exr \\
          --receivers room.ply --render cam.json -o view.exr --preview view.png
    """
    from relight_cli.errors import UsageProblem

    lower = input.lower()
    if lower.endswith(".ply"):
        return _relight_gaussians(**locals())
    if lower.endswith(".npz"):
        return _relight_hand(**locals())
    raise UsageProblem("IN must be a Gaussians .ply (or a hand .npz); cannot tell what this is",
                       input)


def _relight_gaussians(input, output, probe, dgsm, receivers, receivers_out, footprint, samples,
                       shadow_strength, lobe, intensity, t_max, normals, render_camera, background,
                       preview, seed, no_clobber, quiet, **_):
    import math
    import time

    import numpy as np

    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.gaussians_ply import FORMAT, VERSION, read_gaussians, write_gaussians
    from relight_cli.formats.sh_probe_json import read_probe
    from relight_cli.gaussians import transfer as TF
    from relight_cli.provenance import provenance

    # ---- usage checks before any work
    if probe is None:
        raise UsageProblem("Gaussian relighting needs --probe PROBE.json (make one with relight "
                           "sh-probe)")
    if dgsm is not None and receivers is None:
        raise UsageProblem("--dgsm shadows receivers: give --receivers SCENE.ply")
    if receivers_out is not None and receivers is None:
        raise UsageProblem("--receivers-out needs --receivers")
    if preview is not None and render_camera is None:
        raise UsageProblem("--preview needs --render")
    if not (lobe > 0 and math.isfinite(lobe)):
        raise UsageProblem(f"--lobe must be a positive finite number, got {lobe}")
    if not (intensity >= 0 and math.isfinite(intensity)):
        raise UsageProblem(f"--intensity must be a finite number ≥ 0, got {intensity}")
    if t_max is not None and not t_max > 0:
        raise UsageProblem(f"--t-max must be positive, got {t_max}")
    bg = parse_vector(background, 3, "--background")
    if render_camera is not None and not output.lower().endswith(".exr"):
        raise UsageProblem("with --render, -o is an EXR image (name it .exr)", output)
    if render_camera is None and not output.lower().endswith(".ply"):
        raise UsageProblem("-o is the relit Gaussians PLY (name it .ply), or use --render CAM "
                           "-o IMAGE.exr", output)
    for path in (output, receivers_out, preview):
        check_output(path, no_clobber)
    for path in (input, probe, dgsm, receivers, render_camera):
        if path is not None:
            check_input(path)

    start = time.perf_counter()
    avatar = read_gaussians(input)
    sh_probe = read_probe(probe)
    log(f"read {input}: {len(avatar)} Gaussians; probe degree {sh_probe.degree}", quiet)
    try:
        relit = TF.relight_gaussians(avatar, sh_probe.coefficients, q=lobe, intensity=intensity,
                                     t_max=math.inf if t_max is None else t_max,
                                     normal_method=normals)
    except ValueError as exc:  # e.g. --normals stored on a file without normals
        raise DataError(str(exc), input) from None

    scene = None
    if receivers is not None:
        scene = read_gaussians(receivers)
        log(f"read {receivers}: {len(scene)} receiver Gaussians", quiet)
    if dgsm is not None:
        shadow_map = _read_dgsm(dgsm)
        from relight_cli.gaussians.dgsm import sample_transmittance
        T = sample_transmittance(shadow_map, scene.means, scene.scales, scene.rotations,
                                 footprint=footprint, samples=samples, seed=seed)   # [L, M]
        factor = TF.shadow_factor(T, None, shadow_strength)
        scene = TF.attenuate(scene, factor)
        log(f"shadowed receivers: mean factor {factor.mean():.3f}, "
            f"{int((factor < 0.99).sum())} of {len(factor)} darkened", quiet)

    inputs = {"input": input, "probe": probe}
    if receivers:
        inputs["receivers"] = receivers
    if dgsm:
        inputs["dgsm"] = dgsm
    settings = {"lobe": lobe, "intensity": intensity, "t_max": t_max, "normals": normals,
                "footprint": footprint, "samples": samples, "seed": seed,
                "shadow_strength": shadow_strength}
    if receivers_out is not None:
        write_gaussians(receivers_out, scene, provenance(FORMAT, VERSION, inputs,
                                                         dict(settings, role="receivers")))
        log(f"wrote {receivers_out}", quiet)
    if render_camera is None:
        write_gaussians(output, relit, provenance(FORMAT, VERSION, inputs, settings))
        log(f"wrote {output} ({time.perf_counter() - start:.2f} s)", quiet)
        return

    from relight_cli.formats.camera import read_camera
    from relight_cli.formats.exr import write_exr
    from relight_cli.formats.gaussians_ply import concatenate
    from relight_cli.gaussians.splat import render

    camera = read_camera(render_camera)
    inputs["camera"] = render_camera
    everything = relit if scene is None else concatenate([scene, relit])
    image = render(everything, camera, background=bg)
    channels = {"R": image.image[..., 0], "G": image.image[..., 1], "B": image.image[..., 2],
                "A": image.alpha}
    write_exr(output, channels, provenance=provenance("relight/render", 1, inputs,
                                                      dict(settings, background=list(bg))))
    log(f"wrote {output} ({camera.width}x{camera.height}, {len(everything)} Gaussians, "
        f"{time.perf_counter() - start:.2f} s)", quiet)
    if preview is not None:
        from relight_cli.formats.image import write_preview
        write_preview(preview, image.image.astype(np.float32))
        log(f"wrote {preview}", quiet)


def _relight_hand(input, **_):
    """Hand mode (hand.npz + model + env map + camera → image): added by the hand relighting work."""
    from relight_cli.errors import UsageProblem
    raise UsageProblem("hand relighting is not available yet; IN must be a Gaussians .ply for now",
                       input)


def _read_dgsm(path: str):
    """The DGSM reader of formats/dgsm_exr.py (owned by the DGSM module)."""
    from relight_cli.errors import UsageProblem
    try:
        from relight_cli.formats import dgsm_exr
    except ImportError:
        raise UsageProblem("--dgsm is not available in this build (formats/dgsm_exr.py is "
                           "missing)", path) from None
    return dgsm_exr.read_dgsm(path)
