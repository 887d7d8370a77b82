"""Animated Gaussians through a scene, one process per clip (the DGSM paper's setting).

The paper (Mir et al., Deep Gaussian Shadow Maps) relights *animated* 3DGS avatars
moving through a static 3DGS scene: per frame it rebuilds the shadow maps from the moved
occluders (Sec. 3.2, with the receiver ROI and light-space culling of Sec. 3.3 and
ablation D), refits the SH probe at the avatar's position ("a fast, closed-form
per-frame update of the SH probe and transfer scales", Sec. 3.4: a cube map rendered
from the scene there) and relights the avatar (Eq. 9-10).  :func:`frames` is that loop:

* the scene (``receivers``) is read once and the lights are read or estimated once
  (Sec. 3.1, from the scene with the first frame's occluders as the character): the
  scene is static, so are its lights;
* per frame: every source's Gaussians are placed (relight_cli.gaussians.sequence: one
  placement for the whole clip), the DGSM is built in-process (``dgsm`` options) or
  read from the frame's file (``shadow_maps``: a callable frame → DGSM), each object's
  probe is refitted at its centre from the scene (``probe_options``) or one probe is
  used throughout, the objects are relit and shadowed and the view rendered
  (relight_cli.jobs.relight_gaussians.relight).

Everything a frame uses is a function of the inputs and that frame's number (the Monte
Carlo footprint's seed is the options' seed, as a single-frame run's), so a frame
rendered alone equals the same frame of the clip.  Each :class:`ClipFrame` carries the
seconds of each stage (for benchmarks; never written into an output).

    from relight_cli.jobs.gaussian_clip import frames, ClipOptions
    for f in frames(sources, [0, 1, 2], scene, ClipOptions(...), lights=2, camera=cam):
        f.relit.rgb
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ClipOptions:
    """How a clip is made: ``gaussian`` (GaussianOptions: transfer, shadows), ``dgsm``
    (DgsmOptions: build the shadow maps per frame in-process; None: read them or none),
    ``probe`` (ProbeOptions: refit each object's probe per frame at its centre from the
    scene, at a fixed degree; None: one probe for the clip), ``estimator`` (of lights
    given as a count)."""

    gaussian: object
    dgsm: object = None
    probe: object = None
    estimator: str = "paper"


@dataclass
class ClipFrame:
    """One rendered frame: its number, the relit result (relight_cli.jobs.
    relight_gaussians.RelitGaussians), the probes used (one per object), the shadow map
    (or None), the objects' probe positions, and the ``seconds`` of each stage."""

    frame: int
    relit: object
    probes: list
    shadow_map: object = None
    probe_positions: list = field(default_factory=list)
    seconds: dict = field(default_factory=dict)


def object_centre(g) -> np.ndarray:
    """Where an object's probe is fitted: the centre of its robust box (the opacity-
    weighted 1st-99th percentile of its centres, as placements use)."""
    from relight_cli.gaussians.placement import robust_bounds
    lo, hi = robust_bounds(g)
    return (lo + hi) / 2


def clip_lights(lights, sources, scene, estimator: str = "paper", spec: str = "auto"):
    """The clip's lights: a relight/lights record as given, or a count K estimated once
    from the scene with the objects of the recording's first frame as the character
    (paper Sec. 3.1; the same lights whichever frames are rendered)."""
    from relight_cli.errors import UsageProblem
    from relight_cli.formats.gaussians_ply import concatenate
    from relight_cli.jobs.dgsm_build import estimate_lights
    if not isinstance(lights, int):
        return lights
    if scene is None:
        raise UsageProblem("--lights auto:K estimates lights from the scene: give --receivers")
    from relight_cli.gaussians.sequence import recording_start
    objects = [s.frame(recording_start(sources)) for s in sources]
    occ = objects[0] if len(objects) == 1 else concatenate(objects)
    return estimate_lights(scene, lights, spec, occ, estimator)


def frames(sources, frame_numbers, scene, options: ClipOptions, lights=None, probe=None,
           shadow_maps=None, camera=None, background=(0.0, 0.0, 0.0), names=None,
           log=None):
    """Yield a :class:`ClipFrame` per frame number (a generator: a frame is made when it
    is asked for).

    ``sources``: relight_cli.gaussians.sequence.GaussianSource (IN first); ``scene``:
    the receivers' Gaussians (or None); ``lights``: the lights of an in-process build
    (a Lights record; :func:`clip_lights` resolves a count first); ``probe``: the SH probe
    used when ``options.probe`` is None; ``shadow_maps``: frame → DGSM when the maps are
    read (None: built with ``options.dgsm``, or no shadows)."""
    from relight_cli.jobs import relight_gaussians as G
    from relight_cli.jobs.dgsm_build import build
    from relight_cli.jobs.sh_probe import fit

    say = log or (lambda message: None)
    names = names or [s.spec for s in sources]
    static_probes = {}
    for k in frame_numbers:
        seconds = {}
        t = time.perf_counter()
        objects = [s.frame(k) for s in sources]
        seconds["place"] = time.perf_counter() - t

        t = time.perf_counter()
        shadow_map = None
        if shadow_maps is not None:
            shadow_map = shadow_maps(k)
        elif options.dgsm is not None:
            shadow_map = build(objects, lights, options.dgsm, scene, names=names,
                               quiet=True).shadow_map
        seconds["dgsm"] = time.perf_counter() - t

        t = time.perf_counter()
        positions, probes = [], []
        if options.probe is None:
            probes = [probe] * len(objects)
        else:
            for j, (s, g) in enumerate(zip(sources, objects)):
                if j not in static_probes:      # a static object's probe is fitted once
                    centre = object_centre(g)
                    fitted = fit(scene, _at(options.probe, centre))
                    record = (_ProbeRecord(fitted.degree, fitted.coefficients), centre)
                    if not s.moves:
                        static_probes[j] = record
                else:
                    record = static_probes[j]
                probes.append(record[0])
                positions.append(record[1])
        seconds["probe"] = time.perf_counter() - t

        t = time.perf_counter()
        relit = G.relight(objects, probes, options.gaussian, shadow_map, scene, camera,
                          background, names=names, log=say)
        seconds["relight+render"] = time.perf_counter() - t
        yield ClipFrame(k, relit, probes, shadow_map, positions, seconds)


@dataclass
class _ProbeRecord:
    """A fitted probe as relight() reads one (``degree``, ``coefficients``)."""

    degree: int
    coefficients: np.ndarray


def _at(options, centre):
    """``options`` (ProbeOptions) fitted at ``centre``."""
    from dataclasses import replace
    return replace(options, at=tuple(float(v) for v in centre))
