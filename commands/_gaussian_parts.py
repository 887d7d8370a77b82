"""Pieces of ``relight relight AVATAR.ply`` (commands/relight_gaussians.py): the lighting
in IN's frame (``--probe``/ENV, ``--up``), IN loaded for the scene and for writing back in
its own coordinates (``--coordinates``), the receivers-only shadow matte (``--shadow-matte``,
paper Sec. 4.2) and the EXR view's reading and writing.  Each takes the mode's parsed
options ``a`` (commands/relight_gaussians.Run)."""

from __future__ import annotations

from relight_cli.cli.tools import log, parse_vector
from relight_cli.commands._clip import gaussian_options


def lighting(a, log_line):
    """The SH probe lighting IN: --probe read, or ENV's probe fitted (jobs.relight_gaussians.
    env_probe); turned into IN's frame by --up.  (probe, settings it adds)."""
    from dataclasses import replace

    from relight_cli.jobs import relight_gaussians as G
    settings = {}
    if a.env is not None:
        from relight_cli.cli.inputs import load_envmap
        env = load_envmap(a.env)
        log_line(f"read {a.env}: {env.layout} {env.width}x{env.height}")
        probe = G.env_probe(env, a.lobe, a.env, log=log_line)
        settings["env_probe_degree"] = probe.degree
    else:
        from relight_cli.formats.sh_probe_json import read_probe
        probe = read_probe(a.probe)
    if a.up is not None:
        probe = replace(probe, coefficients=G.lighting_in_frame(probe.coefficients,
                                                                upright(a.up)))
        settings["up"] = a.up
    return probe, settings


def upright(text: str):
    """--up's rotation taking IN's up axis to +Y (a usage error for a bad value)."""
    from relight_cli.errors import UsageProblem
    from relight_cli.jobs import relight_gaussians as G
    up = text if "," not in text else parse_vector(text, 3, "--up")
    try:
        return G.upright_rotation(up)
    except ValueError as exc:
        raise UsageProblem(f"--up: {exc}") from None


def coordinates(a) -> str:
    """The relit PLY's frame: --coordinates, else source for IN alone, scene with --object."""
    return a.coordinates or ("scene" if a.objects else "source")


def load_in(a, source, placement, spec):
    """IN placed for the scene, and (when its PLY is written back in its own frame and the
    placement moves it) IN as read, less what the placement prunes, with the similarity
    that placed it: (placed, unplaced or None, similarity or None)."""
    from relight_cli.cli.inputs import load_placed
    from relight_cli.errors import DataError
    from relight_cli.gaussians import placement as PL
    if a.camera is not None or coordinates(a) != "source" or placement.is_identity():
        return load_placed(source, placement, spec, colour_space=a.colour_space), None, None
    unplaced = load_placed(source, PL.Placement(frame=placement.frame), spec,
                           colour_space=a.colour_space)
    try:
        similarity = PL.resolve(placement, unplaced)
        placed = PL.place(unplaced, placement)
        kept = PL.prune(unplaced, placement)       # what crop/min-opacity/max-scale keep
    except ValueError as exc:
        raise DataError(f"cannot place it: {exc}", spec) from None
    return placed, kept, similarity


def shadow_matte(a, specs, parsed, bg, start) -> None:
    """The receivers-only shadow matte of the paper's Sec. 4.2 (``--shadow-matte``)."""
    import time

    from relight_cli.errors import DataError
    from relight_cli.gaussians.from_mesh import load_gaussians
    from relight_cli.jobs import relight_gaussians as G

    shadow_map = read_dgsm(a.dgsm)
    scene = load_gaussians(a.receivers, colour_space=a.colour_space)
    view = read_view(a.camera)
    meshes = None
    if a.shadow_matte == "mesh":
        from relight_cli.gaussians import shadow_matte as SM
        meshes = []
        for spec, (source, placement) in zip(specs, parsed):
            try:
                meshes.append(SM.load_placed_mesh(source, placement))
            except ValueError as exc:
                raise DataError(str(exc), spec) from None
    options = gaussian_options(a)
    options.light_weights = a.light_weights or "intensity"
    matte = G.shadow_matte(a.shadow_matte, scene, shadow_map, view, options, meshes, bg,
                           log=lambda m: log(m, a.quiet), quiet=a.quiet)
    write_view(a, matte.channels, matte.rgb, view, gaussian_inputs(a, parsed, camera=True),
                dict(matte.settings, objects=specs, colour_space=a.colour_space),
                {"relight.matte": f"shadow strength ({a.shadow_matte})"})
    log(f"wrote {a.output} (shadow matte, {a.shadow_matte}: "
        f"{int((matte.strength > 0.1).sum())} of {len(matte.strength)} receivers > 0.1, "
        f"{time.perf_counter() - start:.2f} s)", a.quiet)


def write_view(a, channels, rgb, view, inputs, settings, attributes) -> None:
    """A rendered Gaussian view: -o's EXR (R, G, B, A) and the --preview PNG."""
    from relight_cli.formats.exr import write_exr
    from relight_cli.provenance import provenance
    write_exr(a.output, channels, attributes={**attributes, "relight.camera": view.to_json()},
              provenance=provenance("relight/render", 1, inputs, settings), camera=view)
    if a.preview is not None:
        from relight_cli.preview import write_preview
        write_preview(a.preview, rgb, exposure=a.preview_exposure)


def read_view(path):
    """The camera of --camera (None without one)."""
    if path is None:
        return None
    from relight_cli.formats.camera import read_camera
    return read_camera(path)


def read_dgsm(path: str):
    """The DGSM of --dgsm (formats/dgsm_exr.py)."""
    from relight_cli.formats.dgsm_exr import read_dgsm
    return read_dgsm(path)


def gaussian_inputs(a, parsed, camera: bool) -> dict:
    """The provenance roles of the Gaussian mode's input files."""
    inputs = {"input": parsed[0][0]}
    if a.shadow_matte is None:
        inputs.update({"env": a.env} if a.env is not None else {"probe": a.probe})
    inputs.update({f"object{j}": source for j, (source, _) in enumerate(parsed[1:])})
    inputs.update({role: path for role, path in (("receivers", a.receivers), ("dgsm", a.dgsm))
                   if path})
    if camera:
        inputs["camera"] = a.camera
    return inputs
