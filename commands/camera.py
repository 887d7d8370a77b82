"""``relight camera``: make cameras (look-at, orbit rings, a dome) or import them
(COLMAP text models, nerfstudio transforms.json, a render's EXR header) as
``relight/camera`` JSON (formats/camera.md)."""

from __future__ import annotations

import click

from relight_cli.clitools import (FiniteFloat, check_output, log, no_clobber_option, parse_vector,
                                  quiet_option)


@click.command("camera", short_help="Make cameras (look-at, orbit, dome) or import them (COLMAP, nerfstudio).")
@click.argument("input", metavar="[IN]", required=False, default=None)
@click.option("-o", "--output", required=True, help="Camera JSON ('-' for stdout).")
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
@click.option("--select", default=None, metavar="NAME[,NAME...]",
              help="Keep only these cameras (by name, in this order) of IN or of the rig.")
@click.option("--drop-distortion", is_flag=True,
              help="Import: ignore the lens distortion of COLMAP SIMPLE_RADIAL, RADIAL, OPENCV, "
                   "FULL_OPENCV or nerfstudio OPENCV cameras (refused by default).")
@no_clobber_option
@quiet_option
def command(input, output, eye, target, up, fov, size, orbit, dome, radius, elevation, azimuth,
            name, select, drop_distortion, no_clobber, quiet):
    """Write cameras as relight/camera JSON (formats/camera.md): OpenCV pinhole
    K, world→camera R, t, width, height, name.  One camera is a JSON object,
    several a rig ({"cameras": [...]}).

    \b
    Make one (no IN):
      --eye X,Y,Z [--target X,Y,Z] [--up X,Y,Z]   a look-at camera
      --orbit N --radius R [--elevation DEG,...]   rings of N cameras around --target
      --dome N --radius R [--elevation MIN]        N cameras over a dome around --target
    with --fov (vertical, degrees) and --size WxH; the principal point is the image
    centre.  Azimuth 0 is in front of the target (+Z), 90 is +X; elevation 90 is
    straight above.  Ring and dome cameras have the direction of increasing
    elevation up in their image, which stays defined straight above.

    \b
    Or import IN:
      a COLMAP text model: a folder with cameras.txt and images.txt (or either file);
        models SIMPLE_PINHOLE, PINHOLE; SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV
        only without distortion, or with --drop-distortion; one camera per image,
        named after it, sorted by name
      a nerfstudio / instant-ngp transforms.json ('-' reads it from stdin): one
        camera per frame, named by its file_path, in file order
      a relight/camera JSON (to --select from a rig), or an EXR render (its
        worldToCamera and worldToNDC header attributes)
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
      relight camera sparse/0 -o colmap_cams.json
      relight camera transforms.json --select images/frame_00001.png -o cam.json
      cat transforms.json | relight camera - -o - | jq '.cameras | length'
    """
    from relight_cli import cameras as C
    from relight_cli.errors import UsageProblem
    from relight_cli.formats.camera import FORMAT, VERSION, write_cameras
    from relight_cli.provenance import provenance

    # ---- usage checks before any work
    made = {"--eye": eye, "--orbit": orbit, "--dome": dome}
    modes = [k for k, v in made.items() if v is not None] + (["IN"] if input is not None else [])
    if len(modes) != 1:
        raise UsageProblem("give exactly one of IN (to import), --eye (look-at), --orbit N or "
                           "--dome N" + (f"; got {', '.join(modes)}" if modes else ""))
    synthetic = {"--target": target, "--up": up, "--fov": fov, "--size": size,
                 "--radius": radius, "--elevation": elevation, "--azimuth": azimuth,
                 "--name": name}
    if input is not None:
        given = [k for k, v in synthetic.items() if v is not None]
        if given:
            raise UsageProblem(f"{', '.join(given)} make cameras; they do not apply to an "
                               f"imported IN")
    else:
        if drop_distortion:
            raise UsageProblem("--drop-distortion applies to an imported IN")
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
    if not output.lower().endswith(".json") and output != "-":
        raise UsageProblem("-o is a camera JSON (name it .json, or '-' for stdout)", output)
    check_output(output, no_clobber, text=True)
    names = None
    if select is not None:
        names = [n.strip() for n in select.split(",") if n.strip()]
        if not names:
            raise UsageProblem("--select needs at least one camera name")
        if len(set(names)) != len(names):
            raise UsageProblem("--select names a camera twice")

    # ---- cameras
    settings: dict = {}
    inputs: dict = {}
    if input is None:
        width, height = 256, 256
        if size is not None:
            from relight_cli.clitools import parse_size
            width, height = parse_size(size, "--size")
        fov_deg = 40.0 if fov is None else fov
        centre = parse_vector(target, 3, "--target") if target is not None else (0.0, 0.0, 0.0)
        settings.update(fov=fov_deg, size=[width, height], target=list(centre))
        if eye is not None:
            position = parse_vector(eye, 3, "--eye")
            up_vector = parse_vector(up, 3, "--up") if up is not None else (0.0, 1.0, 0.0)
            try:
                cameras = [C.look_at(position, centre, up_vector, fov_deg, width, height,
                                     name or "")]
            except ValueError as exc:
                raise UsageProblem(f"--eye, --target, --up: {exc}") from None
            settings.update(mode="look-at", eye=list(position), up=list(up_vector))
        else:
            elevations = _elevations(elevation, dome is not None)
            start = 0.0 if azimuth is None else azimuth
            prefix = "cam" if name is None else name
            if orbit is not None:
                cameras = C.orbit(orbit, radius, elevations, centre, start, fov_deg, width,
                                  height, prefix)
                settings.update(mode="orbit", n=orbit)
            else:
                cameras = C.dome(dome, radius, elevations[0], centre, start, fov_deg, width,
                                 height, prefix)
                settings.update(mode="dome", n=dome)
            settings.update(radius=radius, elevation=elevations, azimuth=start)
    else:
        cameras, inputs, source = _import(input, drop_distortion, settings)
        settings.update(mode="import", source=source, drop_distortion=drop_distortion)
    if names is not None:
        try:
            cameras = C.select(cameras, names)
        except KeyError as exc:
            listed = ", ".join(c.name or "''" for c in cameras[:6])
            raise UsageProblem(f"--select: no camera named {exc.args[0]!r} (cameras: {listed}"
                               f"{', ...' if len(cameras) > 6 else ''})", input) from None
        settings["select"] = names
    record = provenance(FORMAT, VERSION, inputs, settings)
    write_cameras(output, cameras, record)
    if output != "-":
        log(f"wrote {output} ({len(cameras)} camera{'s' if len(cameras) != 1 else ''}, "
            f"{cameras[0].width}x{cameras[0].height})", quiet)


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


def _import(path: str, drop_distortion: bool, settings: dict):
    """(cameras, provenance inputs, what kind of source) of IN; stdin, which has no file
    to hash, is recorded in ``settings`` by its SHA-256."""
    import hashlib
    import os
    import sys

    from relight_cli.clitools import check_input
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats import camera_imports as I
    from relight_cli.formats.camera import cameras_from_json

    if path == "-":
        from relight_cli.formats._common import parse_json
        text = sys.stdin.read()
        settings["stdin_sha256"] = hashlib.sha256(text.encode("utf-8")).hexdigest()
        obj = parse_json(text, "<stdin>")
        if I.is_nerfstudio(obj):
            return I.cameras_from_nerfstudio(obj, "<stdin>", drop_distortion), {}, "nerfstudio"
        return cameras_from_json(obj, "<stdin>"), {}, "relight/camera"
    lower = path.lower()
    if os.path.isdir(path) or os.path.basename(lower) in ("cameras.txt", "images.txt"):
        if not os.path.exists(path):
            raise DataError("no such file", path)
        cameras_path, images_path = I.colmap_model_files(path)
        for p in (cameras_path, images_path):
            check_input(p)
        return (I.read_colmap_model(path, drop_distortion),
                {"colmap_cameras": cameras_path, "colmap_images": images_path}, "colmap")
    if lower.endswith(".json"):
        from relight_cli.formats._common import read_json
        obj = read_json(check_input(path))
        if I.is_nerfstudio(obj):
            return (I.cameras_from_nerfstudio(obj, path, drop_distortion),
                    {"transforms": path}, "nerfstudio")
        return cameras_from_json(obj, path), {"cameras": path}, "relight/camera"
    if lower.endswith(".exr"):
        from relight_cli.formats.camera import camera_from_openexr
        from relight_cli.formats.exr import read_exr
        image = read_exr(check_input(path))
        found = [k for k in ("worldToCamera", "worldToNDC") if k in image.attributes]
        if len(found) != 2:
            raise DataError("no worldToCamera and worldToNDC header attributes: not a camera "
                            "render", path)
        camera = camera_from_openexr(image.attributes["worldToCamera"],
                                     image.attributes["worldToNDC"], image.width, image.height,
                                     path)
        return [camera], {"render": path}, "openexr"
    raise UsageProblem("IN must be a COLMAP text model (folder, cameras.txt or images.txt), a "
                       "transforms.json or camera .json ('-' for stdin), or an EXR render", path)
