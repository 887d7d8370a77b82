"""``relight dgsm-build --frames``: one Deep Gaussian Shadow Map per frame of moving
occluders, in one process (the DGSM paper rebuilds its maps every frame, Sec. 3.2 and
ablation D).

The receivers are read once and the lights read or estimated once (auto:K from the
recording's first frame, so a frame built alone equals the same frame of the whole run);
per frame the occluders are placed (one placement for the clip, relight_cli.gaussians.
sequence) and the map built with the receiver ROI and culling.  ``-o``,
``--occluders-out`` and ``--preview`` are patterns holding ``{frame}``;
``--receivers-out`` and ``--lights-out`` are written once.  ``relight relight --dgsm
'PATTERN'`` reads the maps back frame by frame.
"""

from __future__ import annotations

from relight_cli.cli.tools import check_input, check_output, log


def build_frames(p: dict, options, offset) -> None:
    """The run: ``p`` the command's parameters, ``options`` its DgsmOptions (preview set),
    ``offset`` its --translate or None."""
    import time

    from relight_cli.gaussians.sequence import GaussianSource, clip_frames
    from relight_cli.jobs.dgsm_build import build
    from relight_cli.jobs.gaussian_clip import clip_lights
    from relight_cli.sequence import Outputs, check_frame, write_sequence

    start = time.perf_counter()
    check_frame(p["frame"], p["frames"])
    outputs = Outputs(p["frames"], {"-o": (p["output"], "exr"),
                                    "--occluders-out": (p["occluders_out"], "ply"),
                                    "--preview": (p["preview"], "png")})
    if not outputs.sequence:
        check_output(p["output"], p["no_clobber"], kind="exr")
        check_output(p["occluders_out"], p["no_clobber"], kind="ply", what="--occluders-out")
        check_output(p["preview"], p["no_clobber"], kind="png", what="--preview")
    check_output(p["lights_out"], p["no_clobber"], kind="json", what="--lights-out")
    check_output(p["receivers_out"], p["no_clobber"], kind="ply", what="--receivers-out")
    colour_space = p.get("colour_space", "auto")
    sources = [GaussianSource(spec, "OCCLUDER", colour_space=colour_space, offset=offset)
               for spec in p["occluders"]]
    frames = clip_frames(sources, p["frames"], p["frame"])
    if outputs.sequence:
        outputs.check(frames, lambda path, kind, what: check_output(
            path, p["no_clobber"], kind=kind, what=what))

    scene = None
    if p["receivers"] is not None:
        from relight_cli.gaussians.sequence import _load
        scene = _load(check_input(p["receivers"]), colour_space)
    if p["preview_camera"] is not None:
        from relight_cli.formats.camera import read_camera
        options.camera = read_camera(check_input(p["preview_camera"]))
    auto_k = _auto(p["lights_spec"])
    if auto_k is None:
        from relight_cli.formats.lights_json import read_lights
        lights = read_lights(check_input(p["lights_spec"], stdin="--lights"))
    else:
        lights = clip_lights(auto_k, sources, scene, p["estimator"], p["lights_spec"])
    if scene is not None:
        log(f"read {p['receivers']}: {len(scene)} receiver Gaussians", p["quiet"])
    for s in sources:
        log(f"read {s.spec}: " + (f"{len(s.frames)} frames ({s.kind})" if s.moves
                                  else f"{len(s.frame(frames[0]))} Gaussians (static)"),
            p["quiet"])
    log(f"{len(lights)} light(s)" + (" (estimated once, from the recording's first frame)"
                                     if auto_k is not None else ""), p["quiet"])

    names = list(p["occluders"])
    settings_base = {"lights": p["lights_spec"], "half": p["half"],
                     "translate": p["translate"],
                     "estimator": p["estimator"] if auto_k is not None else None,
                     "occluders": names, "colour_space": colour_space}
    first = [True]

    def say(message):
        if first[0]:
            log(message, p["quiet"])

    def made():
        for k in frames:
            objects = [s.frame(k) for s in sources]
            yield k, build(objects, lights, options, scene, names=names,
                           receivers_name=p["receivers"], lights_name=p["lights_spec"],
                           log=say, quiet=True)

    def write(item):
        k, result = item
        first[0] = False
        paths = outputs.paths(k)
        inputs = _inputs(p, sources, k, auto_k)
        settings = {**result.settings, **settings_base, "frame": k}
        _write_frame(result, inputs, settings, paths, p["half"])
        return None

    write_sequence(made(), write, len(frames), "dgsm-build (frames)", p["quiet"],
                   bar=outputs.sequence)
    _write_once(p, scene, lights, auto_k, frames, sources)
    wall = time.perf_counter() - start
    what = p["output"] if not outputs.sequence else f"{len(frames)} frames to {p['output']}"
    log(f"wrote {what} ({wall:.2f} s, {wall / len(frames):.2f} s per frame)", p["quiet"])


def _auto(spec: str):
    from relight_cli.cli.inputs import parse_auto_lights
    return parse_auto_lights(spec)


def _inputs(p, sources, frame, auto_k) -> dict:
    """The provenance roles of one frame's inputs (the occluders' files of that frame)."""
    files = [s.source if s.source.startswith("builtin:") else s.files(frame)[0]
             for s in sources]
    inputs = {"occluders": files[0]} if len(files) == 1 else {
        f"occluder{j}": f for j, f in enumerate(files)}
    if p["receivers"] is not None:
        inputs["receivers"] = p["receivers"]
    if auto_k is None:
        inputs["lights"] = p["lights_spec"]
    return inputs


def _write_frame(result, inputs, settings, paths, half) -> None:
    """One frame's DGSM, --occluders-out PLY and --preview."""
    from relight_cli.formats.dgsm_exr import FORMAT, VERSION, write_dgsm
    from relight_cli.provenance import provenance
    write_dgsm(paths["-o"], result.shadow_map, provenance(FORMAT, VERSION, inputs, settings),
               half=half)
    if paths.get("--occluders-out") is not None:
        from relight_cli.formats.gaussians_ply import FORMAT as GFORMAT
        from relight_cli.formats.gaussians_ply import VERSION as GVERSION
        from relight_cli.formats.gaussians_ply import write_gaussians
        write_gaussians(paths["--occluders-out"], result.occluders, provenance(
            GFORMAT, GVERSION, inputs, {"translate": settings["translate"],
                                        "occluders": settings["occluders"],
                                        "frame": settings["frame"]}))
    if paths.get("--preview") is not None:
        from relight_cli.formats.image import write_png
        write_png(paths["--preview"], result.preview)


def _write_once(p, scene, lights, auto_k, frames, sources) -> None:
    """--receivers-out and --lights-out: the same for every frame, written once."""
    from relight_cli.provenance import provenance
    if p["receivers_out"] is not None and scene is not None:
        from relight_cli.formats.gaussians_ply import FORMAT, VERSION, write_gaussians
        write_gaussians(p["receivers_out"], scene, provenance(
            FORMAT, VERSION, {"receivers": p["receivers"]}, {}))
    if p["lights_out"] is not None:
        from relight_cli.formats.lights_json import FORMAT, VERSION, Lights, write_lights
        inputs = _inputs(p, sources, frames[0], auto_k)
        write_lights(p["lights_out"], Lights(lights.positions, lights.colors,
                                             lights.intensities, lights.names, lights.extra),
                     provenance(FORMAT, VERSION, inputs,
                                {"lights": p["lights_spec"], "estimator": p["estimator"]}))
