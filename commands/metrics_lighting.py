"""``relight metrics lighting``: PAA-Y, APF-Y, NCM-ab of a Gaussian avatar in a Gaussian
scene (DGSM paper Sec. 4.1; :mod:`relight_cli.jobs.metrics`)."""

from __future__ import annotations

import click

from relight_cli.cli import metrics as metrics_io
from relight_cli.cli.tools import (FiniteFloat, check_input, check_output, log, no_clobber_option,
                                   quiet_option, seed_option)

@click.command("lighting", short_help="PAA-Y, APF-Y, NCM-ab of a Gaussian avatar in a Gaussian scene.")
@click.option("--scene", required=True, help="Scene Gaussians PLY (the environment).")
@click.option("--avatar", "avatars", required=True, multiple=True,
              help="Original avatar Gaussians PLY; repeat for several frames.")
@click.option("--relit", "relits", multiple=True,
              help="Relit avatar PLY per frame (same count as --avatar).")
@click.option("--radius", type=FiniteFloat(0, min_open=True), default=1.5, show_default=True,
              help="Scene Gaussians within this distance (metres) of the avatar centre light it.")
@click.option("--neighbours", type=int, default=16, show_default=True,
              help="Neighbours for the local-PCA pseudo-normals.")
@click.option("--normals", "normal_source", type=click.Choice(["pca", "ply"]), default="pca",
              show_default=True, help="Pseudo-normals by weighted local PCA, or the PLY's nx ny nz.")
@click.option("--max-points", type=int, default=512, show_default=True,
              help="Points per side of the seeded subsamples on which the 2-D Wasserstein "
                   "distance of large sets is solved exactly.")
@metrics_io.output_option
@seed_option
@no_clobber_option
@quiet_option
def command(scene, avatars, relits, radius, neighbours, normal_source, max_points, output,
                     seed, no_clobber, quiet):
    """Lighting consistency of a Gaussian avatar with the scene around it (DGSM paper, Sec. 4.1).

    The paper's metrics: luminance factorized as Y ≈ α·E(n; c), E order-3 SH
    (16 coefficients, |c|₂ = 1 fixing the scale), α ≥ 0 per Gaussian, Huber
    loss and 5 % trimming, for the scene within --radius and for the avatar.
    paa_y = |c_avatar − c_scene|₁; apf_y = mean |Y − (s·E(n; c_scene) + b)|
    after a per-frame affine fit; ncm_ab = exact 1-Wasserstein distance of the
    avatar's and the scene's CIE-Lab (a*, b*) point sets (exact on seeded
    subsamples of --max-points per side for large sets; the JSON says which).
    This toolkit's earlier variants are reported beside them as paa_angle
    (degrees between dominant light directions), apf_rms and ncm_ab_weighted
    (formats/metrics_json.md).  Lower is better for all.  Reports orig, relit
    and relit − orig (delta), averaged over frames.

    \b
    Example:
      relight metrics lighting --scene room.ply --avatar avatar.ply --relit relit.ply \\
          --radius 1.5 -o lighting.json
    """
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.gaussians_ply import read_gaussians
    from relight_cli.formats.metrics_json import FORMAT, VERSION, write_metrics
    from relight_cli.jobs.metrics import LightingOptions, lighting
    from relight_cli.provenance import provenance

    check_output(output, no_clobber, kind="json")
    if relits and len(relits) != len(avatars):
        raise UsageProblem(f"{len(relits)} --relit file(s) for {len(avatars)} --avatar frame(s)")
    if neighbours < 4:
        raise UsageProblem("--neighbours must be at least 4")
    if max_points < 16:
        raise UsageProblem("--max-points must be at least 16")
    scene_g = read_gaussians(check_input(scene))
    frames = []
    for path in list(avatars) + list(relits):
        g = read_gaussians(check_input(path))
        if normal_source == "ply" and g.normals is None:
            raise DataError("PLY has no normals (nx ny nz are absent or all zero); "
                            "use --normals pca", path)
        frames.append(g)
    orig, relit = frames[:len(avatars)], (frames[len(avatars):] or None)
    for path, before, after in zip(relits, orig, relit or []):
        if len(after) != len(before):  # a relit avatar is the same Gaussians, recoloured
            raise DataError(f"has {len(after)} Gaussians, its --avatar has {len(before)}", path)
    options = LightingOptions(radius=radius, neighbours=neighbours,
                              ply_normals=normal_source == "ply", max_points=max_points, seed=seed)
    try:
        scores = lighting(scene_g, orig, relit, options)
    except ValueError as exc:
        raise DataError(str(exc), avatars[0] if "avatar" in str(exc) else scene) from None
    inputs = {"scene": scene}
    for i, path in enumerate(avatars):
        inputs[f"avatar:{i}"] = path
    for i, path in enumerate(relits):
        inputs[f"relit:{i}"] = path
    write_metrics(output, scores.record(provenance(FORMAT, VERSION, inputs, scores.settings)))
    log(f"{len(avatars)} frame(s) scored", quiet)
