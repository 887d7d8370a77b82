"""``relight sh-probe``: fit an SH light probe to an environment map or a Gaussian scene."""

from __future__ import annotations

import click

from relight_cli.cli.tools import (FiniteFloat, SquareSize, check_input, check_output,
                                   colour_space_option, log, no_clobber_option, parse_vector, preview_option, progress,
                                   quiet_option)


@click.command("sh-probe", short_help="Fit an SH light probe to an env map or a Gaussian scene.")
@click.argument("input", metavar="IN")
@click.option("-o", "--output", required=True, help="Probe JSON ('-' for stdout).")
@click.option("--degree", default="auto", show_default=True,
              help="SH degree N (0-16), or 'auto': the smallest degree whose irradiance is within "
                   "--tolerance of a direct quadrature of IN and whose radiance rings no deeper "
                   "than --max-negativity (see formats/sh_probe_json.md); when no degree up to "
                   "--max-degree keeps both, nothing is written and the command exits 1 saying "
                   "so (maps with a sun or small bright lights need --window, or a looser "
                   "criterion, or a fixed degree).")
@click.option("--ridge", type=FiniteFloat(0), default=0.0, show_default=True,
              help="Ridge weight λ of the least-squares fit (paper Eq. 7).")
@click.option("--tolerance", type=FiniteFloat(0, 1, min_open=True, max_open=True),
              default=0.03, show_default=True,
              help="For --degree auto: allowed relative RMS irradiance error against a direct "
                   "quadrature of IN (over 1024 normals); at 0.03 Poly Haven HDRIs without "
                   "small bright lights take degree 2 (1-2.4 % error).")
@click.option("--max-negativity", type=FiniteFloat(0), default=2.0, show_default=True,
              help="For --degree auto: deepest negative radiance (ringing) allowed, in units of "
                   "the probe's mean radiance; 2 is the dip of a lone point light at degree 1-2.")
@click.option("--max-degree", type=click.IntRange(1, 16), default=8, show_default=True,
              help="For --degree auto: the highest degree tried.")
@click.option("--window", type=click.Choice(["none", "hanning", "lanczos"]), default="none",
              show_default=True,
              help="Deringing window applied to the fitted bands (Sloan, 'Stupid SH Tricks'), "
                   "width degree+1: hanning (1+cos(pi l/w))/2 or lanczos sinc(l/w). It damps "
                   "the negative lobes of a sun's probe (builtin:sky at degree 8: negativity "
                   "9.1 -> 0.53, negative area 48 % -> 15 %) but blurs, so the same irradiance "
                   "error needs a higher degree (sky: 3 % at degree 14 with hanning).")
@click.option("--at", "at", default=None, metavar="X,Y,Z",
              help="Probe position (metres, world) for a Gaussian scene IN (.ply).")
@click.option("--face-size", type=SquareSize(4, 1024), default=64, show_default=True,
              help="Cube-face size N (or NxN) rendered for a scene probe.")
@click.option("--near", type=FiniteFloat(0, min_open=True), default=0.01, show_default=True,
              help="Near plane (metres) of the scene probe's cube cameras.")
@click.option("--nonfinite", type=click.Choice(["error", "zero", "clamp"]), default="error",
              show_default=True, help="What to do with NaN/Inf env-map pixels.")
@preview_option("Also write the probe's radiance as a labelled lat-long PNG (beside the "
                "env map it was fitted to, on one exposure).")
@colour_space_option
@no_clobber_option
@quiet_option
def command(input, output, degree, ridge, tolerance, max_negativity, max_degree, window, at,
            face_size, near, nonfinite, preview, colour_space, no_clobber, quiet):
    """Fit radiance L(ω) ≈ Σ c_k Y_k(ω) by solid-angle-weighted ridge least squares.

    IN is an environment map (EXR lat-long or cube, .hdr, builtin:sky|studio|
    uniform|point), or a Gaussian scene PLY with --at X,Y,Z: the six 90° cube
    faces of the scene at that point are splatted on the CPU and fitted
    (paper Sec. 3.4).  The JSON holds the real orthonormal SH coefficients
    (3DGS convention), see formats/sh_probe_json.md.

    \b
    Examples:
      relight sh-probe venice_sunset_1k.hdr -o venice.json
      relight sh-probe stage.exr --degree 2 -o stage.json --preview stage.png
      relight sh-probe builtin:sky --window hanning --max-degree 16 -o sky.json
      relight sh-probe room.ply --at 0,1.2,0 -o room-probe.json
      relight sh-probe builtin:sky --degree 2 -o - | relight relight avatar.ply --probe - -o relit.ply
    """
    import time

    from relight_cli.formats.sh_probe_json import FORMAT, VERSION, ShProbe, write_probe
    from relight_cli.jobs import sh_probe as job
    from relight_cli.provenance import provenance

    # ---- options (usage errors, before any work)
    options = _options(input, output, degree, ridge, tolerance, max_negativity, max_degree, at,
                       face_size, near, preview, no_clobber, window)

    # ---- input (data errors), the job, the outputs
    start = time.perf_counter()
    if options.at is None and colour_space != "auto":
        from relight_cli.errors import UsageProblem
        raise UsageProblem("--colour-space is for a Gaussian scene IN (.ply); an env map is "
                           "linear radiance")
    source = _read(input, options.at is not None, nonfinite, quiet, colour_space)
    try:
        probe = job.fit(source, options, log=lambda message: log(message, quiet),
                        progress=lambda it: progress(it, total=6, desc="cube faces", quiet=quiet))
    except job.ProbePromiseBroken as broken:
        broken.path = broken.path or input
        raise
    settings = {"degree": degree, "ridge": ridge,
                **({"colour_space": colour_space} if options.at is not None
                   else {"nonfinite": nonfinite}), **probe.settings}
    write_probe(output, ShProbe(probe.coefficients, probe.degree, ridge, input, options.at,
                                probe.extra, provenance(FORMAT, VERSION, {"input": input},
                                                        settings)))
    if output != "-":
        log(f"wrote {output} (degree {probe.degree}, {len(probe.coefficients)} coefficients, "
            f"{time.perf_counter() - start:.2f} s)", quiet)
    if preview is not None:
        _write_preview(preview, probe, input, source, options.at, options.window, quiet)
        log(f"wrote {preview}", quiet)


def _options(input, output, degree, ridge, tolerance, max_negativity, max_degree, at, face_size,
             near, preview, no_clobber, window="none"):
    """The options' usage errors (exit 2), before any work: the job's ProbeOptions."""
    from relight_cli.errors import UsageProblem
    from relight_cli.jobs.sh_probe import ProbeOptions

    check_output(output, no_clobber, kind="json")
    check_output(preview, no_clobber, kind="png", what="--preview")
    if degree == "auto":
        fixed = None
    else:
        try:
            fixed = int(degree)
        except ValueError:
            raise UsageProblem(f"--degree must be an integer or 'auto', got {degree!r}") from None
        if not 0 <= fixed <= 16:
            raise UsageProblem(f"--degree must be in 0..16, got {fixed}")
    is_scene = input.lower().endswith(".ply")
    if is_scene and at is None:
        raise UsageProblem("a Gaussian scene needs the probe position: --at X,Y,Z")
    if at is not None and not is_scene:
        raise UsageProblem("--at is only for Gaussian scenes (.ply); IN looks like an env map")
    position = parse_vector(at, 3, "--at") if is_scene else None
    return ProbeOptions(fixed, ridge, tolerance, max_negativity, max_degree, position,
                        face_size, near, window)


def _read(input, is_scene: bool, nonfinite, quiet, colour_space="auto"):
    """IN: the Gaussian scene (a .ply) or the env map, logged."""
    if is_scene:
        from relight_cli.formats.gaussians_ply import read_gaussians
        scene = read_gaussians(check_input(input), colour_space=colour_space)
        log(f"read {input}: {len(scene)} Gaussians, SH degree {scene.sh_degree}, "
            f"{scene.source_colour_space} colours", quiet)
        return scene
    from relight_cli.cli.inputs import load_envmap
    env = load_envmap(input, nonfinite=nonfinite)
    log(f"read {input}: {env.layout} {env.width}x{env.height}", quiet)
    return env


def _write_preview(path, probe, input, source, position, window="none", quiet=False):
    """The probe's radiance as a labelled lat-long PNG beside what it was fitted to
    (a progress line: a large cube map's resampling takes seconds)."""
    from relight_cli.formats.image import write_png
    from relight_cli.preview import probe_sheet
    env = source
    with progress(total=4, desc="preview", quiet=quiet) as bar:
        if position is not None:   # what the probe was fitted to: the splatted cube faces
            from relight_cli.preview import samples_latlong
            env = samples_latlong(probe.samples.directions, probe.samples.radiance)
        image = probe_sheet(probe.coefficients, probe.degree, input, env, position,
                            window=window, step=bar.update)
        write_png(path, image)
        bar.update(1)
