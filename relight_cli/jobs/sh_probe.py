"""Fit an SH light probe: ``relight sh-probe`` as a job.

:func:`fit` samples the radiance of a loaded environment map, or of a Gaussian scene
seen from a point (its six cube faces splatted on the CPU, paper Sec. 3.4), and fits
the real SH coefficients by solid-angle-weighted ridge least squares
(:mod:`relight_cli.gaussians.probe`), at a fixed degree or the smallest one the
``auto`` search accepts; it returns them with the settings their provenance records.

    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.jobs.sh_probe import ProbeOptions, fit
    probe = fit(builtin_envmap("sky"), ProbeOptions(degree=2))
    probe.coefficients                      # [9, 3]
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class ProbeOptions:
    """``relight sh-probe``'s options, parsed: ``degree`` (None: the ``auto`` search with
    ``tolerance``, ``max_negativity``, ``max_degree``), ``ridge``; for a scene, the probe
    position ``at`` (X, Y, Z), the cube-face size and the cube cameras' near plane."""

    degree: int | None = None
    ridge: float = 0.0
    tolerance: float = 0.03
    max_negativity: float = 2.0
    max_degree: int = 8
    at: tuple | None = None
    face_size: int = 64
    near: float = 0.01


@dataclass
class Probe:
    """What :func:`fit` made: the radiance ``samples`` fitted, the ``degree`` and its
    ``coefficients``, the probe's ``extra`` record fields and the ``settings`` its
    provenance records (those of the sampling, then those of the degree search)."""

    samples: object
    degree: int
    coefficients: object
    extra: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)


def fit(source, options: ProbeOptions, progress=None, log=None) -> Probe:
    """The probe of ``source``: an EnvMap, or a Gaussian scene seen from ``options.at``
    (``progress``: a wrapper of the cube faces' iterable, or None); ``log``
    (callable(str)) reports the ``auto`` degree search."""
    from relight_cli.gaussians import probe as PR

    settings, extra = {}, {}
    if options.at is not None:
        samples = PR.scene_samples(source, options.at, options.face_size, options.near,
                                   progress=progress)
        settings.update(at=list(options.at), face_size=options.face_size, near=options.near)
    else:
        samples = PR.env_samples(source)
    if options.degree is None:
        choice = PR.choose_degree(samples, options.tolerance, options.ridge, options.max_degree,
                                  options.max_negativity)
        degree, coefficients = choice.degree, choice.coefficients
        extra["degree_search"] = PR.degree_search_record(choice)
        settings.update(tolerance=options.tolerance, max_negativity=options.max_negativity,
                        max_degree=options.max_degree)
        for line in PR.degree_search_log(choice):
            if log is not None:
                log(line)
    else:
        degree = options.degree
        coefficients = PR.fit_probe(samples, degree, options.ridge)
    if options.at is not None:
        extra["face_size"] = options.face_size
    return Probe(samples, degree, coefficients, extra, settings)
