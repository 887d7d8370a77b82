"""``relight camera``: make cameras (look-at, orbit rings, a dome) or import them
(COLMAP text models, nerfstudio transforms.json, a render's EXR header) as
``relight/camera`` JSON (formats/camera.md)."""

from __future__ import annotations

import click

from relight_cli.cli.tools import (FiniteFloat, check_output, log, no_clobber_option, parse_vector,
                                   quiet_option)


@click.command("camera", short_help="Make cameras (look-at, orbit, dome) or import them (COLMAP, nerfstudio).")
@click.option("-o", "--output", default="-", metavar="FILE.json|-",
              help="Camera JSON [default: '-', stdout].")
@click.option("--eye", default=None, metavar="X,Y,Z",
              help="Look-at: the camera centre (metres, world).")
@click.option("--target", default=None, metavar="X,Y,Z",
              help="What the camera (or every camera of a rig) looks at [default: 0,0,0].")
@click.option("--up", default=None, metavar="X,Y,Z",
              help="Look-at: the world direction that points up in the image [default: 0,1,0]; "
                   "parallel to the view direction is an error.")
@click.option("--fov", type=FiniteFloat(0, 180, min_open=True, max_open=True), default=None,
              help="Vertical field of view in degrees, top edge to bottom edge [default: 40].")
@click.option("--size", default=None, metavar="WxH",
              help="Image size, width x height [default: 256x256].")
@click.option("--orbit", type=click.IntRange(1, 100000), default=None, metavar="N",
              help="A rig: N cameras on a ring around --target at --radius, evenly spaced in "
                   "azimuth, one ring per --elevation.")
@click.option("--dome", type=click.IntRange(1, 100000), default=None, metavar="N",
              help="A rig: N cameras spread evenly (Fibonacci lattice) over the sphere of "
                   "--radius above --elevation, looking at --target.")
@click.option("--radius", type=FiniteFloat(0, min_open=True), default=None,
              help="Orbit/dome: distance from --target to each camera (metres).")
@click.option("--elevation", default=None, metavar="DEG[,DEG...]",
              help="Orbit: the rings' elevations above the target's horizontal plane; dome: "
                   "the lowest elevation [default: 0].")
@click.option("--azimuth", type=FiniteFloat(), default=None, metavar="DEG",
              help="Orbit/dome: azimuth of the first camera, 0 = in front (+Z), 90 = +X "
                   "[default: 0].")
@click.option("--name", default=None,
              help="Look-at: the camera's name; orbit/dome: the names' prefix [default: cam → "
                   "cam000, cam001, ...].")
@click.option("--from", "source", default=None, metavar="SOURCE",
              help="Import the cameras of SOURCE: a COLMAP text model (folder, cameras.txt or "
                   "images.txt), a nerfstudio transforms.json, a relight camera or capture "
                   "JSON, or an EXR render ('-': JSON on stdin).")
@click.option("--select", default=None, metavar="NAME[,NAME...]",
              help="Keep only these cameras (by name, in this order) of --from or of the rig.")
@click.option("--drop-distortion", is_flag=True,
              help="Import: ignore the lens distortion of COLMAP SIMPLE_RADIAL, RADIAL, OPENCV, "
                   "FULL_OPENCV or nerfstudio OPENCV cameras (refused by default).")
@no_clobber_option
@quiet_option
def command(output, eye, target, up, fov, size, orbit, dome, radius, elevation, azimuth,
            name, source, select, drop_distortion, no_clobber, quiet):
    """Write cameras as relight/camera JSON (formats/camera.md): OpenCV pinhole
    K, world→camera R, t, width, height, name.  One camera is a JSON object,
    several a rig ({"cameras": [...]}).  The JSON goes to stdout unless -o FILE
    is given.

    \b
    Make them:
      --eye X,Y,Z [--target X,Y,Z] [--up X,Y,Z]   a look-at camera
      --orbit N --radius R [--elevation DEG,...]   rings of N cameras around --target
      --dome N --radius R [--elevation MIN]        N cameras over a dome around --target
    with --fov (vertical, degrees) and --size WxH; the principal point is the image
    centre.  Azimuth 0 is in front of the target (+Z), 90 is +X; elevation 90 is
    straight above.  Ring and dome cameras have the direction of increasing
    elevation up in their image, which stays defined straight above.

    \b
    Or import them, --from SOURCE:
      a COLMAP text model: a folder with cameras.txt and images.txt (or either file);
        models SIMPLE_PINHOLE, PINHOLE; SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV
        only without distortion, or with --drop-distortion; one camera per image,
        named after it, sorted by name
      a nerfstudio / instant-ngp transforms.json: one camera per frame, named by
        its file_path, in file order
      a relight camera JSON (a rig to --select from) or capture.json (its rig)
      an EXR render or capture image: its worldToCamera and worldToNDC header
        attributes, named as relight recorded it (relight.camera)
      '-': any of the JSON ones on stdin
    Imported cameras keep their names: COLMAP image names, nerfstudio file_paths,
    the names of a relight rig or capture, the name in a relight EXR's header.
    COLMAP and nerfstudio put the centre of the top-left pixel at (0.5, 0.5),
    relight at (0, 0): the principal point moves by -0.5 pixel.  nerfstudio's
    camera→world OpenGL poses (y up, looking down -z) become OpenCV's world→camera.
    Rotations must be orthonormal to 1e-3 (then they are made exact); scaled,
    sheared or mirrored poses are refused.

    \b
    Examples:
      relight camera --eye 0.45,0.55,0.6 --target 0,0.15,0 --fov 45 --size 320x240 -o cam.json
      relight camera --orbit 8 --radius 0.6 --elevation 15,45 --target 0,0.1,0 -o rig.json
      relight camera --dome 40 --radius 1 --elevation -20 --size 128x128 -o dome.json
      relight camera --from sparse/0 -o colmap_cams.json
      relight camera --from capture/capture.json --select cam000 -o cam000.json
      relight camera --from render.exr
      cat transforms.json | relight camera --from - | jq '.cameras | length'
    """
    from relight_cli.formats.camera import FORMAT, VERSION, write_cameras
    from relight_cli.jobs import camera as job
    from relight_cli.provenance import provenance

    # ---- options (usage errors, before any work)
    options = _options(output, eye, target, up, fov, size, orbit, dome, radius, elevation,
                       azimuth, name, source, select, drop_distortion, no_clobber)

    # ---- inputs (data errors), the job, the output
    imported, inputs = None, {}
    if source is not None:
        cameras, inputs, kind = _import(source, drop_distortion)
        imported = (cameras, kind)
    made = job.run(options, imported, source)
    cameras = made.cameras
    write_cameras(output, cameras, provenance(FORMAT, VERSION, inputs, made.settings))
    if output != "-":
        log(f"wrote {output} ({len(cameras)} camera{'s' if len(cameras) != 1 else ''}, "
            f"{cameras[0].width}x{cameras[0].height})", quiet)


def _options(output, eye, target, up, fov, size, orbit, dome, radius, elevation, azimuth, name,
             source, select, drop_distortion, no_clobber):
    """The options' usage errors (exit 2), before any work: the job's CameraOptions."""
    from relight_cli.cli.tools import parse_size
    from relight_cli.errors import UsageProblem
    from relight_cli.jobs.camera import CameraOptions

    made = {"--eye": eye, "--orbit": orbit, "--dome": dome}
    modes = [k for k, v in {**made, "--from": source}.items() if v is not None]
    if len(modes) != 1:
        raise UsageProblem("give exactly one of --eye (look-at), --orbit N, --dome N or --from "
                           "SOURCE (import)" + (f"; got {', '.join(modes)}" if modes else ""))
    synthetic = {"--target": target, "--up": up, "--fov": fov, "--size": size,
                 "--radius": radius, "--elevation": elevation, "--azimuth": azimuth,
                 "--name": name}
    if source is not None:
        given = [k for k, v in synthetic.items() if v is not None]
        if given:
            raise UsageProblem(f"{', '.join(given)} make cameras; they do not apply to --from")
    else:
        if drop_distortion:
            raise UsageProblem("--drop-distortion applies to imported cameras (--from)")
        rig_only = {"--radius": radius, "--elevation": elevation, "--azimuth": azimuth}
        if eye is not None:
            given = [k for k, v in rig_only.items() if v is not None]
            if given:
                raise UsageProblem(f"{', '.join(given)} belong to --orbit/--dome, not --eye")
        else:
            if up is not None:
                raise UsageProblem("--up belongs to --eye: orbit and dome cameras keep the "
                                   "direction of increasing elevation up")
            if radius is None:
                raise UsageProblem(f"{modes[0]} needs --radius R (metres)")
    check_output(output, no_clobber, kind="json")
    names = None
    if select is not None:
        names = [n.strip() for n in select.split(",") if n.strip()]
        if not names:
            raise UsageProblem("--select needs at least one camera name")
        if len(set(names)) != len(names):
            raise UsageProblem("--select names a camera twice")
    if source is not None:
        return CameraOptions("import", select=names, drop_distortion=drop_distortion)
    options = CameraOptions({"--eye": "look-at", "--orbit": "orbit", "--dome": "dome"}[modes[0]],
                            fov=40.0 if fov is None else fov, name=name, select=names)
    if size is not None:
        options.size = parse_size(size, "--size")
    if target is not None:
        options.target = parse_vector(target, 3, "--target")
    if eye is not None:
        options.eye = parse_vector(eye, 3, "--eye")
        if up is not None:
            options.up = parse_vector(up, 3, "--up")
    else:
        options.n, options.radius = (orbit if orbit is not None else dome), radius
        options.elevations = _elevations(elevation, dome is not None)
        options.azimuth = 0.0 if azimuth is None else azimuth
    return options


def _elevations(text, dome: bool) -> list[float]:
    from relight_cli.errors import UsageProblem
    if text is None:
        return [0.0]
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise UsageProblem(f"--elevation must be comma-separated degrees, got {text!r}") from None
    if not values or not all(-90 <= v <= 90 for v in values):   # also refuses NaN
        raise UsageProblem(f"--elevation values must be in [-90, 90] degrees, got {text!r}")
    if dome and (len(values) != 1 or values[0] >= 90):
        raise UsageProblem("--dome takes one --elevation, the lowest, below 90 degrees")
    return values


def _import(path: str, drop_distortion: bool):
    """(cameras, provenance inputs, what kind of source) of --from."""
    import os

    from relight_cli.cli.tools import check_input
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats import camera_imports as CI

    lower = path.lower()
    if path == "-" or lower.endswith(".json"):
        from relight_cli.formats._common import read_json
        obj = read_json(check_input(path, stdin="--from"))
        cameras, kind = CI.cameras_from_any_json(obj, path, drop_distortion)
        return cameras, {"source": path}, kind
    if os.path.isdir(path) or os.path.basename(lower) in ("cameras.txt", "images.txt"):
        if not os.path.exists(path):
            raise DataError("no such file", path)
        cameras_path, images_path = CI.colmap_model_files(path)
        for p in (cameras_path, images_path):
            check_input(p)
        return (CI.read_colmap_model(path, drop_distortion),
                {"colmap_cameras": cameras_path, "colmap_images": images_path}, "colmap")
    if lower.endswith(".exr"):
        from relight_cli.formats.camera import camera_from_openexr, openexr_camera_name
        from relight_cli.formats.exr import read_exr
        image = read_exr(check_input(path))
        if not all(k in image.attributes for k in ("worldToCamera", "worldToNDC")):
            raise DataError("no worldToCamera and worldToNDC header attributes: not a camera "
                            "render", path)
        name = openexr_camera_name(image.attributes.get("relight.camera"))
        camera = camera_from_openexr(image.attributes["worldToCamera"],
                                     image.attributes["worldToNDC"], image.width, image.height,
                                     path, name)
        return [camera], {"render": path}, "openexr"
    raise UsageProblem("--from takes a COLMAP text model (folder, cameras.txt or images.txt), "
                       "a .json (transforms.json, cameras, capture; '-' for stdin) or an EXR "
                       "render", path)
