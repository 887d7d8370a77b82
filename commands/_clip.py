"""``relight relight`` Gaussian mode over frames: a clip in one process.

Entered from commands/relight_gaussians.py when a run is a clip (``--frames``,
``--frame``, a moving IN/--object, ``--lights``, ``--probe scene``, ``--dgsm`` holding
``{frame}``, ``--video``).  The work is :mod:`relight_cli.jobs.gaussian_clip`; this module
checks the options, reads what is read once, and writes each frame's outputs and the
video."""

from __future__ import annotations

import click

from relight_cli.cli.tools import check_input, check_output, log

#: The frame rate of a clip whose sources do not declare one.
DEFAULT_FPS = 24.0


_CLIP_OPTIONS = [
    click.option("--frame", "frame", type=click.IntRange(0), default=None, metavar="K",
                 help="One frame of a moving IN/--object (a hand.npz's motion, a "
                      "'{frame}' PLY pattern or a relight/gaussian-sequence index) [default: its "
                      "first]."),
    click.option("--frames", "frames", default=None, metavar="all|A:B[:S]",
                 help="A clip in one process: every frame (all) or the frames A, A+S, … before "
                      "B (A:B[:S], a Python slice). Per frame the moving IN/--object are placed "
                      "(one placement for the clip), the shadow maps built (--lights) or read "
                      "(--dgsm holding {frame}), the probes refitted (--probe scene); -o, "
                      "--preview and --receivers-out are patterns holding {frame}."),
    click.option("--lights", "lights_spec", default=None, metavar="LIGHTS.json|auto:K",
                 help="Build the shadow maps in-process, per frame, from IN and --object over "
                      "--receivers (128x128 octahedral atlas, 64 bins over the receivers' "
                      "distances (dgsm-build --radial roi), ROI and culling) for these point "
                      "lights (a relight/lights JSON, or auto:K: K "
                      "lights estimated once from the scene, paper Sec. 3.1); instead of --dgsm."),
    click.option("--shadow-size", default=None, metavar="N|WxH",
                 help="With --lights: the in-process shadow maps' octahedral atlas, as "
                      "dgsm-build --size [default: 128]."),
    click.option("--probe-degree", type=click.IntRange(0, 8), default=None,
                 help="With --probe scene: the SH degree of the refitted probes, fixed for the "
                      "clip [default: 2]."),
    click.option("--video", default=None, metavar="CLIP.webp|CLIP.png",
                 help="With --frames and --camera: the clip as one animated WebP (lossy, "
                      "small; plays in browsers) or animated PNG (lossless), tone-mapped with "
                      "one exposure for every frame (the first frame's)."),
]


def clip_options(func):
    """The Gaussian mode's clip options (--frame, --frames, --lights, --shadow-size,
    --probe-degree, --video), in the order --help lists them."""
    for option in reversed(_CLIP_OPTIONS):
        func = option(func)
    return func


def clip(a, given: set) -> None:
    """The clip: usage checks, inputs read once, frames rendered and written as they
    come (one output transaction: all or nothing), then the video."""
    import time

    from relight_cli.errors import UsageProblem
    from relight_cli.gaussians.sequence import GaussianSource, clip_frames
    from relight_cli.jobs import gaussian_clip as GC
    from relight_cli.sequence import Outputs, check_frame

    start = time.perf_counter()
    bg = _usage(a, given)
    dgsm_options = _dgsm_options(a)        # its usage errors too, before any input is read
    check_frame(a.frame, a.frames)
    outputs = Outputs(a.frames, {"-o": (a.output, "exr" if a.camera else "ply"),
                                 "--preview": (a.preview, "png"),
                                 "--receivers-out": (a.receivers_out, "ply")})
    sources = [GaussianSource(spec, "IN" if j == 0 else "--object",
                              colour_space=getattr(a, "colour_space", "auto"))
               for j, spec in enumerate((a.input, *a.objects))]
    frames = clip_frames(sources, a.frames, a.frame)
    if outputs.sequence:
        outputs.check(frames, lambda path, kind, what: check_output(
            path, a.no_clobber, kind=kind, what=what))
    if a.video is not None:
        check_output(a.video, a.no_clobber, kind="video", what="--video")

    scene = _read_scene(a)
    view = None
    if a.camera is not None:
        from relight_cli.formats.camera import read_camera
        view = read_camera(check_input(a.camera, stdin="--camera"))
    probe = None
    if a.probe != "scene":
        from relight_cli.formats.sh_probe_json import read_probe
        probe = read_probe(check_input(a.probe, stdin="--probe"))
    options = GC.ClipOptions(gaussian_options(a), dgsm_options, _probe_options(a))
    lights = _lights(a, sources, frames, scene)
    shadow_maps = _shadow_maps(a, sources) if a.dgsm is not None else None
    for s in sources:
        log(f"read {s.spec}: " + (f"{len(s.frames)} frames ({s.kind})" if s.moves
                                  else f"{len(s.frame(frames[0]))} Gaussians"), a.quiet)
    say = _first_frame_log(a.quiet)
    made = GC.frames(sources, frames, scene, options, lights, probe, shadow_maps, view, bg,
                    names=[s.spec for s in sources], log=say)
    settings = _settings(a, sources, options, lights, bg)
    video = (_Video(a.video, _fps(sources), a.preview_exposure) if a.video is not None
             else None)

    def write(f):
        say.done = True
        paths = outputs.paths(f.frame)
        inputs = _inputs(a, sources, f.frame)
        frame_settings = dict(settings, frame=f.frame, **_frame_settings(f, options))
        _write_frame(a, paths, f, view, inputs, frame_settings, bg)
        if video is not None:
            video.add(f.relit.rgb)
        return sum(f.seconds.values()), f.seconds
    from relight_cli.sequence import write_sequence
    done = write_sequence(made, write, len(frames), "relight (frames)", a.quiet,
                          bar=outputs.sequence)
    if video is not None:
        video.write()
    stages = {}
    for _, seconds in done:
        for k, v in seconds.items():
            stages[k] = stages.get(k, 0.0) + v
    wall = time.perf_counter() - start
    cost = ", ".join(f"{k} {v / len(done):.2f}" for k, v in stages.items())
    what = (a.output if not outputs.sequence
            else f"{len(done)} frames to {a.output}")
    log(f"wrote {what} ({wall:.2f} s; per frame: {cost} s)", a.quiet)
    if a.video is not None:
        log(f"wrote {a.video}", a.quiet)


def _usage(a, given):
    """The clip's usage checks (exit 2), before any input is read: the background."""
    from relight_cli.cli.tools import parse_vector
    from relight_cli.errors import UsageProblem
    for wrong, message in (
            (a.shadow_matte is not None,
             "--shadow-matte renders one frame's matte: it does not take --frames, --frame, "
             "--lights, --probe scene, --video or a moving IN (build the frame's DGSM with "
             "dgsm-build --frames)"),
            (a.probe is None,
             "Gaussian relighting needs --probe PROBE.json, or --probe scene to refit it per "
             "frame from --receivers"),
            (a.probe == "scene" and a.receivers is None,
             "--probe scene fits each object's probe from the scene around it: give "
             "--receivers SCENE"),
            (a.probe_degree is not None and a.probe != "scene",
             "--probe-degree sets the degree of --probe scene's refitted probes"),
            (a.shadow_size is not None and a.lights_spec is None,
             "--shadow-size sets the atlas of the shadow maps --lights builds"),
            (a.lights_spec is not None and a.dgsm is not None,
             "--lights builds the shadow maps in-process; --dgsm reads them: give one"),
            (a.lights_spec is not None and a.receivers is None,
             "--lights builds shadow maps over receivers: give --receivers SCENE"),
            (a.dgsm is not None and a.receivers is None,
             "--dgsm shadows receivers: give --receivers SCENE.ply"),
            (a.dgsm is None and a.lights_spec is None and "shadow_strength" in given,
             "--shadow-strength only applies with shadows (--dgsm or --lights)"),
            (a.dgsm is None and a.lights_spec is None and "light_weights" in given,
             "--light-weights only applies with shadows (--dgsm or --lights)"),
            (a.direct_light and a.dgsm is None and a.lights_spec is None,
             "--direct-light takes its lights from the shadow maps (--dgsm or --lights)"),
            (a.self_shadow and a.dgsm is None and a.lights_spec is None,
             "--self-shadow looks the objects up in the shadow maps (--dgsm or --lights)"),
            (a.receivers_out is not None and a.receivers is None,
             "--receivers-out needs --receivers"),
            (a.preview is not None and a.camera is None,
             "--preview needs --camera (a rendered view)"),
            (a.preview_exposure is not None and a.preview is None and a.video is None,
             "--preview-exposure sets the tone mapping of --preview or --video: give one"),
            (a.video is not None and (a.camera is None or a.frames is None),
             "--video plays a clip's views: give --frames and --camera CAMERA.json")):
        if wrong:
            raise UsageProblem(message)
    if a.camera is not None and not a.output.lower().endswith(".exr"):
        raise UsageProblem("with --camera, -o is an EXR image (name it .exr)", a.output)
    if a.camera is None and not a.output.lower().endswith(".ply"):
        raise UsageProblem("-o is the relit Gaussians PLY (name it .ply), or use --camera CAM "
                           "-o IMAGE.exr", a.output)
    if a.frames is None:
        check_output(a.output, a.no_clobber)
        check_output(a.receivers_out, a.no_clobber, kind="ply", what="--receivers-out")
        check_output(a.preview, a.no_clobber, kind="png", what="--preview")
    return parse_vector(a.background, 3, "--background", minimum=0)


def gaussian_options(a):
    """The Gaussian mode's GaussianOptions (shared with commands/relight_gaussians.py)."""
    from relight_cli.jobs.relight_gaussians import GaussianOptions
    return GaussianOptions(lobe=a.lobe, intensity=a.intensity, t_max=a.t_max, normals=a.normals,
                           footprint=a.footprint, samples=a.samples, seed=a.seed,
                           shadow_strength=a.shadow_strength, light_weights=a.light_weights,
                           direct_light=a.direct_light, self_shadow=a.self_shadow)


def check_self_shadow(shadow_map, path) -> None:
    """--self-shadow needs a map whose tables cover the objects' own lookups (built by
    dgsm-build --self-shadow): one line naming the map otherwise."""
    from relight_cli.errors import DataError
    if not all(record.get("self_shadow") for record in shadow_map.roi):
        raise DataError("this shadow map was not built for self-shadowing (its tables do not "
                        "cover the objects' own lookups): build it with dgsm-build "
                        "--self-shadow", path)


def write_ply(path, gaussians, inputs, settings) -> None:
    """A Gaussians PLY with its provenance (shared with commands/relight_gaussians.py)."""
    from relight_cli.formats.gaussians_ply import FORMAT, VERSION, write_gaussians
    from relight_cli.provenance import provenance
    write_gaussians(path, gaussians, provenance(FORMAT, VERSION, inputs, settings))


def _dgsm_options(a):
    """dgsm-build's defaults for an in-process build (None: no build)."""
    if a.lights_spec is None:
        return None
    from relight_cli.cli.tools import parse_size
    from relight_cli.jobs.dgsm_build import DgsmOptions
    w, h = (128, 128) if a.shadow_size is None else parse_size(a.shadow_size, "--shadow-size",
                                                                  minimum=2, maximum=4096)
    return DgsmOptions(size=(h, w), footprint=a.footprint, samples=a.samples, seed=a.seed,
                       self_shadow=a.self_shadow, radial="roi")


def _probe_options(a):
    """sh-probe --at's options at a fixed degree (None: one probe read)."""
    if a.probe != "scene":
        return None
    from relight_cli.jobs.sh_probe import ProbeOptions
    return ProbeOptions(degree=2 if a.probe_degree is None else a.probe_degree)


def _read_scene(a):
    if a.receivers is None:
        return None
    from relight_cli.gaussians.sequence import _load
    scene = _load(check_input(a.receivers), getattr(a, "colour_space", "auto"))
    log(f"read {a.receivers}: {len(scene)} receiver Gaussians", a.quiet)
    return scene


def _lights(a, sources, frames, scene):
    """The in-process build's lights: read, or auto:K estimated once (None: no build)."""
    if a.lights_spec is None:
        return None
    from relight_cli.cli.inputs import parse_auto_lights
    from relight_cli.jobs.gaussian_clip import clip_lights
    k = parse_auto_lights(a.lights_spec)
    if k is None:
        from relight_cli.formats.lights_json import read_lights
        return read_lights(check_input(a.lights_spec, stdin="--lights"))
    lights = clip_lights(k, sources, scene, spec=a.lights_spec)
    log(f"{len(lights)} light(s) estimated from {a.receivers} (once for the clip)", a.quiet)
    return lights


def _shadow_maps(a, sources):
    """frame → DGSM: one file for every frame, or the frame's file of a {frame} pattern
    (each checked against the objects as the single-frame mode does)."""
    from relight_cli.errors import DataError
    from relight_cli.formats.dgsm_exr import read_dgsm
    from relight_cli.gaussians.sequence import is_pattern
    from relight_cli.sequence import OutputPattern

    pattern = OutputPattern(a.dgsm, "--dgsm", ("frame",)) if is_pattern(a.dgsm) else None

    def checked(shadow_map, path):
        if a.self_shadow:
            check_self_shadow(shadow_map, path)
        if shadow_map.groups is not None and len(shadow_map.groups) != len(sources):
            raise DataError(f"the shadow map has {len(shadow_map.groups)} occluder groups "
                            f"({', '.join(shadow_map.group_names)}) but {len(sources)} "
                            f"object(s) were given (IN + --object, in dgsm-build's order)", path)
        return shadow_map

    if pattern is None:
        fixed = checked(read_dgsm(check_input(a.dgsm)), a.dgsm)
        return lambda frame: fixed

    def at(frame):
        path = pattern.format(frame)
        return checked(read_dgsm(check_input(path)), path)
    return at


def _fps(sources) -> float:
    """The clip's frame rate: the first source that declares one, else 24."""
    return next((s.fps for s in sources if s.fps), DEFAULT_FPS)


def _settings(a, sources, options, lights, bg) -> dict:
    """The provenance settings every frame shares."""
    from dataclasses import asdict
    from relight_cli.jobs.relight_gaussians import GaussianOptions
    settings = {k: v for k, v in asdict(options.gaussian).items()
                if k in GaussianOptions.__dataclass_fields__}
    settings["objects"] = [s.spec for s in sources]
    if options.dgsm is not None:
        from relight_cli.jobs.dgsm_build import _settings as dgsm_settings
        from relight_cli.gaussians import transmittance as TR
        settings["dgsm_build"] = dgsm_settings(options.dgsm,
                                               TR.canonical_mapping(options.dgsm.mapping))
        settings["lights"] = a.lights_spec
        if a.lights_spec.startswith("auto"):
            settings["estimated_lights"] = [[float(v) for v in p] for p in lights.positions]
    if options.probe is not None:
        settings["probe"] = {"refit": "scene", "degree": options.probe.degree,
                             "face_size": options.probe.face_size, "near": options.probe.near}
    if a.camera is not None:
        settings["background"] = list(bg)
    return settings


def _frame_settings(f, options) -> dict:
    """What one frame's provenance adds: its probes' positions (refitted) and the
    relight job's own settings (the shadow mapping used)."""
    extra = {k: v for k, v in f.relit.settings.items()
             if k in ("dgsm_mapping", "dgsm_kappa", "light_weights", "shadow_strength")}
    if options.probe is not None:
        extra["probe_at"] = [[float(v) for v in p] for p in f.probe_positions]
    return extra


def _inputs(a, sources, frame) -> dict:
    """The provenance roles of one frame's input files."""
    from relight_cli.gaussians.sequence import is_pattern
    inputs = {}
    for j, s in enumerate(sources):
        role = "input" if j == 0 else f"object{j - 1}"
        if s.kind == "static" and s.source.startswith("builtin:"):
            inputs[role] = s.source
        else:
            inputs[role] = s.files(frame)[0]
    if a.probe != "scene":
        inputs["probe"] = a.probe
    if a.receivers is not None:
        inputs["receivers"] = a.receivers
    if a.dgsm is not None:
        inputs["dgsm"] = a.dgsm.format(frame=frame) if is_pattern(a.dgsm) else a.dgsm
    if a.lights_spec is not None and not a.lights_spec.startswith("auto"):
        inputs["lights"] = a.lights_spec
    if a.camera is not None:
        inputs["camera"] = a.camera
    return inputs


def _write_frame(a, paths, f, view, inputs, settings, bg) -> None:
    """One frame's -o (EXR view or PLY), --preview and --receivers-out."""
    relit = f.relit
    if paths.get("--receivers-out") is not None:
        write_ply(paths["--receivers-out"], relit.receivers,
                   {k: v for k, v in inputs.items() if k != "camera"},
                   dict(settings, role="receivers"))
    if view is None:
        write_ply(paths["-o"], relit.objects, {k: v for k, v in inputs.items() if k != "camera"},
                   settings)
        return
    from relight_cli.formats.exr import write_exr
    from relight_cli.provenance import provenance
    write_exr(paths["-o"], relit.channels, attributes={"relight.camera": view.to_json()},
              provenance=provenance("relight/render", 1, inputs, settings), camera=view)
    if paths.get("--preview") is not None:
        from relight_cli.preview import write_preview
        write_preview(paths["--preview"], relit.rgb, exposure=a.preview_exposure)


class _first_frame_log:
    """The relight job's log lines, said for the first frame only (a clip's later frames
    would repeat them)."""

    def __init__(self, quiet: bool):
        self.quiet, self.done = quiet, False

    def __call__(self, message: str) -> None:
        if not self.done:
            log(message, self.quiet)


class _Video:
    """The clip's frames tone-mapped with one exposure (the first frame's Reinhard scale,
    so the light's change between frames shows and nothing flickers), kept as 8-bit
    frames and written at the end as one animated WebP or PNG."""

    def __init__(self, path: str, fps: float, exposure: float | None = None):
        self.path, self.fps, self.frames, self.exposure = path, fps, [], exposure

    def add(self, rgb) -> None:
        import numpy as np

        from relight_cli.preview import reinhard_scale
        from relight_cli.tonemap import tonemap
        if self.exposure is None:
            self.exposure = reinhard_scale(rgb)
        display = tonemap(rgb, self.exposure)
        self.frames.append(np.clip(np.rint(display * 255.0), 0, 255).astype(np.uint8))

    def write(self) -> None:
        from relight_cli.formats.image import write_animation
        write_animation(self.path, self.frames, self.fps)
