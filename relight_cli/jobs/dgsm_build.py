"""Build Deep Gaussian Shadow Maps: ``relight dgsm-build`` as an engine job.

:func:`build` takes occluder Gaussians already loaded and placed (one or several
objects), the receivers' Gaussians (or none, with ``t_max``), and point lights (a
relight/lights record, or a count K to estimate K lights from the receivers' scene,
paper Sec. 3.1), and returns the DGSM (one table per light; with several objects one
per object and their product), the lights used, the combined occluders, the
optional preview sheet (with the receivers as it draws them) and the settings its
provenance records.  Only what the
receivers need is computed (receiver ROI, light-space occluder culling: see
:func:`relight_cli.gaussians.dgsm.build_dgsm`).

    from relight_cli.gaussians.from_mesh import load_gaussians
    from relight_cli.jobs.dgsm_build import DgsmOptions, build
    result = build([load_gaussians("builtin:hand")], 2, DgsmOptions(size=(64, 64)),
                   receivers=load_gaussians("room_with_lamp.ply"))
    result.shadow_map.transmittance        # [L, K, H, W]

Names (``names``, ``receivers_name``, ``lights_name``) only label log lines, errors
and the preview's title; nothing is read from them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class DgsmOptions:
    """The build's options (``relight dgsm-build``'s flags of the same names).

    ``size`` is (height, width) of the atlas; ``mapping`` may be an old name (``eq5``),
    recorded under its canonical name; ``estimator`` is the variant of the auto:K light
    estimate; ``preview`` also makes the labelled preview sheet, seen from ``camera``
    (an OpenCV camera, or None for one framing the occluders and their shadow), its
    receivers shadowed as ``relight`` shadows them at ``preview_strength`` (a number in
    [0, 1] or ``auto``, which needs ``preview_probe``, the scene's SH probe: an object
    with ``coefficients``; None: auto with a probe, else 1, the paper's full shadow)."""

    size: tuple = (128, 128)
    bins: int = 64
    atlas: str = "octahedral"
    mapping: str = "avg"
    kappa: float = 1.0
    t_max: float | None = None
    roi: bool = True
    roi_radius: float | None = None
    cull: bool = True
    cull_tolerance: float = 1e-7
    footprint: str = "stencil"
    samples: int = 16
    seed: int = 0
    allow_light_inside: bool = False
    self_shadow: bool = False
    radial: str = "full"
    estimator: str = "paper"
    preview: bool = False
    camera: object = None
    preview_strength: object = None
    preview_probe: object = None

    def shown_strength(self):
        """The strength the preview shows: ``preview_strength``, or by default auto with
        a probe (relight's default) and 1 without one."""
        if self.preview_strength is not None:
            return self.preview_strength
        return "auto" if self.preview_probe is not None else 1.0


@dataclass
class DgsmResult:
    """What :func:`build` made: ``shadow_map`` (:class:`relight_cli.gaussians.dgsm.DGSM`),
    ``lights`` (the relight/lights record used: read or estimated), ``occluders`` (all
    occluder Gaussians in one set), ``mapping`` (canonical name), ``preview`` (the
    [H, W, 3] display sheet in [0, 1], or None), ``preview_receivers`` (the receivers
    shadowed as the preview draws them, as relight relight would at its strength, or
    None) and ``settings`` (the build's provenance settings, in order)."""

    shadow_map: object
    lights: object
    occluders: object
    mapping: str
    preview: object = None
    settings: dict = field(default_factory=dict)
    preview_receivers: object = None


def build(occluders, lights, options: DgsmOptions, receivers=None, names=None,
          receivers_name: str = "receivers", lights_name: str = "lights", log=None,
          quiet: bool = False) -> DgsmResult:
    """The DGSM of ``occluders`` (a list of placed Gaussians, one per object) for
    ``lights`` (a :class:`relight_cli.formats.lights_json.Lights`, or an int K: estimate
    K lights from ``receivers``, the character being the occluders).

    ``log``: callable(str) for the notes and per-light lines (None: silent); ``quiet``
    silences the progress bar.  Raises DataError (a light inside an occluder without
    ``allow_light_inside``, NaN receivers, a failed estimate) and UsageProblem (auto:K
    without receivers or an estimator) naming the labels given.
    """
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.gaussians_ply import concatenate
    from relight_cli.gaussians import dgsm as D
    from relight_cli.gaussians import transmittance as TR
    from relight_cli.progress import progress

    say = log or (lambda message: None)
    names = list(names) if names is not None else [f"occluder{j}" for j in range(len(occluders))]
    occ = occluders[0] if len(occluders) == 1 else concatenate(occluders)
    auto_k = lights if isinstance(lights, int) else None
    if auto_k is not None:
        if receivers is None:
            raise UsageProblem("--lights auto:K estimates lights from the scene: give --receivers")
        lights = estimate_lights(receivers, auto_k, lights_name, occ, options.estimator)
    # Logged once every input has been read: a bad input gets one line only.
    if receivers is not None:
        say(f"read {receivers_name}: {len(receivers)} receiver Gaussians")
    for name, obj in zip(names, occluders):
        say(f"read {name}: {len(obj)} occluder Gaussians")
    say(f"{len(lights)} light(s)")

    mapping = TR.canonical_mapping(options.mapping)
    if options.mapping != mapping:
        say(f"note: --mapping {options.mapping} is the old name of {mapping}")
    mix = TR.from_gaussians(occ, mapping, options.kappa)
    _check_inside(mix, lights.positions, options.allow_light_inside,
                  lights_name if auto_k is None else ", ".join(names), say)

    recv_points = None
    if receivers is not None:
        pts, _ = D.footprint_samples(receivers.means, receivers.scales, receivers.rotations,
                                     options.footprint, options.samples, options.seed)
        recv_points = pts.reshape(-1, 3)
        if not np.isfinite(recv_points).all():
            raise DataError("receiver positions hold NaN/Inf", receivers_name)

    kwargs = dict(size=tuple(options.size), bins=options.bins, layout=options.atlas,
                  t_max=options.t_max, roi=options.roi, roi_radius=options.roi_radius,
                  cull=options.cull, cull_tolerance=options.cull_tolerance,
                  intensities=lights.intensities, colors=lights.colors, radial=options.radial)
    desc = "lights" if len(occluders) == 1 else "occluders"
    bar = (lambda it, total: progress(it, total=total, desc=desc, quiet=quiet))
    own = (_self_points(occluders, lights.positions, recv_points, options)
           if options.self_shadow else None)
    if len(occluders) == 1:
        if own is not None:
            recv_points = np.concatenate([p for p in (recv_points, own[0]) if p is not None])
        shadow_map = D.build_dgsm(mix, lights.positions, recv_points, progress=bar, **kwargs)
    else:
        # each object receives the others' shadows: its footprint samples join their ROIs
        group_points = [D.footprint_samples(o.means, o.scales, o.rotations, options.footprint,
                                            options.samples, options.seed)[0].reshape(-1, 3)
                        for o in occluders]
        shadow_map = D.build_dgsm_groups(
            [TR.from_gaussians(o, mapping, options.kappa) for o in occluders], lights.positions,
            recv_points, group_points, names=names, progress=bar, own_receivers=own, **kwargs)
    if options.self_shadow:       # recorded in the map: its tables cover self lookups
        for record in shadow_map.roi:
            record["self_shadow"] = True
    _log_build(say, shadow_map, receivers is not None and options.roi, mapping, options.kappa)

    sheet, shadowed = None, []
    if options.preview:
        sheet = preview_sheet(shadow_map, occ, receivers, options, mapping, len(lights), names,
                              receivers_name if receivers is not None else None, shadowed)
    return DgsmResult(shadow_map, lights, occ, mapping, sheet, _settings(options, mapping),
                      shadowed[0] if shadowed else None)


def _self_points(occluders, lights, recv_points, options: DgsmOptions) -> list:
    """Per occluder, the points its own table must cover for self-shadow lookups
    (relight_cli.gaussians.dgsm.sample_self_transmittance): its footprint samples and the
    same moved towards each light by the lookup's offset, taken with the widest radial bin
    the build can choose (t_max/K ≤ the farthest receiver's distance/(K − ½)), so the
    lookups, which move less or as far, lie between them."""
    from relight_cli.gaussians import dgsm as D
    lights = np.asarray(lights, np.float64).reshape(-1, 3)
    own = [D.footprint_samples(o.means, o.scales, o.rotations, options.footprint,
                               options.samples, options.seed)[0].reshape(-1, 3)
           for o in occluders]
    every = np.concatenate([p for p in [recv_points, *own] if p is not None])
    if options.t_max is not None:
        width = np.full(len(lights), options.t_max / options.bins)
    else:
        far = np.array([np.linalg.norm(every - light, axis=1).max() for light in lights])
        width = far / (options.bins - 0.5)
    out = []
    for o, points in zip(occluders, own):
        moved = D.self_lookup_points(lights, o.means, o.scales, o.rotations, width,
                                     options.footprint, options.samples, options.seed)
        out.append(np.concatenate([points] + [m.reshape(-1, 3) for m in moved]))
    return out


def _check_inside(mix, positions, allow: bool, label: str, say) -> None:
    """A light within 1σ of an occluder Gaussian: DataError naming ``label``, or with
    ``allow`` a warning (its shadows are that Gaussian's)."""
    from relight_cli.errors import DataError
    for li, gi, m in lights_inside(mix, positions):
        message = (f"light {li} at {_fmt(positions[li])} lies inside occluder Gaussian "
                   f"{gi} (Mahalanobis distance {m:.2f} < 1)")
        if not allow:
            raise DataError(message, label, hint="move the light, or pass --allow-light-inside")
        say(f"warning: {message}; its shadows are dominated by that Gaussian")


def _settings(options: DgsmOptions, mapping: str) -> dict:
    """The build's share of the provenance settings (the command adds the inputs' specs)."""
    h, w = options.size
    return {"size": [h, w], "bins": options.bins, "atlas": options.atlas, "mapping": mapping,
            "kappa": options.kappa, "t_max": options.t_max, "roi": options.roi,
            "roi_radius": options.roi_radius, "cull": options.cull,
            "cull_tolerance": options.cull_tolerance, "footprint": options.footprint,
            "samples": options.samples, "seed": options.seed,
            **({"self_shadow": True} if options.self_shadow else {}),
            **({"radial": options.radial} if options.radial != "full" else {})}


def _log_build(say, shadow_map, receivers_roi: bool, mapping: str, kappa: float) -> None:
    """One line per light (its ROI, or a warning when no receiver can be shadowed) and one
    for the build."""
    for li, info in enumerate(shadow_map.roi):
        if receivers_roi and info["receivers"] == 0:
            say(f"warning: light {li}: no receivers in the ROI (none can be shadowed by the "
                f"occluders); its table is all ones")
        else:
            say(f"light {li}: {info['texels']} texels, bins {info['bins'][0]}..{info['bins'][1]}, "
                f"t_max {shadow_map.t_max[li]:.3f} m, min T "
                f"{float(shadow_map.transmittance[li].min()):.3f}")
    st = shadow_map.stats
    say(f"built in {shadow_map.build_seconds:.3f} s ({st['pairs_kept']} ray/Gaussian pairs kept "
        f"of {st['pairs_tested']} tested), opacity mapping {mapping} (κ = {kappa:g})")


def preview_sheet(shadow_map, occluders, receivers, options: DgsmOptions, mapping: str,
                  n_lights: int, names, receivers_name=None, shadowed: list | None = None):
    """The labelled preview ([H, W, 3] display values in [0, 1]): the receivers shadowed
    at :meth:`DgsmOptions.shown_strength` (with the occluders; appended to ``shadowed``
    if given) and their shadow matte seen from ``options.camera``, and each light's
    atlas slice."""
    from relight_cli.preview import dgsm_sheet

    h, w = options.size
    title = (f"dgsm-build: {n_lights} light(s), {options.atlas} atlas {w}x{h}, {options.bins} "
             f"bins, mapping {mapping}\noccluders: {' '.join(names)}"
             + (f"\nreceivers: {receivers_name}" if receivers_name else ""))
    probe = options.preview_probe
    image, _ = dgsm_sheet(shadow_map, occluders, receivers, options.camera, options.footprint,
                          options.samples, options.seed, title,
                          strength=options.shown_strength(),
                          probe_coefficients=None if probe is None else probe.coefficients,
                          shadowed=shadowed)
    return image


def estimate_lights(scene, k: int, spec: str = "auto", character=None, variant: str = "paper"):
    """K point lights estimated from ``scene`` by relight_cli.gaussians.lights' estimator,
    as a relight/lights record; ``spec`` names the request in errors."""
    from relight_cli.errors import DataError
    from relight_cli.gaussians.lights import estimate_lights as estimate
    try:
        lights = estimate(scene, k, character=character, variant=variant).lights   # deterministic
    except ValueError as exc:
        raise DataError(f"light estimation failed: {exc}", spec) from None
    lights.extra = {"estimator": "relight_cli.gaussians.lights.estimate_lights",
                    "variant": variant, "count": int(k),
                    "character": "the occluders (alpha-weighted centroid)"}
    return lights


def lights_inside(mix, positions, threshold: float = 1.0):
    """[(light, gaussian, mahalanobis)] for lights within 1σ of an occluder Gaussian."""
    found = []
    for li, p in enumerate(np.asarray(positions, np.float64)):
        rel = (p - mix.means) / mix.scale_max[:, None]
        local = np.einsum("nji,nj->ni", mix.rotation, rel)
        m2 = (local ** 2 / mix.var).sum(axis=1)
        m2 = np.where(mix.alpha > 0, m2, np.inf)
        j = int(np.argmin(m2))
        if m2[j] < threshold ** 2:
            found.append((li, j, float(np.sqrt(m2[j]))))
    return found


def _fmt(v) -> str:
    return "(" + ", ".join(f"{float(x):.3g}" for x in v) + ")"
