"""``relight envmap``: convert, resample, rotate and inspect environment maps."""

from __future__ import annotations

import click

from relight_cli.cli.tools import (FiniteFloat, check_output, dumps_json, log, no_clobber_option,
                                   parse_size, preview_option, quiet_option)


@click.command("envmap", short_help="Convert, resample, rotate and inspect environment maps.")
@click.argument("input", metavar="IN")
@click.option("-o", "--output",
              help="Output EXR (lat-long or cube, OpenEXR's envmap convention); with --info "
                   "and no EXR wanted, the JSON statistics (FILE.json, or '-' for stdout).")
@click.option("--to", "layout", type=click.Choice(["latlong", "cube"]), default=None,
              help="Output layout (default: the input's).")
@click.option("--size", default=None,
              help="Lat-long WxH (width first, e.g. 32x16), or cube face size N. Default: "
                   "input size (cube→lat-long: 4N×2N; lat-long→cube: H/2).")
@click.option("--rotate-y", "rotate_y", type=FiniteFloat(), default=0.0, show_default=True,
              help="Rotate the environment by DEG about +Y (content at +Z moves towards +X).")
@preview_option("Also write a tone-mapped PNG preview (a cube map as a labelled cross).")
@click.option("--info", "show_info", is_flag=True,
              help="Print JSON statistics (size, layout, min/max/mean, power ∫L dω, "
                   "dominant direction) to stdout, or to -o FILE.json (or -o -) instead of "
                   "an EXR.")
@click.option("--nonfinite", type=click.Choice(["error", "zero", "clamp"]), default="error",
              show_default=True, help="What to do with NaN/Inf pixels in the input.")
@click.option("--negative", type=click.Choice(["error", "clamp"]), default="error",
              show_default=True,
              help="What to do with negative radiance in the input (a filtered or "
                   "reconstructed map's undershoot): refuse it, naming how many pixels and "
                   "how deep, or clamp it to 0 (the power grows by what was cut).")
@click.option("--half", is_flag=True, help="Store 16-bit half floats (default float32).")
@no_clobber_option
@quiet_option
def command(input, output, layout, size, rotate_y, preview, show_info, nonfinite, negative,
            half, no_clobber, quiet):
    """Read IN (EXR lat-long or cube, Radiance .hdr, any OpenImageIO format, or
    builtin:sky|studio|uniform|point) and write it as an EXR environment map.

    Resampling is area-weighted over exact texel solid angles, so the power
    ∫L dω is preserved (exactly for lat-long→lat-long) and a tiny bright source
    is neither lost nor smeared.

    \b
    Examples:
      relight envmap builtin:sky --to latlong --size 32x16 -o sky16.exr
      relight envmap StageEnvCube.exr --to latlong -o stage.exr --preview stage.png
      relight envmap stage.exr --info
      relight envmap stage.exr --info -o - | jq .power
      relight envmap Desk.exr --negative clamp -o desk.exr
    """
    from relight_cli.cli.inputs import load_envmap
    from relight_cli.jobs import envmap as job

    # ---- options (usage errors, before any work)
    options, exr_out, info_out = _options(output, layout, size, rotate_y, preview, show_info,
                                          no_clobber, negative)

    # ---- input (data errors), the job, the outputs
    env = load_envmap(input, nonfinite=nonfinite,
                      negative="keep" if negative == "clamp" else "error")
    log(f"read {input}: {env.layout} {env.width}x{env.height}", quiet)
    done = job.convert(env, options, log=lambda message: log(message, quiet))
    _write(done, input, exr_out, preview, info_out, nonfinite, half, quiet)


def _options(output, layout, size, rotate_y, preview, show_info, no_clobber, negative):
    """The options' usage errors (exit 2), before any work, every output checked: (the
    job's EnvmapOptions, the EXR output or None, the --info JSON's path, '-' or None)."""
    from relight_cli.errors import UsageProblem
    from relight_cli.jobs.envmap import EnvmapOptions

    if output is None and preview is None and not show_info:
        raise UsageProblem("nothing to do: give -o OUT, --preview PNG or --info")
    info_to_file = show_info and output is not None and (output == "-"
                                                         or output.lower().endswith(".json"))
    exr_out = None if (output is None or info_to_file) else output
    if exr_out == "-":
        raise UsageProblem("EXR output cannot go to stdout; give a file name (or --info -o - "
                           "for the JSON statistics)")
    check_output(exr_out, no_clobber, kind="exr")
    check_output(preview, no_clobber, kind="png", what="--preview")
    if info_to_file:
        check_output(output, no_clobber, kind="json")

    # Validate every option before reading anything (usage errors exit 2 fast).
    requested = None
    if size is not None:
        w, h = parse_size(size)
        if layout == "cube":
            if "x" in size.lower():
                raise UsageProblem("--size for a cube map is one face size N, e.g. --size 64")
            requested = (w, 6 * w)
        else:
            if "x" not in size.lower():
                raise UsageProblem(f"--size for a lat-long map is WxH (width first, e.g. "
                                   f"{2 * w}x{w}), got {size!r}")
            if w < 2 or h < 2:
                raise UsageProblem("lat-long maps need at least 2x2 texels")
            requested = (w, h)
    info_out = None if not show_info else output if info_to_file else "-"
    return EnvmapOptions(layout, requested, rotate_y, negative), exr_out, info_out


def _write(done, input, exr_out, preview, info_out, nonfinite, half, quiet):
    """The converted map's outputs: the EXR, the preview, the --info JSON."""
    from relight_cli.formats.envmap import FORMAT, VERSION, write_envmap
    from relight_cli.provenance import provenance

    result = done.env
    if exr_out is not None:
        prov = provenance(FORMAT, VERSION, {"input": input},
                          {**done.settings, "nonfinite": nonfinite, "half": half})
        write_envmap(exr_out, result, provenance=prov, half=half,
                     attributes={"relight.power": done.stats["power"]})
        log(f"wrote {exr_out}", quiet)
    if preview is not None:
        if result.layout == "cube":   # six faces unfolded, named, continuous across edges
            from relight_cli.formats.image import write_png
            from relight_cli.preview import cross_sheet
            write_png(preview, cross_sheet(result, f"envmap {input}" + (f" -> {exr_out}"
                                                                        if exr_out else "")))
        else:
            from relight_cli.preview import write_preview
            write_preview(preview, result.radiance,
                          label=f"lat-long map {result.width}x{result.height}, radiance",
                          note="+Y up, +Z in the middle",
                          title=f"envmap {input}" + (f" -> {exr_out}" if exr_out else ""))
        log(f"wrote {preview}", quiet)
    if info_out is not None:
        from relight_cli.fileio import write_text_atomic
        payload = dict(done.stats)
        payload["source"] = input
        write_text_atomic(info_out, dumps_json(payload))
