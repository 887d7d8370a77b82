"""Make or select cameras: ``relight camera`` as a job.

:func:`run` makes the cameras of :class:`CameraOptions` (a look-at camera, orbit rings
or a dome, :mod:`relight_cli.cameras`) or takes cameras already imported, keeps the
selected ones, and returns them with the settings their provenance records.

    from relight_cli.jobs.camera import CameraOptions, run
    made = run(CameraOptions("orbit", n=8, radius=0.4, elevations=[25.0]))
    made.cameras[1].name                   # 'cam001'
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class CameraOptions:
    """``relight camera``'s options, parsed.

    ``mode`` is ``look-at``, ``orbit``, ``dome`` or ``import``; ``size`` (width, height);
    ``n`` the orbit/dome camera count; ``elevations`` the rings' elevations (a dome's
    lowest first); ``name`` the look-at camera's name or the rig's prefix (None: ``cam``);
    ``select`` the names to keep, in order (None: all)."""

    mode: str
    fov: float = 40.0
    size: tuple = (256, 256)
    target: tuple = (0.0, 0.0, 0.0)
    eye: tuple | None = None
    up: tuple = (0.0, 1.0, 0.0)
    n: int | None = None
    radius: float | None = None
    elevations: list = field(default_factory=lambda: [0.0])
    azimuth: float = 0.0
    name: str | None = None
    select: list | None = None
    drop_distortion: bool = False


@dataclass
class Cameras:
    """What :func:`run` made: the ``cameras`` and the ``settings`` their provenance
    records."""

    cameras: list
    settings: dict


def run(options: CameraOptions, imported=None, source: str | None = None) -> Cameras:
    """The cameras of ``options``: made, or ``imported`` ((cameras, what kind of
    source) read from ``source``) with mode ``import``; then the selected ones
    (UsageProblem naming ``source`` for a name no camera has)."""
    from relight_cli.errors import UsageProblem

    if options.mode == "import":
        cameras, kind = imported
        settings = {"mode": "import", "source": kind, "drop_distortion": options.drop_distortion}
    else:
        cameras, settings = _make(options)
    if options.select is not None:
        from relight_cli import cameras as CAM
        try:
            cameras = CAM.select(cameras, options.select)
        except KeyError as exc:
            listed = ", ".join(c.name or "''" for c in cameras[:6])
            raise UsageProblem(f"--select: no camera named {exc.args[0]!r} (cameras: {listed}"
                               f"{', ...' if len(cameras) > 6 else ''})", source) from None
        settings["select"] = options.select
    return Cameras(cameras, settings)


def _make(o: CameraOptions):
    """(cameras, settings) of a look-at camera, orbit rings or a dome; UsageProblem for
    a look-at camera whose up is parallel to its view direction."""
    from relight_cli import cameras as CAM
    from relight_cli.errors import UsageProblem

    width, height = o.size
    settings = {"fov": o.fov, "size": [width, height], "target": list(o.target)}
    if o.mode == "look-at":
        try:
            cameras = [CAM.look_at(o.eye, o.target, o.up, o.fov, width, height, o.name or "")]
        except ValueError as exc:
            raise UsageProblem(f"--eye, --target, --up: {exc}") from None
        settings.update(mode="look-at", eye=list(o.eye), up=list(o.up))
        return cameras, settings
    prefix = "cam" if o.name is None else o.name
    if o.mode == "orbit":
        cameras = CAM.orbit(o.n, o.radius, o.elevations, o.target, o.azimuth, o.fov, width,
                            height, prefix)
    else:
        cameras = CAM.dome(o.n, o.radius, o.elevations[0], o.target, o.azimuth, o.fov, width,
                           height, prefix)
    settings.update(mode=o.mode, n=o.n)
    settings.update(radius=o.radius, elevation=o.elevations, azimuth=o.azimuth)
    return cameras, settings
